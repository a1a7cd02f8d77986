"""Ground truth for ``condtrack eval``: readers, TAP-Vid coordinates, and alignment with a prediction.

Pixel convention (ours, every position here): x to the right, y down, in pixels,
origin at the *centre* of the top-left pixel. TAP-Vid stores positions
normalised to [0, 1] in raster coordinates, where the top-left *corner* of the
image is (0, 0), the bottom-right corner (1, 1), and pixel centres sit at
(j + 0.5) / W, (i + 0.5) / H. Hence x_ours = x_norm * W - 0.5 and
y_ours = y_norm * H - 0.5 (``tapvid_to_pixels``, inverse ``pixels_to_tapvid``).

Ground-truth CSV: a header naming at least ``point_id,frame,x,y,visible`` (any
order, other columns ignored), one row per point per frame that has ground
truth. A missing row means "no ground truth for that frame": the frame is not
scored. ``visible`` is 0 or 1; x and y must be finite on visible rows and may be
``nan`` on occluded ones.

Before scoring, ``check_queries`` makes sure the ids mean the same points: each
predicted point's query (HDF5: its ``/queries`` row; CSV: its first row) must lie
within ``QUERY_TOLERANCE_PX`` of the ground truth on the query frame wherever the
truth has the point visible there. Points detected on frame 0 (no ``-p``) are
numbered 0.., and their ids coincide with the truth's by chance only. A CSV holds
no queries: a two-way run's first row is the backward pass's frame 0, not the
query, so a CSV point whose first row is off also passes when another of its rows
(the query row among them) lies within the tolerance of the truth; ``score_tracks(queries=...)``
(``eval --queries``) gives a CSV's points their queries instead.

Matching a prediction to the ground truth (``align``) is by ``point_id``:
predicted points absent from the GT are not scored and are listed in
``Aligned.unscored_ids``; GT points absent from the prediction (no row at all)
are not scored and are listed in ``Aligned.missing_ids``, both for the caller to report. Both sides are padded to the
longer frame count: GT frames beyond the prediction count as frames without a
predicted position (not visible, not within any threshold), predicted frames
beyond the GT are not scored.
"""

from __future__ import annotations

import csv
import importlib
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from condtrack_cli.errors import CondtrackError, read_error
from condtrack_cli.io.read import number_column, refuse_sparse, repeated_rows
from condtrack_cli.queries import whole_number
from condtrack_cli.types import Tracks

#: Columns a ground-truth CSV must have.
GT_COLUMNS = ("point_id", "frame", "x", "y", "visible")

#: Largest distance (px) between a predicted point's query and its ground truth on the query frame
#: (queries rounded to whole pixels pass: at most 0.71 px away).
QUERY_TOLERANCE_PX = 1.0


@dataclass(frozen=True)
class GroundTruth:
    """Ground-truth tracks of G points over F frames, in our pixel convention.

    point_id: (G,) int64, sorted, unique.
    gt_xy: (G, F, 2) float64 pixels; NaN where unknown (and possibly where occluded).
    visible: (G, F) bool; False where unknown.
    known: (G, F) bool; False where the GT has no row for the frame (not scored).
    """

    point_id: np.ndarray
    gt_xy: np.ndarray
    visible: np.ndarray
    known: np.ndarray


@dataclass(frozen=True)
class Aligned:
    """A prediction and its ground truth on their P common points and F common frames.

    point_id: (P,) int64 sorted. query_frame: (P,) int64, the prediction's query
    frame (HDF5: its /queries; CSV: the point's first row).
    pred_xy: (P, F, 2), NaN where no position; pred_visible: (P, F) bool;
    pred_cov: (P, F, 2, 2) px^2; pred_dof: (P, F) Student-t nu (inf: Gaussian).
    gt_xy: (P, F, 2); gt_visible, gt_known: (P, F) bool (as in ``GroundTruth``).
    missing_ids: (M,) int64 GT points that the prediction does not have.
    unscored_ids: (U,) int64 predicted points (with a position) that the GT does not have: not scored.
    """

    point_id: np.ndarray
    query_frame: np.ndarray
    pred_xy: np.ndarray
    pred_visible: np.ndarray
    pred_cov: np.ndarray
    pred_dof: np.ndarray
    gt_xy: np.ndarray
    gt_visible: np.ndarray
    gt_known: np.ndarray
    missing_ids: np.ndarray
    unscored_ids: np.ndarray


