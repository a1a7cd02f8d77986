"""Robust parametric motion, global support (paper §5.1), on real photographs.

Frame k is a 400 x 400 crop of a 512 x 512 photograph; frame k-1 is the
photograph resampled at x + U(x) for a known field U (``cv2.remap``), so that
I_{k-1}(x) = I_k(x + U(x)) as the estimator models it; ``rendered_pair`` samples
both frames by cubic B-spline instead and adds noise. Both crops stay inside the
photograph: no empty pixel enters any frame. Frames are rounded to 8 bits.
"""

from __future__ import annotations


import cv2
import numpy as np
import pytest

from condtrack_cli import registry
from condtrack_cli.motion._blocks import block_displacements, block_hypotheses
from condtrack_cli.motion.local import LocalMotion
from condtrack_cli.motion.model import MotionFit, displacement, jacobian, motion_basis
from condtrack_cli.motion.pyramid import build_pyramid, frame_pyramid
from condtrack_cli.motion.robust import GlobalMotion, RobustMotionSettings, estimate_motion
from condtrack_cli.motion.state_noise import state_noise
from condtrack_cli.types import Frame

from conftest import load_asset, render_pair

SIDE = 400  # frames are SIDE x SIDE crops
OFFSET = 56  # of the 512 x 512 photographs, centred
CENTRE = (SIDE - 1) / 2
SCORE_MARGIN = 24  # px of frame border left out of the scored grid

RMS_TOLERANCE = 0.05  # px, RMS displacement error over the scored pixels


def load(name: str) -> np.ndarray:
    """(H, W) float32 grey photograph from the package assets."""
    return load_asset(name).astype(np.float32)


def affine_field(xy: np.ndarray, angle_deg: float = 1.5, zoom: float = 1.02, shift=(3.2, -2.1)) -> np.ndarray:
    """(N, 2) displacement of a rotation and zoom about the frame centre plus a shift (px)."""
    angle = np.deg2rad(angle_deg)
    a = zoom * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    centred = xy - CENTRE
    return centred @ a.T - centred + np.asarray(shift)


def quadratic_field(xy: np.ndarray) -> np.ndarray:
    """(N, 2) pseudo-perspective displacement (px): affine part plus q1, q2 terms, up to ~6 px."""
    u, v = ((xy - CENTRE) / (SIDE / 2)).T
    q1, q2 = 1.2, -0.9
    return np.column_stack((
        2.0 + 1.5 * u - 1.0 * v + q1 * u * u + q2 * u * v,
        -1.5 + 0.8 * u + 2.0 * v + q1 * u * v + q2 * v * v,
    ))


def translation_field(xy: np.ndarray) -> np.ndarray:
    return np.broadcast_to(np.array([2.7, -1.6]), xy.shape)


def grid(step: int = 4, margin: int = SCORE_MARGIN) -> np.ndarray:
    """(N, 2) pixel positions of the scored region, every ``step`` px."""
    ys, xs = np.mgrid[margin : SIDE - margin : step, margin : SIDE - margin : step]
    return np.column_stack((xs.ravel(), ys.ravel())).astype(np.float64)


def frame_pair(field, photo: str = "camera.png") -> tuple[np.ndarray, np.ndarray]:
    """(prev, cur) float32 SIDE x SIDE frames with I_prev(x) = I_cur(x + field(x)), 8-bit grey levels."""
    image = load(photo)
    pixels = grid(step=1, margin=0)
    target = pixels + field(pixels) + OFFSET
    map_x = target[:, 0].reshape(SIDE, SIDE).astype(np.float32)
    map_y = target[:, 1].reshape(SIDE, SIDE).astype(np.float32)
    prev = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR)
    cur = image[OFFSET : OFFSET + SIDE, OFFSET : OFFSET + SIDE]
    return np.round(prev), cur.copy()


