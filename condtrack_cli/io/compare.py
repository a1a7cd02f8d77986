"""Compare two track results field by field, with tolerances (``condtrack compare``).

Used for golden-file checks: a user keeps a track file from a known-good run
and compares every new run against it. Points are matched by ``point_id``;
frames by index, over the longer of the two results (a frame beyond one
result's end has no state there). On every (point, frame) cell where both
results have a position, these fields are compared (P, F: points in both
results, frames compared):

- ``x``, ``y``, ``z_x``, ``z_y``: absolute tolerance ``atol_px`` (px);
- ``cov_*``, ``R_*``: relative tolerance ``rtol_cov`` plus ``COV_ATOL`` px^2;
- ``dof``: relative tolerance ``rtol_cov`` (a file of schema 1.0 has dof inf);
- ``visible``: the number of differing cells, allowed up to ``visible_flips``;
- ``method``: exact.

Per cell: ``state`` (a position in one result only). Per point: ``points`` (a
point id the other result lacks; with ``CSV_FIELDS`` only points that have a
position, as a CSV lists no other), ``query_frame``, ``query_x``, ``query_y``.
Per result: ``n_frames``. Non-finite values are equal only to the same kind:
NaN to NaN, +inf to +inf, -inf to -inf; NaN or inf against any number differs.

Which fields are compared depends on what both files hold: a CSV holds
``CSV_FIELDS`` (its columns; its queries are derived from its rows, its frame
count from its last row), an HDF5 file all of ``HDF5_FIELDS``.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass

import numpy as np

from condtrack_cli.registry import method_codes
from condtrack_cli.types import Tracks

#: Default absolute tolerance on positions (px): the CSV keeps 6 decimals.
ATOL_PX = 1e-4
#: Default relative tolerance on covariances; the CSV's ``%.6e`` keeps 5e-7.
RTOL_COV = 1e-4
#: Absolute floor of the covariance tolerance (px^2), for zeros and subnormals.
COV_ATOL = 1e-12

#: Every field, in report order (structure first, then per-cell values).
HDF5_FIELDS = (
    "points", "n_frames", "query_frame", "query_x", "query_y", "state", "x", "y", "visible", "method",
    "cov_xx", "cov_xy", "cov_yx", "cov_yy", "dof", "z_x", "z_y", "R_xx", "R_xy", "R_yx", "R_yy",
)
#: The fields a CSV holds: its columns (a point is listed when it has a row).
CSV_FIELDS = ("points", "state", "x", "y", "visible", "method", "cov_xx", "cov_xy", "cov_yy", "dof")

#: Field suffix -> index in the last axes of a (..., 2) vector or (..., 2, 2) matrix.
_COORDINATES = {"x": (0,), "y": (1,)}
_ENTRIES = {"xx": (0, 0), "xy": (0, 1), "yx": (1, 0), "yy": (1, 1)}


@dataclass(frozen=True)
class Difference:
    """One differing value: ``a`` and ``b`` as held by each result.

    ``point_id`` is None for ``n_frames``; ``frame`` is None for per-point and
    per-result fields. Values are floats or ints, a method name, or
    "present"/"absent" for ``points`` and ``state``. ``diff`` is |a - b| for two
    finite numbers, else None.
    """

    point_id: int | None
    frame: int | None
    field: str
    a: float | int | str
    b: float | int | str
    diff: float | None


@dataclass(frozen=True)
class Comparison:
    """The outcome of :func:`compare_tracks`.

    counts: per compared field, the number of differing values (``visible``
    counts flips, including allowed ones). top: the largest differences, worst
    first (visibility flips only when over the allowance). n_points: points in
    both results; n_frames: frames compared.
    """

    agree: bool
    counts: dict[str, int]
    top: tuple[Difference, ...]
    fields: tuple[str, ...]
    n_points: int
    n_frames: int
    atol_px: float
    rtol_cov: float
    visible_flips: int


@dataclass(frozen=True)
class _Found:
    """The differing values of one field: (M,) arrays; ``frame`` is -1 off per-cell fields."""

    field: str
    point_id: np.ndarray
    frame: np.ndarray
    score: np.ndarray  # |a - b| / tolerance; inf for a kind or presence mismatch; 1 for a visibility or method flip
    a: np.ndarray
    b: np.ndarray


def _numeric(a: np.ndarray, b: np.ndarray, atol: float, rtol: float) -> tuple[np.ndarray, np.ndarray]:
    """(mismatch, score) of paired float arrays of one shape.

    Finite pairs differ when |a - b| > atol + rtol * max(|a|, |b|); score is
    |a - b| over that tolerance. Non-finite values match only the same kind
    (NaN-NaN, inf of one sign); a kind mismatch scores inf.
    """
    finite = np.isfinite(a) & np.isfinite(b)
    fa, fb = np.where(finite, a, 0.0), np.where(finite, b, 0.0)
    with np.errstate(over="ignore"):
        diff = np.abs(fa - fb)
        tolerance = atol + rtol * np.maximum(np.abs(fa), np.abs(fb))
    same_kind = (np.isnan(a) & np.isnan(b)) | (a == b)
    mismatch = np.where(finite, diff > tolerance, ~same_kind)
    score = np.full(diff.shape, np.inf)
    np.divide(diff, tolerance, out=score, where=finite & (tolerance > 0))
    return mismatch, score


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
    atol_px: float = ATOL_PX,
    rtol_cov: float = RTOL_COV,
    visible_flips: int = 0,
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

    def add(field: str, mismatch: np.ndarray, score: np.ndarray, va: np.ndarray, vb: np.ndarray) -> None:
        """Record the mismatches of a per-point (P,) or per-cell (P, F) field."""
        hits = np.nonzero(mismatch)
        frame = hits[1] if mismatch.ndim == 2 else np.full(len(hits[0]), -1)
        found.append(_Found(field, ids[hits[0]], frame, score[hits], va[hits], vb[hits]))

    if "points" in fields:
        # a point in both results is compared frame by frame ("state"), not here
        only_a = np.setdiff1d(_listed(a, every_query), b.queries.point_id)
        only_b = np.setdiff1d(_listed(b, every_query), a.queries.point_id)
        one_sided = np.concatenate([only_a, only_b])
        in_a = np.array(["present"] * len(only_a) + ["absent"] * len(only_b), dtype=object)
        in_b = np.array(["absent"] * len(only_a) + ["present"] * len(only_b), dtype=object)
        order = np.argsort(one_sided, kind="stable")
        found.append(_Found("points", one_sided[order], np.full(len(one_sided), -1),
                            np.full(len(one_sided), np.inf), in_a[order], in_b[order]))
    if "n_frames" in fields and a.xy.shape[1] != b.xy.shape[1]:
        found.append(_Found("n_frames", np.zeros(1, np.int64), np.full(1, -1), np.full(1, np.inf),
                            np.array([a.xy.shape[1]]), np.array([b.xy.shape[1]])))
    if every_query:
        qa, qb = a.queries, b.queries
        differs = qa.frame[ia] != qb.frame[ib]
        add("query_frame", differs, np.where(differs, np.inf, 0.0), qa.frame[ia], qb.frame[ib])
        for axis, name in enumerate(("query_x", "query_y")):
            va, vb = qa.xy[ia, axis], qb.xy[ib, axis]
            add(name, *_numeric(va, vb, atol_px, 0.0), va, vb)

    state_a = _padded(a.has_state, ia, n_frames, False)  # (P, F)
    state_b = _padded(b.has_state, ib, n_frames, False)
    both = state_a & state_b
    if "state" in fields:
        differs = state_a != state_b
        present = np.array(["absent", "present"], dtype=object)
        add("state", differs, np.where(differs, np.inf, 0.0), present[state_a.astype(int)],
            present[state_b.astype(int)])
    if "visible" in fields:
        va, vb = _padded(a.visible, ia, n_frames, False), _padded(b.visible, ib, n_frames, False)
        flips = both & (va != vb)
        add("visible", flips, flips.astype(float), va.astype(int), vb.astype(int))
    if "method" in fields:
        va, vb = _padded(a.method, ia, n_frames, -1), _padded(b.method, ib, n_frames, -1)
        differs = both & (va != vb)
        names = np.array(method_codes() + ("none",), dtype=object)  # code -1 -> "none"
        add("method", differs, differs.astype(float), names[va], names[vb])
    for prefix, array_a, array_b, atol, rtol, entries in (
        ("", a.xy, b.xy, atol_px, 0.0, _COORDINATES),
        ("cov_", a.cov, b.cov, COV_ATOL, rtol_cov, _ENTRIES),
        ("dof", a.dof, b.dof, 0.0, rtol_cov, {"": ()}),
        ("z_", a.z, b.z, atol_px, 0.0, _COORDINATES),
        ("R_", a.R, b.R, COV_ATOL, rtol_cov, _ENTRIES),
    ):
        wanted = {key: index for key, index in entries.items() if prefix + key in fields}
        if not wanted:
            continue
        pa, pb = _padded(array_a, ia, n_frames, np.nan), _padded(array_b, ib, n_frames, np.nan)
        for key, index in wanted.items():
            va, vb = pa[(Ellipsis,) + index], pb[(Ellipsis,) + index]  # (P, F)
            mismatch, score = _numeric(va, vb, atol, rtol)
            add(prefix + key, both & mismatch, score, va, vb)

    counts = {name: 0 for name in fields}
    for item in found:
        counts[item.field] += len(item.score)
    agree = all(count == 0 or (name == "visible" and count <= visible_flips) for name, count in counts.items())
    shown = [item for item in found if not (item.field == "visible" and counts["visible"] <= visible_flips)]
    return Comparison(
        agree=agree, counts=counts, top=_largest(shown, fields, top), fields=fields,
        n_points=len(ids), n_frames=n_frames, atol_px=atol_px, rtol_cov=rtol_cov, visible_flips=visible_flips,
    )


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
        va, vb = _plain(item.a[i]), _plain(item.b[i])
        finite = isinstance(va, float) and isinstance(vb, float) and np.isfinite(va) and np.isfinite(vb)
        result.append(Difference(
            point_id=None if item.field == "n_frames" else int(item.point_id[i]),
            frame=int(item.frame[i]) if item.frame[i] >= 0 else None,
            field=item.field, a=va, b=vb, diff=abs(va - vb) if finite else None,
        ))
    return tuple(result)


def _plain(value) -> float | int | str:
    """A numpy scalar as a Python float, int or str."""
    if isinstance(value, (np.floating, float)):
        return float(value)
    if isinstance(value, (np.integer, int)):
        return int(value)
    return str(value)
