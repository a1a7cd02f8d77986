"""Matching costs between reference patches and a frame: patches, cost surfaces of eq. (6), sub-pixel refinement."""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

#: Gauss-Newton steps of the sub-pixel refinement (median change after 3 steps: 0.01 px on photographs).
_REFINE_STEPS = 3


def extract_templates(gray: np.ndarray, xy: np.ndarray, size: int) -> np.ndarray:
    """(M, size, size) float32 patches of ``gray`` centred on the sub-pixel positions ``xy``.

    gray: (H, W) float32 grey levels; xy: (M, 2) finite positions (px); size: odd side.
    Patch pixel (i, j) is ``gray`` at (x + j - size//2, y + i - size//2), bilinear,
    with the border replicated (coordinates clamped to the frame).
    """
    height, width = gray.shape
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    grid = np.arange(size) - size // 2
    x = np.clip(xy[:, 0, None] + grid, 0, width - 1)  # (M, size), clamped: border replicate
    y = np.clip(xy[:, 1, None] + grid, 0, height - 1)
    x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    wx, wy = (x - x0)[:, None, :], (y - y0)[:, :, None]
    flat = np.ascontiguousarray(gray).ravel()
    rows0, rows1 = (y0 * width)[:, :, None], (y1 * width)[:, :, None]
    cols0, cols1 = x0[:, None, :], x1[:, None, :]
    top = flat.take(rows0 + cols0) * (1 - wx) + flat.take(rows0 + cols1) * wx
    bottom = flat.take(rows1 + cols0) * (1 - wx) + flat.take(rows1 + cols1) * wx
    return (top * (1 - wy) + bottom * wy).astype(np.float32)


