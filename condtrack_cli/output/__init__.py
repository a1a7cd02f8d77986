"""Writers and readers of track files (CSV and HDF5); see docs/schema.md."""

from condtrack_cli.output.write import write_tracks  # noqa: F401
