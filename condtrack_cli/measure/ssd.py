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
   largest window is sum I^2 - 2 sum I T + sum T^2: the cross term by ``cv2.matchTemplate``,
   the window sums of I and I^2 from the frame's box sums (once per frame).
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
   valley holds equally deep minima all along. ``ambiguity_ratio: null`` turns
   both one-peak tests off (this one and the one on W(z_k), ``response.py``): the
   paper has neither. The local-minimum check stays.

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

from typing import NamedTuple

import numpy as np

from condtrack_cli.measure.interface import Measurement
from condtrack_cli.measure.noise import estimate_noise_sigma, noise_threshold
from condtrack_cli.measure.response import SSDSettings, infinite_covariance, response
from condtrack_cli.measure.surfaces import (FrameSums, extract_templates, frame_sums, matching_cost, pixel_count, refine,
                                            ssd_surfaces)

#: The 8 neighbours (row, column offsets) of a cell.
_NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))

#: Most points per group of the search: bounds the (P, G, G) temporaries (about 100 kB per point at the largest gate).
_CHUNK = 512
#: Fewest points of a search group (:func:`_search_groups`); a class with fewer is measured with the next one up.
_MIN_GROUP = 32


def _half_sizes(gate_cov: np.ndarray, settings: SSDSettings) -> np.ndarray:
    """(P,) search half-size clip(ceil(sqrt(gamma lambda_max(S))), search_min, search_max) (px)."""
    a, b, c = gate_cov[:, 0, 0], gate_cov[:, 0, 1], gate_cov[:, 1, 1]
    with np.errstate(invalid="ignore"):
        largest = (a + c) / 2 + np.sqrt(((a - c) / 2) ** 2 + b * b)
        extent = np.ceil(np.sqrt(settings.gamma * largest))
    extent = np.where(np.isfinite(extent), extent, settings.search_max)
    return np.clip(extent, settings.search_min, settings.search_max).astype(np.intp)


def measure(
    gray: np.ndarray,
    templates: np.ndarray,
    predicted: np.ndarray,
    gate_cov: np.ndarray,
    settings: SSDSettings,
    sigma: float,
    sums: FrameSums | None = None,
) -> Measurement:
    """Match P reference patches in one frame inside their validation gates (paper §5.2).

    gray: (H, W) float32 frame I_k (grey levels). templates: (P, t, t) float32 reference
    patches I~0 around x0 (:func:`extract_templates`). predicted: (P, 2) predicted
    positions (px). gate_cov: (P, 2, 2) innovation covariance S (px^2), e.g. Sigma_{k|k-1}
    + R_nominal. sigma: acquisition noise std (grey levels). sums: the frame's
    :func:`frame_sums` of template-sized windows (computed here when None).

    The gate of a point is {nu = z - predicted : nu^T S^-1 nu <= gamma} within the square
    of half-size clip(ceil(sqrt(gamma lambda_max(S))), search_min, search_max) around the
    rounded prediction, widened to the square of half-size search_min; candidates whose
    centre is outside the frame are excluded. A point with a NaN prediction has no candidate.
    See the module docstring for the steps and :class:`Measurement` for the result.
    """
    predicted, gate_cov, half_sizes, groups = _grouped(predicted, gate_cov, settings)
    count = len(predicted)
    z, R = np.full((count, 2), np.nan), infinite_covariance(count)
    residual, informative, aligned = np.full(count, np.nan), np.zeros(count, bool), np.full(count, np.nan)
    if groups and sums is None:
        sums = frame_sums(gray, settings.template, settings.cost, settings.weight_sigma)
    for points in groups:
        part = _measure_group(gray, sums, templates[points], predicted[points], gate_cov[points],
                              half_sizes[points], settings, sigma)
        z[points], R[points], residual[points], informative[points] = part.z, part.R, part.residual, part.informative
        aligned[points] = part.aligned
    return Measurement(z, R, residual, informative, aligned)


def least_residuals(gray: np.ndarray, templates: np.ndarray, predicted: np.ndarray, gate_cov: np.ndarray,
                    settings: SSDSettings, sums: FrameSums | None = None) -> np.ndarray:
    """(P,) the least residual of each point's gate (grey levels^2), the ``Measurement.residual`` of :func:`measure`
    with the same arguments, NaN where the gate holds no candidate; without the sub-pixel step, R_k or the tests,
    for a caller that uses a match only below some residual (``filters/reference.py``: the re-acquisition).

    In a search of one half-size for every point (a fixed square, as the re-acquisition's), a point's residuals do
    not depend on the other points measured with it: those of the points :func:`measure` is then given alone are
    these (tested). Gates of different sizes are grouped, each group's surfaces cover its largest gate, and
    ``cv2.matchTemplate``'s sums may then differ in their last bits with the window's size."""
    predicted, gate_cov, half_sizes, groups = _grouped(predicted, gate_cov, settings)
    residual = np.full(len(predicted), np.nan)
    if groups and sums is None:
        sums = frame_sums(gray, settings.template, settings.cost, settings.weight_sigma)
    for points in groups:
        part = _gate_minima(gray, sums, templates[points], predicted[points], gate_cov[points], half_sizes[points],
                            settings)
        residual[points] = np.where(part.found, part.residual, np.nan)
    return residual


