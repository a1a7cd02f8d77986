"""The reference of the local field: one robust regression per position on its own window (``exact_local_motion``).

Nothing is shared between positions; the tests compare ``LocalMotion``'s field with it.
"""

from __future__ import annotations

import numpy as np

from condtrack_cli.motion.local.windows import (
    _MONOMIALS,
    RESIDUAL_PRIOR_STD,
    _global_flow,
    _layout,
    local_levels,
    local_model,
    passes,
)
from condtrack_cli.motion.model import MotionFit, displacement
from condtrack_cli.motion.pyramid import build_pyramid, usable_levels
from condtrack_cli.motion.robust import (
    MAD_TO_SIGMA,
    RobustMotionSettings,
    _sample,
    estimate_from_pyramids,
    robust_weights,
)
from condtrack_cli.types import Pyramid


def _masked_median(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(M,) median of each row of values (M, K) over its entries where mask (M, K); 0 for an empty row."""
    count = mask.sum(axis=1)
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    low = np.take_along_axis(ordered, np.maximum((count - 1) // 2, 0)[:, None], 1)[:, 0]
    high = np.take_along_axis(ordered, np.minimum(count // 2, values.shape[1] - 1)[:, None], 1)[:, 0]
    return np.where(count > 0, (low + high) / 2, 0.0)


def exact_local_motion(prev_gray: np.ndarray, cur_gray: np.ndarray, xy: np.ndarray,
                       settings: RobustMotionSettings) -> tuple[np.ndarray, np.ndarray]:
    """The reference: one robust regression per position on its own window (``motion.local``).

    prev_gray, cur_gray: (H, W) float32 frames k-1 and k; xy: (M, 2) positions of
    frame k-1 (px). Same models, cost, pyramid, passes, prior and Q_k as
    ``LocalMotion``, nothing shared between positions. Returns U (M, 2) px and
    Q_k (M, 2, 2) px^2. Vectorised over positions; memory ~ 40 M side^2 numbers.
    """
    shape = prev_gray.shape
    levels = local_levels(shape, settings.levels)
    global_levels = usable_levels(shape, settings.levels)
    depth = max(levels, global_levels)
    prev, cur = build_pyramid(prev_gray, depth), build_pyramid(cur_gray, depth)
    fit = estimate_from_pyramids(Pyramid(prev.base, prev.levels[:global_levels]),
                                 Pyramid(cur.base, cur.levels[:global_levels]), settings)
    return window_regression(prev, cur, _global_flow(fit, shape), fit, xy, settings)


def window_regression(prev: Pyramid, cur: Pyramid, global_flow: np.ndarray, fit: MotionFit, xy: np.ndarray,
                      settings: RobustMotionSettings) -> tuple[np.ndarray, np.ndarray]:
    """The per-window regression of ``exact_local_motion`` on given pyramids and global fit.

    prev, cur: pyramids of frames k-1 and k at least ``local_levels`` deep; global_flow:
    ``_global_flow(fit, shape)``; xy: (M, 2) positions of frame k-1 (px). Returns U (M, 2) px and
    Q_k (M, 2, 2) px^2. Memory ~ 40 M side^2 numbers: callers batch the positions. It is also the
    ``regression`` stage's local motion at each asked position (``motion/regression.py``, issue 29).
    """
    shape = prev.base.shape
    levels = local_levels(shape, settings.levels)
    xy = np.asarray(xy, np.float64)
    count = len(xy)
    translation = np.zeros((count, 2))  # residual translation at the position (px)
    for level in reversed(range(levels)):
        factor = 2**level
        prev_level, cur_level = prev.levels[level], cur.levels[level]
        height, width = prev_level.shape[:2]
        side = _layout(settings, level, (height, width)).side
        half = side / 2
        monomials = _MONOMIALS[local_model(settings, level)]
        m = len(monomials)
        p = 2 * m
        centre = xy / factor
        first = np.ceil(centre - half).astype(int)
        steps = np.arange(side)
        px, py = np.broadcast_arrays(first[:, 0, None, None] + steps, first[:, 1, None, None] + steps[:, None])
        rows, cols = np.clip(py, 0, height - 1), np.clip(px, 0, width - 1)
        prev_values = prev_level[rows, cols].reshape(count, -1, 3).astype(np.float64)
        usable = ((px >= 1) & (px <= width - 2) & (py >= 1) & (py <= height - 2)).reshape(count, -1)
        usable &= np.square(prev_values[:, :, 1]) + np.square(prev_values[:, :, 2]) >= settings.min_gradient**2
        base = (np.stack((px, py), -1) + global_flow[::factor, ::factor][rows, cols] / factor).reshape(count, -1, 2)
        d = np.stack((px - centre[:, 0, None, None], py - centre[:, 1, None, None]), -1).reshape(count, -1, 2) / half
        phi = np.stack([d[..., 0] ** a * d[..., 1] ** b for a, b in monomials], -1)  # (M, side^2, m)
        theta = np.zeros((count, p))
        theta[:, 0], theta[:, m] = translation.T
        for _ in range(passes(level)):
            u = np.stack((phi @ theta[:, :m, None], phi @ theta[:, m:, None]), -1)[:, :, 0]  # (M, side^2, 2)
            positions = (base + u / factor).astype(np.float32)
            warped = _sample(cur_level, positions.reshape(-1, 2)).astype(np.float64).reshape(count, -1, 3)
            valid = usable & np.all((positions >= 0) & (positions <= [width - 1, height - 1]), axis=-1)
            r0 = warped[:, :, 0] - prev_values[:, :, 0]
            g = (warped[:, :, 1:] + prev_values[:, :, 1:]) * (0.5 / factor)
            centred = r0 - _masked_median(r0, valid)[:, None]
            scale = np.maximum(MAD_TO_SIGMA * _masked_median(np.abs(centred), valid), settings.min_scale)
            weights = robust_weights(settings.robust_cost, r0, scale[:, None]) * valid
            y = (g * u).sum(-1) - r0
            design = np.concatenate((g[:, :, :1] * phi, g[:, :, 1:] * phi), -1)  # (M, side^2, p)
            weighted = design * weights[:, :, None]
            matrix = weighted.transpose(0, 2, 1) @ design
            rhs = (weighted * y[:, :, None]).sum(1)
            prior = np.square(scale / RESIDUAL_PRIOR_STD)[:, None, None] * np.eye(p)
            theta = np.linalg.solve(matrix + prior, rhs[:, :, None])[:, :, 0]
        translation = theta[:, (0, m)]
    # Q_k from the last pass's system, s^2 from the residuals after its step, as LocalMotion does
    fitted = (weights * np.square(design @ theta[:, :, None] - y[:, :, None])[:, :, 0]).sum(1)
    variance = np.maximum(fitted / np.maximum(weights.sum(1) - p, 1), settings.min_scale**2)
    inverse = np.linalg.inv(matrix + (variance / RESIDUAL_PRIOR_STD**2)[:, None, None] * np.eye(p))
    noise = variance[:, None, None] * inverse[:, (0, m)][:, :, (0, m)] + settings.q_floor * np.eye(2)
    return displacement(fit, xy) + translation, noise
