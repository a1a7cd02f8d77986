"""The few special functions the tracker needs, in numpy and the standard library.

``scipy.special`` costs about 0.15 s of import in every ``condtrack track`` process (issue 26: a
tenth of a short clip's run); these are the functions it was imported for.
"""

from __future__ import annotations

import functools
import math
from statistics import NormalDist

import numpy as np


def logsumexp(values: np.ndarray, axis, keepdims: bool = False) -> np.ndarray:
    """log sum exp(values) over ``axis`` (an int or a tuple), computed about the maximum; -inf where all are -inf."""
    top = np.max(values, axis=axis, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    with np.errstate(divide="ignore"):
        total = np.log(np.sum(np.exp(values - top), axis=axis, keepdims=True)) + top
    return total if keepdims else np.squeeze(total, axis=axis)


def expit(x: np.ndarray) -> np.ndarray:
    """The logistic function 1 / (1 + exp(-x)), without overflow for any x (inf maps to 1, -inf to 0)."""
    return np.exp(-np.logaddexp(0.0, -x))


def xlogx(x: np.ndarray) -> np.ndarray:
    """x log x elementwise for x >= 0, with 0 log 0 = 0."""
    positive = x > 0
    return np.where(positive, x * np.log(np.where(positive, x, 1.0)), 0.0)


def normal_quantile(p: float) -> float:
    """The standard normal distribution's p-quantile."""
    return NormalDist().inv_cdf(p)


def chi2_cdf(x: float, dof: int) -> float:
    """P(X <= x) for X chi-square with a positive integer ``dof`` (closed forms: Poisson sum for even dof, and
    erf plus the half-integer series for odd dof)."""
    if x <= 0:
        return 0.0
    half = x / 2.0
    if dof % 2 == 0:
        term, total = 1.0, 1.0
        for k in range(1, dof // 2):
            term *= half / k
            total += term
        return max(0.0, 1.0 - math.exp(-half) * total)
    term = math.sqrt(2.0 * x / math.pi) * math.exp(-half)  # sqrt(2 x / pi) e^(-x/2) x^(k-1) / (1 3 ... (2k - 1))
    total = math.erf(math.sqrt(half))
    for k in range(1, (dof - 1) // 2 + 1):
        total -= term
        term *= half / (k + 0.5)
    return min(1.0, max(0.0, total))


@functools.lru_cache(maxsize=4096)
def chi2_quantile(p: float, dof: int) -> float:
    """The p-quantile of the chi-square distribution with a positive integer ``dof`` (bisection on
    :func:`chi2_cdf` to 1e-12 relative)."""
    low, high = 0.0, max(1.0, 2.0 * dof)
    while chi2_cdf(high, dof) < p:
        high *= 2.0
    while high - low > 1e-12 * high:
        middle = 0.5 * (low + high)
        low, high = (middle, high) if chi2_cdf(middle, dof) < p else (low, middle)
    return 0.5 * (low + high)


def chi2_quantiles(p: float, dof: np.ndarray) -> np.ndarray:
    """:func:`chi2_quantile` of each element of an integer array ``dof`` (each distinct value computed once)."""
    values, inverse = np.unique(np.asarray(dof, np.int64), return_inverse=True)
    return np.array([chi2_quantile(p, int(k)) for k in values])[inverse].reshape(np.shape(dof))
