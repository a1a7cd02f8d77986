"""Read track files written by condtrack (CSV or HDF5) back into :class:`Tracks`.

A CSV holds no frame count: its tracks span frames 0 .. the last frame that has
a row. Nor does it hold queries: a point's query is taken to be its first row
(frame 0 once backward tracking filled the frames before the query). A CSV
whose header is not the schema's exact header line, with a negative frame or a
second row for one (point_id, frame), with frames far past what its rows fill
(``CELLS_PER_ROW``), and an HDF5 file of an unknown
``schema_version`` or with a value a CSV row is refused for (a negative variance, a dof not above 2, ...; also
repeated point ids and queries that are no frame and position), are refused (docs/schema.md). Files of schema 1.0 (no
``dof`` column or dataset, no ``/tracks/trackability``) are read as Gaussian
(dof inf where a row exists) with trackability NaN (unknown). h5py is imported
only by the functions that open an HDF5 file (start-up time, issue 13).
"""

from __future__ import annotations

import codecs
import contextlib
import numbers
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from condtrack_cli import READABLE_SCHEMA_VERSIONS
from condtrack_cli.errors import CondtrackError, MissingInput, counted, plain, warn
from condtrack_cli.io.formats import is_hdf5, track_format
from condtrack_cli.io.write import CSV_COLUMNS, CSV_COLUMNS_1, EXTRA_ATTRIBUTES
from condtrack_cli.registry import BUILTIN_METHOD_CODES, method_codes
from condtrack_cli.types import Queries, SequenceInfo, Tracks


#: A CSV's tracks become dense (P, F) arrays, about 100 bytes a cell: a file is refused when that would take more
#: than ``CELLS_PER_ROW`` cells per row and more than ``DENSE_SLACK`` cells in all (two rows with frame 100000000
#: took 9.5 GiB). A condtrack CSV has one row per cell; one with only the visible rows has a few cells per row.
CELLS_PER_ROW = 16
DENSE_SLACK = 2**20


