"""Batched conditional Kalman algebra (paper §3.2, Fig. 1), vectorised over points.

Every function takes arrays with a leading point axis: x (n, 2), Sigma (n, 2, 2),
and returns new arrays (inputs are never modified).
"""

from __future__ import annotations

import numpy as np


def predict(x: np.ndarray, sigma: np.ndarray, A: np.ndarray, b: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fig. 1 prediction: x_{k|k-1} = A x + b; Sigma_{k|k-1} = A Sigma A^T + Q.

    x (n, 2), sigma (n, 2, 2), A (n, 2, 2), b (n, 2), Q (n, 2, 2).
    """
    x_pred = np.einsum("nij,nj->ni", A, x) + b
    sigma_pred = A @ sigma @ np.swapaxes(A, 1, 2) + Q
    return x_pred, sigma_pred


def update(
    x_pred: np.ndarray, sigma_pred: np.ndarray, z: np.ndarray, R: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Fig. 1 update with H = I, skipped where ``valid`` is False (posterior = prior).

    K = Sigma (Sigma + R)^-1; x = x_pred + K (z - x_pred); the covariance in the
    Joseph form (I - K) Sigma (I - K)^T + K R K^T, equal to the paper's
    (I - K) Sigma for the optimal gain but symmetric and positive by construction.
    x_pred (n, 2), sigma_pred (n, 2, 2), z (n, 2), R (n, 2, 2), valid (n,) bool.
    """
    x_post, sigma_post = x_pred.copy(), sigma_pred.copy()
    if not valid.any():
        return x_post, sigma_post
    s, r, zz, xp = sigma_pred[valid], R[valid], z[valid], x_pred[valid]
    gain = s @ np.linalg.inv(s + r)  # K_k = Sigma_{k|k-1} (Sigma_{k|k-1} + R_k)^-1
    x_post[valid] = xp + np.einsum("nij,nj->ni", gain, zz - xp)
    i_minus_k = np.eye(2) - gain
    joseph = i_minus_k @ s @ np.swapaxes(i_minus_k, 1, 2) + gain @ r @ np.swapaxes(gain, 1, 2)
    sigma_post[valid] = (joseph + np.swapaxes(joseph, 1, 2)) / 2
    return x_post, sigma_post


def mahalanobis2(nu: np.ndarray, S: np.ndarray) -> np.ndarray:
    """(n,) nu^T S^-1 nu for innovations nu (n, 2) and covariances S (n, 2, 2) (the gate of §3.2)."""
    return np.einsum("ni,ni->n", nu, np.linalg.solve(S, nu[..., None])[..., 0])
