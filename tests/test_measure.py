"""SSD measurement (paper §5.2): R_k on synthetic residual surfaces (eqs. 8-10), matching on
photographs against a per-point reference, occlusion, the gate, the noise estimate, speed."""

from __future__ import annotations


import cv2
import numpy as np
import pytest
from conftest import load_asset
from pydantic import ValidationError

from condtrack_cli import registry
from condtrack_cli.measure.interface import Measurement
from condtrack_cli.measure.noise import estimate_noise_sigma
from condtrack_cli.measure.response import response_covariance, unit_sum_c, within_2px
from condtrack_cli.measure.ssd import SSDMeasure, SSDSettings, least_residuals, measure
from condtrack_cli.measure.surfaces import (
    SLICED_SIDE, _windows, extract_templates, matching_cost, pixel_count, pixel_weights, ssd_surfaces, zero_mean_minima,
)

SIGMA = 3.0  # acquisition noise std of the synthetic surfaces (grey levels)
M = 121  # template pixels (11 x 11)
NOISE_R = M * 2 * SIGMA**2  # expected SSD of a correct match: m sigma_d^2, sigma_d^2 = 2 sigma^2
N = SSDSettings().support
GRID = np.arange(N) - N // 2


def cross_term_tolerance(template: np.ndarray, patch: np.ndarray) -> float:
    """Bound on the float32 rounding of the cross term sum T'(y) (I(y) - m) (``ssd_surfaces``, cv2.matchTemplate):
    a sum of M products rounds by at most about M eps |T'| |I - m| <= M eps (|T'|^2 + |I - m|^2) / 2 (Cauchy-Schwarz),
    eps = 6e-8; the cost carries it twice. 1e-5 (|T'|^2 + |I - m|^2) holds M = 121 with a margin."""
    centred = np.asarray(template, np.float64) - np.mean(template)
    offset = np.asarray(patch, np.float64) - np.mean(template)
    return 1e-5 * (np.sum(centred**2) + np.sum(offset**2))
DX, DY = np.meshgrid(GRID, GRID)  # (n, n) offsets of the support cells, x along columns


def is_infinite(R: np.ndarray) -> np.ndarray:
    """(P,) True where R is the no-information covariance: diagonal +inf, off-diagonal 0."""
    return np.isinf(R[:, 0, 0]) & np.isinf(R[:, 1, 1]) & (R[:, 0, 1] == 0) & (R[:, 1, 0] == 0)


def surface(quadratic: np.ndarray, scale: float = 20.0) -> np.ndarray:
    """(1, n, n) residuals: the noise level at the minimum plus ``scale`` noise levels per unit of ``quadratic``."""
    return (NOISE_R * (1.0 + scale * quadratic))[None]


# --- R_k on synthetic residual surfaces (eqs. 8-10) -------------------------------------------


def test_sharp_isotropic_bowl_gives_small_isotropic_R():
    R = response_covariance(surface(DX**2 + DY**2), SIGMA, M, SSDSettings())[0]
    eig = np.linalg.eigvalsh(R)
    assert np.isfinite(R).all() and np.allclose(R, R.T)
    assert eig.min() >= SSDSettings().r_floor - 1e-12
    assert eig.max() < 0.35  # std < 0.6 px
    assert eig.max() / eig.min() < 1.05  # isotropic within 5%


def test_edge_valley_gives_R_elongated_along_the_edge():
    angle = np.deg2rad(30.0)
    along = np.array([np.cos(angle), np.sin(angle)])  # the edge direction (x, y)
    across = DX * -along[1] + DY * along[0]  # signed distance to the edge line through the centre
    R = response_covariance(surface(across**2), SIGMA, M, SSDSettings())[0]
    eig, vec = np.linalg.eigh(R)
    assert np.isfinite(R).all()
    assert eig[1] / eig[0] > 4.0
    assert abs(vec[:, 1] @ along) > 0.95  # major axis within 18 degrees of the edge


def test_flat_noise_and_two_peaks_give_infinite_R():
    rng = np.random.default_rng(0)
    flat = 2 * SIGMA**2 * rng.chisquare(M, size=(3, N, N))  # three pure-noise surfaces, no minimum
    two_peaks = surface(np.minimum(DX**2 + DY**2, (DX - 3) ** 2 + DY**2))  # equal minima at 0 and +3 px in x
    uneven = surface(np.minimum(DX**2 + DY**2, (DX + 3) ** 2 + (DY - 2) ** 2 + 0.02))  # second one slightly higher
    surfaces = np.concatenate([flat, two_peaks, uneven])
    for settings in (SSDSettings(), SSDSettings(equalise_alpha=None)):
        assert is_infinite(response_covariance(surfaces, SIGMA, M, settings)).all()


