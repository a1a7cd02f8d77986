"""Two-way smoothing of a finished pass (``filter.smooth``, ``condtrack track --smooth``).

A batch run sees the whole clip, so the estimate of frame k can use frames
after k too. Two smoothers, each a pure function of what the forward filter
recorded, batched over points (arrays (P, F, ...); the only loop is over frames):

- :func:`rts`, the Rauch-Tung-Striebel smoother of the CLF. The CLF's dynamics
  are x_k = A_k x_{k-1} + b_k + w_k (paper eq. 1), A_k per point (the Jacobian
  of the motion at the point); the filter records, per frame, the predicted
  mean x_{k|k-1}, covariance Sigma_{k|k-1} and the A_k it used
  (:class:`TransitionLog`). Backwards from the last frame:
  G_k = Sigma_{k|k} A_{k+1}^T Sigma_{k+1|k}^-1,
  x_{k|F} = x_{k|k} + G_k (x_{k+1|F} - x_{k+1|k}),
  Sigma_{k|F} = Sigma_{k|k} + G_k (Sigma_{k+1|F} - Sigma_{k+1|k}) G_k^T.
  A frame where the point coasted (no usable measurement, R infinite) has
  Sigma_{k|k} = Sigma_{k|k-1}, and the recursion interpolates it between the
  measured frames around it.
- :func:`particle_smoother`, the CNLF's forward-filtering backward-smoothing
  (FFBSm, the marginal smoother of Doucet, Godsill & Andrieu 2000): the
  particles of every frame keep their positions and get smoothed weights
  w_{k|F}^(i) = w_k^(i) sum_j w_{k+1|F}^(j) f(x_{k+1}^(j) | x_k^(i)) / sum_l w_k^(l) f(x_{k+1}^(j) | x_k^(l)),
  f(. | x_k^(i)) = N(mu^(i), Q^(i)) the local dynamics of eq. (5). Chosen over
  backward simulation (FFBSi) and fixed-lag smoothing: the output is a
  marginal mean and covariance per frame, which FFBSm gives exactly from all
  N particles of every frame at O(N^2) per point and frame (FFBSi with N
  backward draws costs the same and adds Monte Carlo noise); a fixed-lag
  smoother reuses the ancestry, which collapses to a few lineages within a
  few resamplings (the path mean already suffers from it), and a short lag
  smooths little.

Both work on segments: ``linked`` (P, F) is True at frame k when the
transition from k-1 to k belongs to the same filter run (the point was
tracked by this filter on both frames); elsewhere the recursion restarts, so
frame k-1 keeps its filtered estimate as the last frame of its segment.
"""

from __future__ import annotations

import numpy as np

from condtrack_cli.filters.gauss2 import inverse2
from condtrack_cli.filters.resampling import sum_over_particles
from condtrack_cli.special import logsumexp


class TransitionLog:
    """Per-frame record of what a filter used to move its points into each frame, by name.

    ``shapes`` gives each recorded array's per-point shape, e.g. A=(2, 2).
    Frames and points without a record are NaN in :meth:`stacked`.
    """

    def __init__(self, n_points: int, **shapes: tuple[int, ...]):
        self.n_points, self.shapes = n_points, shapes
        self.frames: dict[int, dict[str, np.ndarray]] = {}

    def record(self, frame_index: int, index: np.ndarray, **arrays: np.ndarray) -> None:
        """Points ``index`` (n,) moved into frame ``frame_index`` with the (n, *shape) ``arrays``."""
        if frame_index not in self.frames:
            self.frames[frame_index] = {k: np.full((self.n_points, *s), np.nan) for k, s in self.shapes.items()}
        for name, values in arrays.items():
            self.frames[frame_index][name][index] = values

    def stacked(self, name: str, n_frames: int) -> np.ndarray:
        """(P, F, *shape) array ``name`` over frames 0..n_frames-1."""
        out = np.full((self.n_points, n_frames, *self.shapes[name]), np.nan)
        for k, arrays in self.frames.items():
            out[:, k] = arrays[name]
        return out


def error_excess(excess: np.ndarray) -> np.ndarray:
    """(P, F, 2, 2) what the error model (``calibration.py``) added to the filter's covariance, 0 where not recorded.

    The smoothers narrow the filter's own covariance only: the later frames do not
    undo a reference patch's drift or a wrong match, so the smoothed covariance
    keeps the excess the forward pass reported on the same frame (px^2).
    """
    return np.where(np.isnan(excess), 0.0, excess)


