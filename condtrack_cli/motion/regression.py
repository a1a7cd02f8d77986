"""The paper's local motion: a robust regression on the window around each asked position (§5.1, eq. 5; issue 29).

The ``regression`` motion stage. The global fit is the robust stage's (``robust.py``:
brightness IRLS on the whole frame, eq. 3). The local motion is not a shared field:
for every position x that a filter asks about (each CNLF particle x_{k-1}^(i), the
paper's Fig. 2 "pour i = 1 : N, évaluer theta_k^(i)"; each CLF point with local
dynamics), U(x) and Q_k(x) come from the robust parametric regression of §5.1 on
the ``local_window`` x ``local_window`` square centred on x (the paper's 32 x 32),
``local/exact.py: window_regression``, the per-window reference of the shared field
(``motion/local/__init__.py``'s module docstring): coarse to fine on the frames' pyramids, from the
global fit (the paper does not say where the regression starts), affine on the
full-resolution level, Tukey (``robust_cost``) IRLS, Q_k the weighted-least-squares
covariance of the window's translation plus ``q_floor``.

The positions are solved together, vectorised, in batches of BATCH_POSITIONS (memory
~ 40 side^2 numbers a position); the last call's answer is kept, since a filter asks
for U and Q_k at the same positions in turn. Slow by design: the CNLF's 100
particles per point are 100 regressions per point and frame.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from condtrack_cli.motion.interface import MotionStages
from condtrack_cli.motion.local.exact import window_regression
from condtrack_cli.motion.local.windows import _global_flow, local_levels
from condtrack_cli.motion.model import MotionFit
from condtrack_cli.motion.pyramid import frame_pyramid
from condtrack_cli.motion.robust import GlobalMotion, RobustMotionSettings
from condtrack_cli.motion.state_noise import StateNoise
from condtrack_cli.types import Frame, Pyramid

#: Positions solved at once (memory ~ 40 side^2 float64 a position: ~84 MB for 32 px windows).
BATCH_POSITIONS = 256


class RegressionSettings(RobustMotionSettings):
    """The robust stage's settings; the local window's regression has no block-matching start."""

    local_search: int = Field(
        0, ge=0, le=0, description="not used: each window's regression starts from the global fit (paper §5.1 says no start)"
    )


class RegressionField:
    """U(x) and Q_k(x) of eq. (5) by one robust regression per asked position (the ``LocalField`` interface).

    spacing: the step (px) of ``clf.local_dynamics``'s central differences for A_k.
    """

    spacing = 1.0

    def __init__(self, prev: Pyramid, cur: Pyramid, fit: MotionFit, settings: RegressionSettings):
        self.prev, self.cur, self.fit, self.settings = prev, cur, fit, settings
        self.global_flow = _global_flow(fit, prev.base.shape)
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # xy, U, Q of the last call

    def _solve(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xy = np.asarray(xy, np.float64)
        if self._last is not None and self._last[0].shape == xy.shape and np.array_equal(self._last[0], xy):
            return self._last[1], self._last[2]
        flat = xy.reshape(-1, 2)
        u = np.zeros_like(flat)
        q = np.broadcast_to(self.settings.q_floor * np.eye(2), (len(flat), 2, 2)).copy()
        finite = np.flatnonzero(np.isfinite(flat).all(axis=1))  # others: no motion, the floor (never asked in practice)
        for start in range(0, len(finite), BATCH_POSITIONS):
            rows = finite[start : start + BATCH_POSITIONS]
            u[rows], q[rows] = window_regression(self.prev, self.cur, self.global_flow, self.fit, flat[rows],
                                                 self.settings)
        u, q = u.reshape(xy.shape), q.reshape(xy.shape[:-1] + (2, 2))
        self._last = (xy.copy(), u, q)
        return u, q

    def displacement(self, xy: np.ndarray) -> np.ndarray:
        """U(x) (..., 2) px at positions x (..., 2) of frame k-1: the mean x_{k-1} + U of eq. (5)."""
        return self._solve(xy)[0]

    def noise(self, xy: np.ndarray) -> np.ndarray:
        """Q_k(x) (..., 2, 2) px^2 at positions x (..., 2): the window regression's covariance plus q_floor I."""
        return self._solve(xy)[1]


class RegressionMotion:
    """Local-support motion stage (``motion/interface.py``): a ``RegressionField`` per frame pair."""

    def __init__(self, settings: RegressionSettings):
        self.settings = settings

    def field(self, prev: Frame, cur: Frame, fit: MotionFit) -> RegressionField:
        """The per-position regression from ``prev`` to ``cur`` around the global ``fit`` of the same pair."""
        levels = local_levels(prev.image.shape, self.settings.levels)
        return RegressionField(frame_pyramid(prev, levels), frame_pyramid(cur, levels), fit, self.settings)


def make_regression_motion(settings: RegressionSettings, **_context) -> MotionStages:
    """Robust global fit (``robust.py``); the local motion regressed per position (``RegressionMotion``); Q_k."""
    return MotionStages(
        global_motion=GlobalMotion(settings),
        local_motion=RegressionMotion(settings),
        state_noise=StateNoise.of(settings),
    )