def test_equalisation_changes_R_only_when_peaks_are_within_the_noise():
    threshold = 2 * SIGMA**2 * (1.6449 + np.sqrt(2 * M)) ** 2 / 2  # eq. (10) at alpha = 0.05
    row = (DY == 0) & (np.abs(DX) == 1)  # the two horizontal neighbours of the minimum

    def three_cells(step: float) -> np.ndarray:
        base = surface(DX**2 + DY**2)
        base[0][row] = NOISE_R + step
        return base

    within = three_cells(0.9 * (threshold - NOISE_R))  # neighbours just below the noise threshold
    above = three_cells(2.0 * (threshold - NOISE_R))  # neighbours clearly above it
    for rule in ("unit_sum", "likelihood"):
        on, off = SSDSettings(c_rule=rule), SSDSettings(c_rule=rule, equalise_alpha=None)
        R_on, R_off = (response_covariance(within, SIGMA, M, s)[0] for s in (on, off))
        # equalised, the three cells share the mass along x: +6% with unit_sum (its temperature, set by the
        # residual at the minimum, already spreads D_k over noise-level differences), x9 with likelihood
        assert R_on[0, 0] > 1.03 * R_off[0, 0]
        assert R_on[1, 1] == pytest.approx(R_off[1, 1], rel=0.05)
        R_on, R_off = (response_covariance(above, SIGMA, M, s)[0] for s in (on, off))
        np.testing.assert_allclose(R_on, R_off, rtol=1e-12)


def test_c_is_the_papers_normaliser():
    """unit_sum c: sum_W exp(-c r) = 1 exactly, so D_k needs no other normalisation (eq. 8)."""

    rng = np.random.default_rng(1)
    r = NOISE_R * (1 + rng.uniform(0, 30, (20, N * N)))
    r[:, 0] = NOISE_R * rng.uniform(0.5, 1.5, 20)
    c = unit_sum_c(r, np.ones(r.shape, bool), r.min(axis=1))
    np.testing.assert_allclose(np.exp(-c[:, None] * r).sum(axis=1), 1.0, rtol=1e-9)