@functools.lru_cache(maxsize=16)
def _axis_weights(side: int, sigma: float) -> np.ndarray:
    """(side,) read-only weights of one axis of :func:`pixel_weights`."""
    g = np.exp(-0.5 * ((np.arange(side) - side // 2) / sigma) ** 2)
    g *= np.sqrt(g.sum() ** 2 / (g * g).sum() ** 2)  # sum w = sum w^2 over the square of w = g g^T
    g.flags.writeable = False
    return g


def pixel_weights(side: int, sigma: float | None) -> np.ndarray | None:
    """(side, side) weights w of the matching cost's pixels: a Gaussian of std ``sigma`` px around the patch's
    centre, scaled so that sum w = sum w^2 (the weighted sum of n_w = sum w pixel noises then has the mean and the
    variance of an unweighted sum of n_w: the noise tests read n_w as the pixel count); None (sigma None): every
    pixel alike, the paper's eq. (6)."""
    if sigma is None:
        return None
    g = _axis_weights(side, sigma)
    return np.outer(g, g)


def pixel_count(side: int, sigma: float | None) -> float:
    """n_w = sum w of :func:`pixel_weights` (side^2 unweighted): the pixel count that the noise tests read."""
    weights = pixel_weights(side, sigma)
    return float(side * side) if weights is None else float(weights.sum())


class FrameSums(NamedTuple):
    """Window sums of a frame at every pixel (:func:`frame_sums`), border replicated.

    Element [y, x] of each (H, W) float64 table is a sum over the ``side`` x ``side`` window
    centred on pixel (x, y), weighted by :func:`pixel_weights` of ``sigma`` (n = sum w, side^2 without weights):
    ``total`` and ``squares`` (cost 'ssd'), of w I and of w I^2; ``spread`` (the other costs), of
    w I'^2 = max(sum w I^2 - (sum w I)^2 / n, 0) (I' = I less its weighted mean). None: not needed by ``cost``.
    """

    total: np.ndarray | None
    squares: np.ndarray | None
    spread: np.ndarray | None
    side: int
    cost: str
    sigma: float | None = None


def frame_sums(gray: np.ndarray, side: int, cost: str = "ssd", sigma: float | None = None) -> FrameSums:
    """:class:`FrameSums` of the (H, W) float32 frame ``gray`` for windows of odd ``side`` (px), ``cost`` and the
    weights of ``sigma`` (:func:`pixel_weights`): two box filters, or two separable filters with weights (float64,
    border replicated), computed once per frame; each candidate's window sums are then one look-up."""
    import cv2

    if sigma is None:
        window = (side, side)  # float32 in, float64 sums: the same values as from a float64 copy, without making one
        total = cv2.boxFilter(gray, cv2.CV_64F, window, normalize=False, borderType=cv2.BORDER_REPLICATE)
        squares = cv2.sqrBoxFilter(gray, cv2.CV_64F, window, normalize=False, borderType=cv2.BORDER_REPLICATE)
    else:
        g = _axis_weights(side, sigma)
        total = cv2.sepFilter2D(gray, cv2.CV_64F, g, g, borderType=cv2.BORDER_REPLICATE)
        squares = cv2.sepFilter2D(np.square(gray, dtype=np.float64), cv2.CV_64F, g, g, borderType=cv2.BORDER_REPLICATE)
    if cost == "ssd":
        return FrameSums(total, squares, None, side, cost, sigma)
    spread = np.multiply(total, total, out=total)  # max(squares - total^2 / n, 0), in place of total
    spread /= pixel_count(side, sigma)
    np.subtract(squares, spread, out=spread)
    return FrameSums(None, None, np.maximum(spread, 0.0, out=spread), side, cost, sigma)


#: Windows of at least this side (px) are copied one slice per point: at the coarse search's 81-93 px that is
#: several times faster than one gather of every window (most of a short frame's windows there cross its border,
#: which the gather's clamped indices make slowest); below about this side the one gather is faster (timings in
#: bench/history.md, "Speed since 35ed7c7").
SLICED_SIDE = 35


def _windows(table: np.ndarray, centres: np.ndarray, reach: int) -> np.ndarray:
    """(P, g, g) windows of a (H, W) ``table`` around (P, 2) integer (x, y) ``centres``, g = 2 reach + 1.

    Element [p, i, j] is ``table`` at (x + j - reach, y + i - reach) clamped into the frame: for g below
    ``SLICED_SIDE``, one slice per point when the window is inside the frame, clamped indices for the others;
    from it, :func:`_sliced_windows`.
    """
    height, width = table.shape
    g = 2 * reach + 1
    if g >= SLICED_SIDE:
        return _sliced_windows(table, centres, reach)
    starts = centres - reach
    inside = (starts >= 0).all(axis=1) & (starts[:, 0] + g <= width) & (starts[:, 1] + g <= height)
    windows = np.empty((len(centres), g, g), table.dtype)
    if inside.any():
        windows[inside] = sliding_window_view(table, (g, g))[starts[inside, 1], starts[inside, 0]]
    if not inside.all():
        rows = np.clip(starts[~inside, 1, None] + np.arange(g), 0, height - 1)
        cols = np.clip(starts[~inside, 0, None] + np.arange(g), 0, width - 1)
        windows[~inside] = table[rows[:, :, None], cols[:, None, :]]
    return windows


def _sliced_windows(table: np.ndarray, centres: np.ndarray, reach: int) -> np.ndarray:
    """:func:`_windows`, one copy per point: the window's slice where it lies inside the frame, else the slice of
    its part inside the frame, border replicated to g x g (``cv2.copyMakeBorder``; a window wholly outside the frame
    repeats the frame's nearest row or column, as the clamped indices do)."""
    import cv2

    height, width = table.shape
    g = 2 * reach + 1
    windows = np.empty((len(centres), g, g), table.dtype)
    for window, (x, y) in zip(windows, (np.asarray(centres) - reach).tolist()):
        if x >= 0 and y >= 0 and x + g <= width and y + g <= height:
            window[...] = table[y:y + g, x:x + g]
            continue
        x_lo, x_hi = min(max(x, 0), width - 1), min(max(x + g - 1, 0), width - 1)  # the columns the window reads
        y_lo, y_hi = min(max(y, 0), height - 1), min(max(y + g - 1, 0), height - 1)
        left, top = max(min(x_lo - x, g - 1), 0), max(min(y_lo - y, g - 1), 0)  # repeats of the first one
        right, bottom = g - (x_hi - x_lo + 1) - left, g - (y_hi - y_lo + 1) - top
        window[...] = cv2.copyMakeBorder(table[y_lo:y_hi + 1, x_lo:x_hi + 1], top, bottom, left, right,
                                         cv2.BORDER_REPLICATE)
    return windows


def ssd_surfaces(gray: np.ndarray, templates: np.ndarray, centres: np.ndarray, reach: int,
                 cost: str = "ssd", sums: FrameSums | None = None, sigma: float | None = None) -> np.ndarray:
    """(P, G, G) float64 r_k (eq. 6) at integer candidates centres + (dx, dy), |dx|, |dy| <= reach, G = 2 reach + 1.

    Element [p, i, j] is the matching cost between templates[p] (t x t) and the frame
    patch centred on (centres[p, 0] + j - reach, centres[p, 1] + i - reach), frame
    border replicated. The cross term sum I T' (T' = T - mean T) is ``cv2.matchTemplate``
    (TM_CCORR, float32) of T' over each point's frame patch less m = mean T, one call per
    point: at these sizes (t = 11, G <= 39) that loop is 3-6 times faster than one batched
    FFT correlation of every patch (issue 26), and its float32 sums are within about 1e-6
    of the patches' energies of float64 ones. The window sums of I and I^2 are look-ups in
    the frame's ``sums`` (:func:`frame_sums` of t x t windows for ``cost``; computed here when
    None). Exact for every candidate whose centre is inside the frame; the others' values
    are unspecified (the caller excludes them). ``cost`` 'ssd': the SSD,
    sum [T - I]^2 = sum I^2 - 2 sum I T' - 2 m sum I + t^2 m^2 + sum T'^2 (m = mean T).
    'zero_mean': the SSD after giving the frame patch the template's mean,
    sum [T' - I']^2 (T', I' mean-free). 'normalised': after giving it the template's
    mean and contrast, sum [T' - a I']^2 = 2 sum T'^2 (1 - rho) (a = |T'| / |I'|, rho
    their correlation; a flat frame patch has rho = 0). See :func:`matching_cost`.
    """
    import cv2

    t = templates.shape[1]
    g = 2 * reach + 1
    sums = _checked_sums(gray, t, cost, sums, sigma)
    mean, energy, kernels = _centred(templates, pixel_weights(t, sigma))
    patches = np.empty((len(templates), g + t - 1, g + t - 1), np.float32)
    np.subtract(_windows(gray, centres, reach + t // 2), mean, out=patches,
                casting="same_kind")  # I - m in float64, rounded to float32: small sums
    sum_it = np.empty((len(templates), g, g), np.float32)  # sum_y T'(y) (I(z + y) - m) = sum_y T'(y) I(z + y)
    for patch, kernel, out in zip(patches, kernels, sum_it):
        cv2.matchTemplate(patch, kernel, cv2.TM_CCORR, result=out)
    sum_it = sum_it.astype(np.float64)
    if cost == "ssd":
        sum_i, sum_sq = (_windows(table, centres, reach) for table in (sums.total, sums.squares))
        m = mean[:, :, :1]
        n = pixel_count(t, sigma)
        return np.maximum(sum_sq - 2.0 * m * sum_i + n * m * m - 2.0 * sum_it + energy, 0.0)  # eq. (6)
    spread = _windows(sums.spread, centres, reach)  # sum I'^2
    if cost == "zero_mean":
        return _zero_mean_cost(sum_it, spread, energy)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.where(spread > 0, sum_it / np.sqrt(energy * spread), 0.0)
    return 2.0 * energy * (1.0 - np.clip(np.nan_to_num(rho), -1.0, 1.0))


def zero_mean_minima(gray: np.ndarray, templates: np.ndarray, centres: np.ndarray, reach: int,
                     sums: FrameSums | None = None) -> np.ndarray:
    """(P,) the flat index i G + j of the least element of each point's (G, G) 'zero_mean' surface of
    :func:`ssd_surfaces` (G = 2 reach + 1; the first of equal ones): the same surfaces, the same arithmetic, made and
    reduced one point at a time, so that no (P, G, G) array is made (faster at the coarse search's G = 81: timings
    in bench/history.md, "Speed since 35ed7c7")."""
    import cv2

    t = templates.shape[1]
    g = 2 * reach + 1
    sums = _checked_sums(gray, t, "zero_mean", sums)
    mean, energy, kernels = _centred(templates)
    regions = _windows(gray, centres, reach + t // 2)
    spreads = _windows(sums.spread, centres, reach)
    patch = np.empty((g + t - 1, g + t - 1), np.float32)
    sum_it = np.empty((g, g), np.float32)
    cost = np.empty((g, g))
    minima = np.empty(len(templates), np.intp)
    for p, (region, kernel, spread) in enumerate(zip(regions, kernels, spreads)):
        np.subtract(region, mean[p], out=patch, casting="same_kind")
        cv2.matchTemplate(patch, kernel, cv2.TM_CCORR, result=sum_it)
        np.copyto(cost, sum_it)  # float64, as the surfaces' cross terms
        minima[p] = _zero_mean_cost(cost, spread, energy[p]).argmin()
    return minima


def _checked_sums(gray: np.ndarray, side: int, cost: str, sums: FrameSums | None,
                  sigma: float | None = None) -> FrameSums:
    """``sums``, or :func:`frame_sums` of ``gray`` where None; ValueError where they are not of ``side`` px windows for
    ``cost`` and the weights of ``sigma``."""
    if sums is None:
        sums = frame_sums(gray, side, cost, sigma)
    if (sums.side, sums.cost, sums.sigma) != (side, cost, sigma):
        raise ValueError(f"frame_sums of {sums.side} px windows for cost {sums.cost!r}, weights {sums.sigma}: "
                         f"{side} px templates, cost {cost!r}, weights {sigma}")
    return sums


def _centred(templates: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(P, t, t) ``templates``' means m (P, 1, 1) and energies sum w T'^2 (P, 1, 1), float64, and the kernels
    w T' (T' = T - m) as float32 (P, t, t); the means are weighted by the (t, t) ``weights`` w (None: 1)."""
    tmpl = templates.astype(np.float64)
    mean = _mean(tmpl, weights)
    tmpl -= mean
    kernels = tmpl if weights is None else tmpl * weights
    return mean, _weighted(tmpl * tmpl, weights)[:, None, None], kernels.astype(np.float32)


def _zero_mean_cost(sum_it: np.ndarray, spread: np.ndarray, energy: np.ndarray) -> np.ndarray:
    """The 'zero_mean' cost sum I'^2 - 2 sum I T' + sum T'^2, at least 0, in place of the float64 cross terms
    ``sum_it``; ``spread`` sum I'^2 and ``energy`` sum T'^2 broadcast to it."""
    sum_it *= -2.0
    sum_it += spread
    sum_it += energy
    return np.maximum(sum_it, 0.0, out=sum_it)


def matching_cost(templates: np.ndarray, patches: np.ndarray, cost: str, sigma: float | None = None) -> np.ndarray:
    """(M,) the ``cost`` of :func:`ssd_surfaces` (with the weights of ``sigma``) between aligned (M, t, t)
    ``templates`` and ``patches``."""
    a = np.asarray(templates, np.float64)
    b = np.asarray(patches, np.float64)
    weights = pixel_weights(a.shape[1], sigma)
    if cost == "ssd":
        return _weighted((a - b) ** 2, weights)
    a = a - _mean(a, weights)
    b = b - _mean(b, weights)
    if cost == "zero_mean":
        return _weighted((a - b) ** 2, weights)
    energy, spread = _weighted(a * a, weights), _weighted(b * b, weights)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.where(spread > 0, _weighted(a * b, weights) / np.sqrt(energy * spread), 0.0)
    return 2.0 * energy * (1.0 - np.clip(np.nan_to_num(rho), -1.0, 1.0))


def _towards(mid: np.ndarray, after: np.ndarray, before: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Linear interpolation mid + |f| (after - mid) where f >= 0, mid + |f| (before - mid) elsewhere, (P, 1, 1) f."""
    moved = np.where(f >= 0, after, before)
    moved -= mid
    moved *= np.abs(f)
    moved += mid
    return moved


def _shift(window: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """(P, a - 2, b - 2) bilinear samples of (P, a, b) windows at their inner pixels moved by (P, 2) ``offset``.

    |offset| <= 1 px on each axis; the windows' borders supply the neighbours.
    """
    fx, fy = offset[:, 0, None, None], offset[:, 1, None, None]
    rows = _towards(window[:, :, 1:-1], window[:, :, 2:], window[:, :, :-2], fx)
    return _towards(rows[:, 1:-1], rows[:, 2:], rows[:, :-2], fy)


def refine(gray: np.ndarray, templates: np.ndarray, start: np.ndarray, cost: str = "ssd",
           sigma: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(P, 2) sub-pixel z_k: the continuous minimum of eq. (6) within +-0.5 px of the integer minimum ``start``,
    and (P,) r(z_k), the cost there (grey levels^2).

    start: (P, 2) integer-valued positions (px). Gauss-Newton on r(z) = sum_y w(y) [T(y) - I_k(z + y)]^2
    (w the :func:`pixel_weights` of ``sigma``, 1 without) with I_k bilinear (border replicated) and its gradient
    by central differences, ``_REFINE_STEPS`` steps, each clamped so that z stays within the integer minimum's
    cell. The normal matrix is damped by 1e-3 of its trace so that the step along an edge (no
    information) stays small. Other ``cost``: that of :func:`matching_cost`, the
    frame patch given the template's mean (and contrast) at each step (held
    fixed within a step).
    """
    t = templates.shape[1]
    weights = pixel_weights(t, sigma)
    # I_k at start + [-t//2 - 2, t//2 + 2]^2: frame pixels (start is integer), clamped into the frame
    window = _windows(gray, start.astype(np.intp), t // 2 + 2).astype(np.float64)
    reference = templates.astype(np.float64)
    energy = None
    if cost != "ssd":
        reference = reference - _mean(reference, weights)
        energy = _weighted(reference * reference, weights)
    offset = np.zeros(start.shape)
    for step in range(_REFINE_STEPS):
        # I_k at z + [-t//2 - 1, t//2 + 1]^2; at the first step z = start, the window's inner pixels
        moved = _matched(_shift(window, offset) if step else window[:, 1:-1, 1:-1].copy(), cost, energy, weights)
        gx = (moved[:, 1:-1, 2:] - moved[:, 1:-1, :-2]) / 2.0
        gy = (moved[:, 2:, 1:-1] - moved[:, :-2, 1:-1]) / 2.0
        error = reference - moved[:, 1:-1, 1:-1]
        wgx, wgy = (gx, gy) if weights is None else (gx * weights, gy * weights)
        a, b, c = (wgx * gx).sum(axis=(1, 2)), (wgx * gy).sum(axis=(1, 2)), (wgy * gy).sum(axis=(1, 2))
        damping = 1e-3 * (a + c) + 1e-12
        a, c = a + damping, c + damping
        ex, ey = (wgx * error).sum(axis=(1, 2)), (wgy * error).sum(axis=(1, 2))
        det = a * c - b * b
        step = np.stack([c * ex - b * ey, a * ey - b * ex], axis=1) / det[:, None]
        offset = np.clip(offset + step, -0.5, 0.5)
    error = reference - _matched(_shift(window, offset), cost, energy, weights)[:, 1:-1, 1:-1]  # the cost at z_k
    return start + offset, _weighted(error * error, weights)


def _weighted(values: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
    """(P,) sums of (P, t, t) ``values`` weighted by (t, t) ``weights`` (None: 1)."""
    return (values if weights is None else values * weights).sum(axis=(1, 2))


def _mean(values: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
    """(P, 1, 1) means of (P, t, t) ``values`` weighted by (t, t) ``weights`` (None: 1)."""
    if weights is None:
        return values.mean(axis=(1, 2), keepdims=True)
    return _weighted(values, weights)[:, None, None] / weights.sum()


def _matched(moved: np.ndarray, cost: str, energy: np.ndarray | None, weights: np.ndarray | None = None) -> np.ndarray:
    """(P, t + 2, t + 2) frame windows ``moved`` (float64, modified in place) as ``cost`` compares them with the
    reference: as they are (ssd), less the (``weights``-weighted) mean of their inner t x t pixels, and (normalised)
    scaled to the reference's (P,) mean-free ``energy`` over them."""
    if cost != "ssd":
        moved -= _mean(moved[:, 1:-1, 1:-1], weights)
        if cost == "normalised":
            centred = moved[:, 1:-1, 1:-1]
            spread = _weighted(centred * centred, weights)
            moved *= np.sqrt(energy / np.where(spread > 0, spread, np.inf))[:, None, None]
    return moved
