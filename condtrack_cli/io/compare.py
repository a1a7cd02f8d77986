"""Compare two track results, with tolerances (``condtrack compare``): golden files in CI.

A user keeps a track file from a known-good run and compares every new run
with it, often on another machine. The same build on another CPU (OpenCV's
SIMD dispatch, floating-point order) moves values by rounding noise that the
tracker's discrete decisions (a gate, a residual test, a motion rule) can
amplify on a few points into a track pixels away. So "the same result" is
judged per (point, frame) cell, with a budget of differing cells
(:class:`Tolerances`; :data:`TOLERANT` is the default, :data:`STRICT` asks
for the same numbers up to the CSV's rounding).

Points are matched by ``point_id``; frames by index, over the longer of the two
results. Exact, always: ``points`` (a point id the other result lacks; with
``CSV_FIELDS`` only points that have a position, as a CSV lists no other),
``n_frames``, ``query_frame``, ``state`` (a position in one result only);
``query_x``, ``query_y`` within ``QUERY_ATOL_PX`` (queries are
inputs, not computed); ``moved``: a point whose positions differ by more than
``atol_px`` on every frame both results have one (a moved query, which a CSV
does not hold; another CPU's rounding grows along a track from its query frame,
where the two runs still agree, it does not move a whole track). On every cell where both results have a position, the
cell differs where its ``method`` differs (``auto`` chose another filter) or
one of these measures exceeds its tolerance:

- ``xy``, ``z``: the distance between the two positions (px), over ``atol_px``;
- ``cov``, ``R``: ||A - B||_F / max(||A||_F, ||B||_F), the Frobenius norm of the
  difference relative to the matrices (a near-zero off-diagonal entry does not
  count on its own), over ``rtol_cov``;
- ``dof``: |a - b| / max(a, b), over ``rtol_cov``;
- ``visible``: a flip is a *near-tie* where the two positions differ by more than
  ``QUERY_ATOL_PX`` (the two runs fed the visibility decision different numbers;
  the decision is a threshold on them); a flip where both runs hold the same
  position is no tie and is counted against ``visible_flips``. In strict mode
  every flip is.

The results agree when the exact fields match, non-tie flips are at most
``visible_flips``, at most ``max_share`` of the compared cells differ and no
position of a row that both results report visible differs by more than
``max_px``. A row that a result does not see holds its prediction of a lost
point, which may lie far from the other's: where another CPU's rounding tipped
a match, one run keeps the point and the other coasts (the camel, ``cnlf``: 76
px apart, 45 px where both see it), and a point that left the frame is
extrapolated far outside it (KITTI seq009: at 70 000 px with a std of 100 000
px, the two runs 62 px apart; README, "Golden files in CI", has the commands).
Such a row counts as a cell beyond ``atol_px``, not against ``max_px``. Non-finite values are equal only to
the same kind (NaN to NaN, +inf to +inf); NaN or inf against a number differs
(``score`` inf). Which fields are compared depends on what both files hold: a
CSV holds ``CSV_FIELDS``, an HDF5 file all of ``HDF5_FIELDS``.
"""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass, replace

import numpy as np

from condtrack_cli.registry import method_codes
from condtrack_cli.types import Tracks

#: Tolerance on query positions (px), and the position difference above which a visibility flip is a near-tie.
QUERY_ATOL_PX = 1e-4

#: Every field, in report order (structure first, then per-cell measures).
HDF5_FIELDS = ("points", "n_frames", "query_frame", "query_x", "query_y", "state", "method", "moved",
               "visible", "xy", "cov", "dof", "z", "R")
#: The fields a CSV holds: its columns (a point is listed when it has a row).
CSV_FIELDS = ("points", "state", "method", "moved", "visible", "xy", "cov", "dof")
#: Fields that must match exactly (queries within ``QUERY_ATOL_PX``), whatever the tolerances.
EXACT_FIELDS = ("points", "n_frames", "query_frame", "query_x", "query_y", "state", "moved")


@dataclass(frozen=True)
class Tolerances:
    """What counts as the same result.

    atol_px: position distance (px) above which a cell differs; rtol_cov: relative
    covariance (Frobenius) and dof difference above which a cell differs;
    max_share: fraction of compared cells allowed to differ; max_px: largest
    position distance allowed anywhere (px); visible_flips: visibility flips allowed
    beyond near-ties; near_ties: whether a near-tie flip is a differing cell (True)
    or a flip like any other (False).
    """

    atol_px: float
    rtol_cov: float
    max_share: float
    max_px: float
    visible_flips: int = 0
    near_ties: bool = True