def test_R_is_never_singular_negative_or_nan():
    rng = np.random.default_rng(2)
    count = 400
    a, c = rng.uniform(0.0, 30.0, (2, count, 1, 1))  # random bowls, valleys and flats
    b = rng.uniform(-1, 1, (count, 1, 1)) * np.sqrt(a * c)
    shape = a * DX**2 + 2 * b * DX * DY + c * DY**2
    residuals = NOISE_R * (1 + shape + rng.uniform(0, 0.5, (count, N, N)))
    residuals[:, N // 2, N // 2] = NOISE_R * rng.uniform(0.0, 1.0, count)  # the minimum at the centre
    residuals[-50:] = 2 * SIGMA**2 * rng.chisquare(M, size=(50, N, N))  # and pure noise
    residuals[:50, :2] = np.inf  # cells outside the frame
    R = response_covariance(residuals, SIGMA, M, SSDSettings())
    finite = ~is_infinite(R)
    assert finite.sum() > 200 and (~finite).sum() > 20
    assert not np.isnan(R).any()
    assert (np.linalg.eigvalsh(R[finite]) >= SSDSettings().r_floor - 1e-12).all()
    np.testing.assert_array_equal(R[finite], R[finite].transpose(0, 2, 1))


# --- matching on photographs -------------------------------------------------------------------


def downsampled_pair(name: str, shift_hi: tuple[int, int], factor: int, noise: float, rng) -> tuple:
    """Frames 0 and k of ``name`` area-downsampled by ``factor``; frame k's content moved by shift_hi / factor px.

    Integrating pixels of a shifted high-resolution image is how a camera sees a sub-pixel motion.
    Returns (frame0, framek, shift (2,)) with float32 frames carrying Gaussian noise of std ``noise``.
    """
    big = load_asset(name).astype(np.float32)
    h, w = big.shape
    m = 16
    ix, iy = shift_hi

    def crop(dx: int, dy: int) -> np.ndarray:
        part = big[m - dy : h - m - dy, m - dx : w - m - dx]
        small = cv2.resize(part, (part.shape[1] // factor, part.shape[0] // factor), interpolation=cv2.INTER_AREA)
        return small + rng.normal(0, noise, small.shape).astype(np.float32)

    return crop(0, 0), crop(ix, iy), np.array([ix, iy]) / factor


def corners(gray: np.ndarray, border: int, spacing: float = 5.0) -> np.ndarray:
    """(P, 2) Shi-Tomasi corners of ``gray`` at least ``border`` px inside the frame and ``spacing`` px apart."""
    xy = cv2.goodFeaturesToTrack(gray, 400, 0.01, spacing, blockSize=5).reshape(-1, 2).astype(np.float64)
    h, w = gray.shape
    return xy[(xy >= border).all(axis=1) & (xy[:, 0] < w - border) & (xy[:, 1] < h - border)]


@pytest.mark.parametrize(("shift_hi", "factor"), [((1, -3), 4), ((1, -1), 2)])
def test_known_subpixel_shift_is_recovered(shift_hi, factor):
    """Median error < 0.15 px over all points of three photographs, shifts (0.25, -0.75) and (0.5, -0.5) px.

    Measured: medians 0.066 px (177 points) and 0.051 px (783 points) with noise of std 2.
    """
    rng = np.random.default_rng(3)
    settings = SSDSettings()
    errors, informative = [], []
    for name in ("camera.png", "coffee.png", "astronaut.png"):
        frame0, frame1, shift = downsampled_pair(name, shift_hi, factor, 2.0, rng)
        xy = corners(frame0, 16)
        truth = xy + shift
        predicted = truth + rng.uniform(-2, 2, truth.shape)
        gate = np.repeat(4.0 * np.eye(2)[None], len(xy), axis=0)
        m = measure(frame1, extract_templates(frame0, xy, 11), predicted, gate, settings, 2.0)
        errors.append(np.linalg.norm(m.z - truth, axis=1))
        informative.append(m.informative)
    errors, informative = np.concatenate(errors), np.concatenate(informative)
    assert len(errors) > 150
    assert np.median(errors) < 0.15
    assert np.median(errors[informative]) < 0.15 and informative.mean() > 0.75


def test_vectorised_search_equals_per_point_reference():
    """Each point against eq. (6) evaluated literally (float64) and cv2.matchTemplate (float32) on its own."""
    rng = np.random.default_rng(4)
    frame0, frame1, _ = downsampled_pair("camera.png", (3, 2), 2, 2.0, rng)
    xy = corners(frame0, 24)[:150] + rng.uniform(-0.5, 0.5, (150, 2))  # sub-pixel reference positions
    templates = extract_templates(frame0, xy, 11)
    predicted = xy + rng.uniform(-3, 3, xy.shape)
    wide = np.repeat(100.0 * np.eye(2)[None], len(xy), axis=0)  # the ellipse contains the whole square
    settings = SSDSettings(cost="ssd")
    m = measure(frame1, templates, predicted, wide, settings, 2.0)
    h = settings.search_max
    offsets = np.arange(-h, h + 1)
    image = frame1.astype(np.float64)
    for p in range(len(xy)):
        cx, cy = np.rint(predicted[p]).astype(int)
        ssd = np.array(  # eq. (6) at each integer offset (u, v) of the square
            [[np.sum((templates[p] - image[cy + v - 5 : cy + v + 6, cx + u - 5 : cx + u + 6]) ** 2) for u in offsets]
             for v in offsets]
        )
        v, u = np.unravel_index(np.argmin(ssd), ssd.shape)
        best = image[cy + offsets[v] - 5 : cy + offsets[v] + 6, cx + offsets[u] - 5 : cx + offsets[u] + 6]
        assert m.residual[p] == pytest.approx(ssd[v, u], rel=1e-9, abs=cross_term_tolerance(templates[p], best))
        assert np.abs(m.z[p] - [cx + offsets[u], cy + offsets[v]]).max() <= 0.5 + 1e-9  # z within the minimum's cell
        region = frame1[cy - h - 5 : cy + h + 6, cx - h - 5 : cx + h + 6]
        np.testing.assert_allclose(cv2.matchTemplate(region, templates[p], cv2.TM_SQDIFF), ssd, rtol=1e-3, atol=1.0)


@pytest.mark.parametrize("cost", ["ssd", "zero_mean", "normalised"])
@pytest.mark.parametrize("side, sigma", [(11, None), (15, 3.0)])
def test_cost_surfaces_equal_the_per_pair_cost_at_every_candidate_in_the_frame(cost, side, sigma):
    """ssd_surfaces (float32 cross term, window sums from the frame's box sums, or its weighted sums with
    ``measure.weight_sigma``) against matching_cost on each candidate's patch taken directly, border replicated, for
    points in the middle, at the border and with candidates outside the frame (those are not compared);
    within the float32 bound (for the normalised cost, whose cross term X enters as
    2 sum T'^2 (1 - X / sqrt(sum T'^2 sum I'^2)), that bound times sqrt(sum T'^2 / sum I'^2))."""
    rng = np.random.default_rng(8)
    gray = load_asset("coffee.png").astype(np.float32)
    h, w = gray.shape
    xy = np.array([[w / 2, h / 2], [1.0, 2.0], [w - 2.0, h - 1.0], [5.0, h / 3]])
    templates = (extract_templates(gray, xy + rng.uniform(-0.5, 0.5, xy.shape), side)
                 + rng.normal(0, 2, (4, side, side)))
    centres, reach = np.rint(xy).astype(np.intp), 6
    got = ssd_surfaces(gray, templates.astype(np.float32), centres, reach, cost, sigma=sigma)
    offsets = np.arange(-reach, reach + 1)
    for p, (cx, cy) in enumerate(centres):
        for i, v in enumerate(offsets):
            for j, u in enumerate(offsets):
                if 0 <= cx + u < w and 0 <= cy + v < h:
                    patch = extract_templates(gray, np.array([[cx + u, cy + v]], float), side)
                    want = matching_cost(templates[p : p + 1].astype(np.float32), patch, cost, sigma)[0]
                    tolerance = cross_term_tolerance(templates[p], patch[0])
                    if cost == "normalised":
                        tolerance *= np.sqrt(np.var(templates[p]) / np.var(patch[0]))
                    assert got[p, i, j] == pytest.approx(want, rel=1e-7, abs=tolerance), (p, u, v)


def test_weighted_costs_are_the_gaussian_weighted_sums_written_out():
    """measure.weight_sigma: matching_cost is sum_y w(y) [T'(y) - I'(y)]^2 with w a Gaussian of std sigma around the
    patch's centre scaled so that sum w = sum w^2 (the noise tests' pixel count n_w = sum w; about 4 pi sigma^2 when
    the patch holds the Gaussian) and T', I' less their w-weighted means; unweighted: t^2 pixels alike."""
    rng = np.random.default_rng(5)
    a, b = rng.normal(100, 20, (2, 3, 15, 15))
    grid = np.arange(15) - 7
    gauss = np.exp(-(grid[:, None] ** 2 + grid[None, :] ** 2) / (2 * 3.0**2))
    w = gauss * gauss.sum() / (gauss**2).sum()
    assert pixel_weights(15, 3.0) == pytest.approx(w, rel=1e-12)
    assert pixel_count(15, 3.0) == pytest.approx((w * w).sum(), rel=1e-12)
    assert 0.95 * 4 * np.pi * 9 < pixel_count(15, 3.0) < 4 * np.pi * 9
    assert pixel_weights(11, None) is None and pixel_count(11, None) == 121
    centred_a = a - (a * w).sum(axis=(1, 2), keepdims=True) / w.sum()
    centred_b = b - (b * w).sum(axis=(1, 2), keepdims=True) / w.sum()
    want = (w * (centred_a - centred_b) ** 2).sum(axis=(1, 2))
    np.testing.assert_allclose(matching_cost(a, b, "zero_mean", 3.0), want, rtol=1e-12)
    np.testing.assert_allclose(matching_cost(a, b, "ssd", 3.0), (w * (a - b) ** 2).sum(axis=(1, 2)), rtol=1e-12)
    # the weighted noise of a right match: sum w (n_a - n_b)^2 has the mean n_w 2 sigma^2 (sigma: each pixel's noise)
    noise = rng.normal(0, 2.0, (2, 20000, 15, 15))
    assert matching_cost(noise[0], noise[1], "ssd", 3.0).mean() == pytest.approx(pixel_count(15, 3.0) * 8, rel=0.01)


def test_a_known_subpixel_shift_is_recovered_with_weighted_pixels():
    """measure.weight_sigma 3, 15 px patches: the same photographs and shift as the unweighted test, median error
    below 0.15 px (measured 0.066 px over 177 points, unweighted 11 px 0.065 px)."""
    rng = np.random.default_rng(3)
    settings = SSDSettings(template=15, weight_sigma=3.0)
    errors = []
    for name in ("camera.png", "coffee.png", "astronaut.png"):
        frame0, frame1, shift = downsampled_pair(name, (1, -3), 4, 2.0, rng)
        xy = corners(frame0, 16)
        predicted = xy + shift + rng.uniform(-2, 2, xy.shape)
        gate = np.repeat(4.0 * np.eye(2)[None], len(xy), axis=0)
        m = measure(frame1, extract_templates(frame0, xy, 15), predicted, gate, settings, 2.0)
        errors.append(np.linalg.norm(m.z - (xy + shift), axis=1))
    errors = np.concatenate(errors)
    assert len(errors) > 150 and np.median(errors) < 0.15


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("reach", [SLICED_SIDE // 2 - 1, SLICED_SIDE // 2, 40])
def test_windows_read_the_frame_with_its_border_replicated_inside_across_and_beyond_the_border(reach, dtype):
    """_windows on both sides of SLICED_SIDE (one gather; one slice per point, cv2.copyMakeBorder across the border)
    against the clamped indices, exactly, for windows inside the frame, across each border and corner, wholly
    outside it, and larger than the frame."""
    rng = np.random.default_rng(3)
    g = 2 * reach + 1
    for height, width in ((120, 160), (g - 9, g + 3)):
        table = rng.normal(0, 50, (height, width)).astype(dtype)
        centres = np.column_stack([rng.integers(-g, width + g, 60), rng.integers(-g, height + g, 60)])
        centres[:4] = [[width // 2, height // 2], [0, 0], [width - 1, height - 1], [-g, height + g]]
        rows = np.clip(centres[:, 1, None] - reach + np.arange(g), 0, height - 1)
        cols = np.clip(centres[:, 0, None] - reach + np.arange(g), 0, width - 1)
        got = _windows(table, centres, reach)
        assert got.dtype == dtype
        np.testing.assert_array_equal(got, table[rows[:, :, None], cols[:, None, :]])


@pytest.mark.parametrize("reach", [6, 40])
def test_zero_mean_minima_are_the_argmins_of_the_zero_mean_surfaces(reach):
    """zero_mean_minima, made point by point, against the argmin of ssd_surfaces' 'zero_mean' surfaces, exactly: on a
    photograph (points inside, across the border, outside the frame) and on a frame with a flat half (equal costs:
    the first of them)."""
    rng = np.random.default_rng(4)
    photo = load_asset("coffee.png").astype(np.float32)
    flat_half = photo.copy()
    flat_half[:, : photo.shape[1] // 2] = 90.0
    for gray in (photo, flat_half):
        h, w = gray.shape
        xy = np.column_stack([rng.uniform(-20, w + 20, 40), rng.uniform(-20, h + 20, 40)])
        xy[:3] = [[w / 4, h / 2], [2.0, 3.0], [w - 1.0, h - 2.0]]
        templates = extract_templates(photo, np.clip(xy + rng.uniform(-3, 3, xy.shape), 0, [w - 1, h - 1]), 13)
        centres = np.rint(xy).astype(np.intp)
        surfaces = ssd_surfaces(gray, templates, centres, reach, "zero_mean")
        want = surfaces.reshape(len(xy), -1).argmin(axis=1)
        np.testing.assert_array_equal(zero_mean_minima(gray, templates, centres, reach), want)
    ties = (surfaces.reshape(len(xy), -1) == surfaces.reshape(len(xy), -1).min(axis=1, keepdims=True)).sum(axis=1)
    assert (ties > 1).any()  # the flat half's points: every candidate equal


def test_normalised_cost_surface_equals_the_per_pair_cost():
    """The least normalised cost over the search square equals :func:`matching_cost` taken patch by patch."""
    rng = np.random.default_rng(5)
    frame0, frame1, _ = downsampled_pair("camera.png", (3, 2), 2, 2.0, rng)
    xy = np.rint(corners(frame0, 24)[:40])
    templates = extract_templates(frame0, xy + rng.uniform(-0.5, 0.5, xy.shape), 11)
    settings = SSDSettings(cost="normalised", search_min=2)
    m = measure(frame1, templates, xy, np.repeat(0.01 * np.eye(2)[None], len(xy), axis=0), settings, 2.0)
    offsets = np.stack(np.meshgrid(np.arange(-2, 3), np.arange(-2, 3)), -1).reshape(-1, 2)  # the 5 x 5 square
    costs = np.stack([matching_cost(templates, extract_templates(frame1, xy + o, 11), "normalised") for o in offsets])
    energy = ((templates - templates.mean(axis=(1, 2), keepdims=True)) ** 2).sum(axis=(1, 2))
    # cross_term_tolerance with the patch given the template's contrast (its energy that of T'): 1e-5 (2 sum T'^2)
    assert (np.abs(m.residual - costs.min(axis=0)) <= 1e-6 * costs.min(axis=0) + 2e-5 * energy).all()
    flat = np.full_like(templates[:1], 7.0)
    assert matching_cost(templates[:1], flat, "normalised")[0] == pytest.approx(2 * ((templates[0] - templates[0].mean()) ** 2).sum())


def test_normalised_cost_ignores_a_gain_and_offset_change():
    """Frame k at contrast 1.3 and +20 grey levels: the normalised match stays within 0.15 px (median)
    and informative, while the SSD's residuals grow several times and its matches degrade.

    Measured: normalised median error 0.08 px, 92% informative (as without the change); SSD median
    error 0.29 px, 71% informative, median residual 5.9x that without the change.
    """
    rng = np.random.default_rng(6)
    frame0, frame1, shift = downsampled_pair("camera.png", (1, -3), 4, 2.0, rng)
    xy = corners(frame0, 16)
    truth = xy + shift
    predicted = truth + rng.uniform(-2, 2, truth.shape)
    gate = np.repeat(4.0 * np.eye(2)[None], len(xy), axis=0)
    templates = extract_templates(frame0, xy, 11)
    brighter = 128 + 1.3 * (frame1 - 128) + 20
    plain = measure(brighter, templates, predicted, gate, SSDSettings(cost="ssd"), 2.0)
    normalised = measure(brighter, templates, predicted, gate, SSDSettings(cost="normalised"), 2.0)
    same = measure(frame1, templates, predicted, gate, SSDSettings(cost="ssd"), 2.0)
    assert np.median(np.linalg.norm(normalised.z - truth, axis=1)) < 0.15
    assert normalised.informative.mean() > 0.75
    assert np.median(plain.residual) > 4 * np.median(same.residual)
    assert plain.informative.mean() < normalised.informative.mean() - 0.1


def test_points_at_and_beyond_the_frame_border():
    gray = load_asset("coffee.png").astype(np.float32)
    h, w = gray.shape
    xy = np.array([[2.0, 3.0], [w - 2.0, h - 1.5]])
    templates = extract_templates(gray, xy, 11)
    predicted = np.array([[-1.0, 1.0], [w + 1.0, h + 1.0], [-60.0, -60.0], [np.nan, 5.0]])
    gate = np.repeat(4.0 * np.eye(2)[None], 4, axis=0)
    m = measure(gray, np.concatenate([templates, templates]), predicted, gate, SSDSettings(), 2.0)
    np.testing.assert_allclose(m.z[:2], xy, atol=0.05)  # found inside the frame
    assert np.isnan(m.z[2:]).all() and np.isnan(m.residual[2:]).all()  # no candidate in the frame / no prediction
    assert is_infinite(m.R[2:]).all() and not m.informative[2:].any()


@pytest.mark.parametrize("cost", ["ssd", "zero_mean"])
def test_least_residuals_are_the_measurements_residuals_whatever_points_are_measured_with_them(cost):
    """``least_residuals`` is ``measure``'s residual, bit for bit, on points inside, across and beyond the border,
    with a NaN prediction, in gates of several sizes; and ``measure`` gives every point of a fixed square search the
    same measurement alone as among the others (the re-acquisition measures further only some of them)."""
    rng = np.random.default_rng(7)
    frame0, frame1, _ = downsampled_pair("camera.png", (3, 2), 2, 2.0, rng)
    h, w = frame1.shape
    xy = np.concatenate([corners(frame0, 24)[:60], [[2.0, 3.0], [w - 2.0, h - 1.5]]])
    templates = extract_templates(frame0, xy, 11)
    predicted = np.concatenate([xy + rng.uniform(-3, 3, xy.shape), [[-60.0, -60.0], [np.nan, 5.0]]])
    templates = np.concatenate([templates, templates[:2]])
    gates = rng.uniform(0.2, 30.0, len(predicted))[:, None, None] * np.eye(2)
    settings = SSDSettings(cost=cost)
    least = least_residuals(frame1, templates, predicted, gates, settings)
    np.testing.assert_array_equal(least, measure(frame1, templates, predicted, gates, settings, 2.0).residual)
    assert np.isfinite(least[:-2]).all() and np.isnan(least[-2:]).all()
    square = np.repeat(np.eye(2)[None] * (3**2 / settings.gamma), len(predicted), axis=0)
    whole = measure(frame1, templates, predicted, square, settings, 2.0)
    some = rng.permutation(len(predicted))[:20]
    alone = measure(frame1, templates[some], predicted[some], square[some], settings, 2.0)
    for field in ("z", "R", "residual", "informative", "aligned"):
        np.testing.assert_array_equal(getattr(alone, field), getattr(whole, field)[some])


def test_small_search_classes_are_measured_with_the_next_class_up():
    """``_search_groups``: a class of gate sizes with fewer than ``_MIN_GROUP`` points joins the next class up (a
    group's fixed cost outweighs the candidates its few points save); the last class stands alone; every known
    point is in exactly one group, the unknown in none."""
    from condtrack_cli.measure.ssd import _MIN_GROUP, _search_groups

    settings = SSDSettings()  # classes' bounds 2, 3, 5, 8, 12, 16
    half_sizes = np.array([2] * 5 + [3] * (_MIN_GROUP + 8) + [8] * 2 + [16] * 3)
    known = np.ones(len(half_sizes), bool)
    known[0] = False
    groups = _search_groups(half_sizes, known, settings)
    assert [sorted(set(half_sizes[g])) for g in groups] == [[2, 3], [8, 16]]
    assert np.array_equal(np.sort(np.concatenate(groups)), np.arange(1, len(half_sizes)))
    many = _search_groups(np.full(_MIN_GROUP, 2), np.ones(_MIN_GROUP, bool), settings)
    assert [len(g) for g in many] == [_MIN_GROUP]


def test_a_point_measured_with_a_larger_class_is_measured_in_its_own_gate():
    """A point whose few-point class joins a larger one is searched in a larger square, and still measured in its own
    gate: the same integer minimum, z and tests as alone, its residual within the float32 cross term's rounding."""
    rng = np.random.default_rng(11)
    frame0, frame1, _ = downsampled_pair("camera.png", (3, 2), 2, 2.0, rng)
    xy = corners(frame0, 24)[:45]
    templates = extract_templates(frame0, xy, 11)
    predicted = xy + rng.uniform(-1.5, 1.5, xy.shape)
    settings = SSDSettings()
    gates = np.repeat(np.eye(2)[None] * (3.0**2 / settings.gamma), len(xy), axis=0)  # half-side 3 ...
    gates[:5] = np.eye(2) * (2.0**2 / settings.gamma)  # ... and 2 for five points: their class joins the 3's
    together = measure(frame1, templates, predicted, gates, settings, 2.0)
    for p in range(5):
        alone = measure(frame1, templates[p : p + 1], predicted[p : p + 1], gates[p : p + 1], settings, 2.0)
        assert alone.informative[0] == together.informative[p]
        np.testing.assert_allclose(alone.z[0], together.z[p], atol=1e-6)
        np.testing.assert_allclose(alone.R[0], together.R[p], rtol=1e-5, atol=1e-9)
        assert alone.residual[0] == pytest.approx(together.residual[p], rel=1e-5)


# --- occlusion, ambiguity and the gate ---------------------------------------------------------


@pytest.mark.parametrize(("cost", "least_infinite"), [("ssd", 1.0), ("zero_mean", 0.95)])
def test_occluded_points_get_infinite_R(cost, least_infinite):
    """Measured, 73 points under an unrelated texture: all infinite with the SSD, 71 with zero_mean
    (removing the mean lets two of them match into the texture)."""
    rng = np.random.default_rng(5)
    frame0, frame1, shift = downsampled_pair("camera.png", (2, 1), 2, 2.0, rng)
    gravel = load_asset("gravel.png").astype(np.float32)
    occluded_frame = frame1.copy()
    occluded_frame[40:140, 60:200] = gravel[:100, :140]  # an unrelated texture over a band
    xy = corners(frame0, 16)
    inside = (xy[:, 0] > 60 + 14) & (xy[:, 0] < 200 - 14) & (xy[:, 1] > 40 + 14) & (xy[:, 1] < 140 - 14)
    apart = (xy[:, 0] < 60 - 20) | (xy[:, 0] > 200 + 20) | (xy[:, 1] < 40 - 20) | (xy[:, 1] > 140 + 20)
    assert inside.sum() >= 10 and apart.sum() >= 30
    gate = np.repeat(4.0 * np.eye(2)[None], len(xy), axis=0)
    templates = extract_templates(frame0, xy, 11)
    occluded = measure(occluded_frame, templates, xy + shift, gate, SSDSettings(cost=cost), 2.0)
    clear = measure(frame1, templates, xy + shift, gate, SSDSettings(cost=cost), 2.0)
    assert is_infinite(occluded.R[inside]).mean() >= least_infinite and clear.informative[inside].mean() > 0.7
    np.testing.assert_array_equal(occluded.informative[apart], clear.informative[apart])  # points whose search
    for field in ("z", "R", "residual"):  # never sees the occluder: unchanged, but for the box sums' round-off
        np.testing.assert_allclose(getattr(occluded, field)[apart], getattr(clear, field)[apart], rtol=1e-9, atol=1e-12)


def test_a_repeated_patch_in_the_gate_gives_infinite_R():
    gray = load_asset("astronaut.png").astype(np.float32)
    rng = np.random.default_rng(6)
    xy = corners(gray, 40, spacing=30.0)[:40]  # apart enough that no copy covers another point's patch
    templates = extract_templates(gray, xy, 11)
    frame = gray.copy()
    for (x, y), tmpl in zip(np.rint(xy).astype(int), templates):  # a copy of the patch 11 px to the right
        frame[y - 5 : y + 6, x + 6 : x + 17] = tmpl
    frame += rng.normal(0, 1.0, frame.shape).astype(np.float32)
    gate = np.repeat(9.0 * np.eye(2)[None], len(xy), axis=0)  # both copies within the gate, 5.5 px either side
    m = measure(frame, templates, np.rint(xy) + [5.0, 0.0], gate, SSDSettings(), 1.0)
    assert is_infinite(m.R).all()
    small = np.repeat(np.eye(2)[None], len(xy), axis=0)  # control: a gate that holds the original only
    assert measure(frame, templates, np.rint(xy) - [3.0, 0.0], small, SSDSettings(), 1.0).informative.mean() > 0.8


def test_the_gate_is_respected():
    gray = load_asset("coffee.png").astype(np.float32)
    xy = corners(gray, 40)[:60]
    templates = extract_templates(gray, xy, 11)
    predicted = xy + [0.0, -5.0]  # the true match is 5 px below the prediction
    narrow = np.repeat(np.diag([9.0, 0.25])[None], len(xy), axis=0)  # the gate reaches 1.5 px in y (2 with search_min)
    settings = SSDSettings()
    m = measure(gray, templates, predicted, narrow, settings, 1.0)
    found = np.isfinite(m.z[:, 0])
    assert found.all()
    assert (np.abs(m.z[:, 1] - predicted[:, 1]) <= settings.search_min + 0.5).all()
    assert (np.linalg.norm(m.z - xy, axis=1) > 2.0).all()  # the better match outside was not taken
    wide = np.repeat(np.diag([9.0, 9.0])[None], len(xy), axis=0)
    m = measure(gray, templates, predicted, wide, settings, 1.0)
    assert np.median(np.linalg.norm(m.z - xy, axis=1)) < 0.05  # control: with the gate open it is found


# --- noise estimate, helpers, stage ------------------------------------------------------------


@pytest.mark.parametrize("name", ["camera.png", "coffee.png", "astronaut.png"])
def test_noise_sigma_recovers_added_noise(name):
    rng = np.random.default_rng(7)
    gray = load_asset(name).astype(np.float32)
    noisy = gray + rng.normal(0, 3.0, gray.shape).astype(np.float32)
    assert estimate_noise_sigma(noisy) == pytest.approx(3.0, rel=0.2)


def test_noise_sigma_is_never_below_the_8_bit_rounding_noise():
    ramp = np.add.outer(np.arange(64.0), np.arange(96.0)).astype(np.float32)  # no noise at all
    assert estimate_noise_sigma(ramp) == pytest.approx(1 / np.sqrt(12))
    with pytest.raises(ValueError, match="sigma"):
        response_covariance(surface(DX**2 + DY**2), 0.0, M, SSDSettings())


def test_extract_templates_is_bilinear_with_replicated_border():
    gray = load_asset("camera.png").astype(np.float32)
    xy = np.array([[100.0, 50.0], [100.25, 50.5], [3.7, 200.2], [-2.0, -3.0], [510.6, 511.9]])
    patches = extract_templates(gray, xy, 9)
    assert patches.shape == (5, 9, 9) and patches.dtype == np.float32
    np.testing.assert_array_equal(patches[0], gray[46:55, 96:105])
    for p, (x, y) in enumerate(xy):
        reference = cv2.getRectSubPix(gray, (9, 9), (float(x), float(y)))
        np.testing.assert_allclose(patches[p], reference, atol=0.02)


def test_settings_are_checked():
    with pytest.raises(ValidationError, match="odd"):
        SSDSettings(template=10)
    with pytest.raises(ValidationError, match="search_min"):
        SSDSettings(search_min=5, search_max=4)
    with pytest.raises(ValidationError):
        SSDSettings(c_rule="other")


def test_registered_stage_wraps_the_functions():
    stage = registry.get("measure", "ssd").factory(SSDSettings(noise_sigma=2.5))
    assert isinstance(stage, SSDMeasure)
    gray = load_asset("coffee.png").astype(np.float32)
    assert stage.noise_sigma(gray) == 2.5
    assert SSDMeasure(SSDSettings()).noise_sigma(gray) == estimate_noise_sigma(gray)
    xy = corners(gray, 30)[:20]
    gate = np.repeat(np.eye(2)[None], 20, axis=0)
    a = stage.measure(gray, stage.templates(gray, xy), xy + 0.4, gate, 2.5)
    b = measure(gray, extract_templates(gray, xy, 11), xy + 0.4, gate, stage.settings, 2.5)
    assert isinstance(a, Measurement)
    for field in ("z", "R", "residual", "informative"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


def test_within_2px_is_the_5x5_binary_dilation_of_each_slice():
    """The one-peak test's dilation equals scipy.ndimage's with a 5 x 5 square per slice (exact: booleans)."""
    from scipy import ndimage

    rng = np.random.default_rng(3)
    structure = np.zeros((3, 5, 5), bool)
    structure[1] = True  # within one slice only
    for shape, density in (((7, 9, 9), 0.05), ((4, 5, 11), 0.2), ((3, 1, 1), 0.5), ((0, 9, 9), 0.1)):
        cells = rng.random(shape) < density
        assert np.array_equal(within_2px(cells), ndimage.binary_dilation(cells, structure=structure))
