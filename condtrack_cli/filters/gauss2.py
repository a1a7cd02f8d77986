"""Closed-form algebra of 2-D Gaussians, batched over any leading axes (the CNLF and the smoothers)."""

from __future__ import annotations

import numpy as np


def inverse2(m: np.ndarray) -> np.ndarray:
    """Inverses of (..., 2, 2) symmetric positive-definite matrices, in closed form."""
    a, b, d = m[..., 0, 0], m[..., 0, 1], m[..., 1, 1]
    det = a * d - b * b
    out = np.empty_like(m)
    out[..., 0, 0], out[..., 1, 1] = d / det, a / det
    out[..., 0, 1] = out[..., 1, 0] = -b / det
    return out


def log_gauss2(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """log N(x; mean, cov) for (..., 2) points and (..., 2, 2) covariances."""
    d = x - mean
    inv = inverse2(cov)
    quad = np.einsum("...i,...ij,...j->...", d, inv, d)
    det = cov[..., 0, 0] * cov[..., 1, 1] - cov[..., 0, 1] ** 2
    return -0.5 * quad - 0.5 * np.log(det) - np.log(2 * np.pi)


def sample_gauss2(rng: np.random.Generator, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Draws from N(mean, cov), (..., 2) and (..., 2, 2), with a closed-form 2x2 Cholesky factor."""
    a, b, d = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    l11 = np.sqrt(a)
    l21 = b / l11
    l22 = np.sqrt(np.maximum(d - l21 * l21, 0.0))
    e = rng.standard_normal(mean.shape)
    return mean + np.stack([l11 * e[..., 0], l21 * e[..., 0] + l22 * e[..., 1]], axis=-1)