def repeated_rows(point_id: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """(N,) bool: the rows whose (point_id, frame) pair an earlier row already has."""
    order = np.lexsort((frame, point_id))  # stable: the first of equal rows stays unmarked
    repeated = np.zeros(len(frame), bool)
    repeated[order[1:]] = (point_id[order[1:]] == point_id[order[:-1]]) & (frame[order[1:]] == frame[order[:-1]])
    return repeated


def refuse_sparse(path: Path, frames: np.ndarray, lines: np.ndarray, n_points: int) -> None:
    """CondtrackError when (``n_points``, last frame + 1) arrays would have more cells than the ``frames`` (N,) rows
    fill (``CELLS_PER_ROW``), naming the line of the last frame; called before the arrays are made."""
    if len(frames) and n_points * (int(frames.max()) + 1) > max(CELLS_PER_ROW * len(frames), DENSE_SLACK):
        last = int(np.argmax(frames))
        raise CondtrackError(
            f"{path}: line {lines[last]} has frame {int(frames[last])}, but the file has {len(frames)} rows for "
            f"{n_points} points: too few to fill its frames (a row per point and frame is expected)")


def number_column(cells: np.ndarray, dtype: type, lines: np.ndarray, path: Path, name: str) -> np.ndarray:
    """(N,) str ``cells`` of column ``name`` as ``dtype``; CondtrackError naming the file line of the first bad cell."""
    try:
        return cells.astype(dtype)
    except (ValueError, OverflowError):
        bad = next(i for i, cell in enumerate(cells) if not _parses(cell, dtype))
        kind = "a whole number (64-bit)" if np.issubdtype(dtype, np.integer) else "a number"
        raise CondtrackError(f"{path}: line {lines[bad]}, column '{name}': {str(cells[bad])!r} is not {kind}") from None


def _parses(cell: str, dtype: type) -> bool:
    try:
        np.array([cell]).astype(dtype)
    except (ValueError, OverflowError):
        return False
    return True


def _read_csv(path: Path) -> tuple[Tracks, dict[str, Any]]:
    try:
        lines = path.read_bytes().removeprefix(codecs.BOM_UTF8).decode("ascii").splitlines()  # BOM: a spreadsheet's
    except OSError as error:
        raise CondtrackError(f"{path}: cannot read the track file ({error})") from None
    except UnicodeDecodeError as error:
        raise CondtrackError(f"{path}: not a condtrack CSV (byte {error.object[error.start]:#04x} at offset "
                             f"{error.start} is not ASCII)") from None
    header = tuple(lines[0].split(",")) if lines else ()
    if header not in (CSV_COLUMNS, CSV_COLUMNS_1):
        raise CondtrackError(f"{path}: not a condtrack CSV (expected the header {','.join(CSV_COLUMNS)})")
    numbered = [(number, line.split(",")) for number, line in enumerate(lines[1:], start=2) if line]
    wrong = next(((number, row) for number, row in numbered if len(row) != len(header)), None)
    if wrong is not None:
        raise CondtrackError(f"{path}: line {wrong[0]} has {len(wrong[1])} fields, expected {len(header)}")
    line_of = np.array([number for number, _ in numbered], dtype=np.int64)  # (N,) file line of each row
    table = np.array([row for _, row in numbered], dtype=str).reshape(-1, len(header))
    column = {
        name: number_column(table[:, i], np.int64 if name in ("point_id", "frame", "visible") else np.float64,
                            line_of, path, name)
        for i, name in enumerate(header[:-1])
    }
    ids, frames, visible = column["point_id"], column["frame"], column["visible"]
    row_dof = column.get("dof", np.full(len(ids), np.inf))  # schema 1.0: Gaussian
    values = np.column_stack([column[name] for name in ("x", "y", "cov_xx", "cov_xy", "cov_yy")])
    for bad, what in ((frames < 0, "frame is negative"), ((visible != 0) & (visible != 1), "visible is not 0 or 1"),
                      (~np.isfinite(values[:, :2]).all(axis=1), "x, y is {x}, {y}: a row is a position, always finite"),
                      ((values[:, 2] < 0) | (values[:, 4] < 0), "cov_xx, cov_yy is {cov_xx}, {cov_yy}: a variance is "
                       "never negative"),
                      (np.isnan(values[:, 2:]).any(axis=1) & ~np.isnan(values[:, 2:]).all(axis=1),
                       "cov_xx, cov_xy, cov_yy is {cov_xx}, {cov_xy}, {cov_yy}: a covariance is undefined (nan) as a "
                       "whole or not at all"),
                      (~(row_dof > 2), "dof is {dof}, expected a number above 2 or inf (Gaussian)"),
                      (repeated_rows(ids, frames), "a second row for the same point_id and frame")):
        if bad.any():
            row = int(np.argmax(bad))
            cells = dict(zip(header, table[row]))  # the row's text, for a message showing the value read
            raise CondtrackError(f"{path}: line {line_of[row]} (point_id {ids[row]}, frame {frames[row]}): "
                                 + what.format_map(cells))
    visible = visible.astype(bool)
    method = _codes_of(path, table[:, -1])
    point_ids, first_row, point_index = np.unique(ids, return_index=True, return_inverse=True)
    n_points, n_frames = len(point_ids), (int(frames.max()) + 1 if len(frames) else 0)
    refuse_sparse(path, frames, line_of, n_points)
    xy = np.full((n_points, n_frames, 2), np.nan)
    cov = np.full((n_points, n_frames, 2, 2), np.nan)
    dof = np.full((n_points, n_frames), np.nan)
    vis = np.zeros((n_points, n_frames), bool)
    codes = np.full((n_points, n_frames), -1, np.int8)
    xy[point_index, frames] = values[:, :2]
    cov[point_index, frames] = values[:, [2, 3, 3, 4]].reshape(-1, 2, 2)
    dof[point_index, frames] = row_dof
    vis[point_index, frames] = visible
    codes[point_index, frames] = method
    first_frame = np.full(n_points, np.iinfo(np.int64).max)
    np.minimum.at(first_frame, point_index, frames)
    queries = Queries(point_ids, first_frame, xy[np.arange(n_points), first_frame])
    empty = np.full_like(xy, np.nan)
    tracks = Tracks(queries, xy, cov, dof, vis, codes, empty, np.full_like(cov, np.nan))
    return tracks, {"n_frames": n_frames}


def _codes_of(path: Path, names: np.ndarray) -> np.ndarray:
    """int8 codes (indices into ``registry.method_codes()``) of method ``names``; CondtrackError for an unregistered one."""
    codes = method_codes()
    unknown = set(np.unique(names)) - set(codes)
    if unknown:
        raise CondtrackError(f"{path}: unknown method {plain(sorted(unknown)[0])}; valid: {', '.join(codes)}")
    return np.select([names == name for name in codes], np.arange(len(codes))).astype(np.int8)


def _check_layout(tracks: Tracks) -> None:
    """ValueError when arrays read from an HDF5 file depart from the schema's shapes, float types or method codes."""
    p, f = len(tracks.queries), (tracks.xy.shape[1] if tracks.xy.ndim == 3 else -1)
    for name, array, shape in (
        ("xy", tracks.xy, (p, f, 2)), ("cov", tracks.cov, (p, f, 2, 2)), ("dof", tracks.dof, (p, f)),
        ("visible", tracks.visible, (p, f)),
        ("method_code", tracks.method, (p, f)), ("z", tracks.z, (p, f, 2)), ("R", tracks.R, (p, f, 2, 2)),
        ("trackability", tracks.trackability, (p,)),
    ):
        if array.shape != shape:
            raise ValueError(f"{name} has shape {array.shape}, expected {shape}")
        if name not in ("visible", "method_code") and array.dtype.kind != "f":  # no NaN (no state) in an integer
            raise ValueError(f"{name} holds {array.dtype} values, not floats")
    if ((tracks.method < -1) | (tracks.method >= len(method_codes()))).any():
        raise ValueError(f"method_code outside -1 .. {len(method_codes()) - 1}")


def _check_queries(point_id: np.ndarray, table: np.ndarray) -> None:
    """ValueError when an HDF5 file's /tracks/point_id (P,) is not P distinct whole numbers, or its /queries is not
    (P, 3) numbers whose first column is frame numbers (whole, >= 0) and whose positions are finite."""
    if point_id.ndim != 1 or point_id.dtype.kind not in "iu":
        raise ValueError(f"point_id holds {point_id.dtype} values of shape {point_id.shape}, expected (P,) whole "
                         "numbers")
    ids, counts = np.unique(point_id, return_counts=True)
    if (counts > 1).any():
        raise ValueError(f"point_id {plain(ids[np.argmax(counts > 1)])} is repeated")
    if table.shape != (len(point_id), 3) or table.dtype.kind not in "iuf":
        raise ValueError(f"queries holds {table.dtype} values of shape {table.shape}, expected ({len(point_id)}, 3) "
                         "numbers")
    frame = table[:, 0]
    bad = ~(np.isfinite(table).all(axis=1) & (frame >= 0) & (frame == np.floor(frame)))
    if bad.any():
        row = int(np.argmax(bad))
        raise ValueError(f"queries row {row} (point_id {plain(point_id[row])}) is {plain(table[row])}: expected a "
                         "frame number (whole, >= 0) and a finite position")


#: Relative difference of a covariance's two off-diagonal entries that a track file may hold: the rounding of the
#: products that made them (files written before 9c8e680 held covariances symmetric to about 1e-16 of their trace).
SYMMETRY_TOLERANCE = 1e-9


def symmetric(cov: np.ndarray) -> np.ndarray:
    """(...) bool: the (..., 2, 2) covariances whose off-diagonal entries are equal, or differ by at most
    ``SYMMETRY_TOLERANCE`` times the sum of the diagonal's magnitudes."""
    with np.errstate(invalid="ignore"):  # inf - inf: not within the tolerance, equal entries aside
        gap = np.abs(cov[..., 0, 1] - cov[..., 1, 0])
        return (cov[..., 0, 1] == cov[..., 1, 0]) | (
            gap <= SYMMETRY_TOLERANCE * (np.abs(cov[..., 0, 0]) + np.abs(cov[..., 1, 1])))


def check_values(tracks: Tracks) -> None:
    """ValueError naming the first point_id and frame whose values an HDF5 file holds where a CSV's row would be
    refused (:func:`_read_csv`): a position partly or not finite, a negative variance, a covariance partly NaN or
    not symmetric, a dof not above 2 where the point has a state; or a query past the tracks' frames."""
    xy, cov, state = tracks.xy, tracks.cov, tracks.has_state
    late = tracks.queries.frame >= xy.shape[1]
    if late.any():
        row = int(np.argmax(late))
        raise ValueError(f"queries row {row} (point_id {plain(tracks.queries.point_id[row])}) has frame "
                         f"{plain(tracks.queries.frame[row])}, past the {xy.shape[1]} frames of xy")
    undefined = np.isnan(cov)
    for name, values, bad, what in (
        ("xy", xy, ~(state | np.isnan(xy).all(axis=-1)), "a position is finite, or NaN (no state) as a whole"),
        ("cov", cov, (cov[..., [0, 1], [0, 1]] < 0).any(axis=-1), "a variance is never negative"),
        ("cov", cov, undefined.any(axis=(-2, -1)) & ~undefined.all(axis=(-2, -1)),
         "a covariance is undefined (NaN) as a whole or not at all"),
        ("cov", cov, ~(symmetric(cov) | (undefined[..., 0, 1] & undefined[..., 1, 0])),
         "its two off-diagonal entries differ (a covariance matrix is symmetric)"),
        ("dof", tracks.dof, state & ~(tracks.dof > 2), "expected a number above 2 or inf (Gaussian) where the point "
         "has a state"),
    ):
        if bad.any():
            p, k = np.unravel_index(int(np.argmax(bad)), bad.shape)
            raise ValueError(f"{name} at point_id {plain(tracks.queries.point_id[p])}, frame {k} is "
                             f"{plain(values[p, k])}: {what}")


def _check_attributes(meta: dict[str, Any], n_frames: int) -> None:
    """ValueError when a root attribute that the readers use departs from docs/schema.md: ``n_frames`` the
    ``n_frames`` frames of /tracks/xy, ``width`` and ``height`` (both or neither) whole numbers above 0, ``fps`` a
    finite number >= 0, ``input`` and ``config`` strings. Each may be absent (a file written by hand)."""
    def whole(value: Any) -> bool:
        return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))

    if "n_frames" in meta and not (whole(meta["n_frames"]) and meta["n_frames"] >= 0):
        raise ValueError(f"root attribute 'n_frames' is {plain(meta['n_frames'])}, not a whole number of frames")
    if "n_frames" in meta and meta["n_frames"] != n_frames:
        raise ValueError(f"root attribute 'n_frames' is {plain(meta['n_frames'])}, but /tracks/xy has "
                         f"{counted(n_frames, 'frame')}")
    if ("width" in meta) != ("height" in meta):
        raise ValueError(f"root attribute '{'height' if 'width' in meta else 'width'}' is missing beside the other")
    for key in ("width", "height"):
        if key in meta and not (whole(meta[key]) and meta[key] > 0):
            raise ValueError(f"root attribute '{key}' is {plain(meta[key])}, not a whole number of pixels above 0")
    fps = meta.get("fps", 0.0)
    if not (isinstance(fps, numbers.Real) and not isinstance(fps, (bool, np.bool_)) and 0 <= fps < np.inf):
        raise ValueError(f"root attribute 'fps' is {plain(fps)}, not a finite number >= 0")
    for key in ("input", "config"):
        if key in meta and not isinstance(meta[key], str):
            raise ValueError(f"root attribute '{key}' is {plain(meta[key])}, not a string")