def rendered_pair(field, photo: str, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Like ``frame_pair`` but both frames sampled by cubic B-spline (not the estimator's bilinear
    interpolation) with Gaussian noise of std ``noise`` grey levels, as a camera would give them."""
    return render_pair(load(photo), field, SIDE, noise, seed)


def rms_error(fit: MotionFit, field, xy: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.square(displacement(fit, xy) - field(xy)), axis=1))))


@pytest.fixture(scope="module")
def affine_frames() -> tuple[np.ndarray, np.ndarray]:
    return frame_pair(affine_field)


@pytest.fixture(scope="module")
def affine_fit(affine_frames) -> MotionFit:
    return estimate_motion(*affine_frames, RobustMotionSettings(model="affine"))


PATCH_SIDE = 179  # ~ a fifth of the 400 x 400 frame
PATCH_CORNER = (40, 190)  # (x, y) of its top-left pixel in frame k-1
PATCH_SHIFT = (6, -5)  # its own motion from frame k-1 to frame k (px)


def patch_mask(corner, margin: int = 0) -> np.ndarray:
    """(SIDE, SIDE) bool, the patch square at ``corner`` grown by ``margin`` px."""
    mask = np.zeros((SIDE, SIDE), bool)
    x, y = corner
    mask[max(y - margin, 0) : y + PATCH_SIDE + margin, max(x - margin, 0) : x + PATCH_SIDE + margin] = True
    return mask


@pytest.fixture(scope="module")
def occluded_frames(affine_frames) -> tuple[np.ndarray, np.ndarray]:
    """The affine pair with a gravel square moving by PATCH_SHIFT on top of the background."""
    gravel = load("gravel.png")[100 : 100 + PATCH_SIDE, 100 : 100 + PATCH_SIDE]
    prev, cur = (frame.copy() for frame in affine_frames)
    x, y = PATCH_CORNER
    prev[y : y + PATCH_SIDE, x : x + PATCH_SIDE] = gravel
    x, y = PATCH_CORNER[0] + PATCH_SHIFT[0], PATCH_CORNER[1] + PATCH_SHIFT[1]
    cur[y : y + PATCH_SIDE, x : x + PATCH_SIDE] = gravel
    return prev, cur


def background_grid() -> np.ndarray:
    """Scored positions away from the patch in both frames (and from where it lands in frame k)."""
    xy = grid()
    moved = (PATCH_CORNER[0] + PATCH_SHIFT[0], PATCH_CORNER[1] + PATCH_SHIFT[1])
    # Background under the patch in frame k comes from up to ~8 px away in frame k-1: 12 px keeps clear of it.
    covered = patch_mask(PATCH_CORNER, 12) | patch_mask(moved, 12)
    rows, cols = xy[:, 1].astype(int), xy[:, 0].astype(int)
    return xy[~covered[rows, cols]]


def test_affine_warp_is_recovered(affine_fit):
    error = rms_error(affine_fit, affine_field, grid())
    assert error <= RMS_TOLERANCE, f"RMS displacement error {error:.4f} px > {RMS_TOLERANCE} px"
    assert affine_fit.theta.shape == (6,) and affine_fit.theta_cov.shape == (6, 6)
    assert affine_fit.weights.shape == (SIDE, SIDE) and affine_fit.weights.dtype == np.float32
    assert 0 < affine_fit.scale < 10, "residual scale of a clean pair should be a few grey levels"


def test_affine_warp_is_recovered_on_noisy_spline_rendered_frames():
    """No help from the test's own interpolation: cubic B-spline rendering, noise of 2 grey levels."""
    fit = estimate_motion(*rendered_pair(affine_field, "camera.png", noise=2.0, seed=1), RobustMotionSettings())
    error = rms_error(fit, affine_field, grid())
    assert error <= RMS_TOLERANCE, f"RMS displacement error {error:.4f} px > {RMS_TOLERANCE} px"


@pytest.mark.parametrize("cost", ["tukey", "geman_mcclure", "cauchy"])
def test_affine_warp_is_recovered_under_an_independently_moving_patch(occluded_frames, cost):
    fit = estimate_motion(*occluded_frames, RobustMotionSettings(model="affine", robust_cost=cost))
    error = rms_error(fit, affine_field, background_grid())
    assert error <= RMS_TOLERANCE, f"{cost}: background RMS error {error:.4f} px > {RMS_TOLERANCE} px"
    patch = patch_mask(PATCH_CORNER, -8)  # the patch's interior in frame k-1
    background = ~patch_mask(PATCH_CORNER, 12) & (fit.weights > 0)
    on_patch, off_patch = float(fit.weights[patch].mean()), float(fit.weights[background].mean())
    assert on_patch < 0.5 * off_patch, f"{cost}: mean weight {on_patch:.2f} on the patch vs {off_patch:.2f} off it"


def test_support_restricts_the_regression(occluded_frames):
    support = ~patch_mask(PATCH_CORNER, 12)
    fit = estimate_motion(*occluded_frames, RobustMotionSettings(robust_cost="cauchy"), support=support)
    error = rms_error(fit, affine_field, background_grid())
    assert error <= RMS_TOLERANCE, f"RMS error {error:.4f} px > {RMS_TOLERANCE} px with the patch outside the support"


def test_translation_is_recovered_and_pixels_leaving_the_frame_weigh_nothing():
    fit = estimate_motion(*frame_pair(translation_field), RobustMotionSettings(model="translation"))
    error = rms_error(fit, translation_field, grid())
    assert error <= RMS_TOLERANCE, f"RMS error {error:.4f} px > {RMS_TOLERANCE} px"
    # x + 2.7 > SIDE - 1 on the last three columns, y - 1.6 < 0 on the first two rows
    assert np.all(fit.weights[:, -3:] == 0) and np.all(fit.weights[:2] == 0)
    assert np.all((fit.weights >= 0) & (fit.weights <= 1))


def test_quadratic_is_recovered():
    fit = estimate_motion(*frame_pair(quadratic_field, "astronaut.png"), RobustMotionSettings(model="quadratic"))
    error = rms_error(fit, quadratic_field, grid())
    assert error <= RMS_TOLERANCE, f"RMS error {error:.4f} px > {RMS_TOLERANCE} px"


def test_affine_cannot_fit_the_quadratic_field():
    """The quadratic test is not passed by an affine fit: the q1, q2 terms matter."""
    fit = estimate_motion(*frame_pair(quadratic_field, "astronaut.png"), RobustMotionSettings(model="affine"))
    assert rms_error(fit, quadratic_field, grid()) > 5 * RMS_TOLERANCE


def test_motion_basis_and_displacement_shapes(affine_fit):
    xy = grid(step=50)
    assert motion_basis("translation", xy, affine_fit.origin, affine_fit.length).shape == (len(xy), 2, 2)
    assert motion_basis("quadratic", xy, affine_fit.origin, affine_fit.length).shape == (len(xy), 2, 8)
    basis = motion_basis("affine", xy, affine_fit.origin, affine_fit.length)
    np.testing.assert_allclose(displacement(affine_fit, xy), basis @ affine_fit.theta, rtol=0, atol=1e-12)


@pytest.mark.parametrize("model", ["affine", "quadratic"])
def test_jacobian_matches_finite_differences(model):
    rng = np.random.default_rng(3)
    p = {"affine": 6, "quadratic": 8}[model]
    theta = rng.normal(0.0, 3.0, p)
    fit = MotionFit(model, theta, np.eye(p), np.array([320.0, 240.0]), 320.0, np.ones((2, 2), np.float32), 1.0)
    xy = rng.uniform(0, 640, (20, 2))
    step = 1e-4
    columns = [
        ((xy + d) + displacement(fit, xy + d) - (xy - d) - displacement(fit, xy - d)) / (2 * step)
        for d in (np.array([step, 0.0]), np.array([0.0, step]))
    ]
    numeric = np.stack(columns, axis=2)  # (N, 2, 2): column j = d/dx_j
    np.testing.assert_allclose(jacobian(fit, xy), numeric, rtol=0, atol=1e-7)
    if model == "affine":  # A_k of eq. (1) is the same everywhere
        np.testing.assert_allclose(jacobian(fit, xy), np.broadcast_to(jacobian(fit, xy[:1]), (20, 2, 2)), atol=1e-15)


def test_state_noise_is_symmetric_positive_definite_above_the_floor(affine_fit):
    xy = grid(step=40)
    q_floor = 0.25
    noise = state_noise(affine_fit, xy, q_floor)
    assert noise.shape == (len(xy), 2, 2)
    np.testing.assert_allclose(noise, noise.transpose(0, 2, 1), rtol=0, atol=1e-15)
    assert np.linalg.eigvalsh(noise).min() >= q_floor - 1e-12
    basis = motion_basis("affine", xy, affine_fit.origin, affine_fit.length)
    np.testing.assert_allclose(noise - q_floor * np.eye(2), basis @ affine_fit.theta_cov @ basis.transpose(0, 2, 1))


def test_textureless_frames_give_no_motion_and_a_wide_covariance():
    blank = np.full((120, 160), 128, np.float32)
    fit = estimate_motion(blank, blank, RobustMotionSettings())
    np.testing.assert_array_equal(fit.theta, 0.0)
    assert np.all(np.isfinite(fit.theta_cov))
    smallest = np.linalg.eigvalsh(state_noise(fit, np.array([[80.0, 60.0]]), 0.25)).min()
    assert smallest > 100, f"an unconstrained fit must say so: Q_k eigenvalue {smallest:.1f} px^2 <= 100"


def test_stage_keeps_the_pyramids_with_the_frames_and_matches_the_function(affine_frames):
    stages = registry.get("motion", "robust").factory(RobustMotionSettings())
    assert isinstance(stages.global_motion, GlobalMotion) and isinstance(stages.local_motion, LocalMotion)
    prev_gray, cur_gray = affine_frames
    prev = Frame(0, prev_gray.astype(np.uint8))
    cur = Frame(1, cur_gray.astype(np.uint8))
    fit = stages.global_motion.fit(prev, cur)
    built = prev.pyramid, cur.pyramid
    assert built[0] is not None and built[1] is not None
    again = stages.global_motion.fit(prev, cur)
    assert (prev.pyramid, cur.pyramid) == built  # not rebuilt: the same objects
    direct = estimate_motion(prev_gray, cur_gray, RobustMotionSettings())
    for estimate in (again, direct):  # deterministic, bit for bit
        np.testing.assert_array_equal(fit.theta, estimate.theta)
        np.testing.assert_array_equal(fit.weights, estimate.weights)
    other = GlobalMotion(RobustMotionSettings(model="translation")).fit(prev, cur)
    assert other.model == "translation"
    with pytest.raises(ValueError):
        fit.theta[0] = 1.0  # the fit is handed to several filters, hence read-only


def test_a_pyramid_deepened_later_equals_one_built_deep(affine_frames):
    """The global fit builds a frame's pyramid, the local field (deeper) extends it: same levels as built at once."""
    frame = Frame(0, affine_frames[0].astype(np.uint8))
    shallow = frame_pyramid(frame, 2)
    assert len(shallow.levels) == 2 and len(frame.pyramid.levels) == 2
    deep = frame_pyramid(frame, 4)
    assert deep.levels[0] is shallow.levels[0]  # the levels already built are kept
    for kept, built in zip(deep.levels, build_pyramid(frame.gray, 4).levels, strict=True):
        np.testing.assert_array_equal(kept, built)
    assert len(frame_pyramid(frame, 3).levels) == 3 and len(frame.pyramid.levels) == 4


def test_frames_of_different_shapes_are_refused(affine_frames):
    prev, cur = affine_frames
    with pytest.raises(ValueError, match="differ in shape"):
        estimate_motion(prev, cur[:-1], RobustMotionSettings())


def test_block_displacements_find_a_subpixel_shift():
    texture = cv2.pyrDown(cv2.pyrDown(load("gravel.png")))  # 128 x 128, as smooth as a coarse level
    shift = (2.3, -1.6)  # blocks moving up to radius - 1/2 = 2.5 px are found
    moved = cv2.warpAffine(texture, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (128, 128),
                           borderMode=cv2.BORDER_REFLECT)
    centres, moves = block_displacements(texture, moved, radius=3, min_gradient=1.0, support=None)
    assert len(moves) >= 200, f"only {len(moves)} of 225 blocks have a clear minimum"
    # a parabola through the SSD minimum is biased by < 0.1 px; the start only needs to be within ~0.5 px
    error = np.abs(np.median(moves, axis=0) - shift).max()
    assert error < 0.15, f"median block displacement off by {error:.3f} px (tolerance 0.15 px)"
    assert np.all((centres >= 3) & (centres <= 128 - 3))


def test_block_hypotheses_give_the_majority_motion_first():
    rng = np.random.default_rng(5)
    centres = rng.uniform(0, 400, (60, 2))
    basis = motion_basis("affine", centres, np.array([200.0, 200.0]), 200.0)
    background = np.array([1.0, 0.5, -0.8, -2.0, 0.8, 0.4])
    moves = basis @ background + rng.normal(0, 0.05, (60, 2))
    moves[:24] = [3.0, 4.0]  # 40 % of the blocks on an object moving by (3, 4) px
    first, second = block_hypotheses(basis, moves, inlier_distance=0.3)
    np.testing.assert_allclose(first, background, atol=0.1)
    np.testing.assert_allclose(basis @ second, np.broadcast_to([3.0, 4.0], (60, 2)), atol=1e-6)
    again = block_hypotheses(basis, moves, inlier_distance=0.3)
    np.testing.assert_array_equal(again[0], first)  # fixed seed: deterministic