def tapvid_to_pixels(points: np.ndarray, width: int, height: int) -> np.ndarray:
    """(..., 2) TAP-Vid normalised (x, y) -> (..., 2) pixels in our convention (new array)."""
    return np.asarray(points, np.float64) * np.array([width, height], np.float64) - 0.5


def pixels_to_tapvid(xy: np.ndarray, width: int, height: int) -> np.ndarray:
    """(..., 2) pixels in our convention -> (..., 2) TAP-Vid normalised (x, y) (new array)."""
    return (np.asarray(xy, np.float64) + 0.5) / np.array([width, height], np.float64)


def _refuse_rows(mask: np.ndarray, lines: np.ndarray, path: Path, what: str) -> None:
    """CondtrackError naming the first line where ``mask`` (N,) is True."""
    if mask.any():
        raise CondtrackError(f"{path}: line {lines[np.argmax(mask)]}: {what}")


def _whole_column(cells: np.ndarray, lines: np.ndarray, path: Path, what: str) -> np.ndarray:
    """(N,) str ``cells`` as exact int64 (``12``, and ``12.0`` or ``1.2e1`` too, never through a float, which rounds
    ids above 2^53 and overflows beyond 2^63); CondtrackError ``what`` naming the line of the first other cell."""
    try:
        return cells.astype(np.int64)  # plain integers, the usual file: exact and vectorised
    except (ValueError, OverflowError):
        pass
    values = np.empty(len(cells), np.int64)
    for index, cell in enumerate(cells):
        try:
            values[index] = whole_number(str(cell))
        except ValueError as error:
            raise CondtrackError(f"{path}: line {lines[index]}: {what}: {str(cell).strip()!r} {error}") from None
    return values


def load_gt_csv(path: str | Path) -> GroundTruth:
    """Read a ground-truth CSV (see the module docstring); F = last frame with a row + 1.

    Raises CondtrackError naming the file, line and column on any problem.
    """
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:  # -sig: a spreadsheet's byte-order mark
            rows = list(csv.reader(f))
    except UnicodeDecodeError:
        raise CondtrackError(f"{path}: not a text CSV; the ground truth is a CSV with the columns "
                             f"{','.join(GT_COLUMNS)} (or a TAP-Vid pickle, with --gt-format tapvid)") from None
    except (OSError, csv.Error) as error:
        raise read_error(error, f"{path}: cannot read the ground truth ({error})") from None
    header = [name.strip() for name in rows[0]] if rows else []
    absent = [name for name in GT_COLUMNS if name not in header]
    if absent:
        raise CondtrackError(
            f"{path}: ground-truth column(s) {', '.join(absent)} missing from the header "
            f"(expected {','.join(GT_COLUMNS)})"
        )
    body = [(number, row) for number, row in enumerate(rows[1:], start=2) if row]
    if not body:
        raise CondtrackError(f"{path}: no ground-truth rows")
    wrong = next(((number, row) for number, row in body if len(row) != len(header)), None)
    if wrong is not None:
        raise CondtrackError(f"{path}: line {wrong[0]} has {len(wrong[1])} fields, the header {len(header)}")
    lines = np.array([number for number, _ in body])  # (N,) file line of each row
    table = np.array([row for _, row in body], dtype=str)  # (N, C)
    values = {name: number_column(table[:, header.index(name)], np.float64, lines, path, name)
              for name in ("x", "y", "visible")}
    pid = _whole_column(table[:, header.index("point_id")], lines, path, "point_id is not an integer")
    frame = _whole_column(table[:, header.index("frame")], lines, path, "frame is not a non-negative integer")
    vis = values["visible"]
    xy = np.stack([values["x"], values["y"]], axis=-1)  # (N, 2)
    _refuse_rows(frame < 0, lines, path, "frame is not a non-negative integer")
    _refuse_rows((vis != 0) & (vis != 1), lines, path, "visible is not 0 or 1")
    _refuse_rows(np.isinf(xy).any(axis=1), lines, path, "x or y is infinite")
    _refuse_rows((vis == 1) & np.isnan(xy).any(axis=1), lines, path, "a visible row needs finite x and y")

    point_id, point_index = np.unique(pid, return_inverse=True)
    refuse_sparse(path, frame, lines, len(point_id))
    n_points, n_frames = len(point_id), int(frame.max()) + 1
    _refuse_rows(repeated_rows(point_index, frame), lines, path, "a second row for the same point_id and frame")

    gt_xy = np.full((n_points, n_frames, 2), np.nan)
    visible = np.zeros((n_points, n_frames), bool)
    known = np.zeros((n_points, n_frames), bool)
    gt_xy[point_index, frame] = xy
    visible[point_index, frame] = vis == 1
    known[point_index, frame] = True
    return GroundTruth(point_id, gt_xy, visible, known)


