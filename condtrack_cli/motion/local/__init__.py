"""Robust parametric motion between two frames, local support (paper §5.1, eq. 5): ``local_field``, ``LocalMotion``.

One algorithm in the order it runs: ``windows.py`` (models per level, node and
block layouts, window sums), ``start.py`` (the coarsest level's block-matching
start), ``level.py`` (one level's warp + IRLS passes over both supports and the
final choice of support and Q_k), ``systems.py`` (the small per-node normal
equations and their solves); ``exact.py`` is the per-window reference the tests
compare the field with.

The CNLF moves each particle x_{k-1}^(i) by the motion of a window R (side
``local_window``, 32 px by default) centred on it:
p(x_k | x_{k-1}) = N(x_{k-1} + U(x_{k-1}), Q_k(x_{k-1})) (eq. 5). This module
estimates U and Q_k once per frame pair on a grid of windows (``LocalMotion``,
``LocalField``) and samples them at any positions.

The per-window regression (``exact_local_motion``, the reference):

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

import numpy as np

from condtrack_cli.motion.field import LocalField
from condtrack_cli.motion.interface import MotionStages
from condtrack_cli.motion.local.level import _choose, _Level, _level_pass
from condtrack_cli.motion.local.start import _searched_start
from condtrack_cli.motion.local.windows import _global_flow, _interpolate, local_levels, passes
from condtrack_cli.motion.model import MotionFit, displacement
from condtrack_cli.motion.pyramid import frame_pyramid
from condtrack_cli.motion.robust import GlobalMotion, RobustMotionSettings
from condtrack_cli.motion.state_noise import StateNoise
from condtrack_cli.types import Frame, Pyramid


def local_field(prev: Pyramid, cur: Pyramid, fit: MotionFit, settings: RobustMotionSettings,
                workspaces: dict | None = None) -> LocalField:
    """The local motion field from pyramids of frames k-1 and k (``build_pyramid``, local depth) and the global fit.

    See the ``motion.local`` docstring for the estimator and what it shares between windows.
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


def make_robust_motion(settings: RobustMotionSettings, **_context) -> MotionStages:
    """Robust parametric motion: global support (``robust.py``), local support (``LocalMotion``), Q_k (``state_noise.py``)."""
    return MotionStages(
        global_motion=GlobalMotion(settings),
        local_motion=LocalMotion(settings),
        state_noise=StateNoise.of(settings),
    )
