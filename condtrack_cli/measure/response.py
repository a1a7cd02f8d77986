"""R_k from the residuals on the support W(z_k): paper eqs. (8)-(10), the uniform test and the one-peak test.

The noise model, the choice of c in eq. (8) and the floor of R_k are explained in
:mod:`condtrack_cli.measure.ssd`. ``SSDSettings``, the stage's settings, live here, the
lower of the two modules, so that ssd.py imports this one and not the reverse.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from condtrack_cli.measure.noise import noise_threshold
from condtrack_cli.settings import StageSettings
from condtrack_cli.special import chi2_quantiles, logsumexp, xlogx


class SSDSettings(StageSettings):
    """Settings of the SSD measurement (paper §5.2)."""

    frame_windows = ("template",)
    odd_fields = ("template", "support")

    template: int = Field(11, ge=3, le=63, description="side t of the reference patch (px, odd)")
    support: int = Field(7, ge=3, le=15, description="side n of the support W(z_k) of the response D_k (px, odd)")
    gamma: float = Field(9.21, gt=0, description="gate nu^T S^-1 nu <= gamma (9.21: chi-square, 2 dof, 99%)")
    search_min: int = Field(2, ge=1, le=32, description="least search half-size (px); the gate holds this square")
    search_max: int = Field(16, ge=1, le=32, description="largest search half-size (px)")
    noise_sigma: float | None = Field(
        None, gt=0, description="acquisition noise std (grey levels); null: estimated on the images (Immerkær)"
    )
    equalise_alpha: float | None = Field(
        0.05, gt=0, lt=1, description="level of the eq. (10) test; residuals within the noise are equalised (null: off)"
    )
    uniform_alpha: float = Field(0.05, gt=0, lt=1, description="level of the chi-square test of D_k against uniform")
    c_rule: Literal["unit_sum", "likelihood"] = Field(
        "unit_sum", description="c of eq. (8): unit_sum (paper: sum_W exp(-c r) = 1) or likelihood (1/(4 sigma^2))"
    )
    ambiguity_ratio: float | None = Field(
        0.5, gt=0, lt=1,
        description="a second minimum with at least this fraction of the peak's response: R infinite (null: off, the paper's)",
    )
    uniform_test: Literal["g", "pearson"] = Field(
        "g", description="form of the chi-square test of D_k against uniform: g (likelihood ratio) or pearson (the paper's)"
    )
    cost: Literal["ssd", "zero_mean", "normalised"] = Field(
        "zero_mean",
        description="matching cost: ssd (eq. 6), zero_mean or normalised (SSD after matching the patch's mean, and contrast)",
    )
    r_floor: float = Field(1 / 12, gt=0, description="variance added to R_k on each axis (px^2): a grid cell's spread")
    weight_sigma: float | None = Field(
        None, ge=0.5, le=64,
        description="std of the Gaussian weights of the patch's pixels in the matching cost, around its centre (px, "
                    "at least 0.5: less weighs the centre pixel alone); null: every pixel alike (the paper's eq. 6)",
    )

    @field_validator("search_max")
    @classmethod
    def _ordered(cls, value: int, info: ValidationInfo) -> int:
        if value < info.data.get("search_min", 0):
            raise ValueError("must be at least search_min")
        return value


def within_2px(cells: np.ndarray) -> np.ndarray:
    """(P, a, b) bool: the cells at most 2 px (Chebyshev) from a True cell of ``cells`` (P, a, b) in the same slice.

    A binary dilation of each (a, b) slice by a 5 x 5 square (none across slices),
    done as two separable ORs of shifted views; numpy, not scipy.ndimage, whose
    import costs about 0.05 s of every run's start-up (issue 13).
    """
    count, rows, cols = cells.shape
    padded = np.zeros((count, rows + 4, cols + 4), bool)
    padded[:, 2:-2, 2:-2] = cells
    along_x = padded[:, :, :cols].copy()
    for shift in range(1, 5):
        along_x |= padded[:, :, shift : shift + cols]
    dilated = along_x[:, :rows].copy()
    for shift in range(1, 5):
        dilated |= along_x[:, shift : shift + rows]
    return dilated


def unit_sum_c(r: np.ndarray, available: np.ndarray, r_min: np.ndarray) -> np.ndarray:
    """(P,) the c of eq. (8) with sum over W of exp(-c r) = 1; +inf where min r = 0.

    r: (P, k) residuals, available: (P, k) bool, r_min: (P,) their minimum.
    g(c) = log sum exp(-c (r - r_min)) - c r_min is convex and decreasing from
    g(0) = log k > 0, so Newton's method from c = 0 increases monotonically to the root.
    """
    delta = np.where(available, r - r_min[:, None], 0.0)
    positive = r_min > 0
    c = np.zeros(len(r))
    for _ in range(200):
        w = np.where(available, np.exp(-c[:, None] * delta), 0.0)
        total = w.sum(axis=1)
        g = np.log(total) - c * r_min
        slope = -(w * delta).sum(axis=1) / total - r_min
        active = positive & (np.abs(g) > 1e-12)
        if not active.any():
            break
        c = np.where(active, c - g / np.where(active, slope, 1.0), c)
    return np.where(positive, c, np.inf)


def _parabola_offset(left: np.ndarray, centre: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Vertex of the parabola through (-1, left), (0, centre), (1, right), clamped to [-0.5, 0.5] px.

    0 where the three do not make a finite upward parabola (a neighbour outside the frame, a flat run).
    """
    with np.errstate(invalid="ignore"):
        curvature = left - 2.0 * centre + right
        usable = np.isfinite(curvature) & (curvature > 0)
        offset = np.where(usable, (left - right) / (2.0 * np.where(usable, curvature, 1.0)), 0.0)
    return np.clip(offset, -0.5, 0.5)