def _single_video(data: object, path: Path) -> dict:
    """The one TAP-Vid video dict in ``data``: the dict itself, or the only entry of a dict or list of them."""
    if isinstance(data, dict) and "points" in data:
        return data
    if isinstance(data, dict):
        videos, names = list(data.values()), [str(name) for name in data]
    elif isinstance(data, (list, tuple)):
        videos, names = list(data), [f"#{i}" for i in range(len(data))]
    else:
        raise CondtrackError(f"{path}: not a TAP-Vid pickle (a {type(data).__name__}, expected a dict)")
    if len(videos) != 1:
        shown = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
        raise CondtrackError(
            f"{path}: holds {len(videos)} videos ({shown}); evaluate one video at a time "
            "(save the one you tracked in its own pickle)"
        )
    if not isinstance(videos[0], dict) or "points" not in videos[0]:
        raise CondtrackError(f"{path}: the video {names[0]} is not a TAP-Vid video dict")
    return videos[0]


def _frame_size(video: object, path: Path) -> tuple[int, int]:
    """(width, height) of a TAP-Vid ``video``: an (F, H, W, 3) array or a sequence of encoded frames."""
    first = video[0] if isinstance(video, (list, tuple, np.ndarray)) and len(video) else None
    if isinstance(first, bytes):
        import cv2

        image = cv2.imdecode(np.frombuffer(first, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is not None:
            return int(image.shape[1]), int(image.shape[0])
    else:
        try:
            shape = np.shape(video)
        except ValueError:  # a list of frames of unequal sizes: numpy's "inhomogeneous shape"
            shape = ()
        if len(shape) == 4:
            return int(shape[2]), int(shape[1])
    raise CondtrackError(f"{path}: 'video' is neither an (F, H, W, 3) array nor a list of encoded frames")


#: The only globals a TAP-Vid pickle may name: NumPy's array, dtype and scalar rebuilders (under ``numpy.core``
#: when NumPy 1 wrote the file, ``numpy._core`` for NumPy 2) and the bytes decoder of pickle protocols 0-2.
_PICKLE_GLOBALS = {
    "numpy": {"ndarray", "dtype"}, "multiarray": {"_reconstruct", "scalar"}, "numeric": {"_frombuffer"},
    "_codecs": {"encode"},
}


class _ArraysOnly(pickle.Unpickler):
    """An unpickler of NumPy arrays, dicts, lists, tuples, strings, bytes and numbers only: a pickle naming any other
    callable (``os.system`` in a crafted ``__reduce__``) is refused before anything is called."""

    def find_class(self, module: str, name: str):
        package, _, leaf = module.rpartition(".")
        key = leaf if package in ("numpy.core", "numpy._core") else module
        if name not in _PICKLE_GLOBALS.get(key, ()):
            raise pickle.UnpicklingError(f"refused: it names {module}.{name}, neither a NumPy array nor a plain value")
        if key in ("numpy", "_codecs"):
            return super().find_class(module, name)
        try:  # the installed NumPy's own module: numpy.core is a deprecated alias in NumPy 2
            return getattr(importlib.import_module(f"numpy._core.{key}"), name)
        except ImportError:
            return getattr(importlib.import_module(f"numpy.core.{key}"), name)


def _numbers(video: dict, key: str, path: Path, kinds: str) -> np.ndarray:
    """``video[key]`` as an array of one of the NumPy ``kinds`` (``'iuf'``: integers or floats, ``'b'`` booleans);
    CondtrackError naming the entry for strings, objects, complex numbers or ragged lists."""
    try:
        array = np.asarray(video[key])
    except ValueError:  # ragged nested lists
        raise CondtrackError(f"{path}: '{key}' is not an array (lists of unequal lengths?)") from None
    if array.dtype.kind not in kinds:
        raise CondtrackError(f"{path}: '{key}' holds {array.dtype} values, not numbers")
    return array


def load_gt_tapvid(path: str | Path) -> GroundTruth:
    """Read TAP-Vid ground truth from a pickle (one video) and convert it to our pixel convention.

    The pickle holds a dict with ``video`` (F, H, W, 3) uint8 (or a list of
    JPEG/PNG-encoded frames, as in TAP-Vid-Kinetics), ``points`` (P, F, 2)
    normalised (x, y) numbers and ``occluded`` (P, F) bool (or 0/1 numbers); or a dict (or list) of such
    videos, of which there must be exactly one. Every frame of every point is
    known; ``point_id`` is the row index 0..P-1; a visible point's x and y must be
    finite (as a CSV row's). The pickle is read by
    :class:`_ArraysOnly`: a file naming anything but NumPy arrays, dicts, lists,
    strings and numbers is refused before any of it runs.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            data = _ArraysOnly(f).load()
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ImportError, ValueError, TypeError) as error:
        raise read_error(error, f"{path}: cannot read the TAP-Vid pickle ({error})") from None
    video = _single_video(data, path)
    for key in ("video", "points", "occluded"):
        if key not in video:
            raise CondtrackError(f"{path}: the TAP-Vid video has no '{key}' entry")
    width, height = _frame_size(video["video"], path)
    points = _numbers(video, "points", path, "iuf")
    occluded = _numbers(video, "occluded", path, "biuf")
    if not np.isin(occluded, (0, 1)).all():
        raise CondtrackError(f"{path}: 'occluded' holds values other than true/false (0 or 1)")
    occluded = occluded.astype(bool)
    if points.ndim != 3 or points.shape[2] != 2 or occluded.shape != points.shape[:2]:
        raise CondtrackError(
            f"{path}: 'points' {points.shape} and 'occluded' {occluded.shape} are not (P, F, 2) and (P, F)"
        )
    with np.errstate(over="ignore"):  # a normalised 1e308 is no pixel either: refused below, with no warning
        gt_xy = tapvid_to_pixels(points, width, height)
    bad = ~occluded & ~np.isfinite(gt_xy).all(axis=2)
    if bad.any():
        point, frame = np.argwhere(bad)[0]
        raise CondtrackError(f"{path}: point {point}, frame {frame}: a visible point needs finite x and y "
                             f"(got {points[point, frame, 0]}, {points[point, frame, 1]})")
    return GroundTruth(np.arange(len(points), dtype=np.int64), gt_xy, ~occluded, np.ones(occluded.shape, bool))


def _pad_frames(array: np.ndarray, n_frames: int, fill: float | bool) -> np.ndarray:
    """(P, F, ...) -> (P, n_frames, ...) with ``fill`` after frame F (n_frames >= F)."""
    pad = [(0, 0), (0, n_frames - array.shape[1])] + [(0, 0)] * (array.ndim - 2)
    return np.pad(array, pad, constant_values=fill)


def align(pred: Tracks, gt: GroundTruth) -> Aligned:
    """Match ``pred`` to ``gt`` by point_id, on max(F_pred, F_gt) frames (see the module docstring).

    A predicted point without any position counts as absent from the prediction,
    as it would in a CSV. Raises CondtrackError when the prediction repeats a
    point_id or shares none with the GT.
    """
    ids = np.asarray(pred.queries.point_id, np.int64)
    if len(np.unique(ids)) != len(ids):
        raise CondtrackError("the prediction has a repeated point_id")
    present = pred.has_state.any(axis=1)  # (P_pred,)
    common, pred_index, gt_index = np.intersect1d(ids[present], gt.point_id, return_indices=True)
    if not len(common):
        raise CondtrackError(
            f"no point_id in common between the prediction ({int(present.sum())} points) "
            f"and the ground truth ({len(gt.point_id)} points)"
        )
    pred_index = np.flatnonzero(present)[pred_index]
    n_frames = max(pred.xy.shape[1], gt.gt_xy.shape[1])
    pred_xy = _pad_frames(pred.xy[pred_index], n_frames, np.nan)
    return Aligned(
        point_id=common,
        query_frame=np.asarray(pred.queries.frame, np.int64)[pred_index],
        pred_xy=pred_xy,
        pred_visible=_pad_frames(pred.visible[pred_index], n_frames, False),
        pred_cov=_pad_frames(pred.cov[pred_index], n_frames, np.nan),
        pred_dof=_pad_frames(pred.dof[pred_index], n_frames, np.nan),
        gt_xy=_pad_frames(gt.gt_xy[gt_index], n_frames, np.nan),
        gt_visible=_pad_frames(gt.visible[gt_index], n_frames, False),
        gt_known=_pad_frames(gt.known[gt_index], n_frames, False),
        missing_ids=np.setdiff1d(gt.point_id, common),
        unscored_ids=np.setdiff1d(ids[present], common),
    )


def check_queries(pred: Tracks, gt: GroundTruth, tolerance: float = QUERY_TOLERANCE_PX, *,
                  any_row: bool = False) -> None:
    """Refuse a prediction whose queries are not on the ground truth of the same point_id (module docstring).

    Points without any position, absent from the truth, or whose truth is not
    visible on their query frame are not checked. ``any_row`` (a CSV, whose
    queries are its first rows): a point also passes when any of its rows lies
    within ``tolerance`` px of its visible truth. CondtrackError names the first
    point_id whose query is more than ``tolerance`` px from its truth.
    """
    present = pred.has_state.any(axis=1)
    ids = np.asarray(pred.queries.point_id, np.int64)[present]
    _, pred_index, gt_index = np.intersect1d(ids, gt.point_id, return_indices=True)
    pred_index = np.flatnonzero(present)[pred_index]
    frame = np.asarray(pred.queries.frame, np.int64)[pred_index]
    on_truth = frame < gt.gt_xy.shape[1]
    frame, query_xy = frame[on_truth], np.asarray(pred.queries.xy, np.float64)[pred_index[on_truth]]
    gt_index = gt_index[on_truth]
    truth_xy = gt.gt_xy[gt_index, frame]
    distance = np.linalg.norm(query_xy - truth_xy, axis=1)
    wrong = gt.visible[gt_index, frame] & ~(distance <= tolerance)
    if any_row:
        shared = min(pred.xy.shape[1], gt.gt_xy.shape[1])
        rows = pred.xy[pred_index[on_truth], :shared] - gt.gt_xy[gt_index, :shared]  # (P', F', 2), NaN off the rows
        wrong &= ~(gt.visible[gt_index, :shared] & (np.hypot(rows[..., 0], rows[..., 1]) <= tolerance)).any(axis=1)
    if wrong.any():
        i = int(np.argmax(wrong))
        raise CondtrackError(
            f"point_id {gt.point_id[gt_index[i]]}: the prediction's query on frame {frame[i]} "
            f"({query_xy[i, 0]:.2f}, {query_xy[i, 1]:.2f}) is {distance[i]:.2f} px from the ground truth "
            f"({truth_xy[i, 0]:.2f}, {truth_xy[i, 1]:.2f}), more than {tolerance:g} px"
            + (", as are its other rows" if any_row else "") + ": track from the ground "
            "truth's queries (-p); detected points are numbered 0.. and their ids mean nothing to the truth"
        )
