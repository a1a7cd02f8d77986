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
    """The standard normal distribution's p-quantile (-inf at p <= 0, inf at p >= 1, as scipy's ndtri: a level
    such as 1 - 1e-20 rounds to 1)."""
    if p <= 0.0 or p >= 1.0:
        return -math.inf if p <= 0.0 else math.inf
    return NormalDist().inv_cdf(p)


def chi2_cdf(x: float, dof: int) -> float:
    """P(X <= x) for X chi-square with a positive integer ``dof``: closed forms, the Poisson sum for even dof
    and erf less the half-integer series for odd dof, each term taken in log space (no overflow for any x)."""
    if x <= 0:
        return 0.0
    half = x / 2.0
    if dof % 2 == 0:
        log_term, tail = -half, 0.0  # log of e^(-x/2) (x/2)^k / k!, k = 0 .. dof/2 - 1
        for k in range(dof // 2):
            if k:
                log_term += math.log(half / k)
            tail += math.exp(log_term)
        return min(1.0, max(0.0, 1.0 - tail))
    total = math.erf(math.sqrt(half))
    log_term = 0.5 * math.log(2.0 * x / math.pi) - half  # log of sqrt(2x/pi) e^(-x/2) x^(k-1) / (1 3 ... (2k - 1))
    for k in range(1, (dof - 1) // 2 + 1):
        total -= math.exp(log_term)
        log_term += math.log(half / (k + 0.5))
    return min(1.0, max(0.0, total))


#: Most bisection steps of :func:`chi2_quantile`: from a bracket of 2^1000 to 1e-12 relative, or to the smallest float.
_BISECTIONS = 1200


@functools.lru_cache(maxsize=4096)
def chi2_quantile(p: float, dof: int) -> float:
    """The p-quantile of the chi-square distribution with a positive integer ``dof`` (bisection on
    :func:`chi2_cdf` to 1e-12 relative). The closed forms subtract from 1 (or erf), so the quantile is
    exact to about 1e-16 / min(p, 1 - p) relative (tests/test_special.py); levels beyond that end bounded."""
    if p <= 0.0 or p >= 1.0:
        return 0.0 if p <= 0.0 else math.inf
    low, high = 0.0, max(1.0, 2.0 * dof)
    while chi2_cdf(high, dof) < p and high < 1e300:
        high *= 2.0
    for _ in range(_BISECTIONS):  # each halves the bracket; the bound ends it where floating point cannot
        if high - low <= 1e-12 * high:
            break
        middle = 0.5 * (low + high)
        low, high = (middle, high) if chi2_cdf(middle, dof) < p else (low, middle)
    return 0.5 * (low + high)


def chi2_quantiles(p: float, dof: np.ndarray) -> np.ndarray:
    """:func:`chi2_quantile` of each element of an integer array ``dof`` (each distinct value computed once)."""
    values, inverse = np.unique(np.asarray(dof, np.int64), return_inverse=True)
    return np.array([chi2_quantile(p, int(k)) for k in values])[inverse].reshape(np.shape(dof))
