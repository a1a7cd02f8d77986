"""Writers and readers of track files (CSV and HDF5); see docs/schema.md.

Imports nothing: ``condtrack_cli.io.formats`` stays light for the command line.
"""
