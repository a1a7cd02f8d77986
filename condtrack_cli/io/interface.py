"""Contract of an ``output`` stage: tracks in, a track file out (docs/schema.md).

A writer is registered with ``register("output", format_name, OutputSettings)``
(the format name is the one ``io/formats.py`` gives the file's suffix) on the
function itself, called ``writer(tracks, path, info, meta, settings)``; it writes
``path`` (a temporary name that ``write_tracks`` renames when the writer returns).
The built-in writers are rows of ``registry.BUILTINS`` instead.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

from pydantic import Field

from condtrack_cli.settings import StageSettings
from condtrack_cli.types import SequenceInfo, Tracks


class OutputSettings(StageSettings):
    """Settings of the CSV and HDF5 writers."""

    unbounded_floats = ("max_std",)  # a threshold: compared, never computed with

    hdf5_compression: int = Field(4, ge=0, le=9, description="gzip level of HDF5 datasets (0 = none)")
    store_measurements: bool = Field(True, description="write /measurements/z and /measurements/R to HDF5")
    store_particles: bool = Field(False, description="write the CNLF's particles to HDF5 (/particles/xy; large)")
    store_segmentation: bool = Field(False, description="write the motion segmentation maps of auto to HDF5 (/segmentation)")
    backward: bool = Field(True, description="also track each point backward from its query frame (its rows before it); false: rows from the query frame on only, no backward pass (--forward-only)")
    max_std: float | None = Field(None, gt=0, description="write a row as not visible when the std along its covariance's major axis exceeds this (px; --max-std); null: off")


class Writer(Protocol):
    """``writer(tracks, path, info, meta, settings)``: write ``tracks`` of the sequence ``info`` to ``path``.

    tracks: (P, F, ...) arrays (``types.Tracks``: xy px, cov px^2, ...); meta: run
    attributes (config YAML, method, seed, hashes) stored where the format can.
    """

    def __call__(self, tracks: Tracks, path: Path, info: SequenceInfo, meta: dict[str, Any],
                 settings: OutputSettings) -> None: ...