def _read_hdf5(path: Path) -> tuple[Tracks, dict[str, Any]]:
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as error:
        raise CondtrackError(f"{path}: not a readable HDF5 file ({error})") from None
    with f:
        try:
            meta = {key: (value.decode() if isinstance(value, bytes) else value) for key, value in f.attrs.items()}
            version = meta.get("schema_version")
            if version is None:  # another program's HDF5 file (a TAP-Vid or a model's), not a damaged track file
                raise CondtrackError(f"{path}: not a condtrack track file (an HDF5 file without the root attribute "
                                     "'schema_version')")
            if version not in READABLE_SCHEMA_VERSIONS:
                raise CondtrackError(
                    f"{path}: schema_version {plain(version)} is not supported (this condtrack reads "
                    f"{' and '.join(map(repr, READABLE_SCHEMA_VERSIONS))})"
                )
            t = f["tracks"]
            point_ids, queries_table = t["point_id"][()], f["queries"][()]
            _check_queries(point_ids, queries_table)
            queries = Queries(point_ids, queries_table[:, 0].astype(np.int64), queries_table[:, 1:3])
            xy = t["xy"][()]
            nan = np.full(xy.shape, np.nan)  # float whatever xy holds (an integer xy is refused below)
            z = f["measurements/z"][()] if "measurements" in f else nan
            R = f["measurements/R"][()] if "measurements" in f else np.full(xy.shape + (2,), np.nan)
            # the file's code table; without one, the built-in codes (docs/schema.md)
            names = np.array(t["method_code"].attrs.get("names", ",".join(BUILTIN_METHOD_CODES)).split(","))
            file_codes = np.append(_codes_of(path, names), np.int8(-1))  # the file's code -1 (last) stays -1
            has_state = np.isfinite(xy).all(axis=-1)
            before_2 = version == "1.0"  # schema 2.0 added dof and trackability: a 2.0 file without them is incomplete
            dof = np.where(has_state, np.inf, np.nan) if before_2 else t["dof"][()]  # schema 1.0: Gaussian
            scores = np.full(len(queries), np.nan) if before_2 else t["trackability"][()]  # 1.0: unknown, NaN
            tracks = Tracks(queries, xy, t["cov"][()], dof, t["visible"][()].astype(bool),
                            file_codes[t["method_code"][()]], z, R, trackability=scores)
            _check_layout(tracks)
            _check_attributes(meta, xy.shape[1])
            check_values(tracks)
        except (KeyError, OSError, RuntimeError, TypeError, ValueError, IndexError) as error:
            # h5py reports damaged metadata as OSError or RuntimeError
            raise CondtrackError(f"{path}: damaged or incomplete condtrack HDF5 file ({error})") from None
    return tracks, meta


