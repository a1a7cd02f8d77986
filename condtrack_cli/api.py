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

import contextlib
import itertools
import numbers
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from condtrack_cli import MAX_SEED, pipeline, registry, types
from condtrack_cli.config import Config, load_config, not_in_csv, stored_config, yaml_scalar
from condtrack_cli.detect.trackability import POLICIES, query_scores, screen_queries, trackability_settings
from condtrack_cli.errors import CondtrackError, InvalidArgument, InvalidArgumentType, plain, python_value, warn
from condtrack_cli.io import read as io_read
from condtrack_cli.io.formats import track_format
from condtrack_cli.io.interface import OutputSettings
from condtrack_cli.io.write import write_tracks
from condtrack_cli.hashes import config_hash, queries_hash
from condtrack_cli.predictive import trusted
from condtrack_cli.progress import Progress
from condtrack_cli.queries import queries_from_rows, read_queries

#: File attributes of a run (beyond the sequence's) that :meth:`Tracks.to_hdf5` writes and ``read_tracks`` keeps.
RUN_ATTRIBUTES = ("config", "method", "seed", "config_hash", "queries_hash", "smoothed", "max_std")


@dataclass(frozen=True)
class Tracks:
    """A tracking result: P points over the F frames of a sequence (pixels; x right, y down, origin at the
    centre of the top-left pixel).

    ``result`` is the pipeline's :class:`condtrack_cli.types.Tracks` (with the
    raw measurements z, R and the optional datasets); ``info`` the sequence;
    ``config`` the resolved config (None for a CSV read back: a CSV holds none);
    ``attributes`` the run's file attributes (config YAML, method, seed, smoothed, and the hashes: ``condtrack_cli.hashes``).

    Example (from the repository's root, as every example here; tests/test_doctests.py runs them):

    >>> import numpy as np
    >>> import condtrack_cli as ct
    >>> t = ct.track("sample_sequences/occlusion", queries=np.array([[0, 120.0, 80.0], [5, 200.5, 64.0]]), method="clf")
    >>> t.xy.shape, t.cov.shape, t.visible.shape, t.info.n_frames
    ((2, 30, 2), (2, 30, 2, 2), (2, 30), 30)
    >>> t.method.tolist(), t.queries.frame.tolist(), t.attributes["seed"]
    (['clf', 'clf'], [0, 5], 0)
    >>> t  # the shapes and what made them, not the arrays
    Tracks(2 points x 30 frames, clf 2, input 'sample_sequences/occlusion' 320x240 px, seed 0)
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
    def dof(self) -> np.ndarray:
        """(P, F) float64 degrees of freedom nu > 2 of each row's bivariate Student-t predictive distribution
        (covariance ``cov``, scale matrix ``cov (nu - 2) / nu``); inf: Gaussian; NaN where no state."""
        return self.result.dof

    @property
    def visible(self) -> np.ndarray:
        """(P, F) bool."""
        return self.result.visible

    @property
    def method(self) -> np.ndarray:
        """(P,) str: the method that produced most of each point's frames ("" for a point with no state)."""
        return np.array(self.result.point_methods(), dtype=str)

    @property
    def trackability(self) -> np.ndarray:
        """(P,) float64 Shi-Tomasi score of each query at its query frame, (grey/px)^2: the smaller eigenvalue of the
        structure tensor over ``detect.block``; a point is trackable above ``detect.min_eigenvalue``. NaN where
        unknown (a CSV, or an HDF5 file of schema 1.0)."""
        return self.result.trackability

    @property
    def queries(self) -> types.Queries:
        """The query of each point: ``point_id`` (P,), ``frame`` (P,), ``xy`` (P, 2) px."""
        return self.result.queries

    def __repr__(self) -> str:
        """One line: points x frames, the points per method, the input and its frame size (an HDF5 file's or a run's),
        the seed; the arrays, the config and the hashes stay out (a notebook cell ending with ``t`` showed them all)."""
        n_points, n_frames = self.xy.shape[:2]
        parts = [f"{n_points} points x {n_frames} frames"] + ([self.result.method_split()] if n_points else [])
        parts += [f"input {self.info.input!r} {self.info.width}x{self.info.height} px"] if self.info.width else []
        parts += [f"seed {self.attributes['seed']}"] if "seed" in self.attributes else []
        return f"Tracks({', '.join(parts)})"

    def to_csv(self, path: str | Path) -> None:
        """Write the long CSV (docs/schema.md) to ``path`` (a .csv name), atomically.

        >>> import condtrack_cli as ct
        >>> t = ct.track("sample_sequences/occlusion", queries="sample_sequences/occlusion/queries.csv", method="stk")
        >>> t.to_csv("occlusion.csv")
        >>> from pathlib import Path
        >>> Path("occlusion.csv").read_text().splitlines()[0]
        'point_id,frame,x,y,cov_xx,cov_xy,cov_yy,dof,visible,method'
        """
        self._write(path, "csv")

    def to_hdf5(self, path: str | Path) -> None:
        """Write the HDF5 file (docs/schema.md) to ``path`` (a .h5 or .hdf5 name), atomically.

        >>> import h5py
        >>> import condtrack_cli as ct
        >>> t = ct.track("sample_sequences/occlusion", queries="sample_sequences/occlusion/queries.csv", method="stk")
        >>> t.to_hdf5("occlusion.h5")
        >>> with h5py.File("occlusion.h5") as f:
        ...     print(f["tracks/xy"].shape, f.attrs["method"])
        (64, 30, 2) stk
        """
        self._write(path, "hdf5")

    def _write(self, path: str | Path, expected: str) -> None:
        check_path("path", path)
        if track_format(path, "output") != expected:
            raise CondtrackError(f"{path}: a {expected} file needs a {'.csv' if expected == 'csv' else '.h5 or .hdf5'} name")
        settings = self.config.output if self.config is not None else OutputSettings()
        for name in sorted({key.split("/")[0] for key in self.result.extras} if expected == "csv" else ()):
            warn(not_in_csv(name))
        write_tracks(self.result, path, self.info, self.attributes, settings)


