"""The Python API: ``track`` a sequence into :class:`Tracks`, ``read_tracks`` a track file back.

``condtrack track`` runs :func:`track_sequence`, the same code path as
:func:`track`, so that the two give identical arrays for the same input,
queries, config and seed::

    import condtrack_cli as ct
    t = ct.track("sample_sequences/occlusion", queries="sample_sequences/occlusion/queries.csv", method="clf")
    t.xy.shape            # (P, F, 2) px
    t.to_hdf5("out.h5")   # the file condtrack track -o out.h5 writes
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from condtrack_cli import MAX_SEED, pipeline, registry, types
from condtrack_cli.config import Config, load_config, resolve
from condtrack_cli.errors import CondtrackError, InvalidArgument, InvalidArgumentType, plain
from condtrack_cli.io import read as io_read
from condtrack_cli.io.formats import track_format
from condtrack_cli.io.interface import OutputSettings
from condtrack_cli.io.write import write_tracks
from condtrack_cli.hashes import config_hash, queries_hash
from condtrack_cli.progress import Progress
from condtrack_cli.queries import queries_from_rows, read_queries

#: File attributes of a run (beyond the sequence's) that :meth:`Tracks.to_hdf5` writes and ``read_tracks`` keeps.
RUN_ATTRIBUTES = ("config", "method", "seed", "config_hash", "queries_hash", "smoothed")


@dataclass(frozen=True)
class Tracks:
    """A tracking result: P points over the F frames of a sequence (pixels; x right, y down, origin at the
    centre of the top-left pixel).

    ``result`` is the pipeline's :class:`condtrack_cli.types.Tracks` (with the
    raw measurements z, R and the optional datasets); ``info`` the sequence;
    ``config`` the resolved config (None for a CSV read back: a CSV holds none);
    ``attributes`` the run's file attributes (config YAML, method, seed, smoothed, and the hashes: ``condtrack_cli.hashes``).
    """

    result: types.Tracks
    info: types.SequenceInfo
    config: Config | None
    attributes: dict[str, Any]

    @property
    def xy(self) -> np.ndarray:
        """(P, F, 2) float64 px, NaN where the point has no state."""
        return self.result.xy

    @property
    def cov(self) -> np.ndarray:
        """(P, F, 2, 2) float64 px^2 posterior covariance; NaN undefined, inf unbounded."""
        return self.result.cov

    @property
    def visible(self) -> np.ndarray:
        """(P, F) bool."""
        return self.result.visible

    @property
    def method(self) -> np.ndarray:
        """(P,) str: the method that produced most of each point's frames ("" for a point with no state)."""
        return np.array(self.result.point_methods(), dtype=str)

    @property
    def queries(self) -> types.Queries:
        """The query of each point: ``point_id`` (P,), ``frame`` (P,), ``xy`` (P, 2) px."""
        return self.result.queries

    def to_csv(self, path: str | Path) -> None:
        """Write the long CSV (docs/schema.md) to ``path`` (a .csv name), atomically."""
        self._write(path, "csv")

    def to_hdf5(self, path: str | Path) -> None:
        """Write the HDF5 file (docs/schema.md) to ``path`` (a .h5 or .hdf5 name), atomically."""
        self._write(path, "hdf5")

    def _write(self, path: str | Path, expected: str) -> None:
        if track_format(path, "output") != expected:
            raise CondtrackError(f"{path}: a {expected} file needs a {'.csv' if expected == 'csv' else '.h5 or .hdf5'} name")
        settings = self.config.output if self.config is not None else OutputSettings()
        write_tracks(self.result, path, self.info, self.attributes, settings)


def check_seed(seed: Any) -> None:
    """Refuse a seed that is not a whole number from 0 to ``MAX_SEED``, in the words of ``condtrack track --seed``."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise InvalidArgumentType(f"seed: {plain(seed)} is not a valid integer")
    if not 0 <= seed <= MAX_SEED:
        raise InvalidArgument(f"seed: {plain(seed)} is not in the range 0<=x<={MAX_SEED}")


def track_sequence(
    input_path: str | Path, config: Config, queries: str | Path | np.ndarray | None = None, seed: int = 0,
    progress_factory=None,
) -> tuple[Tracks, Any]:
    """Track ``input_path`` (a frame folder or a video) with a validated ``config``: the path of ``condtrack track``.

    Returns the tracks and the opened frame source (for an overlay).

    ``queries``: a CSV path, an (N, 3) array of ``frame, x, y`` rows, or None
    (detect on frame 0). ``progress_factory(forward_frames, backward_frames)`` returns a per-frame
    callback with ``close()`` (:class:`condtrack_cli.progress.Progress`); None tracks silently.
    """
    check_seed(seed)
    given = queries
    frames_stage = config.stage("frames")
    source = registry.get("frames", frames_stage.name).factory(frames_stage.settings, str(input_path))
    info = source.info
    config.check_fits_frame(info.width, info.height, detecting=queries is None, where=info.input)
    if queries is None or isinstance(queries, (str, Path)):
        queries = read_queries(queries, info) if queries is not None else None
    else:
        queries = queries_from_rows(queries, info)
    backward_frames = int(queries.frame.max()) + 1 if queries is not None and queries.frame.max() > 0 else 0
    progress = progress_factory(info.n_frames, backward_frames) if progress_factory else None
    try:
        result = pipeline.run(source, info, config, queries, seed=seed, on_frame=progress)
    finally:
        if progress is not None:
            progress.close()
    attributes = {"config": config.to_yaml(), "method": config.method, "seed": seed,
                  "config_hash": config_hash(config), "queries_hash": queries_hash(given), "smoothed": config.smooth}
    return Tracks(result, info, config, attributes), source


def track(
    source: str | Path, queries: str | Path | np.ndarray | None = None, method: str | None = None,
    config: str | Path | Mapping[str, Any] | None = None, seed: int = 0, progress: bool = False,
) -> Tracks:
    """Track points through ``source``, a folder of frames or a video file.

    queries: a CSV path (``frame,x,y[,point_id]``), an (N, 3) array of
    ``frame, x, y`` rows (point ids 0..N-1), or None to detect points on frame 0.
    method: a registered tracking method (overrides ``filter.method``).
    config: a YAML path or a nested mapping with the YAML's sections, validated
    like ``condtrack track -c`` (same errors). seed: 0 .. ``MAX_SEED``. progress: a progress display on stderr.
    Raises :class:`condtrack_cli.CondtrackError` on bad input (a bad argument value or type: its subclasses
    ``InvalidArgument``, a ValueError, and ``InvalidArgumentType``, a TypeError).
    """
    tracks, _ = track_sequence(source, load_config(config, [], method), queries, seed, Progress if progress else None)
    return tracks


def read_tracks(path: str | Path) -> Tracks:
    """Read a .csv, .h5 or .hdf5 track file back into :class:`Tracks`.

    An HDF5 file gives back its sequence, config and run attributes; a CSV holds
    none of them (``config`` is None, ``info`` has the frame count only) nor the measurements.
    """
    result, meta = io_read.read_tracks(path)
    info = types.SequenceInfo(
        input=str(meta.get("input", "")), width=int(meta.get("width", 0)), height=int(meta.get("height", 0)),
        n_frames=int(meta["n_frames"]), fps=float(meta.get("fps", 0.0)),
    )
    config = resolve(yaml.safe_load(meta["config"])) if "config" in meta else None
    attributes = {key: meta[key] for key in RUN_ATTRIBUTES if key in meta}
    return Tracks(result, info, config, attributes)