def read_tracks(path: str | Path) -> tuple[Tracks, dict[str, Any]]:
    """Read a .csv, .h5 or .hdf5 track file; CondtrackError naming the file on any problem."""
    path = Path(path)
    if not path.exists():
        raise MissingInput(f"{path}: no such file")
    if not path.is_file():
        raise CondtrackError(f"{path}: not a regular file (a folder?)")
    return _read_csv(path) if track_format(path) == "csv" else _read_hdf5(path)


@contextlib.contextmanager
def stored_particles(path: Path, tracks: Tracks) -> Iterator[Any]:
    """The open ``/particles/xy`` dataset (P, F, N, 2) of an HDF5 track file, or None when it holds none."""
    if not is_hdf5(path):
        yield None
        return
    import h5py

    with h5py.File(path, "r") as f:
        dataset = f.get("particles/xy")
        if dataset is not None and (
            dataset.ndim != 4 or dataset.shape[:2] != tracks.xy.shape[:2] or dataset.shape[3] != 2
        ):
            raise CondtrackError(
                f"{path}: /particles/xy has shape {dataset.shape}, "
                f"expected (P, F, N, 2) with (P, F) = {tracks.xy.shape[:2]}"
            )
        yield dataset


def matched_to_input(tracks: Tracks, meta: dict[str, Any], tracks_path: Path, info: SequenceInfo) -> Tracks:
    """``tracks`` checked against the input; a CSV's tracks (which end at their last row) padded to its length.

    An HDF5 file of another frame size or count is refused. A CSV holds neither:
    it is refused when it has rows past the input's end, and gets a warning
    (:class:`CondtrackWarning`) when it has no row, ends before it or has visible positions outside its frame.
    """
    ours = f"{info.input} has {info.width}x{info.height} px, {counted(info.n_frames, 'frame')}"
    if "width" in meta:
        theirs = (int(meta["width"]), int(meta["height"]), tracks.xy.shape[1])
        if theirs != (info.width, info.height, info.n_frames):
            raise CondtrackError(
                f"{tracks_path} was tracked on {theirs[0]}x{theirs[1]} px, {counted(theirs[2], 'frame')}, but {ours}"
            )
        return tracks
    extra = info.n_frames - tracks.xy.shape[1]
    if extra < 0:
        raise CondtrackError(f"{tracks_path} has rows up to frame {tracks.xy.shape[1] - 1}, but {ours}")
    if not tracks.xy.shape[1]:
        empty = "no track (0 frames)" if is_hdf5(tracks_path) else "no track row (a header only)"
        warn(f"{tracks_path} holds {empty}: no point to show on {info.input}")
    elif extra:
        warn(f"{tracks_path} has rows up to frame {tracks.xy.shape[1] - 1}, but {ours}: was it tracked on another input?")
    shown = tracks.xy[tracks.visible]
    outside = int((np.isfinite(shown).all(axis=-1) & ~info.contains(shown)).sum())
    if outside:
        warn(f"{tracks_path} has {outside} visible position(s) outside the {info.width}x{info.height} frame of "
             f"{info.input}: was it tracked on another input?")

    def pad(array: np.ndarray, fill: Any) -> np.ndarray:
        return np.concatenate([array, np.full((len(array), extra) + array.shape[2:], fill, array.dtype)], axis=1)

    return Tracks(tracks.queries, pad(tracks.xy, np.nan), pad(tracks.cov, np.nan), pad(tracks.dof, np.nan),
                  pad(tracks.visible, False),
                  pad(tracks.method, -1), pad(tracks.z, np.nan), pad(tracks.R, np.nan))


def stored_extras(path: Path, tracks: Tracks) -> dict[str, np.ndarray]:
    """The optional datasets (``Tracks.extras``: ``particles/xy``, ``segmentation``) that the HDF5 track file ``path``
    of ``tracks`` holds, read whole; {} for a CSV. CondtrackError naming the file when one cannot be read."""
    if not is_hdf5(path):
        return {}
    import h5py

    with stored_particles(path, tracks), h5py.File(path, "r") as f:  # stored_particles checks the particles' shape
        try:
            return {name: f[name][()] for name in EXTRA_ATTRIBUTES if name in f}
        except (OSError, RuntimeError, TypeError, ValueError) as error:
            raise CondtrackError(f"{path}: damaged or incomplete condtrack HDF5 file ({error})") from None


def stored_datasets(path: Path) -> tuple[str, str]:
    """('stored' / 'not stored') for the measurements and the particles of a track file."""
    if not is_hdf5(path):
        return "not stored (CSV)", "not stored (CSV)"
    import h5py

    with h5py.File(path, "r") as f:
        measurements = "stored" if "measurements/z" in f else "not stored"
        particles = f.get("particles/xy")
        return measurements, (f"stored, {particles.shape[2]} per point" if particles is not None else "not stored")
