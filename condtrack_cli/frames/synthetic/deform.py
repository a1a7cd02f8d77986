"""Smooth non-rigid deformations for the ``nonrigid`` scene: Gaussian radial-basis displacement bumps.

A deformation of frame-0 positions is defined by its *backward* form, which the
renderer evaluates on every pixel: a point at u (frame-0 pixels, before the
global motion) shows the material that sits at ``x0 = u + D(u, k)`` on frame 0, with

    D(u, k) = sum_j a_j(k) v_j exp(-|u - c_j|^2 / (2 s_j^2)),
    a_j(k) = A_j (sin(2 pi f_j t_k + phi_j) - sin(phi_j)),   t_k = k / (F - 1),

so D(., 0) = 0. The forward map (where the material of x0 is on frame k) is the
inverse, found by Newton's method on u + D(u, k) = x0 (:meth:`Bumps.forward`),
converged to 1e-10 px: exact ground truth whatever the renderer's grid.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

#: Newton's method stops when every step is below this (px), after at most NEWTON_STEPS steps.
NEWTON_TOLERANCE = 1e-10
NEWTON_STEPS = 50
#: Smallest Jacobian determinant of a random deformation (:func:`random_bumps`): no fold, no strong squeeze.
MIN_JACOBIAN = 0.5


@dataclass(frozen=True)
class Bumps:
    """J Gaussian bumps over F frames.

    centres: (J, 2) c_j in frame-0 pixels; directions: (J, 2) unit v_j (or (J, C): a C-valued field, as the
    ``nonrigid`` scene's contrast gain, (J, 1)); sigmas: (J,) s_j px; amplitudes: (J, F) a_j(k) (px for a
    displacement), zero on frame 0.
    """

    centres: np.ndarray
    directions: np.ndarray
    sigmas: np.ndarray
    amplitudes: np.ndarray

    def _weights(self, u: np.ndarray, k: int) -> np.ndarray:
        """(N, J) a_j(k) exp(-|u - c_j|^2 / (2 s_j^2)) at u (N, 2)."""
        squared = (u[:, 0, None] - self.centres[:, 0]) ** 2 + (u[:, 1, None] - self.centres[:, 1]) ** 2
        return np.exp(squared * (-0.5 / self.sigmas**2)) * self.amplitudes[:, k]

    def displacement(self, u: np.ndarray, k: int) -> np.ndarray:
        """(N, 2) D(u, k) at u (N, 2) px ((N, C) for (J, C) directions)."""
        return self._weights(u, k) @ self.directions

    def jacobian(self, u: np.ndarray, k: int) -> np.ndarray:
        """(N, 2, 2) d(u + D(u, k)) / du at u (N, 2)."""
        # d/du [w_j v_j] = v_j (grad w_j)^T, grad w_j = -w_j (u - c_j) / s_j^2
        grad = -(self._weights(u, k) / self.sigmas**2)[..., None] * (u[:, None, :] - self.centres[None])
        return np.eye(2) + np.einsum("ja,njb->nab", self.directions, grad)

    def forward(self, x0: np.ndarray, k: int) -> np.ndarray:
        """(N, 2) u with u + D(u, k) = x0 for x0 (N, 2), by Newton's method from u = x0 - D(x0, k).

        ValueError when it does not converge (a deformation that folds).
        """
        u = x0 - self.displacement(x0, k)
        for _ in range(NEWTON_STEPS):
            step = np.linalg.solve(self.jacobian(u, k), (u + self.displacement(u, k) - x0)[..., None])[..., 0]
            u = u - step
            if np.max(np.abs(step), initial=0.0) < NEWTON_TOLERANCE:
                return u
        raise ValueError(f"the deformation of frame {k} could not be inverted (it folds)")


def random_bumps(rng: np.random.Generator, size: tuple[int, int], n_frames: int, count: int = 8) -> Bumps:
    """``count`` bumps over a W x H frame: centres inside it, widths s_j 6-10 % of the smaller side, peak amplitudes
    A_j 4-8 px (|a_j| <= 2 A_j), 1.5-3 cycles over the sequence, random directions and phases.

    Where the bumps together would fold the frame (the Jacobian determinant of u -> u + D(u, k) below
    ``MIN_JACOBIAN`` somewhere on a 4 px grid over the frame and 8 px beyond), every amplitude is scaled down by
    0.8 until it no longer does.
    """
    w, h = size
    side = min(w, h)
    angle = rng.uniform(0, 2 * np.pi, count)
    peak, cycles, phase = rng.uniform(4.0, 8.0, count), rng.uniform(1.5, 3.0, count), rng.uniform(0, 2 * np.pi, count)
    t = np.arange(n_frames) / (n_frames - 1)
    bumps = Bumps(
        centres=np.column_stack([rng.uniform(0.1, 0.9, count) * (w - 1), rng.uniform(0.1, 0.9, count) * (h - 1)]),
        directions=np.column_stack([np.cos(angle), np.sin(angle)]),
        sigmas=rng.uniform(0.06, 0.10, count) * side,
        amplitudes=peak[:, None] * (np.sin(2 * np.pi * cycles[:, None] * t + phase[:, None]) - np.sin(phase)[:, None]),
    )
    grid = np.stack(np.meshgrid(np.arange(-8.0, w + 8, 4), np.arange(-8.0, h + 8, 4)), axis=-1).reshape(-1, 2)
    while min(np.linalg.det(bumps.jacobian(grid, k)).min() for k in range(n_frames)) < MIN_JACOBIAN:
        bumps = replace(bumps, amplitudes=0.8 * bumps.amplitudes)
    return bumps
