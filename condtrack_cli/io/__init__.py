"""Writers and readers of track files (CSV and HDF5); see docs/schema.md."""

from condtrack_cli.io.write import write_tracks  # noqa: F401
