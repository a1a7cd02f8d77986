"""The predictive distribution of a row (docs/schema.md, "Predictive distribution"): a bivariate Student-t.

A row's position (x, y), covariance C (px^2) and nu = ``dof`` > 2 (inf: Gaussian)
state where the true point is. The ellipse of level p is {d : d^T C^-1 d <= m(p, nu)}.
Shared by the evaluation (coverage), the overlays (95 % ellipses) and ``--max-std``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from condtrack_cli.types import Tracks


def major_std(cov: np.ndarray) -> np.ndarray:
    """(...) standard deviation (px) along the major axis of each covariance (..., 2, 2) px^2: the square root of its
    larger eigenvalue; inf where a variance is infinite (unbounded), NaN where the covariance is NaN (none)."""
    undefined = np.isnan(cov).any(axis=(-2, -1))
    unbounded = np.isinf(cov).any(axis=(-2, -1)) & ~undefined
    finite = ~undefined & ~unbounded
    a, b, c = (np.where(finite, cov[..., i, j], 0.0) for i, j in ((0, 0), (0, 1), (1, 1)))
    std = np.sqrt(np.maximum((a + c) / 2 + np.hypot((a - c) / 2, b), 0.0))
    return np.where(unbounded, np.inf, np.where(undefined, np.nan, std))


def trusted(tracks: "Tracks", max_std: float | None) -> "Tracks":
    """``tracks`` with the rows whose ``major_std`` exceeds ``max_std`` px written as not visible (``--max-std``).

    A row without a covariance (NaN: the method has none) keeps its visibility; an unbounded one is not visible.
    None: ``tracks`` as they are.
    """
    if max_std is None:
        return tracks
    return dataclasses.replace(tracks, visible=tracks.visible & ~(major_std(tracks.cov) > max_std))


def chi2_2dof(level: float | np.ndarray) -> float | np.ndarray:
    """chi2.ppf(level, 2): the chi-square law with 2 degrees of freedom has CDF 1 - exp(-q / 2), so -2 ln(1 - p)."""
    return -2.0 * np.log1p(-np.asarray(level, float)) if isinstance(level, np.ndarray) else -2.0 * math.log1p(-level)


def ellipse_m2(level: float | np.ndarray, dof: float | np.ndarray) -> np.ndarray:
    """The bound on d^T C^-1 d of the level-``level`` ellipse of a bivariate Student-t with covariance C.

    dof: nu > 2 (inf: Gaussian, ``chi2_2dof``). With scale matrix C (nu - 2) / nu, d^T C^-1 d nu / (nu - 2) / 2
    follows Fisher's F(2, nu), whose CDF is 1 - (1 + 2 x / nu)^(-nu / 2): the bound is (nu - 2) ((1 - p)^(-2 / nu) - 1).
    """
    level, dof = np.asarray(level, float), np.asarray(dof, float)
    finite = np.isfinite(dof)
    nu = np.where(finite, dof, 4.0)  # 4.0: any nu > 2, off the mask
    student = (nu - 2.0) * np.expm1(-2.0 / nu * np.log1p(-level))
    return np.where(finite, student, chi2_2dof(level))


def ellipse_level(m2: np.ndarray, dof: np.ndarray | float) -> np.ndarray:
    """The level of the smallest ellipse holding an error of d^T C^-1 d = ``m2`` (the inverse of ``ellipse_m2``).

    Student-t: 1 - (1 + m2 / (nu - 2))^(-nu / 2); Gaussian (nu = inf): 1 - exp(-m2 / 2).
    """
    m2, dof = np.asarray(m2, float), np.asarray(dof, float)
    finite = np.isfinite(dof)
    nu = np.where(finite, dof, 4.0)  # 4.0: any nu > 2, off the mask
    return np.where(finite, -np.expm1(-nu / 2.0 * np.log1p(m2 / (nu - 2.0))), -np.expm1(-m2 / 2.0))