def check_seed(seed: Any) -> None:
    """Refuse a seed that is not a whole number from 0 to ``MAX_SEED``, in the words of ``condtrack track --seed``."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise InvalidArgumentType(f"seed: {plain(seed)} is not a valid integer")
    if not 0 <= seed <= MAX_SEED:
        raise InvalidArgument(f"seed: {plain(seed)} is not in the range 0<=x<={MAX_SEED}")


def check_path(name: str, value: Any) -> None:
    """Refuse ``value`` unless it is a path (a str or os.PathLike), naming the argument ``name``."""
    if not isinstance(value, (str, os.PathLike)):
        raise InvalidArgumentType(f"{name}: expected a file or folder path, got {type(value).__name__}")


def track_sequence(
    input_path: str | Path, config: Config, queries: str | os.PathLike | np.ndarray | None = None, seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[Tracks, Any]:
    """Track ``input_path`` (a frame folder, a multi-page TIFF or a video) with a validated ``config``: the path of ``condtrack track``.

    Returns the tracks and the opened frame source (for an overlay).

    ``queries``: a CSV path, an (N, 3) array of ``frame, x, y`` rows, or None
    (detect on frame 0). ``progress(done, total)`` is called after each frame the run reads: ``total``
    counts the forward pass's frames and the backward pass's (the frames up to the last query frame).
    """
    check_seed(seed)
    seed = int(seed)  # np.int32(3) or np.uint8(3) is the seed 3, written as the file's int64 like any seed
    given = queries
    frames_stage = config.stage("frames")
    source = registry.get("frames", frames_stage.name).build(frames_stage.settings, str(input_path))
    info = source.info
    config.check_fits_frame(info.width, info.height, detecting=queries is None, where=info.input)
    if queries is None or isinstance(queries, (str, os.PathLike)):
        queries = read_queries(queries, info) if queries is not None else None
    else:
        queries = queries_from_rows(queries, info)
    block, floor, policy = trackability_settings(config.stage("detect").settings)
    if queries is not None and policy != "keep":  # the trackability test (issue 29): drop and error act before tracking
        queries, _ = screen_queries(queries, query_scores(source, queries, block), floor, policy)
    last = pipeline.backward_start(config, queries)
    backward_frames = last + 1 if last else 0
    on_frame = None
    if progress is not None:
        total, done = info.n_frames + backward_frames, itertools.count(1)

        def on_frame(index: int, estimate: types.FrameEstimate) -> None:
            progress(next(done), total)

    max_std = config.output.max_std
    result = pipeline.run(source, info, config, queries, seed=seed, on_frame=on_frame)  # scores queries on the way
    screen_queries(result.queries, result.trackability, floor, "keep")  # keep's warning (the others screened above)
    result = trusted(result, max_std)
    attributes = {"config": config.to_yaml(), "method": config.method, "seed": seed,
                  "config_hash": config_hash(config), "queries_hash": queries_hash(given), "smoothed": config.smooth,
                  "max_std": float("inf") if max_std is None else float(max_std)}
    return Tracks(result, info, config, attributes), source


def track(
    source: str | Path, queries: str | os.PathLike | np.ndarray | None = None, method: str | None = None,
    config: str | os.PathLike | Mapping[str, Any] | None = None, seed: int = 0,
    progress: bool | Callable[[int, int], None] = False, untrackable: str | None = None,
    max_std: float | None = None, forward_only: bool = False,
) -> Tracks:
    """Track points through ``source``, a folder of frames, a multi-page TIFF or a video file.

    queries: a CSV path (``frame,x,y[,point_id]``), an (N, 3) array of
    ``frame, x, y`` rows (point ids 0..N-1), or None to detect points on frame 0.
    method: a registered tracking method (overrides ``filter.method``).
    config: a YAML path or a nested mapping with the YAML's sections, validated
    like ``condtrack track -c`` (same errors). seed: 0 .. ``MAX_SEED``. progress: True for the command line's
    progress bar (on a terminal), or a callable ``progress(done, total)`` called after
    each frame read (``total``: the forward pass's frames plus the backward pass's).
    max_std: rows whose standard deviation along their covariance's major axis exceeds this many
    pixels are reported not visible (``output.max_std``, ``condtrack track --max-std``).
    forward_only: track each point from its query frame on only, with no rows before it
    (``output.backward: false``, ``condtrack track --forward-only``).
    untrackable: what to do with queries whose Shi-Tomasi score is at or below ``detect.min_eigenvalue``
    (overrides ``detect.untrackable``, as ``condtrack track --untrackable``): "keep" (tracked, with a
    warning; the default), "drop" (left out of the result, the others keep their point ids) or "error"
    (raise). The scores are in ``Tracks.trackability``.
    Raises :class:`condtrack_cli.CondtrackError` on bad input (a bad argument value or type: its subclasses
    ``InvalidArgument``, a ValueError, and ``InvalidArgumentType``, a TypeError); what the command
    line prints as ``warning:`` lines are :class:`condtrack_cli.CondtrackWarning` warnings.

    >>> import condtrack_cli as ct
    >>> done = []
    >>> t = ct.track("sample_sequences/occlusion", method="stk", progress=lambda k, n: done.append((k, n)))
    >>> t.xy.shape, done[0], done[-1]  # points detected on frame 0: no backward pass, 30 frames in all
    ((209, 30, 2), (1, 30), (30, 30))
    """
    check_path("source", source)
    progress, forward_only, method = map(python_value, (progress, forward_only, method))  # np.bool_(True) is True
    if not (isinstance(progress, bool) or callable(progress)):
        raise InvalidArgumentType(f"progress: expected True, False or a callable(done, total), got {type(progress).__name__}")
    if untrackable is not None and not isinstance(untrackable, str):
        raise InvalidArgumentType(f"untrackable: expected one of {', '.join(POLICIES)}, got {type(untrackable).__name__}")
    if untrackable is not None and untrackable not in POLICIES:
        raise InvalidArgument(f"untrackable: {plain(untrackable)} is not one of {', '.join(POLICIES)}")
    if not isinstance(forward_only, bool):
        raise InvalidArgumentType(f"forward_only: expected True or False, got {type(forward_only).__name__}")
    if method is not None and not isinstance(method, str):
        raise InvalidArgumentType(f"method: expected a method name (str), got {type(method).__name__}")
    options = {name: override for name, override, given in (
        ("untrackable", f"detect.untrackable={untrackable}", untrackable is not None),
        ("max_std", f"output.max_std={yaml_scalar(python_value(max_std))}", max_std is not None),
        ("forward_only", "output.backward=false", forward_only)) if given}
    with Progress() if progress is True else contextlib.nullcontext(progress or None) as callback:
        tracks, _ = track_sequence(source, load_config(config, (), method, options), queries, seed, callback)
    return tracks


def read_tracks(path: str | Path) -> Tracks:
    """Read a .csv, .h5 or .hdf5 track file back into :class:`Tracks`.

    An HDF5 file gives back its sequence, config and run attributes, and its particles and segmentation when it
    holds them (``t.result.extras``); a CSV holds none of them (``config`` is None, ``info`` has the frame count
    only) nor the measurements. A config this version does not take (another version's, with a key since renamed or
    removed) is left out with a warning (``config`` None).

    >>> import numpy as np
    >>> import condtrack_cli as ct
    >>> t = ct.track("sample_sequences/occlusion", queries="sample_sequences/occlusion/queries.csv", method="clf")
    >>> t.to_hdf5("occlusion.h5")
    >>> back = ct.read_tracks("occlusion.h5")
    >>> np.array_equal(back.xy, t.xy, equal_nan=True), back.config == t.config, back.info.width
    (True, True, 320)
    """
    check_path("path", path)
    result, meta = io_read.read_tracks(path)
    result = replace(result, extras=io_read.stored_extras(Path(path), result))
    info = types.SequenceInfo(
        input=str(meta.get("input", "")), width=int(meta.get("width", 0)), height=int(meta.get("height", 0)),
        n_frames=result.xy.shape[1], fps=float(meta.get("fps", 0.0)),
    )
    config = stored_config(path, meta)
    attributes = {key: python_value(meta[key]) for key in RUN_ATTRIBUTES if key in meta}  # h5py's np.int64: int
    return Tracks(result, info, config, attributes)
