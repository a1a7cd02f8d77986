"""SSD matching in the validation gate (paper §5.2, eq. 6) and R_k from the correlation surface (eqs. 8-10).

Pixel convention: positions are (x, y) in pixels, x to the right, y down, origin
at the centre of the top-left pixel (see :mod:`condtrack_cli.types`). Residuals
are sums of squared grey-level differences (grey levels^2); covariances are px^2.

The measurement of one point, all P points at once:

1. Search (eq. 6). The candidates z are integer pixels around the rounded
   prediction inside the validation gate {nu : nu^T S^-1 nu <= gamma}, clipped
   to a square of half-size clip(ceil(sqrt(gamma * lambda_max(S))), search_min,
   search_max) and never smaller than the square of half-size search_min;
   candidates whose centre is outside the frame are excluded. The residual
   r_k(z) = sum_y [I~0(x0 + y) - I_k(z + y)]^2 of every offset of the batch's
   largest window is computed by FFT correlation, r = sum I^2 - 2 sum I T + sum T^2.
   The integer z_k is the smallest residual in the gate; it is refined to the
   continuous minimum of eq. (6) within its cell by Gauss-Newton on the
   bilinearly interpolated frame (a parabola through the 3 x 3 residuals is
   biased by up to 0.4 px on sharp photographs: SSD surfaces are not parabolic
   over +-1 px and not separable at corners).
2. R_k (eqs. 8-10), on the n x n support W(z_k) centred on the integer minimum,
   see :func:`response_covariance`.
3. Ambiguity over the whole gate: R_k is infinite when the integer minimum is not
   a local minimum (a lower residual lies just outside the gate) or when the gate
   holds, beyond W(z_k), a local minimum of r_k whose response exp(-c r) is at
   least ``ambiguity_ratio`` times the peak's (a second deep minimum that the
   Gaussian on W(z_k) cannot represent; residuals equalised by eq. 10 count as
   deep as the peak). A straight edge longer than W(z_k) is such a case: its
   valley holds equally deep minima all along.

Noise model (paper, before eq. 10): I_k(z) - I~0(x0) ~ N(0, sigma_d^2) per pixel
under a correct match. Both images carry acquisition noise of std sigma, so
sigma_d^2 = 2 sigma^2; the paper's "sigma" in r/sigma is this variance.
(The template is bilinearly interpolated, which lowers its noise a little; the
test of eq. 10 is then slightly lenient, i.e. equalises slightly less.)

Choice of c (eq. 8). The paper defines c as the factor that makes the response
sum to one over W(z_k): sum_W exp(-c r_k(z)) = 1 (the project's design notes left c
open; the paper's text fixes it, and the paper wins). That c is unique when min r > 0
(the sum decreases from n^2 at c = 0 to 0), scale-free (r -> a r gives c -> c/a),
and acts as a temperature proportional to the residual at the minimum,
1/c = r_min / ln(sum_W exp(-c (r - r_min))): a match degraded by deformation,
blur or illumination (larger r_min) gives a flatter response and a larger R_k,
and an occluded patch (large, nearly constant residuals) gives a nearly uniform
response that the uniform test recognises. ``c_rule: likelihood`` uses instead
c = 1 / (2 sigma_d^2) = 1 / (4 sigma^2), the Gaussian likelihood of the patch
under the noise model: it ignores every error but pixel noise, so textured
points get R_k at the floor and occlusions go undetected by the uniform test.

Floor of R_k. D_k lives on unit grid cells; R_k is the second moment about z_k of
the density that spreads each cell's mass uniformly over its cell, i.e. the
discrete moments of eq. 9 plus 1/12 px^2 per axis (``r_floor``). R_k is then
symmetric with both eigenvalues >= r_floor: never singular, never negative.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from pydantic import Field, ValidationInfo, field_validator
from scipy import fft, ndimage, special

from condtrack_cli.config import StageSettings
from condtrack_cli.registry import register
from condtrack_cli.threads import fft_workers

#: Most points per group of the search: bounds the (P, G, G) temporaries (about 100 kB per point at the largest gate).
_CHUNK = 512

#: Gauss-Newton steps of the sub-pixel refinement (median change after 3 steps: 0.01 px on photographs).
_REFINE_STEPS = 3

#: Cells within 2 px (Chebyshev) inside each (a, b) slice of a (P, a, b) stack, none across slices.
_WITHIN_2PX = np.zeros((3, 5, 5), bool)
_WITHIN_2PX[1] = True

#: Std of the rounding of grey levels to integers (grey levels): the least noise of an 8-bit frame.
_QUANTISATION_STD = 1.0 / np.sqrt(12.0)

#: Immerkær's (1996) operator: the difference of two Laplacians; zero on planes, sum of squares 36.
_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


class SSDSettings(StageSettings):
    """Settings of the SSD measurement (paper §5.2)."""

    frame_windows = ("template",)

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
    ambiguity_ratio: float = Field(
        0.5, gt=0, lt=1, description="a second minimum with at least this fraction of the peak's response: R infinite"
    )
    cost: Literal["ssd", "zero_mean", "normalised"] = Field(
        "zero_mean",
        description="matching cost: ssd (eq. 6), zero_mean or normalised (SSD after matching the patch's mean, and contrast)",
    )
    r_floor: float = Field(1 / 12, gt=0, description="variance added to R_k on each axis (px^2): a grid cell's spread")

    @field_validator("template", "support")
    @classmethod
    def _odd(cls, value: int) -> int:
        if value % 2 == 0:
            raise ValueError("must be odd")
        return value

    @field_validator("search_max")
    @classmethod
    def _ordered(cls, value: int, info: ValidationInfo) -> int:
        if value < info.data.get("search_min", 0):
            raise ValueError("must be at least search_min")
        return value


@dataclass(frozen=True)
class Measurement:
    """The SSD measurements of P points on one frame.

    z: (P, 2) float64 measured position (px, sub-pixel); NaN where no candidate was in the gate.
    R: (P, 2, 2) float64 covariance of z (px^2, eq. 9); diagonal +inf (off-diagonal 0) where the
       surface carries no information (and where z is NaN); otherwise symmetric with eigenvalues
       >= ``r_floor``.
    residual: (P,) float64 r_k(z_k), the SSD at the integer minimum (grey levels^2); NaN with z.
    informative: (P,) bool, R finite.
    """

    z: np.ndarray
    R: np.ndarray
    residual: np.ndarray
    informative: np.ndarray


def extract_templates(gray: np.ndarray, xy: np.ndarray, size: int) -> np.ndarray:
    """(M, size, size) float32 patches of ``gray`` centred on the sub-pixel positions ``xy``.

    gray: (H, W) float32 grey levels; xy: (M, 2) finite positions (px); size: odd side.
    Patch pixel (i, j) is ``gray`` at (x + j - size//2, y + i - size//2), bilinear,
    with the border replicated (coordinates clamped to the frame).
    """
    height, width = gray.shape
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    grid = np.arange(size) - size // 2
    x = np.clip(xy[:, 0, None] + grid, 0, width - 1)  # (M, size), clamped: border replicate
    y = np.clip(xy[:, 1, None] + grid, 0, height - 1)
    x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    wx, wy = (x - x0)[:, None, :], (y - y0)[:, :, None]
    flat = np.ascontiguousarray(gray).ravel()
    rows0, rows1 = (y0 * width)[:, :, None], (y1 * width)[:, :, None]
    cols0, cols1 = x0[:, None, :], x1[:, None, :]
    top = flat.take(rows0 + cols0) * (1 - wx) + flat.take(rows0 + cols1) * wx
    bottom = flat.take(rows1 + cols0) * (1 - wx) + flat.take(rows1 + cols1) * wx
    return (top * (1 - wy) + bottom * wy).astype(np.float32)


def estimate_noise_sigma(gray: np.ndarray) -> float:
    """Acquisition noise std of one frame (grey levels).

    Immerkær's operator N = [[1,-2,1],[-2,4,-2],[1,-2,1]] (J. Immerkær, "Fast noise
    variance estimation", CVIU 64(2), 1996) cancels planes and leaves 36 sigma^2 of
    white noise. Immerkær averages |I * N| over the whole frame, which counts
    texture and edges as noise (2x too high on a textured photograph); here the
    response is read only where the image has the least structure (the quarter of
    pixels with the smallest 7 x 7 mean squared gradient of the image smoothed by a
    Gaussian of std 2 px, smoothing that leaves the structure measure free of the
    noise), and its scale is the median absolute value (robust to the remaining
    edges): sigma = median |I * N| / (0.6745 * 6). Measured: sigma = 3 added to
    the camera, coffee and astronaut photographs reads 3.0-3.3 (whole-frame
    Immerkær: 4.2-6.2); a frame that is all texture (gravel) still reads high.
    The result is at least 1/sqrt(12), the rounding noise of 8-bit frames, so that
    a noise-free synthetic frame does not give 0.
    """
    image = np.asarray(gray, np.float32)
    if min(image.shape) < 3:
        raise ValueError(f"need a frame of at least 3 x 3 pixels, got {image.shape}")
    response = cv2.filter2D(image, cv2.CV_32F, _IMMERKAER, borderType=cv2.BORDER_REFLECT)[1:-1, 1:-1]
    smooth = cv2.GaussianBlur(image, (0, 0), 2.0)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3)
    structure = cv2.boxFilter(gx * gx + gy * gy, -1, (7, 7), borderType=cv2.BORDER_REFLECT)[1:-1, 1:-1]
    flattest = structure <= np.quantile(structure, 0.25)
    sigma = float(np.median(np.abs(response[flattest])) / (special.ndtri(0.75) * 6.0))
    return max(sigma, _QUANTISATION_STD)


def _noise_threshold(sigma: float, m: int, alpha: float) -> float:
    """Largest residual consistent with noise at level ``alpha`` (grey levels^2), eq. (10).

    sqrt(2 r / sigma_d^2) - sqrt(2 m) ~ N(0, 1) with sigma_d^2 = 2 sigma^2 and m
    template pixels; r is consistent with noise when that is below the (1 - alpha)
    quantile q, i.e. r < sigma_d^2 (q + sqrt(2 m))^2 / 2.
    """
    sigma_d2 = 2.0 * sigma**2
    q = special.ndtri(1.0 - alpha)
    return sigma_d2 * (q + np.sqrt(2.0 * m)) ** 2 / 2.0  # eq. (10) solved for r


def _unit_sum_c(r: np.ndarray, available: np.ndarray, r_min: np.ndarray) -> np.ndarray:
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
    oblique valley, which the grid samples with one-cell gaps, stays one group.
    """
    group = np.zeros_like(cells)
    index = np.arange(len(cells))
    group[index, row, col] = cells[index, row, col]
    while True:
        grown = cells & ndimage.binary_dilation(group, structure=_WITHIN_2PX)
        if np.array_equal(grown, group):
            return (cells & ~group).any(axis=(1, 2))
        group = grown


def _response(
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
        within_noise = available & (r < _noise_threshold(sigma, m, settings.equalise_alpha))
        r = np.where(within_noise, r_min[:, None, None], r)
    flat_r = r.reshape(count, -1)
    flat_available = available.reshape(count, -1)
    if settings.c_rule == "unit_sum":
        c = _unit_sum_c(flat_r, flat_available, r_min)
    else:
        c = np.full(count, 1.0 / (4.0 * sigma**2))  # 1 / (2 sigma_d^2): Gaussian likelihood of the patch
    excess = np.where(available, r - r_min[:, None, None], np.inf)
    with np.errstate(invalid="ignore"):
        energy = np.where(excess == 0, 0.0, c[:, None, None] * excess)  # c (r - r_min), with inf * 0 = 0
    log_d = -energy - special.logsumexp(-energy, axis=(1, 2), keepdims=True)
    d = np.exp(log_d)  # eq. (8): D_k = exp(-c r_k) / sum_W exp(-c r_k)

    delta = _parabola_vertex(r_raw) if offset is None else np.asarray(offset, np.float64)  # z_k - centre (px)
    grid = np.arange(n) - half
    du = grid[None, None, :] - delta[:, 0, None, None]  # (P, n, n) x - x_k
    dv = grid[None, :, None] - delta[:, 1, None, None]  # (P, n, n) y - y_k
    sxx = (d * du * du).sum(axis=(1, 2))  # eq. (9): sigma_uv = sum_W D_k (u - u_k)(v - v_k)
    sxy = (d * du * dv).sum(axis=(1, 2))
    syy = (d * dv * dv).sum(axis=(1, 2))
    R = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2) + settings.r_floor * np.eye(2)

    # Chi-square goodness of fit in its likelihood-ratio (G) form, one pseudo-observation per available
    # cell: G = 2 N KL(D_k || law), asymptotically chi-square with N - 1 degrees of freedom for the uniform
    # law. With N = 49 at 5%, the uniform law is rejected when KL > 0.67 nat: D_k fills less than half of W.
    entropy = -special.xlogy(d, d).sum(axis=(1, 2))
    kl_uniform = np.log(n_available) - entropy
    critical = 2.0 * special.gammaincinv(np.maximum(n_available - 1, 1) / 2, 1.0 - settings.uniform_alpha)  # chi2 quantile
    uniform_rejected = 2.0 * n_available * kl_uniform > critical
    det = R[:, 0, 0] * R[:, 1, 1] - R[:, 0, 1] ** 2
    rxx, rxy, ryy = R[:, 0, 0, None, None], R[:, 0, 1, None, None], R[:, 1, 1, None, None]
    quadratic = ryy * du * du - 2 * rxy * du * dv + rxx * dv * dv
    log_g = np.where(available, -0.5 * quadratic / det[:, None, None], -np.inf)  # N(z_k, R_k) on W
    log_g = np.where(available, log_g - special.logsumexp(log_g, axis=(1, 2), keepdims=True), 0.0)
    kl_gauss = (special.xlogy(d, d) - d * log_g).sum(axis=(1, 2))
    peak = available & (energy <= np.log(1.0 / settings.ambiguity_ratio))  # D_k >= ambiguity_ratio * max D_k
    centre = np.full(count, half)
    one_mode = ~_separate(peak, centre, centre)
    informative = ~empty & (n_available >= 2) & uniform_rejected & (kl_gauss < kl_uniform) & one_mode
    return R, informative, c


def _infinite(count: int) -> np.ndarray:
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
       grid samples with one-cell gaps, stays one group).
    """
    R, informative, _ = _response(residuals, sigma, m, settings, offset)
    return np.where(informative[:, None, None], R, _infinite(len(R)))


def _half_sizes(gate_cov: np.ndarray, settings: SSDSettings) -> np.ndarray:
    """(P,) search half-size clip(ceil(sqrt(gamma lambda_max(S))), search_min, search_max) (px)."""
    a, b, c = gate_cov[:, 0, 0], gate_cov[:, 0, 1], gate_cov[:, 1, 1]
    with np.errstate(invalid="ignore"):
        largest = (a + c) / 2 + np.sqrt(((a - c) / 2) ** 2 + b * b)
        extent = np.ceil(np.sqrt(settings.gamma * largest))
    extent = np.where(np.isfinite(extent), extent, settings.search_max)
    return np.clip(extent, settings.search_min, settings.search_max).astype(np.intp)


def _spectrum(values: np.ndarray, length: int) -> np.ndarray:
    """(P, length, length // 2 + 1) 2-D real FFT of (P, a, b) arrays zero-padded to length x length."""
    return fft.rfft2(values, s=(length, length), workers=fft_workers())


def _ssd_surfaces(gray: np.ndarray, templates: np.ndarray, centres: np.ndarray, reach: int,
                  cost: str = "ssd") -> np.ndarray:
    """(P, G, G) float64 r_k (eq. 6) at integer candidates centres + (dx, dy), |dx|, |dy| <= reach, G = 2 reach + 1.

    Element [p, i, j] is the matching cost between templates[p] and the frame patch
    centred on (centres[p, 0] + j - reach, centres[p, 1] + i - reach), frame border
    replicated. From each point's frame patch less the template's mean (I, which
    keeps the cancellation small) and T' = T - mean T: the window sums of I and I^2
    (cumulative sums) and of I T' (FFT correlation). ``cost`` 'ssd': the SSD,
    sum [T' - I]^2 = sum I^2 - 2 sum I T' + sum T'^2. 'zero_mean': the SSD after
    giving the frame patch the template's mean, sum [T' - I']^2 (T', I' mean-free).
    'normalised': after giving it the template's mean and contrast, sum [T' - a I']^2
    = 2 sum T'^2 (1 - rho) (a = |T'| / |I'|, rho their correlation; a flat frame
    patch has rho = 0). See :func:`matching_cost`.
    """
    height, width = gray.shape
    t = templates.shape[1]
    span = np.arange(-(reach + t // 2), reach + t // 2 + 1)
    g = 2 * reach + 1
    length = fft.next_fast_len(len(span), real=True)  # >= the patch side: the kept outputs do not wrap
    image = np.ascontiguousarray(gray).ravel()
    tmpl = templates.astype(np.float64)
    mean = tmpl.mean(axis=(1, 2), keepdims=True)
    tmpl -= mean
    energy = (tmpl * tmpl).sum(axis=(1, 2))[:, None, None]  # sum T'^2
    rows = np.clip(centres[:, 1, None] + span, 0, height - 1)
    cols = np.clip(centres[:, 0, None] + span, 0, width - 1)
    patch = image.take(rows[:, :, None] * width + cols[:, None, :]) - mean
    cross = _spectrum(patch, length) * _spectrum(tmpl[:, ::-1, ::-1], length)  # sum_y T'(y) I(z + y)
    sum_it = fft.irfft2(cross, s=(length, length), workers=fft_workers())[:, t - 1 : t - 1 + g, t - 1 : t - 1 + g]
    sum_sq = _window_sums(patch * patch, t, g)
    if cost == "ssd":
        return np.maximum(sum_sq - 2.0 * sum_it + energy, 0.0)  # eq. (6)
    sum_i = _window_sums(patch, t, g)
    spread = np.maximum(sum_sq - sum_i * sum_i / (t * t), 0.0)  # sum I'^2
    if cost == "zero_mean":
        return np.maximum(spread - 2.0 * sum_it + energy, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.where(spread > 0, sum_it / np.sqrt(energy * spread), 0.0)
    return 2.0 * energy * (1.0 - np.clip(np.nan_to_num(rho), -1.0, 1.0))


def _window_sums(values: np.ndarray, t: int, g: int) -> np.ndarray:
    """(P, g, g) sums of (P, g + t - 1, g + t - 1) ``values`` over each t x t window, by cumulative sums."""
    total = np.zeros((values.shape[0], values.shape[1] + 1, values.shape[2] + 1))
    np.cumsum(np.cumsum(values, axis=1), axis=2, out=total[:, 1:, 1:])
    return total[:, t:, t:] - total[:, :g, t:] - total[:, t:, :g] + total[:, :g, :g]


def matching_cost(templates: np.ndarray, patches: np.ndarray, cost: str) -> np.ndarray:
    """(M,) the ``cost`` of :func:`_ssd_surfaces` between aligned (M, t, t) ``templates`` and ``patches``."""
    a = np.asarray(templates, np.float64)
    b = np.asarray(patches, np.float64)
    if cost == "ssd":
        return ((a - b) ** 2).sum(axis=(1, 2))
    a = a - a.mean(axis=(1, 2), keepdims=True)
    b = b - b.mean(axis=(1, 2), keepdims=True)
    if cost == "zero_mean":
        return ((a - b) ** 2).sum(axis=(1, 2))
    energy, spread = (a * a).sum(axis=(1, 2)), (b * b).sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.where(spread > 0, (a * b).sum(axis=(1, 2)) / np.sqrt(energy * spread), 0.0)
    return 2.0 * energy * (1.0 - np.clip(np.nan_to_num(rho), -1.0, 1.0))


def _shift(window: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """(P, a - 2, b - 2) bilinear samples of (P, a, b) windows at their inner pixels moved by (P, 2) ``offset``.

    |offset| <= 1 px on each axis; the windows' borders supply the neighbours.
    """
    fx, fy = offset[:, 0, None, None], offset[:, 1, None, None]
    left, mid, right = window[:, :, :-2], window[:, :, 1:-1], window[:, :, 2:]
    rows = mid + np.where(fx >= 0, fx * (right - mid), -fx * (left - mid))
    up, mid, down = rows[:, :-2], rows[:, 1:-1], rows[:, 2:]
    return mid + np.where(fy >= 0, fy * (down - mid), -fy * (up - mid))


def _refine(gray: np.ndarray, templates: np.ndarray, start: np.ndarray, cost: str = "ssd") -> np.ndarray:
    """(P, 2) sub-pixel z_k: the continuous minimum of eq. (6) within +-0.5 px of the integer minimum ``start``.

    Gauss-Newton on r(z) = sum_y [T(y) - I_k(z + y)]^2 with I_k bilinear (border
    replicated) and its gradient by central differences, ``_REFINE_STEPS`` steps,
    each clamped so that z stays within the integer minimum's cell. The normal
    matrix is damped by 1e-3 of its trace so that the step along an edge (no
    information) stays small. Other ``cost``: that of :func:`matching_cost`, the
    frame patch given the template's mean (and contrast) at each step (held
    fixed within a step).
    """
    t = templates.shape[1]
    window = extract_templates(gray, start, t + 4).astype(np.float64)  # I_k at start + [-t//2 - 2, t//2 + 2]^2
    reference = templates.astype(np.float64)
    if cost != "ssd":
        reference = reference - reference.mean(axis=(1, 2), keepdims=True)
        energy = (reference * reference).sum(axis=(1, 2))
    offset = np.zeros(start.shape)
    for _ in range(_REFINE_STEPS):
        moved = _shift(window, offset)  # I_k at z + [-t//2 - 1, t//2 + 1]^2
        if cost != "ssd":
            inner = moved[:, 1:-1, 1:-1]
            centred = inner - inner.mean(axis=(1, 2), keepdims=True)
            spread = (centred * centred).sum(axis=(1, 2))
            gain = np.sqrt(energy / np.where(spread > 0, spread, np.inf))[:, None, None] if cost == "normalised" else 1.0
            moved = (moved - inner.mean(axis=(1, 2), keepdims=True)) * gain
        gx = (moved[:, 1:-1, 2:] - moved[:, 1:-1, :-2]) / 2.0
        gy = (moved[:, 2:, 1:-1] - moved[:, :-2, 1:-1]) / 2.0
        error = reference - moved[:, 1:-1, 1:-1]
        a, b, c = (gx * gx).sum(axis=(1, 2)), (gx * gy).sum(axis=(1, 2)), (gy * gy).sum(axis=(1, 2))
        damping = 1e-3 * (a + c) + 1e-12
        a, c = a + damping, c + damping
        ex, ey = (gx * error).sum(axis=(1, 2)), (gy * error).sum(axis=(1, 2))
        det = a * c - b * b
        step = np.stack([c * ex - b * ey, a * ey - b * ex], axis=1) / det[:, None]
        offset = np.clip(offset + step, -0.5, 0.5)
    return start + offset


def measure(
    gray: np.ndarray,
    templates: np.ndarray,
    predicted: np.ndarray,
    gate_cov: np.ndarray,
    settings: SSDSettings,
    sigma: float,
) -> Measurement:
    """Match P reference patches in one frame inside their validation gates (paper §5.2).

    gray: (H, W) float32 frame I_k (grey levels). templates: (P, t, t) float32 reference
    patches I~0 around x0 (:func:`extract_templates`). predicted: (P, 2) predicted
    positions (px). gate_cov: (P, 2, 2) innovation covariance S (px^2), e.g. Sigma_{k|k-1}
    + R_nominal. sigma: acquisition noise std (grey levels).

    The gate of a point is {nu = z - predicted : nu^T S^-1 nu <= gamma} within the square
    of half-size clip(ceil(sqrt(gamma lambda_max(S))), search_min, search_max) around the
    rounded prediction, widened to the square of half-size search_min; candidates whose
    centre is outside the frame are excluded. A point with a NaN prediction has no candidate.
    See the module docstring for the steps and :class:`Measurement` for the result.
    """
    predicted = np.asarray(predicted, np.float64).reshape(-1, 2)
    gate_cov = np.asarray(gate_cov, np.float64).reshape(-1, 2, 2)
    count = len(predicted)
    known = np.isfinite(predicted).all(axis=1)
    z, R = np.full((count, 2), np.nan), _infinite(count)
    residual, informative = np.full(count, np.nan), np.zeros(count, bool)
    if not known.any():
        return Measurement(z, R, residual, informative)
    half_sizes = _half_sizes(gate_cov, settings)
    for points in _search_groups(half_sizes, known, settings):
        part = _measure_group(gray, templates[points], predicted[points], gate_cov[points],
                              half_sizes[points], settings, sigma)
        z[points], R[points], residual[points], informative[points] = part.z, part.R, part.residual, part.informative
    return Measurement(z, R, residual, informative)


def _search_groups(half_sizes: np.ndarray, known: np.ndarray, settings: SSDSettings) -> list[np.ndarray]:
    """Index arrays of the ``known`` points by class of search half-size, at most _CHUNK points each.

    The classes' upper bounds grow by half from ``search_min``; a group's surfaces cover its
    largest gate, so the group computes at most about 1.5^2 as many candidates as its gates hold,
    instead of every point paying for the largest gate of the frame.
    """
    bounds = [settings.search_min]
    while bounds[-1] < settings.search_max:
        bounds.append(min(int(np.ceil(1.5 * bounds[-1])), settings.search_max))
    classes = np.searchsorted(bounds, half_sizes)
    groups = []
    for index in range(len(bounds)):
        members = np.flatnonzero(known & (classes == index))
        groups += [members[start : start + _CHUNK] for start in range(0, len(members), _CHUNK)]
    return groups


def _measure_group(gray: np.ndarray, templates: np.ndarray, predicted: np.ndarray,
                   gate_cov: np.ndarray, half_sizes: np.ndarray, settings: SSDSettings, sigma: float) -> Measurement:
    """:func:`measure` of P points with finite predictions and their (P,) search half-sizes."""
    count = len(predicted)
    t = templates.shape[1]
    half = settings.support // 2
    largest = int(half_sizes.max())
    reach = largest + half  # the candidates plus the margin of the support W(z_k)
    centres = np.rint(predicted).astype(np.intp)
    grid = np.arange(-reach, reach + 1)
    height, width = gray.shape
    x = centres[:, 0, None, None] + grid[None, None, :]  # (P, 1, G) candidate columns
    y = centres[:, 1, None, None] + grid[None, :, None]  # (P, G, 1) candidate rows
    r_full = _ssd_surfaces(gray, templates, centres, reach, settings.cost)
    r_full = np.where((x >= 0) & (x < width) & (y >= 0) & (y < height), r_full, np.inf)  # outside the frame

    inner = slice(half, half + 2 * largest + 1)  # the candidate offsets, |dx|, |dy| <= largest
    dx, dy = grid[None, None, inner], grid[None, inner, None]
    nu_x, nu_y = x[:, :, inner] - predicted[:, 0, None, None], y[:, inner] - predicted[:, 1, None, None]
    a, b, c = gate_cov[:, 0, 0, None, None], gate_cov[:, 0, 1, None, None], gate_cov[:, 1, 1, None, None]
    det = a * c - b * b
    proper = np.isfinite(det) & (det > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        quadratic = (c * nu_x**2 - 2 * b * nu_x * nu_y + a * nu_y**2) / np.where(proper, det, 1.0)
    mahalanobis = np.where(proper, quadratic, 0.0)  # nu^T S^-1 nu; a degenerate S leaves only the square
    chebyshev = np.maximum(np.abs(dx), np.abs(dy))
    gate = (chebyshev <= half_sizes[:, None, None]) & ((mahalanobis <= settings.gamma) | (chebyshev <= settings.search_min))
    candidates = r_full[:, inner, inner]
    gated = np.where(gate, candidates, np.inf)
    flat = gated.reshape(count, -1).argmin(axis=1)
    found = np.isfinite(gated.reshape(count, -1)[np.arange(count), flat])
    side = 2 * largest + 1
    row = np.where(found, flat // side, largest) + half  # the integer minimum, index into r_full
    col = np.where(found, flat % side, largest) + half
    residual = r_full[np.arange(count), row, col]

    integer = np.stack([centres[:, 0] + col - reach, centres[:, 1] + row - reach], axis=1).astype(np.float64)
    z = _refine(gray, templates, integer, settings.cost)

    offsets = np.arange(-half, half + 1)
    rows, cols = (row[:, None] + offsets)[:, :, None], (col[:, None] + offsets)[:, None, :]
    support = r_full[np.arange(count)[:, None, None], rows, cols]  # W(z_k), (P, n, n)
    R, informative, c_eq8 = _response(support, sigma, t * t, settings, z - integer)

    peak = residual[:, None, None]
    neighbours = support[:, half - 1 : half + 2, half - 1 : half + 2]
    at_minimum = (neighbours >= peak).all(axis=(1, 2))  # else a lower residual lies just outside the gate
    lowest_around = np.full(candidates.shape, np.inf)
    for v, u in ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)):
        shifted = r_full[:, half + v : half + v + side, half + u : half + u + side]
        np.minimum(lowest_around, shifted, out=lowest_around)
    level = gated
    if settings.equalise_alpha is not None:  # eq. (10) over the gate, as on the support
        level = np.where(gated < _noise_threshold(sigma, t * t, settings.equalise_alpha), peak, gated)
    with np.errstate(invalid="ignore"):
        excess = c_eq8[:, None, None] * (level - peak)
    competitive = (level == peak) | (excess <= np.log(1.0 / settings.ambiguity_ratio))  # exp(-c r) >= ratio * peak's
    distance = np.maximum(np.abs(dy + reach - row[:, None, None]), np.abs(dx + reach - col[:, None, None]))
    second = gate & (distance > half) & (candidates <= lowest_around) & competitive  # deep local minima beyond W
    informative = found & informative & at_minimum & ~second.any(axis=(1, 2))
    R = np.where(informative[:, None, None], R, _infinite(count))
    return Measurement(
        z=np.where(found[:, None], z, np.nan), R=R, residual=np.where(found, residual, np.nan), informative=informative
    )


class SSDMeasure:
    """The ``ssd`` measurement stage: :func:`measure` and its helpers bound to settings."""

    def __init__(self, settings: SSDSettings):
        self.settings = settings

    def templates(self, gray: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """(M, t, t) float32 reference patches around (M, 2) positions of a (H, W) float32 frame."""
        return extract_templates(gray, xy, self.settings.template)

    def cost(self, templates: np.ndarray, patches: np.ndarray) -> np.ndarray:
        """(M,) :func:`matching_cost` of aligned (M, t, t) patch pairs with this stage's cost."""
        return matching_cost(templates, patches, self.settings.cost)

    def noise_sigma(self, gray: np.ndarray) -> float:
        """The configured acquisition noise std, or its estimate on ``gray`` (grey levels)."""
        if self.settings.noise_sigma is not None:
            return self.settings.noise_sigma
        return estimate_noise_sigma(gray)

    def measure(
        self, gray: np.ndarray, templates: np.ndarray, predicted: np.ndarray, gate_cov: np.ndarray, sigma: float
    ) -> Measurement:
        """:func:`measure` with this stage's settings."""
        return measure(gray, templates, predicted, gate_cov, self.settings, sigma)


@register("measure", "ssd", SSDSettings, "SSD matching with R_k from the correlation surface")
def make_ssd(settings: SSDSettings, **_context) -> SSDMeasure:
    """SSD matching in the gate with R_k from the correlation surface (paper §5.2)."""
    return SSDMeasure(settings)
