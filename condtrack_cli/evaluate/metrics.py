"""TAP-Vid accuracy metrics and the calibration of the predicted covariances (coverage, NEES).

The definitions are those of TAP-Vid (Doersch et al., "TAP-Vid: A Benchmark for
Tracking Any Point in a Video", NeurIPS 2022, and ``compute_tapvid_metrics`` in
google-deepmind/tapnet), in pixels of the evaluated sequence (no rescaling to
256 x 256):

- Scored frames. ``'first'``: the frames strictly after each point's query frame;
  ``'strided'``: every frame but the query frame. Frames without ground truth
  (``gt_known`` False) are never scored.
- Within x: the predicted position is at a Euclidean distance *strictly* below x
  pixels from the ground truth, x in ``THRESHOLDS`` = 1, 2, 4, 8, 16.
- ``pts_within_x`` (<delta^x): over GT-visible scored frames, the fraction within
  x, whatever the predicted visibility. ``delta_avg``: their mean.
- ``jaccard_x`` = TP / (GT-visible + FP), with TP = GT visible, predicted visible
  and within x; FP = predicted visible and (GT occluded or not within x), both
  over scored frames. ``AJ``: their mean.
- ``OA``: the fraction of scored frames whose predicted visibility equals the GT
  visibility.

A frame on which the prediction has no position (NaN) counts as predicted
*not visible* and *not within* any threshold.

Additions of ours:

- ``median_err``: the median distance over GT-visible scored frames, a frame
  without a predicted position counting as an infinite distance (so it is null
  when more than half of those frames have no prediction).
- ``cov50``, ``cov90``, ``cov95``, ``cov99`` (coverage at level p): the fraction
  of GT-visible scored frames whose GT position lies in the predicted ellipse of
  level p of the row's distribution: the bivariate Student-t with covariance C
  and nu = ``dof`` degrees of freedom (docs/schema.md), {d : d^T C^-1 d <=
  (nu - 2) ((1 - p)^(-2 / nu) - 1)} with d the error, which for nu = inf is the
  Gaussian's {d : d^T C^-1 d <= chi2.ppf(p, 2)}; a calibrated distribution gives
  p. ``cov50_gauss`` ... ``cov99_gauss``: the same with every row read as
  Gaussian (the reading of a tool that ignores ``dof``). A covariance with an
  infinite entry is unbounded and contains every position. Frames without a
  prediction, with a NaN covariance, or with a finite covariance that is not
  positive definite have no ellipse and are not counted. Null when no frame is
  counted.
- ``nees``: the mean normalised estimation error squared d^T C^-1 d over the
  GT-visible scored frames with a finite positive-definite covariance (ideal 2,
  the mean of a chi-square with 2 degrees of freedom; above 2: overconfident).
  Null when there is no such frame.
- ``cov_finite``: the fraction of GT-visible scored frames with a predicted
  position and a finite positive-definite covariance (the share on which the
  coverage says something; an unbounded covariance passes every coverage test).
  Null without covariances or without GT-visible scored frames.
- ``cov50_rescaled``: ``cov50`` once every covariance is multiplied by the one
  factor k that makes ``cov95`` 0.95 (the least k with at least 95 % of the
  counted frames inside their 95 % ellipse). It separates a wrong scale from a
  wrong shape: if the errors are Gaussian with the covariances' shape, whatever
  their scale, it is 0.5; above 0.5 the errors are heavier-tailed than their
  covariances (a tight core and a far tail), which no inflation factor can
  calibrate at 50 % and 95 % at once. Null when no frame is counted or when
  k would be 0 (95 % of the counted frames unbounded or exact).

Null values: a metric that cannot be computed is ``None`` (JSON ``null``). In
particular, when the scored GT has no occluded frame, ``OA``, ``AJ`` and the
Jaccards are ``None``: with every GT position visible there is no visibility to
judge (a tracker that calls everything visible would score OA = 1 and Jaccard =
<delta^x), so they would only repeat ``pts_within_x``.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from condtrack_cli.predictive import chi2_2dof, ellipse_m2

#: Distance thresholds in pixels.
THRESHOLDS = (1, 2, 4, 8, 16)

#: Query modes: which frames of a point are scored.
QUERY_MODES = ("first", "strided")

#: Probability masses of the coverage ellipses reported (key ``cov<100 p>``).
COVERAGE_LEVELS = (0.5, 0.9, 0.95, 0.99)


def coverage_key(level: float) -> str:
    """The metric key of the coverage at ``level``: 0.95 -> ``'cov95'``."""
    return f"cov{round(100 * level)}"

#: The keys of ``tapvid_metrics``' result, in display order.
METRIC_KEYS = (
    ("delta_avg", "AJ", "OA")
    + tuple(f"pts_within_{x}" for x in THRESHOLDS)
    + tuple(f"jaccard_{x}" for x in THRESHOLDS)
    + ("median_err",)
    + tuple(coverage_key(p) for p in COVERAGE_LEVELS)
    + tuple(coverage_key(p) + "_gauss" for p in COVERAGE_LEVELS)
    + ("nees", "cov_finite", "cov50_rescaled", "n_points", "n_frames")
)


def scored_frames(query_frame: np.ndarray, n_frames: int, mode: Literal["first", "strided"]) -> np.ndarray:
    """(P, F) bool: the frames scored for each point, before removing frames without GT.

    query_frame: (P,) int, each point's query frame. ``'first'``: frames > query
    frame; ``'strided'``: frames != query frame.
    """
    if mode not in QUERY_MODES:
        raise ValueError(f"unknown query mode {mode!r}; valid: {', '.join(QUERY_MODES)}")
    frames = np.arange(n_frames)[None, :]  # (1, F)
    q = np.asarray(query_frame)[:, None]  # (P, 1)
    return frames > q if mode == "first" else frames != q


def _ratio(numerator: np.ndarray | int, denominator: np.ndarray | int) -> float | None:
    """numerator / denominator as a float, None when the denominator is 0."""
    return float(numerator / denominator) if denominator else None


def _mean_or_none(values: list[float | None]) -> float | None:
    """Mean of ``values``, None if any is None."""
    return None if any(v is None for v in values) else float(np.mean(values))


def normalised_error(error: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The squared Mahalanobis distance of each error under its covariance, and which ellipses exist.

    error: (..., 2) predicted minus GT position, NaN where there is no prediction.
    cov: (..., 2, 2) predicted covariance in px^2.

    Returns ``(unbounded, bounded, m2)``, all (...): ``unbounded`` (bool) where the
    error is finite and the covariance has an infinite entry and no NaN (its ellipse
    is the whole plane); ``bounded`` (bool) where the error is finite and the
    covariance finite and positive definite; ``m2`` (float) = d^T C^-1 d where
    ``bounded``, 0 elsewhere.
    """
    has_error = np.isfinite(error).all(axis=-1)
    unbounded = has_error & np.isinf(cov).any(axis=(-2, -1)) & ~np.isnan(cov).any(axis=(-2, -1))
    finite = np.isfinite(cov).all(axis=(-2, -1))
    sxx, sxy, syx, syy = (np.where(finite, cov[..., i, j], 0.0) for i, j in ((0, 0), (0, 1), (1, 0), (1, 1)))
    det = sxx * syy - sxy * syx
    bounded = has_error & finite & (sxx > 0) & (det > 0)
    # Sanitised operands so that no NaN/inf arithmetic (and no warning) happens off the mask.
    dx, dy = (np.where(bounded, error[..., k], 0.0) for k in (0, 1))
    det_safe = np.where(bounded, det, 1.0)
    with np.errstate(over="ignore", invalid="ignore"):  # an error beyond the float range (1e200 px off) is inf away
        m2 = (syy * dx * dx - (sxy + syx) * dx * dy + sxx * dy * dy) / det_safe
    m2 = np.where(np.isnan(m2), np.inf, m2)  # inf - inf of two such terms: as far
    return unbounded, bounded, m2


