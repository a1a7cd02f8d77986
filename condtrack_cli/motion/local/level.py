"""One pyramid level of the local field: its work arrays, warp + IRLS passes over both supports, the final choice.

Each pass warps frame k by the dense field, sums the pixels' products of the
normal equations over blocks and solves every node's window system; the last
pass's systems give each node's support and Q_k.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from condtrack_cli.motion.local.systems import (
    _backward,
    _cholesky,
    _forward,
    _normal_equations,
    _translation_covariance,
    _with_ridge,
)
from condtrack_cli.motion.local.windows import (
    RESIDUAL_PRIOR_STD,
    _interpolate,
    _Layout,
    _layout,
    _window_sums,
    local_model,
)
from condtrack_cli.motion.robust import MAD_TO_SIGMA, RobustMotionSettings, robust_weights

#: Pixels whose global robust weight is at least this follow the dominant motion.
DOMINANT_WEIGHT = 0.5

#: |r| thresholds (grey levels) whose window counts give the window's median |r|: FIRST_THRESHOLD 2^j.
FIRST_THRESHOLD = 0.25
THRESHOLDS = 10


class _Planes:
    """Block sums of float32 planes of one level's padded shape (``_Layout.padded``).

    The planes are interleaved in groups of up to four channels, as ``cv2.resize``
    wants them, one group at a time: one interleaved buffer per group width is
    kept between passes and calls (fresh pages are slow).
    """

    def __init__(self, lay: _Layout):
        self.lay = lay
        self.buffers: dict[int, np.ndarray] = {}  # channels -> (h_padded, w_padded, channels) float32

    def block_sums(self, planes: list[np.ndarray]) -> np.ndarray:
        """(hn, wn, count) float32 sums of each (h_padded, w_padded) plane over the layout's blocks."""
        block = self.lay.block
        rows, cols = self.lay.node_shape
        sums = np.zeros((rows, cols, len(planes)), np.float32)
        for start in range(0, len(planes), 4):
            members = planes[start : start + 4]
            if len(members) not in self.buffers:
                self.buffers[len(members)] = np.empty(self.lay.padded + (len(members),), np.float32)
            group = cv2.merge(members, self.buffers[len(members)])
            if block > 1:
                group = cv2.resize(group, (group.shape[1] // block, group.shape[0] // block),
                                   interpolation=cv2.INTER_AREA)
            group = group.reshape(group.shape[0], group.shape[1], -1)
            sums[: group.shape[0], : group.shape[1], start : start + group.shape[2]] = group
        sums *= block**2
        return sums


def _split_into(planes: list[np.ndarray], index: int, product: np.ndarray, dominant: np.ndarray) -> None:
    """Write ``product`` on dominant pixels to ``planes[index]`` and on the others to ``planes[index + 1]``."""
    on_dominant, other = planes[index], planes[index + 1]
    np.multiply(product, dominant, out=on_dominant)
    np.subtract(product, on_dominant, out=other)


def _median_from_counts(counts: np.ndarray) -> np.ndarray:
    """Median |r| (grey) from counts (..., T + 1) of residuals by interval of |r| (T = THRESHOLDS).

    Interval j holds FIRST_THRESHOLD 2^(j-1) < |r| <= FIRST_THRESHOLD 2^j (j = 0:
    |r| <= FIRST_THRESHOLD; j = T: above the last threshold).
    Log-linear within the interval holding the half count (the first starting at
    half the first threshold); the last threshold when more than half exceed it.
    """
    intervals = counts[..., :-1]
    below = np.cumsum(intervals, axis=-1) - intervals
    half = counts.sum(-1, keepdims=True) / 2
    # each interval adds the fraction of it that lies under the half count
    crossed = np.clip((half - below) / np.maximum(intervals, 1e-6), 0, 1).sum(-1)
    return FIRST_THRESHOLD * 2.0 ** (crossed - 1)


class _Workspace:
    """Work arrays of one level layout, reused from pass to pass and frame to frame (fresh pages are slow).

    Pixel arrays have the padded shape (``_Layout.padded``); padding pixels are never valid.
    """

    def __init__(self, lay: _Layout):
        height, width = lay.padded
        self.maps = lay.maps_to(lay.padded, lay.level)  # node coordinates of the level's pixels
        self.block_sums = _Planes(lay).block_sums  # of the pass's products and of the chosen support's totals
        self.residual = np.empty((height, width, 4), np.float32)
        self.base = np.empty((height, width, 2), np.float32)
        self.positions = np.empty((height, width, 2), np.float32)
        self.warped = np.empty((height, width, 3), np.float32)
        self.planes = [np.empty((height, width), np.float32) for _ in range(22)]
        self.scale_step = 2 if lay.block % 2 == 0 else 1  # the scales use every other pixel when blocks allow
        rows, cols = lay.node_shape
        blocks = ((np.arange(0, height, self.scale_step) // lay.block)[:, None] * cols
                  + np.arange(0, width, self.scale_step) // lay.block)
        self.block_index = (blocks * (THRESHOLDS + 2)).astype(np.intp)  # first bin of each sampled pixel's block
        self.search = None  # the block-matching start's batch arrays (``_SearchBatch``), made on the coarsest level


class _Level:
    """What the passes on one pyramid level share: frames, pixel positions under U_g, supports, work arrays."""

    def __init__(self, prev: np.ndarray, cur: np.ndarray, level: int, global_flow: np.ndarray,
                 weights: np.ndarray, settings: RobustMotionSettings, workspaces: dict):
        height, width = prev.shape[:2]
        self.cur, self.factor = cur, 2**level
        self.lay = _layout(settings, level, (height, width))
        if self.lay not in workspaces:
            workspaces[self.lay] = _Workspace(self.lay)
        self.work = work = workspaces[self.lay]
        rows, cols = self.lay.padded
        pad = (0, rows - height, 0, cols - width)
        prev = cv2.copyMakeBorder(prev, *pad, cv2.BORDER_CONSTANT, dst=work.warped)  # free until a pass warps
        self.intensity, self.gx, self.gy = cv2.split(prev, work.planes[19:22])
        flow = cv2.multiply(global_flow[:: self.factor, :: self.factor], 1 / self.factor)
        self.base = cv2.copyMakeBorder(flow, *pad, cv2.BORDER_REPLICATE, dst=work.base)
        self.base[:, :, 0] += np.arange(cols, dtype=np.float32)  # s + U_g(s), level px
        self.base[:, :, 1] += np.arange(rows, dtype=np.float32)[:, None]
        if weights.shape != (height, width):
            weights = cv2.resize(weights, (width, height), interpolation=cv2.INTER_AREA)
        self.dominant = cv2.copyMakeBorder(weights, *pad, cv2.BORDER_CONSTANT) >= DOMINANT_WEIGHT  # follows U_g
        self.dominant_f = self.dominant.astype(np.float32)
        self.dominant_mask = self.dominant.view(np.uint8)
        self.usable = np.square(self.gx) + np.square(self.gy) >= settings.min_gradient**2
        self.usable[height - 1 :] = self.usable[:, width - 1 :] = False  # last row and column (one-sided
        self.usable[0] = self.usable[:, 0] = False  # Sobel gradient), first ones, and the padding

    def scales(self, residual: np.ndarray, valid: np.ndarray, floor: float) -> np.ndarray:
        """(hn, wn) robust scale (grey) of each node's window: 1.4826 median |r| over its valid pixels, >= floor.

        The median comes from window counts of |r| under FIRST_THRESHOLD 2^j
        (``_median_from_counts``) over every ``scale_step``-th pixel in x and y,
        not centred on the median of r.
        """
        step = self.work.scale_step
        _, exponent = np.frexp(np.abs(residual[::step, ::step]) / FIRST_THRESHOLD)  # |r| <= 2^j t0 iff exponent <= j
        bins = THRESHOLDS + 2  # exponents 0 .. THRESHOLDS - 1, above, invalid
        binned = np.where(valid[::step, ::step], np.clip(exponent, 0, THRESHOLDS), THRESHOLDS + 1)
        rows, cols = self.lay.node_shape
        counts = np.bincount((self.work.block_index + binned).ravel(), minlength=rows * cols * bins)
        counts = counts.reshape(rows, cols, bins)[:, :, :-1].astype(np.float32)  # exact: small integers
        windows = _window_sums(counts, self.lay, ((0, 0),))[0, 0]
        median = _median_from_counts(windows)
        return np.where(windows.sum(-1) >= 1, np.maximum(MAD_TO_SIGMA * median, floor), floor)


@dataclass(frozen=True)
class _Systems:
    """One pass's window systems on one level, for both supports (first axis: dominant, non-dominant).

    matrix[i][j] (j >= i), rhs[i], theta[i]: (2, hn, wn) J^T W J, J^T W y and
    the solution (px). The pass's pixel planes (h, w) (padded): weights w,
    gradient g (gx, gy, grey per full-resolution px, 0 where not valid) and y,
    the right side of the pixel's equation g^T U(s) = y(s).
    """

    matrix: list
    rhs: list
    theta: list
    weights: np.ndarray
    gx: np.ndarray
    gy: np.ndarray
    y: np.ndarray

    def residual_nodes(self) -> np.ndarray:
        """(hn, wn, 4) float32 residual translation (px) at the nodes: x, y of the dominant solution, then the other."""
        m = len(self.theta) // 2
        return np.dstack((self.theta[0][0], self.theta[m][0], self.theta[0][1], self.theta[m][1])).astype(np.float32)


def _pixel_field(residual: np.ndarray, level: _Level) -> list[np.ndarray]:
    """[u_x, u_y] (h, w) float32: each pixel's residual translation, from its own support's field.

    residual: (h, w, 4) x, y of the dominant field then of the other one (px).
    Written into the level's work arrays.
    """
    fields = cv2.split(residual, level.work.planes[:4])
    u = level.work.planes[4:6]
    for component, dominant, other in zip(u, fields[:2], fields[2:]):
        np.copyto(component, other)
        cv2.copyTo(dominant, level.dominant_mask, component)
    return u


def _level_pass(level: _Level, residual: np.ndarray, settings: RobustMotionSettings) -> _Systems:
    """One warp + IRLS pass of every window of one level, both supports (``motion.local``).

    residual: (h, w, 4) float32 residual translation (full-resolution px) of the
    dominant field then of the other one at the level's pixels; each pixel is
    linearised at its own support's. Work arrays are reused and arithmetic is
    in place where it can be: fresh pages are slow (``motion.local``).
    """
    factor, lay = level.factor, level.lay
    ux, uy = _pixel_field(residual, level)
    positions = cv2.scaleAdd(cv2.merge((ux, uy), level.work.positions), 1 / factor, level.base,
                              dst=level.work.positions)
    warped = cv2.remap(level.cur, positions, None, cv2.INTER_LINEAR, dst=level.work.warped,
                       borderMode=cv2.BORDER_REPLICATE)
    r0, gx, gy = cv2.split(warped, level.work.planes[6:9])
    height, width = lay.shape
    valid = cv2.inRange(positions, (0, 0), (width - 1, height - 1)) > 0  # inside frame k (padding: not usable)
    valid &= level.usable
    r0 -= level.intensity  # I_k(s + U(s)) - I_{k-1}(s)
    half = np.float32(0.5 / factor)  # mean of both frames' gradients, per full-resolution px
    gx += level.gx
    gx *= half
    gy += level.gy
    gy *= half
    scale = level.scales(r0, valid, settings.min_scale)
    weights = robust_weights(settings.robust_cost, r0, _interpolate(scale[:, :, None], level.work.maps)[:, :, 0])
    weights *= valid
    y = gx * ux  # the pixel's equation: g^T U(s) = y(s) = g^T u(s) - r0
    uy *= gy
    y += uy
    y -= r0
    wgx, wgy = weights * gx, weights * gy
    planes = level.work.planes[9:19]
    for index, (a, b) in enumerate(((wgx, gx), (wgx, gy), (wgy, gy), (wgx, y), (wgy, y))):
        _split_into(planes, 2 * index, np.multiply(a, b, out=uy), level.dominant_f)
    sums = level.work.block_sums(planes)
    matrix, rhs = _normal_equations(sums, lay, local_model(settings, lay.level))
    lower = _cholesky(_with_ridge(matrix, np.square(scale / RESIDUAL_PRIOR_STD)))
    theta = _backward(lower, _forward(lower, rhs))
    gx *= valid
    gy *= valid
    return _Systems(matrix, rhs, theta, weights, gx, gy, y)


def _choose(systems: _Systems, residual: np.ndarray, level: _Level,
            settings: RobustMotionSettings) -> tuple[np.ndarray, np.ndarray]:
    """Each node's residual translation (hn, wn, 2) px and Q_k - q_floor I (hn, wn, 3) px^2 (``motion.local``).

    residual: (h, w, 4) the pass's solutions at the pixels, as for ``_level_pass``. A node
    keeps the dominant support when it holds at least half its window's robustly
    weighted gradient energy sum w |g|^2 (its inliers' information), the other
    one otherwise; Q_k comes from that support's normal equations, with s^2 from
    the pixels' residuals g^T u(s) - y(s) under the solution at the pixels (not
    from sum w y^2 - theta^T J^T W y, which the block approximation would bias).
    """
    p = len(systems.theta)
    m = p // 2
    ux, uy = _pixel_field(residual, level)
    after = systems.gx * ux + systems.gy * uy - systems.y  # linearised residual after the step
    weights = systems.weights
    planes = level.work.planes[9:15]
    for index, plane in enumerate((weights * (systems.gx * systems.gx + systems.gy * systems.gy),
                                   weights * after * after, weights)):
        _split_into(planes, 2 * index, plane, level.dominant_f)
    totals = np.moveaxis(_window_sums(level.work.block_sums(planes), level.lay, ((0, 0),))[0, 0], 2, 0
                         ).astype(np.float64)
    energy, squares, weight_sum = totals[0:2], totals[2:4], totals[4:6]
    chosen = energy[0] < energy[1]  # False: dominant, True: non-dominant

    def pick(array: np.ndarray) -> np.ndarray:
        return np.where(chosen, array[1], array[0])

    theta = [pick(t) for t in systems.theta]
    matrix = [[None if entry is None else pick(entry) for entry in row] for row in systems.matrix]
    variance = np.maximum(pick(squares) / np.maximum(pick(weight_sum) - p, 1), settings.min_scale**2)
    lower = _cholesky(_with_ridge(matrix, variance / RESIDUAL_PRIOR_STD**2))
    cov = variance[:, :, None] * _translation_covariance(lower, m)
    return np.stack((theta[0], theta[m]), -1), cov
