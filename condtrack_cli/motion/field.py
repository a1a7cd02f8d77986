"""The local motion field handed to the filters: U(x) and Q_k(x) of eq. (5) on a grid, sampled at any positions.

Two local estimators build one: ``local/`` (the robust regression on a grid of
windows, nodes every few px) and ``dense.py`` (the DIS field, a node per pixel). The
``regression`` stage's ``RegressionField`` (``regression.py``) has the same interface
(``displacement``, ``noise``, ``spacing``) but regresses at each asked position instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from condtrack_cli.motion.robust import _sample


@dataclass(frozen=True)
class LocalField:
    """Local motion from frame k-1 to frame k on a grid of windows (arrays are read-only).

    flow: (hn, wn, 2) float32, U at the nodes (px). cov: (hn, wn, 3) float32, Q_k - q_floor I at
    the nodes as (xx, xy, yy) px^2. Node (i, j) sits at position
    (origin + j spacing, origin + i spacing) of frame k-1 (px, the package's
    pixel convention). q_floor: px^2, added by ``noise``.
    """

    flow: np.ndarray
    cov: np.ndarray
    origin: float
    spacing: float
    q_floor: float

    def _at(self, values: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """(..., C) float64 bilinear samples of node values (hn, wn, C) at positions xy (..., 2) px.

        Positions beyond the outer nodes take the nearest node's value.
        """
        xy = np.asarray(xy, np.float64)
        grid = ((xy.reshape(-1, 2) - self.origin) / self.spacing).astype(np.float32)
        return _sample(values, grid).astype(np.float64).reshape(xy.shape[:-1] + (values.shape[2],))

    def displacement(self, xy: np.ndarray) -> np.ndarray:
        """U(x) (..., 2) px at positions x (..., 2) of frame k-1: the mean x_{k-1} + U of eq. (5)."""
        return self._at(self.flow, xy)

    def noise(self, xy: np.ndarray) -> np.ndarray:
        """Q_k(x) (..., 2, 2) px^2 at positions x (..., 2): symmetric, eigenvalues >= q_floor (eq. 5)."""
        xx, xy_, yy = np.moveaxis(self._at(self.cov, xy), -1, 0)
        xx, yy = np.maximum(xx, 0.0), np.maximum(yy, 0.0)  # float32 rounding of a variance near 0
        bound = np.sqrt(xx * yy)  # keeps float32 rounding from making a nearly singular cov indefinite
        cov = np.empty(xx.shape + (2, 2))
        cov[..., 0, 0], cov[..., 1, 1] = xx + self.q_floor, yy + self.q_floor
        cov[..., 0, 1] = cov[..., 1, 0] = np.clip(xy_, -bound, bound)
        return cov
