"""The one table from a track file's suffix to its format; every writer, reader and command chooses through it."""

from __future__ import annotations

from pathlib import Path

from condtrack_cli.errors import CondtrackError

#: Track-file suffix (lower case) -> format name, which is also the name of the registered output stage.
FORMATS = {".csv": "csv", ".h5": "hdf5", ".hdf5": "hdf5"}


def track_format(path: str | Path, what: str = "track file") -> str:
    """'csv' or 'hdf5' for ``path``'s suffix; CondtrackError naming the file (as a ``what``) otherwise."""
    path = Path(path)
    try:
        return FORMATS[path.suffix.lower()]
    except KeyError:
        raise CondtrackError(f"{path}: unknown {what} format '{path.suffix}' (use .csv, .h5 or .hdf5)") from None


def is_hdf5(path: str | Path) -> bool:
    """True when ``path``'s suffix names an HDF5 track file (no error for other suffixes)."""
    return FORMATS.get(Path(path).suffix.lower()) == "hdf5"