#: The default: another CPU, thread count or floating-point order passes (README, "Golden files in CI").
TOLERANT = Tolerances(atol_px=0.5, rtol_cov=0.2, max_share=0.05, max_px=50.0)
#: The same numbers on the same machine: every cell within the CSV's rounding, no flip.
STRICT = Tolerances(atol_px=1e-4, rtol_cov=1e-4, max_share=0.0, max_px=math.inf, near_ties=False)


@dataclass(frozen=True)
class Difference:
    """One differing value: ``a`` and ``b`` as held by each result.

    ``point_id`` is None for ``n_frames``; ``frame`` is None for per-point and
    per-result fields. Values are floats or ints, a method name, "present"/"absent"
    for ``points`` and ``state``, an [x, y] list for ``xy`` and ``z``, an
    [xx, xy, yx, yy] list for ``cov`` and ``R``; for ``moved`` the point's positions
    on its frame of smallest distance, ``diff`` that distance. ``diff`` is the field's measure
    (px for positions, relative for ``cov``, ``R`` and ``dof``) where finite, else None.
    """

    point_id: int | None
    frame: int | None
    field: str
    a: float | int | str | list
    b: float | int | str | list
    diff: float | None


@dataclass(frozen=True)
class Comparison:
    """The outcome of :func:`compare_tracks`.

    counts: per compared field, the number of differing values (``visible``: every
    flip; ``ties`` of them near-ties). cells: compared cells; differing_cells: cells
    where a measure exceeds its tolerance (near-tie flips included). max_px: the
    largest position distance (0 without cells); max_px_seen: the largest on cells that both results report
    visible, what ``Tolerances.max_px`` caps (``max_px`` without visibilities). top: the largest differences,
    worst first. n_points: points in both results; n_frames: frames compared.
    """

    agree: bool
    counts: dict[str, int]
    ties: int
    cells: int
    differing_cells: int
    max_px: float
    max_px_seen: float
    top: tuple[Difference, ...]
    fields: tuple[str, ...]
    n_points: int
    n_frames: int
    tolerances: Tolerances


@dataclass(frozen=True)
class _Found:
    """The differing values of one field: (M,) arrays; ``frame`` is -1 off per-cell fields."""

    field: str
    point_id: np.ndarray
    frame: np.ndarray
    score: np.ndarray  # measure / tolerance; inf for a kind or presence mismatch; 1 for a flip
    a: np.ndarray
    b: np.ndarray
    diff: np.ndarray  # the measure, nan where not finite


