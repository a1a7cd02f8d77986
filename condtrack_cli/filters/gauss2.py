"""Closed-form algebra of 2-D Gaussians, batched over any leading axes (the CNLF and the smoothers).

Written out per component rather than with ``np.linalg`` or ``np.einsum``, whose
generic loops are slow on many small 2x2 blocks (the CNLF's (P, N, 2, 2)); the
products and sums are those ``np.einsum`` computes, in its order, so the results
equal its results bit for bit.
"""

from __future__ import annotations

import numpy as np


def _inverse_terms(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(xx, xy, yy) terms of the inverses of (..., 2, 2) symmetric matrices, and their determinants (...)."""
    a, b, d = m[..., 0, 0], m[..., 0, 1], m[..., 1, 1]
    det = a * d - b * b
    return d / det, -b / det, a / det, det


def inverse2(m: np.ndarray) -> np.ndarray:
    """Inverses of (..., 2, 2) symmetric positive-definite matrices, in closed form."""
    xx, xy, yy, _ = _inverse_terms(m)
    out = np.empty_like(m)
    out[..., 0, 0], out[..., 1, 1] = xx, yy
    out[..., 0, 1] = out[..., 1, 0] = xy
    return out


def symmetrize(m: np.ndarray) -> np.ndarray:
    """Set both off-diagonal entries of (..., 2, 2) float matrices ``m`` to their mean, in place, and return ``m``
    (a reported covariance's xy and yx, which sums of products can leave a bit apart; halved before the sum, so
    that no finite entry overflows, and equal entries stay as they are)."""
    m[..., 0, 1] = m[..., 1, 0] = 0.5 * m[..., 0, 1] + 0.5 * m[..., 1, 0]
    return m


def matvec2(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(..., 2) products m v of (..., 2, 2) matrices and (..., 2) vectors (broadcast)."""
    v0, v1 = v[..., 0], v[..., 1]
    first = m[..., 0, 0] * v0 + m[..., 0, 1] * v1
    out = np.empty(first.shape + (2,))
    out[..., 0] = first
    out[..., 1] = m[..., 1, 0] * v0 + m[..., 1, 1] * v1
    return out


def log_gauss2(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """log N(x; mean, cov) for (..., 2) points and (..., 2, 2) symmetric covariances."""
    d = x - mean
    d0, d1 = d[..., 0], d[..., 1]
    xx, xy, yy, det = _inverse_terms(cov)
    quad = (d0 * xx) * d0 + (d0 * xy) * d1 + (d1 * xy) * d0 + (d1 * yy) * d1  # d^T cov^-1 d
    return -0.5 * quad - 0.5 * np.log(det) - np.log(2 * np.pi)


def sample_gauss2(mean: np.ndarray, cov: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Draws from N(mean, cov), (..., 2) and (..., 2, 2): mean + L e, L the closed-form 2x2 Cholesky factor of cov
    and e (..., 2) standard normal draws."""
    a, b, d = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    l11 = np.sqrt(a)
    l21 = b / l11
    l22 = np.sqrt(np.maximum(d - l21 * l21, 0.0))
    e0, e1 = e[..., 0], e[..., 1]
    out = np.empty(e.shape)
    out[..., 0] = mean[..., 0] + l11 * e0
    out[..., 1] = mean[..., 1] + (l21 * e0 + l22 * e1)
    return out
