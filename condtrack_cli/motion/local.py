"""Robust parametric motion between two frames, local support (paper §5.1, eq. 5).

Why one long module: it is one algorithm, the shared local field, whose layout, level,
workspace and system types are private to it, and its exact per-window reference that
the tests compare it with; split, the parts would only ever be read together.

The CNLF moves each particle x_{k-1}^(i) by the motion of a window R (side
``local_window``, 32 px by default) centred on it:
p(x_k | x_{k-1}) = N(x_{k-1} + U(x_{k-1}), Q_k(x_{k-1})) (eq. 5). This module
estimates U and Q_k once per frame pair on a grid of windows (``LocalMotion``,
``LocalField``) and samples them at any positions.

The per-window regression (``exact_local_motion``, the reference; ``window_regression`` is also the
``regression`` stage's local motion at each asked position, ``regression.py``, issue 29):

- U(s) = U_g(s) + P(d) theta on the window: U_g the global fit (``robust.py``),
  d = s - x the offset from the window centre, P(d) = [phi(d), 0; 0, phi(d)]
  with phi = [1, d_x/h, d_y/h] (h the half side; theta in px at the window's
  edge). The global motion carries the bulk of the displacement, theta is the
  window's residual motion: affine on the full-resolution level, so that the
  window of a turning object is unbiased at its centre; translation (phi = [1])
  on coarser levels, which only need to land in its basin, and everywhere when
  ``model='translation'``. U(x) = U_g(x) + (theta_0, theta_3), the window's
  displacement at its centre.
- theta minimises sum_{s in R} rho(grad I^T U(s) + dI/dt) as ``robust.py``
  does: its pyramid (``build_pyramid``), coarse to fine from the coarsest
  level's block-matching start (below; theta = 0 with ``local_search`` 0),
  linearised at the mean of both frames' gradients, cost ``robust_cost``,
  pixels with a gradient under ``min_gradient``, on the border or leaving
  frame k left out; the robust scale is 1.4826 MAD of the window's own
  residuals; a weak Gaussian prior (std RESIDUAL_PRIOR_STD px) on theta keeps
  every system invertible. On level l the window keeps its side in full-
  resolution px (local_window / 2^l level px, at least MIN_WINDOW): it is the
  paper's R seen coarser. FINEST_PASSES / COARSE_PASSES warp + IRLS passes per
  level. Levels: ``levels``, the coarsest with a shorter side >= MIN_LOCAL_SIDE
  px (deeper than the global fit's pyramid can go: windows are small); on
  320 x 240 frames (3 levels) residual motions up to 11 px are caught.
- The start: on the coarsest level each window is block-matched over integer
  shifts up to ``local_search`` px from the global motion (zero-mean SSD), and
  starts from its best shift where that halves the unshifted cost (median over
  3 x 3 windows). The passes alone catch a residual of about 2 px of the
  coarsest level; the global quadratic model misses by more on wide baselines
  and near parallax (oxford_merton1: median 13.8 px; ``bench --support``).
- Q_k(x) = s^2 [(J^T W J + (s / RESIDUAL_PRIOR_STD)^2 I)^-1]_translation + q_floor I,
  the paper leaving Q_k open: the weighted-least-squares covariance of the
  window's translation (J the linearised residual's p columns, W the robust
  weights, s^2 the weighted residual variance over sum(W) - p degrees of
  freedom, at least min_scale^2) plus the floor for what the window's model
  does not explain. Without texture it grows to about RESIDUAL_PRIOR_STD^2;
  on texture it is about s^2 / sum(w |g|^2), far under q_floor. Along a
  straight edge only the noise's gradients constrain the motion, so Q_k - q_floor
  stays small there (a few 0.01 px^2): q_floor has to cover the aperture problem.

What ``LocalMotion.field`` shares. On each level, per pass: one warp of frame k
by a dense per-pixel field, the per-pixel products of the normal equations
(w g g^T and w g y) summed over blocks of B x B pixels, each window's moments
sum w g g^T phi phi^T and sum w g y phi recombined from the K x K blocks it
covers (``_window_sums``: separable filters whose taps are the blocks' offsets
d^a), and one p x p solve per node, a node per block (K = FINEST_BLOCKS = 8 on
the full-resolution level, B = 4 px; COARSE_BLOCKS = 4 on coarser ones). The
cost per pass is that of a few passes over the pixels whatever the number of
positions asked for. Differences from the per-window regression:

1. Linearisation point. Each pixel s is linearised at the dense field u(s)
   (bilinear between nodes), not at each window's own motion; its equation
   g^T U(s) = g^T u(s) - r(s) stays exact to first order.
2. Robust weights and scale. w(s) comes from the residual at u(s) and the scale
   of the window around s, not from the residual at each window's motion. The
   scale is 1.4826 times the median |r|, from window counts of |r| under
   FIRST_THRESHOLD 2^j on every other pixel, log-interpolated (within ~7 %),
   not centred on the median of r.
3. Motion boundaries. Under (1) and (2) a pixel of another motion looks like an
   inlier (u(s) is its own motion), so a window across two motions would
   average them. Pixels are therefore split by the global fit's robust weights
   (>= DOMINANT_WEIGHT: they follow the dominant motion, as in the paper's §5.3
   map): every node solves one system per support, each pixel is linearised at
   its own support's field, and a node keeps the support holding at least half
   of its window's robustly weighted gradient energy sum w |g|^2. Two
   non-dominant motions within one window are still mixed.
4. Block positions. In the moments each pixel sits at its block's centre, with
   the block's spread added to the second moments ((B^2 - 1) / 12 per axis).
5. Positions. Windows sit on the nodes; a position between nodes gets the
   bilinear mix of its four nodes' U and Q_k (exact for an affine field). Off
   the frame, the nearest node's.
6. Q_k comes from the last pass's system, s^2 from the pixels' linearised
   residuals under the pass's solution interpolated to the pixels.

Measured (tests/test_local_motion.py, ring scene: a textured disk turning on a
ring 4-11 px/frame apart from its background), field minus exact regression on
windows inside one motion: median 0.08 px, 90th percentile 0.19 px on the
turning disk (mostly item 4), 0.003 / 0.007 px on the background; within half
a window of the disk's outline they differ by up to several px (median 0.15
px), where both often miss the truth. Q_k - q_floor agrees within a median
ratio of 1.02.

Speed: work arrays are kept per level layout from frame to frame and updated in
place: fresh pages are slow (on this project's 2-core machine the page faults
of fresh temporaries cost up to as much as the arithmetic of a pass).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from condtrack_cli.motion.field import LocalField
from condtrack_cli.motion.model import MotionFit, displacement, warp_maps
from condtrack_cli.motion.pyramid import build_pyramid, frame_pyramid, usable_levels
from condtrack_cli.motion.robust import (
    MAD_TO_SIGMA,
    RobustMotionSettings,
    _sample,
    estimate_from_pyramids,
    robust_weights,
)
from condtrack_cli.types import Frame, Pyramid

#: Shortest side (px) of the coarsest level of the local pyramid.
MIN_LOCAL_SIDE = 32

#: Smallest window side on a level (level px): coarse levels widen the window rather than go below it.
MIN_WINDOW = 8

#: Blocks per window side K on the finest level and on coarser ones (one node per block).
FINEST_BLOCKS = 8
COARSE_BLOCKS = 4

#: Warp + IRLS passes on the finest level and on each coarser one.
FINEST_PASSES = 2
COARSE_PASSES = 3

#: Prior std (px) of each residual-motion parameter: keeps every window's system
#: invertible; Q_k reaches about its square where the window has no texture.
RESIDUAL_PRIOR_STD = 16.0

#: Relative floor of each window system's diagonal: float32 sums of rank-one terms
#: are positive semi-definite to about 1e-6 of their largest entry only.
NUMERICAL_RIDGE = 1e-5

#: Pixels whose global robust weight is at least this follow the dominant motion.
DOMINANT_WEIGHT = 0.5

#: The coarsest level's block-matching start moves a node only where its best
#: shift's cost is under this fraction of the cost without a shift.
SEARCH_GAIN = 0.5

#: Most pixels of shifted frames per batch of the block-matching start (bounds its temporaries, ~40 B a pixel).
SEARCH_BATCH_PIXELS = 2**18

#: |r| thresholds (grey levels) whose window counts give the window's median |r|: FIRST_THRESHOLD 2^j.
FIRST_THRESHOLD = 0.25
THRESHOLDS = 10

#: Basis monomials (a, b) of (d_x/h)^a (d_y/h)^b, per motion component, of each local model.
_MONOMIALS = {"translation": ((0, 0),), "affine": ((0, 0), (1, 0), (0, 1))}


def local_model(settings: RobustMotionSettings, level: int) -> str:
    """The window's residual model on pyramid level ``level``: 'translation' (p=2) or 'affine' (p=6).

    Affine on the finest level unless ``settings.model`` is 'translation';
    translation on coarser levels, which only need to land in its basin.
    """
    return "affine" if level == 0 and settings.model != "translation" else "translation"


def local_levels(shape: tuple[int, int], levels: int) -> int:
    """``levels`` capped so that the coarsest level's shorter side is >= MIN_LOCAL_SIDE px."""
    return min(levels, 1 + max(0, int(np.log2(min(shape) / MIN_LOCAL_SIDE))))