def coverage_inside(error: np.ndarray, cov: np.ndarray, level: float = 0.95,
                    dof: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Whether each error lies in the ellipse of level ``level`` of its row's distribution.

    error: (..., 2) predicted minus GT position, NaN where there is no prediction.
    cov: (..., 2, 2) predicted covariance in px^2. dof: (...) Student-t nu (None: Gaussian, as nu = inf).

    Returns ``(counted, inside)``, both (...) bool: ``counted`` where an ellipse
    exists (finite error, and a covariance with an infinite entry or finite and
    positive definite); ``inside`` where counted and d^T C^-1 d <= ``ellipse_m2(level, dof)``
    (always, for an infinite covariance).
    """
    unbounded, bounded, m2 = normalised_error(error, cov)
    bound = ellipse_m2(level, np.inf if dof is None else np.where(bounded, dof, np.inf))
    return unbounded | bounded, unbounded | (bounded & (m2 <= bound))


def calibration_metrics(error: np.ndarray, cov: np.ndarray | None, rows: np.ndarray,
                        dof: np.ndarray | None = None) -> dict[str, float | None]:
    """The coverage keys, ``nees``, ``cov_finite`` and ``cov50_rescaled`` (module docstring) over the ``rows`` (P, F) bool.

    error: (P, F, 2) predicted minus GT (NaN where no prediction); cov: (P, F, 2, 2) or None (all null);
    dof: (P, F) the rows' Student-t nu, or None (every row Gaussian).
    """
    keys = ([coverage_key(p) for p in COVERAGE_LEVELS] + [coverage_key(p) + "_gauss" for p in COVERAGE_LEVELS]
            + ["nees", "cov_finite", "cov50_rescaled"])
    if cov is None:
        return dict.fromkeys(keys)
    unbounded, bounded, m2 = normalised_error(error, cov)
    unbounded, bounded = unbounded & rows, bounded & rows
    counted = int((unbounded | bounded).sum())
    nu = np.inf if dof is None else np.where(bounded & ~np.isnan(dof), dof, np.inf)
    out = {coverage_key(p): _ratio((unbounded | (bounded & (m2 <= ellipse_m2(p, nu)))).sum(), counted)
           for p in COVERAGE_LEVELS}
    out.update({coverage_key(p) + "_gauss": _ratio((unbounded | (bounded & (m2 <= chi2_2dof(p)))).sum(), counted)
                for p in COVERAGE_LEVELS})
    out["nees"] = float(m2[bounded].mean()) if bounded.any() else None
    out["cov_finite"] = _ratio(bounded.sum(), rows.sum())
    out["cov50_rescaled"] = rescaled_coverage(np.where(bounded, m2, 0.0)[unbounded | bounded], 0.5, 0.95)
    return out


def rescaled_coverage(m2: np.ndarray, level: float, anchor: float) -> float | None:
    """Coverage at ``level`` once the covariances are scaled by the least k giving coverage >= ``anchor``.

    m2: (n,) d^T C^-1 d of the counted frames (0 for an unbounded covariance: inside at every scale).
    Scaling C by k divides m2 by k; k = the ceil(anchor n)-th smallest m2 / chi2.ppf(anchor, 2).
    None when n = 0 or k = 0.
    """
    if not m2.size:
        return None
    k = np.sort(m2)[math.ceil(anchor * m2.size) - 1] / chi2_2dof(anchor)
    return float(np.mean(m2 <= k * chi2_2dof(level))) if k > 0 else None


def tapvid_metrics(
    pred_xy: np.ndarray,
    pred_visible: np.ndarray,
    pred_cov: np.ndarray | None,
    gt_xy: np.ndarray,
    gt_visible: np.ndarray,
    gt_known: np.ndarray,
    query_frame: np.ndarray,
    mode: Literal["first", "strided"],
    pred_dof: np.ndarray | None = None,
) -> dict[str, float | int | None]:
    """TAP-Vid metrics of one sequence, pooled over points and frames (see the module docstring).

    pred_xy: (P, F, 2) predicted positions in pixels, NaN where none.
    pred_visible: (P, F) bool predicted visibility (ignored where pred_xy is NaN).
    pred_cov: (P, F, 2, 2) predicted covariances in px^2, or None (then the coverages, nees and cov_finite are None).
    gt_xy: (P, F, 2) GT positions in pixels (finite where visible and known).
    gt_visible: (P, F) bool GT visibility. gt_known: (P, F) bool, False where the
    GT says nothing about the frame (never scored).
    query_frame: (P,) int each point's query frame. mode: ``'first'`` or ``'strided'``.
    pred_dof: (P, F) Student-t nu of each row (inf: Gaussian), or None (every row Gaussian).

    Returns a dict with exactly the keys of ``METRIC_KEYS``: floats in [0, 1]
    (``median_err`` in pixels) or None where not computable; ``n_points`` = P and
    ``n_frames`` = F as ints.
    """
    n_points, n_frames = gt_visible.shape
    scored = scored_frames(query_frame, n_frames, mode) & gt_known  # (P, F)
    gt_vis = gt_visible & scored  # (P, F) GT-visible scored frames
    gt_occ = ~gt_visible & scored  # (P, F) GT-occluded scored frames
    has_pred = np.isfinite(pred_xy).all(axis=-1)  # (P, F)
    pred_vis = pred_visible & has_pred
    dist = np.hypot(*np.moveaxis(pred_xy - gt_xy, -1, 0))  # (P, F), NaN where no prediction
    within = dist[None] < np.array(THRESHOLDS, float)[:, None, None]  # (T, P, F), False where NaN
    n_vis = int(gt_vis.sum())
    judge_visibility = bool(gt_occ.any())

    tp = (within & pred_vis & gt_vis).sum(axis=(1, 2))  # (T,)
    fp = (pred_vis & (gt_occ | (gt_vis & ~within))).sum(axis=(1, 2))  # (T,)
    pts = [_ratio(n, n_vis) for n in (within & gt_vis).sum(axis=(1, 2))]
    jac = [_ratio(t, n_vis + f) if judge_visibility else None for t, f in zip(tp, fp)]
    out: dict[str, float | int | None] = {
        "delta_avg": _mean_or_none(pts),
        "AJ": _mean_or_none(jac),
        "OA": _ratio(((pred_vis == gt_visible) & scored).sum(), scored.sum()) if judge_visibility else None,
    }
    out.update({f"pts_within_{x}": v for x, v in zip(THRESHOLDS, pts)})
    out.update({f"jaccard_{x}": v for x, v in zip(THRESHOLDS, jac)})

    errors = np.where(has_pred, dist, np.inf)[gt_vis]
    median = float(np.median(errors)) if errors.size else math.inf
    out["median_err"] = median if math.isfinite(median) else None

    out.update(calibration_metrics(pred_xy - gt_xy, pred_cov, gt_vis, pred_dof))
    out["n_points"], out["n_frames"] = int(n_points), int(n_frames)
    return out