def _grouped(predicted: np.ndarray, gate_cov: np.ndarray,
             settings: SSDSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
    """(P, 2) predictions and (P, 2, 2) gate covariances as float64 arrays, the (P,) search half-sizes and the
    :func:`_search_groups` of the points with finite predictions."""
    predicted = np.asarray(predicted, np.float64).reshape(-1, 2)
    gate_cov = np.asarray(gate_cov, np.float64).reshape(-1, 2, 2)
    half_sizes = _half_sizes(gate_cov, settings)
    return predicted, gate_cov, half_sizes, _search_groups(half_sizes, np.isfinite(predicted).all(axis=1), settings)


def searched(predicted: np.ndarray, gate_cov: np.ndarray, xy: np.ndarray, settings: SSDSettings) -> np.ndarray:
    """(n,) bool: :func:`measure`'s gate around (n, 2) ``predicted`` with covariance (n, 2, 2) ``gate_cov`` holds the
    candidate nearest to (n, 2) positions ``xy`` (the frame's bounds aside)."""
    half_sizes = _half_sizes(gate_cov, settings)
    offset = np.rint(xy) - np.rint(predicted)  # the candidate's offset from the rounded prediction
    chebyshev = np.abs(offset).max(axis=1)
    nu = np.rint(xy) - predicted
    with np.errstate(invalid="ignore"):
        inside = np.einsum("ni,ni->n", nu, np.linalg.solve(gate_cov, nu[..., None])[..., 0]) <= settings.gamma
    return (chebyshev <= half_sizes) & (inside | (chebyshev <= settings.search_min))


def _search_groups(half_sizes: np.ndarray, known: np.ndarray, settings: SSDSettings) -> list[np.ndarray]:
    """Index arrays of the ``known`` points by class of search half-size, at most _CHUNK points each.

    The classes' upper bounds grow by half from ``search_min``; a group's surfaces cover its
    largest gate, so the group computes at most about 1.5^2 as many candidates as its gates hold,
    instead of every point paying for the largest gate of the frame. A class of fewer than
    ``_MIN_GROUP`` points is measured with the next class up (the last class as it is): a group's
    fixed cost, about 300 numpy calls whatever its points (1.5-3 ms), is that of measuring some 30
    points, more than a few points save in candidates (bench/history.md, "Tenth round").
    """
    bounds = [settings.search_min]
    while bounds[-1] < settings.search_max:
        bounds.append(min(int(np.ceil(1.5 * bounds[-1])), settings.search_max))
    classes = np.searchsorted(bounds, half_sizes)
    groups = []
    carried = np.zeros(0, np.intp)  # the smaller classes' few points, measured with the next class up
    for index in range(len(bounds)):
        members = np.concatenate([carried, np.flatnonzero(known & (classes == index))])
        if len(members) < _MIN_GROUP and index < len(bounds) - 1:
            carried = members
            continue
        carried = np.zeros(0, np.intp)
        groups += [members[start : start + _CHUNK] for start in range(0, len(members), _CHUNK)]
    return groups


class _GateMinima(NamedTuple):
    """The residual surfaces of P points and their least residual in the gate (:func:`_gate_minima`)."""

    r_full: np.ndarray  #: (P, G, G) residuals of the candidates and the support's margin (inf outside the frame)
    gate: np.ndarray  #: (P, G', G') bool, the candidates in the gate (G' = 2 largest + 1)
    candidates: np.ndarray  #: (P, G', G') the candidates' residuals (a view of r_full)
    gated: np.ndarray  #: (P, G', G') the candidates' residuals, inf outside the gate
    found: np.ndarray  #: (P,) bool, a finite residual in the gate
    row: np.ndarray  #: (P,) the integer minimum's row in r_full
    col: np.ndarray  #: (P,) and its column
    residual: np.ndarray  #: (P,) the least residual in the gate (the window's centre's where none)
    integer: np.ndarray  #: (P, 2) the integer minimum's position (px)


def _gate_minima(gray: np.ndarray, sums: FrameSums, templates: np.ndarray, predicted: np.ndarray,
                 gate_cov: np.ndarray, half_sizes: np.ndarray, settings: SSDSettings) -> _GateMinima:
    """Step 1 of :func:`measure` (eq. 6) for P points with finite predictions and their (P,) search half-sizes: the
    residual surfaces and the integer minimum in each gate; ``sums``: the frame's :func:`frame_sums`."""
    count = len(predicted)
    half = settings.support // 2
    largest = int(half_sizes.max())
    reach = largest + half  # the candidates plus the margin of the support W(z_k)
    centres = np.rint(predicted).astype(np.intp)
    grid = np.arange(-reach, reach + 1)
    height, width = gray.shape
    x = centres[:, 0, None, None] + grid[None, None, :]  # (P, 1, G) candidate columns
    y = centres[:, 1, None, None] + grid[None, :, None]  # (P, G, 1) candidate rows
    r_full = ssd_surfaces(gray, templates, centres, reach, settings.cost, sums, settings.weight_sigma)
    np.copyto(r_full, np.inf, where=((x < 0) | (x >= width)) | ((y < 0) | (y >= height)))  # outside the frame

    inner = slice(half, half + 2 * largest + 1)  # the candidate offsets, |dx|, |dy| <= largest
    dx, dy = grid[None, None, inner], grid[None, inner, None]
    nu_x, nu_y = x[:, :, inner] - predicted[:, 0, None, None], y[:, inner] - predicted[:, 1, None, None]
    a, b, c = gate_cov[:, 0, 0, None, None], gate_cov[:, 0, 1, None, None], gate_cov[:, 1, 1, None, None]
    det = a * c - b * b
    proper = np.isfinite(det) & (det > 0)
    with np.errstate(invalid="ignore", divide="ignore"):  # nu^T S^-1 nu, one (P, G', G') array updated in place
        mahalanobis = 2 * b * nu_x * nu_y
        np.subtract(c * nu_x**2, mahalanobis, out=mahalanobis)
        mahalanobis += a * nu_y**2
        mahalanobis /= np.where(proper, det, 1.0)
    mahalanobis[~proper[:, 0, 0]] = 0.0  # a degenerate S leaves only the square
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
    return _GateMinima(r_full, gate, candidates, gated, found, row, col, residual, integer)


def _measure_group(gray: np.ndarray, sums: FrameSums, templates: np.ndarray, predicted: np.ndarray,
                   gate_cov: np.ndarray, half_sizes: np.ndarray, settings: SSDSettings, sigma: float) -> Measurement:
    """:func:`measure` of P points with finite predictions and their (P,) search half-sizes; ``sums``: the frame's
    :func:`frame_sums`."""
    count = len(predicted)
    t = templates.shape[1]
    half = settings.support // 2
    r_full, gate, candidates, gated, found, row, col, residual, integer = _gate_minima(
        gray, sums, templates, predicted, gate_cov, half_sizes, settings)
    z, at_z = refine(gray, templates, integer, settings.cost, settings.weight_sigma)

    offsets = np.arange(-half, half + 1)
    rows, cols = (row[:, None] + offsets)[:, :, None], (col[:, None] + offsets)[:, None, :]
    support = r_full[np.arange(count)[:, None, None], rows, cols]  # W(z_k), (P, n, n)
    pixels = pixel_count(t, settings.weight_sigma)  # the noise tests' pixel count
    R, informative, c_eq8 = response(support, sigma, pixels, settings, z - integer)

    peak = residual[:, None, None]
    neighbours = support[:, half - 1 : half + 2, half - 1 : half + 2]
    at_minimum = (neighbours >= peak).all(axis=(1, 2))  # else a lower residual lies just outside the gate
    second = np.zeros(count, bool)  # a deep local minimum in the gate beyond W(z_k)
    if settings.ambiguity_ratio is not None:  # None: off (the paper's), only eq. (10) and the uniform test judge
        log_ratio = np.log(1.0 / settings.ambiguity_ratio)
        equalised = -np.inf if settings.equalise_alpha is None else noise_threshold(sigma, pixels, settings.equalise_alpha)
        # The depth test below accepts the residuals up to a bound (it is monotone in the residual): a looser
        # bound (twice its excess, 4 ulps more) leaves it the candidates it may accept, of the points it can change.
        with np.errstate(divide="ignore", invalid="ignore"):
            slack = np.where(c_eq8 > 0, 2.0 * log_ratio / c_eq8, np.inf) + 4.0 * np.spacing(residual)
        limit = np.where(found & informative & at_minimum, np.maximum(residual + slack, equalised), -np.inf)
        point, i, j = np.nonzero(gated <= limit[:, None, None])
        beyond = gate[point, i, j] & ((np.abs(i + half - row[point]) > half) | (np.abs(j + half - col[point]) > half))
        point, i, j = point[beyond], i[beyond], j[beyond]  # in the gate, beyond W(z_k)
        level, lowest = candidates[point, i, j], residual[point]
        minimum = level <= np.min([r_full[point, i + half + v, j + half + u] for v, u in _NEIGHBOURS], axis=0)
        if settings.equalise_alpha is not None:  # eq. (10) over the gate, as on the support
            level = np.where(level < equalised, lowest, level)
        with np.errstate(invalid="ignore"):
            excess = c_eq8[point] * (level - lowest)
        competitive = (level == lowest) | (excess <= log_ratio)  # exp(-c r) >= ratio * peak's
        second[point[minimum & competitive]] = True
    informative = found & informative & at_minimum & ~second
    R = np.where(informative[:, None, None], R, infinite_covariance(count))
    return Measurement(
        z=np.where(found[:, None], z, np.nan), R=R, residual=np.where(found, residual, np.nan), informative=informative,
        aligned=np.where(found, np.minimum(residual, at_z), np.nan),
    )


class SSDMeasure:
    """The ``ssd`` measurement stage: :func:`measure` and its helpers bound to settings."""

    def __init__(self, settings: SSDSettings):
        self.settings = settings
        self.template_side = settings.template  #: side t of the reference patches (px)
        #: n_w, the pixel count of the noise tests: t^2, or sum w with ``weight_sigma`` (``surfaces.pixel_weights``)
        self.pixel_count = pixel_count(settings.template, settings.weight_sigma)
        #: the last frame measured and its :func:`frame_sums`, reused while the same frame is measured again
        #: (``auto`` measures its CLF and its CNLF points apart)
        self._sums: tuple[np.ndarray, FrameSums] | None = None
        self._resized: dict[int, SSDMeasure] = {}  #: :meth:`resized`'s stages, one per side

    def resized(self, side: int) -> SSDMeasure:
        """This stage with reference patches of odd ``side`` px (its own window sums), the same one for each side:
        the CLF's and the CNLF's points of ``auto`` share its sums."""
        if side == self.template_side:
            return self
        if side not in self._resized:
            self._resized[side] = SSDMeasure(self.settings.model_copy(update={"template": side}))
        return self._resized[side]

    def templates(self, gray: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """(M, t, t) float32 reference patches around (M, 2) positions of a (H, W) float32 frame."""
        return extract_templates(gray, xy, self.settings.template)

    def cost(self, templates: np.ndarray, patches: np.ndarray) -> np.ndarray:
        """(M,) :func:`matching_cost` of aligned (M, t, t) patch pairs with this stage's cost."""
        return matching_cost(templates, patches, self.settings.cost, self.settings.weight_sigma)

    def searched(self, predicted: np.ndarray, gate_cov: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """:func:`searched` with this stage's settings."""
        return searched(predicted, gate_cov, xy, self.settings)

    def noise_sigma(self, gray: np.ndarray) -> float:
        """The configured acquisition noise std, or its estimate on ``gray`` (grey levels)."""
        if self.settings.noise_sigma is not None:
            return self.settings.noise_sigma
        return estimate_noise_sigma(gray)

    def measure(
        self, gray: np.ndarray, templates: np.ndarray, predicted: np.ndarray, gate_cov: np.ndarray, sigma: float
    ) -> Measurement:
        """:func:`measure` with this stage's settings; the frame's window sums computed once per frame."""
        return measure(gray, templates, predicted, gate_cov, self.settings, sigma, self._frame_sums(gray))

    def least_residuals(self, gray: np.ndarray, templates: np.ndarray, predicted: np.ndarray,
                        gate_cov: np.ndarray) -> np.ndarray:
        """:func:`least_residuals` with this stage's settings and the frame's window sums."""
        return least_residuals(gray, templates, predicted, gate_cov, self.settings, self._frame_sums(gray))

    def _frame_sums(self, gray: np.ndarray) -> FrameSums:
        """The frame's :func:`frame_sums`, computed once per frame (``auto`` measures its CLF and its CNLF points
        apart)."""
        if self._sums is None or self._sums[0] is not gray:
            self._sums = (gray, frame_sums(gray, self.settings.template, self.settings.cost, self.settings.weight_sigma))
        return self._sums[1]


def make_ssd(settings: SSDSettings, **_context) -> SSDMeasure:
    """SSD matching in the gate with R_k from the correlation surface (paper §5.2)."""
    return SSDMeasure(settings)