def passes(level: int) -> int:
    """Warp + IRLS passes on pyramid level ``level`` (0: full resolution)."""
    return FINEST_PASSES if level == 0 else COARSE_PASSES


@dataclass(frozen=True)
class _Layout:
    """Windows of one pyramid level of ``shape`` (h, w) px.

    Pixels are summed over blocks of ``block`` px (block (i, j) covers rows
    i B .. i B + B - 1, columns j B .. j B + B - 1); a window is ``blocks`` x
    ``blocks`` blocks (side K B px); there is one node per block. Node (i, j)
    sits at level position (origin + j B, origin + i B) and its window covers
    the pixels s with -side/2 <= s - node < side/2.
    """

    level: int
    block: int
    blocks: int
    shape: tuple[int, int]

    @property
    def side(self) -> int:
        return self.block * self.blocks

    @property
    def origin(self) -> float:
        return (self.block - 1) / 2 - (self.blocks % 2 == 0) * self.block / 2

    @property
    def padded(self) -> tuple[int, int]:
        """(h, w) rounded up to whole blocks: the shape of the level's work arrays."""
        return tuple(-(-n // self.block) * self.block for n in self.shape)

    @property
    def node_shape(self) -> tuple[int, int]:
        """Nodes (blocks) per column and row: enough to hold every pixel and reach the last one."""
        return tuple(int(np.ceil((n - 1 - self.origin) / self.block)) + 1 for n in self.shape)

    def offsets(self) -> np.ndarray:
        """(K,) position of each block's centre relative to its window's centre (level px)."""
        return (np.arange(self.blocks) - (self.blocks - 1) / 2) * self.block

    def node_positions(self) -> np.ndarray:
        """(rows, columns, 2) full-resolution positions of the nodes (px)."""
        rows, cols = self.node_shape
        return 2**self.level * np.dstack(np.meshgrid(self.origin + self.block * np.arange(cols),
                                                     self.origin + self.block * np.arange(rows)))

    def maps_to(self, shape: tuple[int, int], level: int) -> np.ndarray:
        """(h, w, 2) float32 node coordinates of the pixels of a level (h, w) of pyramid level ``level``."""
        height, width = shape
        scale = 2.0 ** (level - self.level)
        maps = np.empty((height, width, 2), np.float32)
        maps[:, :, 0] = (scale * np.arange(width) - self.origin) / self.block
        maps[:, :, 1] = ((scale * np.arange(height) - self.origin) / self.block)[:, None]
        return maps


def _layout(settings: RobustMotionSettings, level: int, shape: tuple[int, int]) -> _Layout:
    side = max(settings.local_window / 2**level, MIN_WINDOW)
    block = max(1, round(side / (FINEST_BLOCKS if level == 0 else COARSE_BLOCKS)))
    return _Layout(level, block, max(1, round(side / block)), shape)


def _global_flow(fit: MotionFit, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 2) float32 U_g(x) of the global fit at every pixel (px)."""
    map_x, map_y = warp_maps(fit.model, fit.theta, fit.origin, fit.length, shape)
    height, width = shape
    map_x -= np.arange(width, dtype=np.float32)
    map_y -= np.arange(height, dtype=np.float32)[:, None]
    return np.dstack((map_x, map_y))


def _interpolate(nodes: np.ndarray, maps: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(h, w, C) float32 bilinear samples of node values (hn, wn, C) at node coordinates ``maps`` (h, w, 2)."""
    sampled = cv2.remap(np.ascontiguousarray(nodes, np.float32), maps, None, cv2.INTER_LINEAR, dst=out,
                        borderMode=cv2.BORDER_REPLICATE)
    return sampled.reshape(maps.shape[:2] + (nodes.shape[2],))


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


def _window_sums(sums: np.ndarray, lay: _Layout, orders) -> dict:
    """Window moments sum_{s in R} f(s) (d_x / h)^a (d_y / h)^b at the nodes, for the (a, b) in ``orders``.

    sums: (hn, wn, C) block sums of f; d = s - node, h = side / 2. Each pixel
    counts at its block's centre, plus the spread of a block's pixels about it
    ((B^2 - 1) / 12 per axis in order 2). Returns {(a, b): (hn, wn, C)}, dtype of ``sums``.
    """
    offsets = lay.offsets() / (lay.side / 2)
    anchor = lay.blocks // 2
    along_x = {a: cv2.filter2D(sums, -1, offsets[None] ** a, anchor=(anchor, 0), borderType=cv2.BORDER_CONSTANT)
               for a in {a for a, _ in orders}}
    moments = {(a, b): cv2.filter2D(along_x[a], -1, offsets[:, None] ** b, anchor=(0, anchor),
                                    borderType=cv2.BORDER_CONSTANT).reshape(sums.shape) for a, b in orders}
    spread = (lay.block**2 - 1) / 12 / (lay.side / 2) ** 2
    for order in ((2, 0), (0, 2)):
        if order in moments:
            moments[order] = moments[order] + spread * moments[0, 0]
    return moments


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


# Small symmetric systems, one per support and node: nested lists of (2, hn, wn) arrays.


def _cholesky(matrix: list) -> list:
    """Lower Cholesky factor L (L[i][j], j <= i) of positive definite matrices given by matrix[i][j], j >= i."""
    p = len(matrix)
    lower = [[None] * p for _ in range(p)]
    for j in range(p):
        lower[j][j] = np.sqrt(matrix[j][j] - sum(lower[j][k] ** 2 for k in range(j)))
        for i in range(j + 1, p):
            lower[i][j] = (matrix[j][i] - sum(lower[i][k] * lower[j][k] for k in range(j))) / lower[j][j]
    return lower


def _forward(lower: list, rhs: list) -> list:
    """z with L z = rhs."""
    z = []
    for i in range(len(rhs)):
        z.append((rhs[i] - sum(lower[i][k] * z[k] for k in range(i))) / lower[i][i])
    return z


def _backward(lower: list, z: list) -> list:
    """x with L^T x = z."""
    p = len(z)
    x = [None] * p
    for i in reversed(range(p)):
        x[i] = (z[i] - sum(lower[k][i] * x[k] for k in range(i + 1, p))) / lower[i][i]
    return x


def _with_ridge(matrix: list, prior: np.ndarray) -> list:
    """matrix + (prior + NUMERICAL_RIDGE max diagonal) I; prior (grey/px)^2 (the prior's precision times s^2)."""
    ridge = prior + NUMERICAL_RIDGE * np.max([matrix[i][i] for i in range(len(matrix))], axis=0)
    return [[entry + ridge if i == j else entry for j, entry in enumerate(row)] for i, row in enumerate(matrix)]


def _translation_covariance(lower: list, m: int) -> np.ndarray:
    """(..., 3) entries xx, xy, yy of the translation block (indices 0 and m) of N^-1, N = L L^T."""
    p = len(lower)
    shape = lower[0][0].shape
    columns = []
    for i in (0, m):
        unit = [np.full(shape, float(k == i)) for k in range(p)]
        columns.append(_forward(lower, unit))  # L^-1 e_i: (N^-1)_ij = (L^-1 e_i) . (L^-1 e_j)
    x, y = columns
    return np.stack((sum(a * a for a in x), sum(a * b for a, b in zip(x, y)), sum(b * b for b in y)), axis=-1)


def _normal_equations(sums: np.ndarray, lay: _Layout, model: str) -> tuple[list, list]:
    """Each node's window system, both supports: matrix[i][j] (j >= i) and rhs[i], each (2, hn, wn).

    sums: (hn, wn, 10) block sums of w g_x g_x, w g_x g_y, w g_y g_y, w g_x y,
    w g_y y, each as (dominant, non-dominant). The basis is
    P(d) = [phi(d), 0; 0, phi(d)], phi the monomials of d / (side / 2).
    """
    monomials = _MONOMIALS[model]
    m = len(monomials)
    orders = sorted({(ai + aj, bi + bj) for ai, bi in monomials for aj, bj in monomials})
    moments = _window_sums(sums, lay, orders)
    for order in moments:  # each float32 moment is let go as soon as its float64 copy replaces it
        moments[order] = np.ascontiguousarray(np.moveaxis(moments[order], 2, 0), np.float64)  # (10, hn, wn)
    product = {(0, 0): 0, (0, 1): 2, (1, 0): 2, (1, 1): 4}  # g_c g_c' -> first channel of its support pair
    matrix = [[None] * (2 * m) for _ in range(2 * m)]
    rhs = [None] * (2 * m)
    for i, (ai, bi) in enumerate(monomials):
        for c in (0, 1):
            rhs[c * m + i] = moments[ai, bi][6 + 2 * c : 8 + 2 * c]
        for j, (aj, bj) in enumerate(monomials):
            for ci in (0, 1):
                for cj in (0, 1):
                    if ci * m + i <= cj * m + j:
                        channel = product[ci, cj]
                        matrix[ci * m + i][cj * m + j] = moments[ai + aj, bi + bj][channel : channel + 2]
    return matrix, rhs


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


class _SearchBatch:
    """Work arrays of one batch of shifts of the block-matching start on one level layout (``_shift_costs``)."""

    def __init__(self, lay: _Layout):
        rows, cols = lay.padded
        node_rows, node_cols = lay.node_shape
        self.size = size = max(1, SEARCH_BATCH_PIXELS // (rows * cols))  # shifts per batch
        self.positions = np.empty((size, rows, cols, 2), np.float32)
        self.warped = np.empty((size * rows, cols), np.float32)
        self.valid = np.empty((size, rows, cols), np.float32)
        self.difference = np.empty((size, rows, cols), np.float32)
        self.squares = np.empty((size, rows, cols), np.float32)
        self.merged = np.empty((size * rows, cols, 3), np.float32)
        # each shift's block sums and blocks - 1 rows of zeros below them; only the block sums are ever written
        self.sums = np.zeros((size, node_rows + lay.blocks - 1, node_cols, 3), np.float32)


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
    """One warp + IRLS pass of every window of one level, both supports (module docstring).

    residual: (h, w, 4) float32 residual translation (full-resolution px) of the
    dominant field then of the other one at the level's pixels; each pixel is
    linearised at its own support's. Work arrays are reused and arithmetic is
    in place where it can be: fresh pages are slow (module docstring).
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
    """Each node's residual translation (hn, wn, 2) px and Q_k - q_floor I (hn, wn, 3) px^2 (module docstring).

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


def _searched_start(level: _Level, radius: int) -> np.ndarray:
    """(hn, wn, 4) float32 residual translation (full-resolution px) each node starts from on the coarsest level.

    Block matching of each node's window over integer shifts up to ``radius``
    level px from the global motion (both supports get the same start). The
    cost of a shift is the zero-mean SSD per pixel of the window (a brightness
    offset between the frames is not motion), over pixels landing inside frame
    k, at least half the window. A node keeps the shift of least cost (the
    first in raster order of (dy, dx) on a tie) where that cost is under
    SEARCH_GAIN times the unshifted one, else 0: on weak texture every shift
    costs about the same and the global motion is the better start. The starts
    are then median-filtered over 3 x 3 nodes. The shifts are evaluated in
    batches (``_shift_costs``): a shift of a small coarsest level is too little
    work per OpenCV or numpy call.
    """
    lay = level.lay
    side = 2 * radius + 1
    shifts = np.stack(np.meshgrid(np.arange(-radius, radius + 1), np.arange(-radius, radius + 1)), -1)
    shifts = shifts.reshape(-1, 2).astype(np.float32)  # (dx, dy), dy-major
    if level.work.search is None:
        level.work.search = _SearchBatch(lay)
    batch = level.work.search.size
    best_cost = np.full(lay.node_shape, np.inf)
    best = np.zeros(lay.node_shape + (2,), np.float32)
    reference = np.ascontiguousarray(level.cur[:, :, 0])
    for first in range(0, len(shifts), batch):
        costs = _shift_costs(level, reference, shifts[first : first + batch])
        index = costs.argmin(axis=0)
        cost = np.take_along_axis(costs, index[None], 0)[0]
        better = cost < best_cost
        best_cost = np.where(better, cost, best_cost)
        best[better] = shifts[first + index[better]]
        if first <= radius * side + radius < first + batch:
            unshifted = costs[radius * side + radius - first]
    moved = best_cost < SEARCH_GAIN * unshifted
    start = np.where(moved[:, :, None], best * np.float32(level.factor), np.float32(0))
    start = cv2.medianBlur(start, 3)  # per component over 3 x 3 nodes: an isolated false match does not start a node
    return np.dstack((start, start))


def _shift_costs(level: _Level, reference: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """(S, hn, wn) float64 zero-mean SSD per pixel of each node's window under each of S shifts (S, 2) (level px).

    inf where fewer than half the window's pixels land inside frame k. The S
    (at most ``level.work.search.size``) shifted frames are stacked along the rows,
    and each shift's block sums get blocks - 1 rows of zeros below them, so that
    the window sums of one shift see zeros beyond its own blocks as they would
    alone (BORDER_CONSTANT).
    """
    lay, batch = level.lay, level.work.search
    height, width = lay.shape
    rows, cols = lay.padded
    count = len(shifts)
    positions = np.add(level.base[None], shifts[:, None, None, :], out=batch.positions[:count])
    positions = positions.reshape(count * rows, cols, 2)
    warped = cv2.remap(reference, positions, None, cv2.INTER_LINEAR, dst=batch.warped[: count * rows],
                       borderMode=cv2.BORDER_REPLICATE)
    valid = batch.valid[:count]
    np.copyto(valid.reshape(count * rows, cols), cv2.inRange(positions, (0, 0), (width - 1, height - 1)),
              casting="unsafe")
    valid /= 255
    valid[:, height:], valid[:, :, width:] = 0, 0  # the padding
    difference = np.subtract(warped.reshape(count, rows, cols), level.intensity, out=batch.difference[:count])
    difference *= valid
    squares = np.multiply(difference, difference, out=batch.squares[:count])
    planes = [plane.reshape(count * rows, cols) for plane in (difference, squares, valid)]
    summed = cv2.merge(planes, batch.merged[: count * rows])
    block = lay.block
    if block > 1:
        summed = cv2.resize(summed, (cols // block, count * rows // block), interpolation=cv2.INTER_AREA)
    node_rows, node_cols = lay.node_shape
    sums = batch.sums[:count]
    sums[:, : rows // block, : cols // block] = summed.reshape(count, rows // block, cols // block, 3)
    sums[:, : rows // block, : cols // block] *= block**2
    windows = _window_sums(sums.reshape(-1, node_cols, 3), lay, ((0, 0),))[0, 0]
    windows = windows.reshape(count, -1, node_cols, 3)[:, :node_rows].astype(np.float64)
    total, square_sum, valid_count = windows[..., 0], windows[..., 1], windows[..., 2]
    enough = 0.5 * lay.side**2
    pixels = np.maximum(valid_count, 1)
    return np.where(valid_count >= enough, (square_sum - total**2 / pixels) / pixels, np.inf)


def local_field(prev: Pyramid, cur: Pyramid, fit: MotionFit, settings: RobustMotionSettings,
                workspaces: dict | None = None) -> LocalField:
    """The local motion field from pyramids of frames k-1 and k (``build_pyramid``, local depth) and the global fit.

    See the module docstring for the estimator and what it shares between windows.
    workspaces: work arrays by level layout, filled on first use; pass the same
    dict for every frame pair of a sequence to reuse them.
    """
    workspaces = {} if workspaces is None else workspaces
    global_flow = _global_flow(fit, prev.base.shape)
    nodes, node_layout = None, None
    for index in reversed(range(len(prev.levels))):
        level = _Level(prev.levels[index], cur.levels[index], index, global_flow, fit.weights, settings, workspaces)
        if nodes is None and settings.local_search:
            nodes, node_layout = _searched_start(level, int(np.ceil(settings.local_search / level.factor))), level.lay
            residual = _interpolate(nodes, level.work.maps, level.work.residual)
        elif nodes is None:
            residual = np.zeros(level.lay.padded + (4,), np.float32)
        else:
            residual = _interpolate(nodes, node_layout.maps_to(level.lay.padded, index), level.work.residual)
        for _ in range(passes(index)):
            systems = None  # the last pass's systems go before this pass makes its own (memory)
            systems = _level_pass(level, residual, settings)
            nodes, node_layout = systems.residual_nodes(), level.lay
            residual = _interpolate(nodes, level.work.maps, level.work.residual)
    translation, cov = _choose(systems, residual, level, settings)
    node_xy = level.lay.node_positions()
    flow = displacement(fit, node_xy.reshape(-1, 2)).reshape(translation.shape) + translation
    flow, cov = flow.astype(np.float32), cov.astype(np.float32)
    for array in (flow, cov):
        array.flags.writeable = False
    return LocalField(flow, cov, float(node_xy[0, 0, 0]), float(level.lay.block), settings.q_floor)


class LocalMotion:
    """Local-support motion stage (CNLF dynamics, ``motion/interface.py``): one field per frame pair."""

    def __init__(self, settings: RobustMotionSettings):
        self.settings = settings
        self._workspaces = {}  # work arrays by level layout, kept from frame to frame (not thread-safe)

    def field(self, prev: Frame, cur: Frame, fit: MotionFit) -> LocalField:
        """The field from ``prev`` to ``cur`` on the global ``fit`` of the same pair; pyramids from ``frame_pyramid``."""
        levels = local_levels(prev.image.shape, self.settings.levels)
        return local_field(frame_pyramid(prev, levels), frame_pyramid(cur, levels), fit, self.settings, self._workspaces)


def _masked_median(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(M,) median of each row of values (M, K) over its entries where mask (M, K); 0 for an empty row."""
    count = mask.sum(axis=1)
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    low = np.take_along_axis(ordered, np.maximum((count - 1) // 2, 0)[:, None], 1)[:, 0]
    high = np.take_along_axis(ordered, np.minimum(count // 2, values.shape[1] - 1)[:, None], 1)[:, 0]
    return np.where(count > 0, (low + high) / 2, 0.0)


def exact_local_motion(prev_gray: np.ndarray, cur_gray: np.ndarray, xy: np.ndarray,
                       settings: RobustMotionSettings) -> tuple[np.ndarray, np.ndarray]:
    """The reference: one robust regression per position on its own window (module docstring).

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
    Q_k (M, 2, 2) px^2. Memory ~ 40 M side^2 numbers: callers batch the positions.
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