def _same_kind(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Where non-finite entries of ``a`` and ``b`` (same shape) match: NaN-NaN, inf of one sign, finite-finite."""
    return (np.isfinite(a) & np.isfinite(b)) | (np.isnan(a) & np.isnan(b)) | (a == b)


def _distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, F) distances (px) between (P, F, 2) positions; nan where an entry is not finite."""
    with np.errstate(invalid="ignore"):
        return np.hypot(a[..., 0] - b[..., 0], a[..., 1] - b[..., 1])


def _relative(a: np.ndarray, b: np.ndarray, size=np.abs) -> np.ndarray:
    """size(a - b) / max(size(a), size(b)) (0 for two zeros; nan if not finite); ``size`` |.| by default."""
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.maximum(size(a), size(b))
        diff = size(a - b)
        return np.where(diff == 0, 0.0, diff / np.where(norm > 0, norm, 1.0))


def _relative_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, F) ||a - b||_F / max(||a||_F, ||b||_F) of (P, F, 2, 2) matrices (0 for two zeros; nan if not finite)."""
    return _relative(a, b, lambda m: np.linalg.norm(m, axis=(-2, -1)))


def _padded(array: np.ndarray, rows: np.ndarray, n_frames: int, fill) -> np.ndarray:
    """``array[rows]`` (R, F', ...) extended with ``fill`` to (R, n_frames, ...)."""
    out = np.full((len(rows), n_frames) + array.shape[2:], fill, dtype=array.dtype)
    out[:, : array.shape[1]] = array[rows]
    return out


def _listed(tracks: Tracks, every_query: bool) -> np.ndarray:
    """(P',) ids the result lists: every query, or (as a CSV) the points with a position somewhere."""
    ids = tracks.queries.point_id
    return ids if every_query else ids[tracks.has_state.any(axis=1)]


def compare_tracks(
    a: Tracks,
    b: Tracks,
    tolerances: Tolerances = TOLERANT,
    fields: Collection[str] = HDF5_FIELDS,
    top: int = 10,
) -> Comparison:
    """Compare ``a`` and ``b`` on ``fields`` (``CSV_FIELDS`` when either came from a CSV).

    Vectorised over points and frames; see the module docstring for the rules.
    """
    unknown = set(fields) - set(HDF5_FIELDS)
    if unknown:
        raise ValueError(f"unknown fields {sorted(unknown)}")
    fields = tuple(name for name in HDF5_FIELDS if name in fields)
    every_query = "query_frame" in fields
    ids, ia, ib = np.intersect1d(a.queries.point_id, b.queries.point_id, return_indices=True)
    n_frames = max(a.xy.shape[1], b.xy.shape[1])
    found: list[_Found] = []

    def add(field: str, mismatch: np.ndarray, score: np.ndarray, va: np.ndarray, vb: np.ndarray,
            diff: np.ndarray | None = None) -> None:
        """Record the mismatches of a per-point (P,) or per-cell (P, F) field."""
        hits = np.nonzero(mismatch)
        frame = hits[1] if mismatch.ndim == 2 else np.full(len(hits[0]), -1)
        measure = np.full(len(hits[0]), np.nan) if diff is None else diff[hits]
        found.append(_Found(field, ids[hits[0]], frame, score[hits], va[hits], vb[hits], measure))

    def structural(field: str, point_id: np.ndarray, va: np.ndarray, vb: np.ndarray) -> None:
        """Record per-point or per-result mismatches that are never tolerated."""
        n = len(point_id)
        found.append(_Found(field, point_id, np.full(n, -1), np.full(n, np.inf), va, vb, np.full(n, np.nan)))

    if "points" in fields:
        # a point in both results is compared frame by frame ("state"), not here
        only_a = np.setdiff1d(_listed(a, every_query), b.queries.point_id)
        only_b = np.setdiff1d(_listed(b, every_query), a.queries.point_id)
        one_sided = np.concatenate([only_a, only_b])
        in_a = np.array(["present"] * len(only_a) + ["absent"] * len(only_b), dtype=object)
        in_b = np.array(["absent"] * len(only_a) + ["present"] * len(only_b), dtype=object)
        order = np.argsort(one_sided, kind="stable")
        structural("points", one_sided[order], in_a[order], in_b[order])
    if "n_frames" in fields and a.xy.shape[1] != b.xy.shape[1]:
        structural("n_frames", np.zeros(1, np.int64), np.array([a.xy.shape[1]]), np.array([b.xy.shape[1]]))
    if every_query:
        qa, qb = a.queries, b.queries
        differs = qa.frame[ia] != qb.frame[ib]
        add("query_frame", differs, np.where(differs, np.inf, 0.0), qa.frame[ia], qb.frame[ib])
        for axis, name in enumerate(("query_x", "query_y")):
            va, vb = qa.xy[ia, axis], qb.xy[ib, axis]
            with np.errstate(invalid="ignore"):
                diff = np.abs(va - vb)
            moved = ~_same_kind(va, vb) | (diff > QUERY_ATOL_PX)
            add(name, moved, np.where(np.isfinite(diff), diff / QUERY_ATOL_PX, np.inf), va, vb, diff)

    state_a = _padded(a.has_state, ia, n_frames, False)  # (P, F)
    state_b = _padded(b.has_state, ib, n_frames, False)
    both = state_a & state_b
    differing = np.zeros(both.shape, bool)  # cells over a tolerance: a method, a near-tie flip or a measure
    if "state" in fields:
        differs = state_a != state_b
        present = np.array(["absent", "present"], dtype=object)
        add("state", differs, np.where(differs, np.inf, 0.0), present[state_a.astype(int)],
            present[state_b.astype(int)])
    if "method" in fields:
        va, vb = _padded(a.method, ia, n_frames, -1), _padded(b.method, ib, n_frames, -1)
        other_method = both & (va != vb)
        names = np.array(method_codes() + ("none",), dtype=object)  # code -1 -> "none"
        add("method", other_method, other_method.astype(float), names[va], names[vb])
        differing |= other_method

    xy_a, xy_b = _padded(a.xy, ia, n_frames, np.nan), _padded(b.xy, ib, n_frames, np.nan)
    distance = np.where(both, _distance(xy_a, xy_b), 0.0)  # (P, F) px
    if "moved" in fields and n_frames:  # (without a frame nothing moved)
        moved = both.any(axis=1) & ((distance > tolerances.atol_px) | ~both).all(axis=1)
        nearest = np.where(both, distance, np.inf).argmin(axis=1)  # (P,) each point's frame of smallest distance
        rows = np.arange(len(ids))
        add("moved", moved, np.where(moved, np.inf, 0.0), xy_a[rows, nearest], xy_b[rows, nearest],
            distance[rows, nearest])
    ties = 0
    seen = both  # the cells whose distance max_px caps
    if "visible" in fields:
        va, vb = _padded(a.visible, ia, n_frames, False), _padded(b.visible, ib, n_frames, False)
        seen = both & va & vb
        flips = both & (va != vb)
        tie = flips & (distance > QUERY_ATOL_PX) if tolerances.near_ties else np.zeros_like(flips)
        ties = int(tie.sum())
        differing |= tie
        add("visible", flips, np.where(tie, 1.0, np.inf), va.astype(int), vb.astype(int))
    for field, array_a, array_b, measure, tolerance in (
        ("xy", a.xy, b.xy, _distance, tolerances.atol_px),
        ("cov", a.cov, b.cov, _relative_matrix, tolerances.rtol_cov),
        ("dof", a.dof, b.dof, _relative, tolerances.rtol_cov),
        ("z", a.z, b.z, _distance, tolerances.atol_px),
        ("R", a.R, b.R, _relative_matrix, tolerances.rtol_cov),
    ):
        if field not in fields:
            continue
        pa, pb = _padded(array_a, ia, n_frames, np.nan), _padded(array_b, ib, n_frames, np.nan)
        kind = _same_kind(pa, pb).all(axis=tuple(range(2, pa.ndim)))  # (P, F): every entry of the cell
        diff = measure(pa, pb)
        finite = np.isfinite(diff)
        mismatch = both & np.where(finite, diff > tolerance, ~kind)
        score = np.full(diff.shape, np.inf)
        np.divide(diff, tolerance, out=score, where=finite & (tolerance > 0))
        differing |= mismatch
        if pa.ndim == 4:  # a matrix shown as its 4 entries
            pa, pb = pa.reshape(pa.shape[:2] + (4,)), pb.reshape(pb.shape[:2] + (4,))
        add(field, mismatch, score, pa, pb, diff)

    counts = {name: 0 for name in fields}
    for item in found:
        counts[item.field] += len(item.score)
    cells, n_differing = int(both.sum()), int(differing.sum())
    max_px = float(distance.max(initial=0.0)) if "xy" in fields else 0.0
    max_px_seen = float(np.where(seen, distance, 0.0).max(initial=0.0)) if "xy" in fields else 0.0
    agree = (
        all(counts[name] == 0 for name in EXACT_FIELDS if name in fields)
        and counts.get("visible", 0) - ties <= tolerances.visible_flips
        and n_differing <= tolerances.max_share * cells
        and not max_px_seen > tolerances.max_px
    )
    return Comparison(
        agree=agree, counts=counts, ties=ties, cells=cells, differing_cells=n_differing, max_px=max_px,
        max_px_seen=max_px_seen,
        top=_largest(found, fields, top), fields=fields, n_points=len(ids), n_frames=n_frames, tolerances=tolerances,
    )


def with_options(base: Tolerances, **options: float | int | None) -> Tolerances:
    """``base`` with the options that are not None replaced (the command line's explicit flags)."""
    return replace(base, **{name: value for name, value in options.items() if value is not None})


def _largest(found: list[_Found], fields: tuple[str, ...], top: int) -> tuple[Difference, ...]:
    """The ``top`` differences of highest score; ties by field order, point id, then frame."""
    if not found or top <= 0:
        return ()
    score = np.concatenate([item.score for item in found])
    rank = np.concatenate([np.full(len(item.score), fields.index(item.field)) for item in found])
    point = np.concatenate([item.point_id for item in found])
    frame = np.concatenate([item.frame for item in found])
    source = np.concatenate([np.full(len(item.score), k) for k, item in enumerate(found)])
    local = np.concatenate([np.arange(len(item.score)) for item in found])
    order = np.lexsort((frame, point, rank, -score))[:top]
    result = []
    for k in order:
        item, i = found[source[k]], local[k]
        diff = float(item.diff[i])
        result.append(Difference(
            point_id=None if item.field == "n_frames" else int(item.point_id[i]),
            frame=int(item.frame[i]) if item.frame[i] >= 0 else None,
            field=item.field, a=_plain(item.a[i]), b=_plain(item.b[i]), diff=diff if np.isfinite(diff) else None,
        ))
    return tuple(result)


def _plain(value) -> float | int | str | list:
    """A numpy scalar or 1-D array as a Python float, int, str or list of floats."""
    if isinstance(value, np.ndarray):
        return [float(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value)
    if isinstance(value, (np.integer, int)):
        return int(value)
    return str(value)
