"""Particle weights and resampling schemes, vectorised over points: arrays (n points, N particles).

Schemes are looked up by name in ``RESAMPLERS``; each maps normalised weights
(n, N) and one uniform draw per row (n,) to ancestor indices (n, N).
"""

from __future__ import annotations

import numpy as np

from condtrack_cli.special import logsumexp


def normalise(log_w: np.ndarray) -> np.ndarray:
    """(n, N) log-weights -> normalised log-weights (each row sums to 1 in linear space)."""
    return log_w - logsumexp(log_w, axis=1, keepdims=True)


def sum_over_particles(values: np.ndarray, axis: int) -> np.ndarray:
    """``values.sum(axis)`` over the particle axis ``axis``, equal to it bit for bit, faster on (..., N, 2) arrays.

    numpy adds along a middle axis in index order, one short inner loop per trailing element; a copy
    with the particle axis first gets the same sums, in the same order, by adding whole rows in turn.
    """
    return np.ascontiguousarray(np.moveaxis(values, axis, 0)).sum(axis=0)


def _row_searchsorted(edges: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Per row, the index of the first edge > value: (n, K) increasing edges in [0, 1], (n, M) values in [0, 1)."""
    n, k = edges.shape
    rows = np.arange(n)[:, None]
    found = np.searchsorted((edges + 2 * rows).ravel(), (values + 2 * rows).ravel(), side="right")
    return np.minimum(found.reshape(values.shape) - rows * k, k - 1)


def systematic(weights: np.ndarray, uniform: np.ndarray) -> np.ndarray:
    """(n, N) ancestor indices drawn by systematic resampling of (n, N) normalised weights, (n,) ``uniform`` in
    [0, 1) the rows' draws."""
    count = weights.shape[1]
    u = (uniform[:, None] + np.arange(count)) / count  # N evenly spaced draws per row
    edges = np.cumsum(weights, axis=1)
    edges[:, -1] = 1.0
    return _row_searchsorted(edges, u)


def residual(weights: np.ndarray, uniform: np.ndarray) -> np.ndarray:
    """(n, N) ancestor indices by residual resampling of (n, N) normalised weights: floor(N w) copies, the rest
    systematic on the remainders with the rows' (n,) ``uniform`` draws in [0, 1)."""
    n, count = weights.shape
    copies = np.floor(count * weights)
    taken = copies.sum(axis=1, keepdims=True)  # (n, 1) deterministic copies
    slot = np.arange(count)[None, :]
    kept = _row_searchsorted(np.cumsum(copies, axis=1) / count, np.broadcast_to(slot / count, (n, count)))  # slot -> its particle
    remainder = count * weights - copies
    edges = np.cumsum(remainder, axis=1) / np.maximum(remainder.sum(axis=1, keepdims=True), 1e-300)
    edges[:, -1] = 1.0
    u = np.clip((uniform[:, None] + slot - taken) / np.maximum(count - taken, 1), 0.0, 1.0 - 1e-12)
    return np.where(slot < taken, kept, _row_searchsorted(edges, u))


RESAMPLERS = {"systematic": systematic, "residual": residual}
