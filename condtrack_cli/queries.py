"""Query points: read from a CSV (``frame,x,y`` and optional ``point_id``) or detected."""

from __future__ import annotations

import csv
import decimal
from pathlib import Path

import numpy as np

from condtrack_cli.errors import CondtrackError, InvalidArgument, InvalidArgumentType, read_error
from condtrack_cli.types import Queries, SequenceInfo

REQUIRED_COLUMNS = ("frame", "x", "y")
#: Columns read as exact 64-bit integers (never through a float, which rounds ids above 2^53).
INTEGER_COLUMNS = ("frame", "point_id")
INT64 = np.iinfo(np.int64)


def whole_number(cell: str) -> int:
    """``cell`` as an exact whole number in the int64 range ('12', '12.0' and '1.2e1' are 12); ValueError saying why not."""
    try:
        number = decimal.Decimal(cell.strip())
    except decimal.InvalidOperation:
        raise ValueError("is not a number") from None
    if not number.is_finite() or number != number.to_integral_value():
        raise ValueError("is not a whole number")
    if not INT64.min <= number <= INT64.max:
        raise ValueError(f"is outside the 64-bit integer range [{INT64.min}, {INT64.max}]")
    return int(number)


def read_queries(path: str | Path, info: SequenceInfo) -> Queries:
    """Queries from ``path``, checked against the sequence; ordered by point_id.

    The header holds ``frame``, ``x``, ``y`` and optionally ``point_id``, in any
    order, each once; any other column is refused (a misspelt ``point_id`` would
    renumber the points), and so is a row with a value beyond the header's columns.
    Without a ``point_id`` column the points are numbered 0.. in file order. A
    point must lie inside the frame ([-0.5, W-0.5] x [-0.5, H-0.5], the pixel
    convention of docs/schema.md; not checked where ``info`` has no size, width 0: a track file's, whose positions
    need only be finite) and its frame in [0, n_frames).
    """
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as handle:  # -sig: a spreadsheet's byte-order mark
            reader = csv.reader(handle)
            rows = [(reader.line_num, row) for row in reader]  # the file's line of each row (a row ends on it)
    except (OSError, UnicodeDecodeError) as error:
        raise read_error(error, f"{path}: cannot read the queries file ({error})") from None
    if not rows:
        raise CondtrackError(f"{path}: empty queries file (expected a header frame,x,y[,point_id])")
    header = [name.strip() for name in rows[0][1]]
    for index, name in enumerate(header):
        if name not in (*REQUIRED_COLUMNS, "point_id"):
            raise CondtrackError(f"{path}: unknown column '{name}' (the header must have frame,x,y[,point_id])")
        if name in header[:index]:
            raise CondtrackError(f"{path}: column '{name}' appears twice in the header")
    for name in REQUIRED_COLUMNS:
        if name not in header:
            raise CondtrackError(f"{path}: missing column '{name}' (the header must have frame,x,y[,point_id])")
    body = [(line, row) for line, row in rows[1:] if any(cell.strip() for cell in row)]  # blank lines skipped
    if not body:
        raise CondtrackError(f"{path}: no query rows")
    lines = np.array([line for line, _ in body], dtype=np.int64)
    for line, row in body:  # a value beyond the header's columns has no column to be read as
        if any(cell.strip() for cell in row[len(header):]):
            raise CondtrackError(f"{path}: row {line} has {len(row)} fields, the header {len(header)}")
    columns = {name: header.index(name) for name in (*REQUIRED_COLUMNS, "point_id") if name in header}
    values = {}
    for name, column in columns.items():
        parse = whole_number if name in INTEGER_COLUMNS else float
        cells = []
        for line, row in body:
            cell = row[column] if column < len(row) else ""
            try:
                cells.append(parse(cell))
            except ValueError as error:
                reason = str(error) if parse is whole_number else "is not a number"
                raise CondtrackError(f"{path}: row {line}, column '{name}': {cell!r} {reason}") from None
        values[name] = np.array(cells, dtype=np.int64 if parse is whole_number else np.float64)
    point_id = values["point_id"] if "point_id" in values else np.arange(len(body), dtype=np.int64)
    frame = values["frame"]
    xy = np.column_stack([values["x"], values["y"]])
    return checked_queries(str(path), point_id, frame, xy, info, lines)


