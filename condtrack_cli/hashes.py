"""What made an output, as hashes stored in it (HDF5 attributes) and in a batch's manifest.

``config_hash``: sha256 (hex) of the resolved configuration's canonical YAML
(``Config.to_yaml()``, UTF-8): every key with its value, defaults included, in
a fixed order, so the same effective settings (from a file, ``--set`` or
``-m``) hash alike and any changed value changes the hash.

``queries_hash``: sha256 (hex) of the queries given: a file's bytes, or an
array's float64 bytes (C order); "" when the points are detected.

``input_fingerprint``: sha256 (hex) of the input's identity, cheap to take
(no pixel is read): its resolved path and, for a frame folder, the name, size
and mtime of every frame file, for a video its size and mtime. It is stored in
a batch's manifest only (the output files stay as they are).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from condtrack_cli.config import Config
from condtrack_cli.errors import CondtrackError
from condtrack_cli.frames.readers import IMAGE_EXTENSIONS


def config_hash(config: Config) -> str:
    """sha256 (hex) of ``config.to_yaml()`` encoded as UTF-8."""
    return hashlib.sha256(config.to_yaml().encode("utf-8")).hexdigest()


def queries_hash(queries: str | os.PathLike | np.ndarray | None) -> str:
    """sha256 (hex) of a queries file's bytes or of an (N, 3) array's float64 bytes; "" for None."""
    if queries is None:
        return ""
    if not isinstance(queries, (str, os.PathLike)):
        return hashlib.sha256(np.ascontiguousarray(queries, dtype=np.float64).tobytes()).hexdigest()
    try:
        return hashlib.sha256(Path(queries).read_bytes()).hexdigest()
    except OSError as error:
        raise CondtrackError(f"{queries}: cannot read ({error.strerror})") from None


def input_fingerprint(path: str | Path) -> str:
    """sha256 (hex) of ``path``'s resolved path and its frames' names, sizes and mtimes; "" when it cannot be listed."""
    resolved = Path(path).resolve()
    try:
        if resolved.is_dir():
            entries = sorted(os.scandir(resolved), key=lambda entry: entry.name)
            stats = [(entry.name, entry.stat()) for entry in entries
                     if not entry.name.startswith(".") and Path(entry.name).suffix.lower() in IMAGE_EXTENSIONS
                     and entry.is_file()]
        else:
            stats = [("", resolved.stat())]
    except OSError:
        return ""  # the run itself will name the problem
    text = "\n".join([str(resolved), *(f"{name}\t{st.st_size}\t{st.st_mtime_ns}" for name, st in stats)])
    return hashlib.sha256(text.encode("utf-8", "surrogateescape")).hexdigest()