def rts(
    xy: np.ndarray, cov: np.ndarray, x_pred: np.ndarray, cov_pred: np.ndarray, A: np.ndarray, linked: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Rauch-Tung-Striebel smoothing of filtered estimates, per point and segment.

    xy (P, F, 2), cov (P, F, 2, 2): filtered x_{k|k}, Sigma_{k|k}; x_pred (P, F, 2),
    cov_pred (P, F, 2, 2), A (P, F, 2, 2): prediction into frame k and the A_k it
    used; linked (P, F) bool: the transition k-1 -> k is part of the segment.
    Returns the smoothed (P, F, 2) means and (P, F, 2, 2) covariances (the
    filtered ones where no later frame is linked).
    """
    xs, cs = xy.copy(), cov.copy()
    for k in range(xy.shape[1] - 2, -1, -1):
        on = np.flatnonzero(linked[:, k + 1])
        if not on.size:
            continue
        sigma, sigma_next = cov[on, k], cov_pred[on, k + 1]
        gain = sigma @ np.swapaxes(A[on, k + 1], 1, 2) @ np.linalg.inv(sigma_next)  # G_k
        xs[on, k] = xy[on, k] + np.einsum("nij,nj->ni", gain, xs[on, k + 1] - x_pred[on, k + 1])
        smoothed = sigma + gain @ (cs[on, k + 1] - sigma_next) @ np.swapaxes(gain, 1, 2)
        cs[on, k] = (smoothed + np.swapaxes(smoothed, 1, 2)) / 2
    return xs, cs


def particle_smoother(
    particles: np.ndarray, log_w: np.ndarray, mu: np.ndarray, Q: np.ndarray, linked: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """FFBSm: smoothed means and covariances of weighted particles, per point and segment.

    particles (P, F, N, 2) and their normalised filter log-weights log_w (P, F, N)
    on each frame (NaN particles where the point is not on the filter); mu
    (P, F, N, 2), Q (P, F, N, 2, 2): the dynamics N(mu^(i), Q^(i)) that moved
    particle i of frame k-1 into frame k (eq. 5); linked (P, F) bool as in :func:`rts`.
    Returns (P, F, 2) means and (P, F, 2, 2) covariances under the smoothed
    weights, NaN where the point has no particles.
    """
    smoothed = log_w.copy()
    for k in range(particles.shape[1] - 2, -1, -1):
        on = np.flatnonzero(linked[:, k + 1])
        if not on.size:
            continue
        log_f = transition_log_density(particles[on, k + 1], mu[on, k + 1], Q[on, k + 1])
        w_k = log_w[on, k]
        predicted = logsumexp(w_k[:, :, None] + log_f, axis=1)  # (n, j): log sum_l w_k^(l) f(x_{k+1}^(j) | x_k^(l))
        backward = logsumexp(smoothed[on, k + 1][:, None, :] + log_f - predicted[:, None, :], axis=2)  # (n, i)
        unnormalised = w_k + backward
        smoothed[on, k] = unnormalised - logsumexp(unnormalised, axis=1, keepdims=True)
    return weighted_moments(particles, smoothed)


def transition_log_density(x_next: np.ndarray, mu: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """(n, N, N) log N(x_next^(j); mu^(i), Q^(i)) at [:, i, j] for x_next, mu (n, N, 2) and Q (n, N, 2, 2).

    The quadratic form is written out (three products per pair) rather than
    broadcast through ``log_gauss2``: this N^2 table is the smoother's whole cost.
    """
    inv = inverse2(Q)
    log_norm = -0.5 * np.log(Q[..., 0, 0] * Q[..., 1, 1] - Q[..., 0, 1] ** 2) - np.log(2 * np.pi)  # (n, N)
    dx = x_next[:, None, :, 0] - mu[:, :, None, 0]
    dy = x_next[:, None, :, 1] - mu[:, :, None, 1]
    quad = inv[..., 0, 0, None] * dx * dx + 2 * inv[..., 0, 1, None] * dx * dy + inv[..., 1, 1, None] * dy * dy
    return log_norm[..., None] - 0.5 * quad


def weighted_moments(particles: np.ndarray, log_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (..., 2) and covariance (..., 2, 2) of particles (..., N, 2) with normalised log-weights (..., N)."""
    w = np.exp(log_w)
    mean = sum_over_particles(w[..., None] * particles, axis=-2)
    d = particles - mean[..., None, :]
    return mean, np.einsum("...n,...ni,...nj->...ij", w, d, d)