def queries_from_rows(rows: np.ndarray, info: SequenceInfo) -> Queries:
    """Queries from an (N, 3) array of ``frame, x, y`` rows (points numbered 0..N-1), checked like a CSV's."""
    if np.ma.is_masked(rows):  # np.asarray would keep the values under the mask and track them
        row = int(np.flatnonzero(np.ma.getmaskarray(rows).reshape(len(rows), -1).any(axis=1))[0])
        raise InvalidArgument(f"queries: row {row} is masked; give the rows to track (e.g. rows[~rows.mask.any(axis=1)])")
    try:
        given = np.asarray(rows)
    except ValueError:  # rows of different lengths: numpy's "inhomogeneous shape", not a shape to report
        raise InvalidArgument("queries: expected a non-empty (N, 3) array of frame, x, y; got rows of different "
                              "lengths") from None
    if given.dtype.kind not in "iuf":
        raise InvalidArgumentType(f"queries: expected an (N, 3) array of numbers frame, x, y; got dtype {given.dtype}")
    rows = given.astype(np.float64)
    if rows.ndim != 2 or rows.shape[1] != 3 or not len(rows):
        raise InvalidArgument(f"queries: expected a non-empty (N, 3) array of frame, x, y; got shape {rows.shape}")
    if not np.isfinite(rows).all() or not np.all(rows[:, 0] == np.round(rows[:, 0])):
        row = int(np.argmax(~np.isfinite(rows).all(axis=1) | (rows[:, 0] != np.round(rows[:, 0]))))
        raise CondtrackError(f"queries: row {row}: frame must be a whole number and x, y finite")
    index = np.arange(len(rows), dtype=np.int64)
    frame = given[:, 0] if given.dtype.kind in "iu" else rows[:, 0]  # an integer frame as given: float64 rounds 2^53 + 1
    return checked_queries("queries", index, frame, rows[:, 1:], info, index)


def checked_queries(where: str, point_id: np.ndarray, frame: np.ndarray, xy: np.ndarray, info: SequenceInfo,
                    rows: np.ndarray) -> Queries:
    """Queries ordered by point_id after checking ids, frames and positions against the sequence.

    ``where`` names the source in errors, which report query i as row ``rows[i]`` (a CSV's line, an array's row
    index); ``frame`` holds whole numbers, as integers or floats (an array's, cast once checked: a float beyond
    int64 would not cast).
    """
    unique_ids, counts = np.unique(point_id, return_counts=True)
    if (counts > 1).any():
        raise CondtrackError(f"{where}: point_id {int(unique_ids[np.argmax(counts > 1)])} appears more than once")
    bad_frame = (frame < 0) | (frame >= info.n_frames)
    if bad_frame.any():
        index = int(np.argmax(bad_frame))
        raise CondtrackError(f"{where}: row {rows[index]}: frame {int(frame[index])} is outside the sequence "
                             f"(0..{info.n_frames - 1})")
    frame = frame.astype(np.int64)
    inside = info.contains(xy) if info.width else np.isfinite(xy).all(axis=1)  # width 0: no frame size known
    if not inside.all():
        index = int(np.argmax(~inside))
        finite = bool(np.isfinite(xy[index]).all())
        reason = f"is outside the {info.width}x{info.height} frame" if info.width and finite else "is not finite"
        raise CondtrackError(f"{where}: row {rows[index]}: point ({xy[index, 0]:g}, {xy[index, 1]:g}) {reason}")
    order = np.argsort(point_id, kind="stable")
    return Queries(point_id[order], frame[order], xy[order])


def detected_queries(xy: np.ndarray, info: SequenceInfo, detector: str) -> Queries:
    """Queries for (M, 2) points detected on frame 0, numbered 0..M-1, checked against the detect stage's contract
    (``detect/interface.py``: numbers, finite, inside the frame) and refused naming stage ``detector`` otherwise."""
    where = f"detect stage '{detector}'"
    if not isinstance(xy, np.ndarray) or xy.ndim != 2 or xy.shape[1] != 2 or xy.dtype.kind not in "iuf":
        got = (f"shape {xy.shape}, dtype {xy.dtype}" if isinstance(xy, np.ndarray)
               else f"a {type(xy).__name__}")
        raise CondtrackError(f"{where} returned {got}; expected an (M, 2) float64 array of positions (px)")
    m = len(xy)
    xy = xy.astype(np.float64)
    if not np.isfinite(xy).all():
        raise CondtrackError(f"{where}: point {int(np.argmax(~np.isfinite(xy).all(axis=1)))} is not finite")
    index = np.arange(m, dtype=np.int64)
    return checked_queries(where, index, np.zeros(m, np.int64), xy, info, index)