def _parabola_vertex(residuals: np.ndarray) -> np.ndarray:
    """(P, 2) offset (dx, dy) of the separable parabola's vertex from the centre of (P, n, n) residuals."""
    mid = residuals.shape[1] // 2
    centre = residuals[:, mid, mid]
    dx = _parabola_offset(residuals[:, mid, mid - 1], centre, residuals[:, mid, mid + 1])
    dy = _parabola_offset(residuals[:, mid - 1, mid], centre, residuals[:, mid + 1, mid])
    return np.stack([dx, dy], axis=1)


def _separate(cells: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """(P,) True where some of ``cells`` (P, a, b) are 3 px or more (Chebyshev) from the group of cell (row, col).

    The group grows from (row, col) through cells at most 2 px apart, so that a steep
    oblique valley, which the grid samples with one-cell gaps, stays one group. Its first
    step takes every cell within 2 px of (row, col): the points whose cells all lie there
    (a sharp peak, the usual case) are settled without growing.
    """
    rows, cols = np.arange(cells.shape[1]), np.arange(cells.shape[2])
    near = (np.abs(rows[:, None] - row[:, None, None]) <= 2) & (np.abs(cols - col[:, None, None]) <= 2)
    grow = ~cells[np.arange(len(cells)), row, col] | (cells & ~near).any(axis=(1, 2))
    cells, row, col = cells[grow], row[grow], col[grow]
    group = np.zeros_like(cells)
    index = np.arange(len(cells))
    group[index, row, col] = cells[index, row, col]
    while True:
        grown = cells & within_2px(group)
        if np.array_equal(grown, group):
            separate = np.zeros(len(grow), bool)
            separate[grow] = (cells & ~group).any(axis=(1, 2))
            return separate
        group = grown


def response(
    residuals: np.ndarray, sigma: float, m: int, settings: SSDSettings, offset: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """R_k, its informativeness and c on (P, n, n) supports; see :func:`response_covariance`.

    Returns R (P, 2, 2) before the infinite substitution, informative (P,) bool and c (P,) (1/grey levels^2).
    """
    if not sigma > 0:
        raise ValueError(f"the noise std sigma must be positive, got {sigma}")
    r = np.asarray(residuals, np.float64)
    count, n = r.shape[0], r.shape[1]
    half = n // 2
    available = np.isfinite(r)
    empty = ~available.any(axis=(1, 2))  # no residual at all: computed on zeros, reported uninformative
    available |= empty[:, None, None]
    n_available = available.sum(axis=(1, 2))
    r = np.where(available, r, np.inf)
    r[empty] = 0.0
    r_raw, r_min = r, r.min(axis=(1, 2))
    if settings.equalise_alpha is not None:  # eq. (10): residuals within the noise are all set to the lowest one
        within_noise = available & (r < noise_threshold(sigma, m, settings.equalise_alpha))
        r = np.where(within_noise, r_min[:, None, None], r)
    flat_r = r.reshape(count, -1)
    flat_available = available.reshape(count, -1)
    if settings.c_rule == "unit_sum":
        c = unit_sum_c(flat_r, flat_available, r_min)
    else:
        c = np.full(count, 1.0 / (4.0 * sigma**2))  # 1 / (2 sigma_d^2): Gaussian likelihood of the patch
    excess = np.where(available, r - r_min[:, None, None], np.inf)
    with np.errstate(invalid="ignore"):
        energy = np.where(excess == 0, 0.0, c[:, None, None] * excess)  # c (r - r_min), with inf * 0 = 0
    log_d = -energy - logsumexp(-energy, axis=(1, 2), keepdims=True)
    d = np.exp(log_d)  # eq. (8): D_k = exp(-c r_k) / sum_W exp(-c r_k)

    delta = _parabola_vertex(r_raw) if offset is None else np.asarray(offset, np.float64)  # z_k - centre (px)
    grid = np.arange(n) - half
    du = grid[None, None, :] - delta[:, 0, None, None]  # (P, n, n) x - x_k
    dv = grid[None, :, None] - delta[:, 1, None, None]  # (P, n, n) y - y_k
    sxx = (d * du * du).sum(axis=(1, 2))  # eq. (9): sigma_uv = sum_W D_k (u - u_k)(v - v_k)
    sxy = (d * du * dv).sum(axis=(1, 2))
    syy = (d * dv * dv).sum(axis=(1, 2))
    R = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2) + settings.r_floor * np.eye(2)

    # Chi-square goodness of fit, one pseudo-observation per available cell (observed N D_k, expected 1 per
    # cell), asymptotically chi-square with N - 1 degrees of freedom under the uniform law. ``g``: the
    # likelihood-ratio form G = 2 N KL(D_k || uniform); with N = 49 at 5%, the uniform law is rejected when
    # KL > 0.67 nat: D_k fills less than half of W. ``pearson``: the paper's "test du chi-deux",
    # X^2 = sum (N D_k - 1)^2 = N^2 sum D_k^2 - N (it rejects more readily: a peak on a few cells weighs more).
    d_log_d = xlogx(d)
    entropy = -d_log_d.sum(axis=(1, 2))
    kl_uniform = np.log(n_available) - entropy
    critical = chi2_quantiles(1.0 - settings.uniform_alpha, np.maximum(n_available - 1, 1))
    if settings.uniform_test == "pearson":
        statistic = np.where(available, np.square(n_available[:, None, None] * d - 1.0), 0.0).sum(axis=(1, 2))
    else:
        statistic = 2.0 * n_available * kl_uniform
    uniform_rejected = statistic > critical
    det = R[:, 0, 0] * R[:, 1, 1] - R[:, 0, 1] ** 2
    rxx, rxy, ryy = R[:, 0, 0, None, None], R[:, 0, 1, None, None], R[:, 1, 1, None, None]
    quadratic = ryy * du * du - 2 * rxy * du * dv + rxx * dv * dv
    log_g = np.where(available, -0.5 * quadratic / det[:, None, None], -np.inf)  # N(z_k, R_k) on W
    log_g = np.where(available, log_g - logsumexp(log_g, axis=(1, 2), keepdims=True), 0.0)
    kl_gauss = (d_log_d - d * log_g).sum(axis=(1, 2))
    informative = ~empty & (n_available >= 2) & uniform_rejected & (kl_gauss < kl_uniform)
    if settings.ambiguity_ratio is not None:  # None: off (the paper's)
        judged = np.flatnonzero(informative)  # the one-peak test can only turn these uninformative
        peak = available[judged] & (energy[judged] <= np.log(1.0 / settings.ambiguity_ratio))  # D_k >= ratio * max D_k
        centre = np.full(len(judged), half)
        informative[judged] = ~_separate(peak, centre, centre)
    return R, informative, c


def infinite_covariance(count: int) -> np.ndarray:
    """(count, 2, 2) the covariance of no information: diagonal +inf, off-diagonal 0."""
    R = np.zeros((count, 2, 2))
    R[:, [0, 1], [0, 1]] = np.inf
    return R


def response_covariance(
    residuals: np.ndarray, sigma: float, m: int, settings: SSDSettings, *, offset: np.ndarray | None = None
) -> np.ndarray:
    """R_k (P, 2, 2) in px^2 from residual surfaces, paper eqs. (8)-(10) and the uniform test.

    residuals: (P, n, n) r_k on the support W(z_k), centred on the integer minimum
    (grey levels^2; +inf marks a cell without a residual, e.g. outside the frame).
    sigma: acquisition noise std (grey levels). m: template pixel count (t^2).
    offset: (P, 2) sub-pixel z_k minus the centre cell (px, within +-0.5); default: the
    vertex of the separable parabola through the centre 3 x 3 of ``residuals``.

    1. Eq. (10): cells whose residual is consistent with noise at ``equalise_alpha``
       are set to the lowest residual (none is favoured over another).
    2. Eq. (8): D_k = exp(-c r_k), normalised over W (c per ``c_rule``, module docstring).
    3. Eq. (9): R_k = sum_W D_k (z - z_k)(z - z_k)^T about the sub-pixel minimum z_k,
       plus ``r_floor`` * I.
    4. R_k is infinite (diagonal +inf) unless: the chi-square test rejects the uniform
       law for D_k at ``uniform_alpha`` (a flat surface, an occluded patch, does not);
       the Gaussian N(z_k, R_k) fits D_k better than the uniform law; and the cells with
       D_k >= ``ambiguity_ratio`` * max D_k form one group (two peaks 3 px or more apart
       do not; cells 2 px apart are grouped so that a steep oblique valley, which the
       grid samples with one-cell gaps, stays one group; not tested with ``ambiguity_ratio``
       null). The uniform test's statistic is ``uniform_test``'s (G or Pearson's).
    """
    R, informative, _ = response(residuals, sigma, m, settings, offset)
    return np.where(informative[:, None, None], R, infinite_covariance(len(R)))
