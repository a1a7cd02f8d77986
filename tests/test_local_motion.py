"""Local robust motion (paper §5.1 local support, eq. 5): the shared field against the truth and the exact regression.

Global warps: frame k is a 320 x 320 crop from the centre of a photograph,
frame k-1 the photograph sampled by cubic B-spline at x + U(x) (both with noise,
seeded), so that I_{k-1}(x) = I_k(x + U(x)). Two motions: the ``ring`` scene, a
textured disk turning on a ring over gravel, 4-11 px/frame apart from the
background (median 7.8); its centre c_k = maps[1, k] c_0 stays on a circle about
the frame centre (``synthetic.ring``), which gives c_0 by least squares.

Measured when written (seed 0, 320 x 240), each against its tolerance:
- global warps, windows that constrain the motion: RMS 0.007-0.065 px (<= 0.1);
  all positions: RMS 0.007-0.13 px, >= 99 % within 0.5 px, Q_k covering every
  error at the 99 % chi-square level;
- ring, positions >= a half window (16 px) from the disk's outline: 100 % of
  2065 disk and 43523 background positions within 0.5 px of the truth (>= 90 %);
- field minus exact per-position regression there: median 0.083 px, 90th
  percentile 0.19 px, max 0.40 px on the turning disk (<= 0.15 / 0.3), 0.003 /
  0.007 px on the background (<= 0.02 / 0.05); Q_k - q_floor ratio median 1.02.
  Within a half window of the outline (not asserted): median 0.15 px, 90th
  percentile 5.4 px.
"""

from __future__ import annotations


import numpy as np
import pytest
from scipy.optimize import least_squares

from condtrack_cli.frames.synthetic import make_scene
from condtrack_cli.motion.field import LocalField
from condtrack_cli.motion.local import LocalMotion
from condtrack_cli.motion.local.exact import exact_local_motion
from condtrack_cli.motion.robust import GlobalMotion, RobustMotionSettings
from condtrack_cli.types import Frame

from conftest import load_asset, render_pair

SIDE = 320  # global-warp frames are SIDE x SIDE crops, from the centre of the photographs
CENTRE = (SIDE - 1) / 2
MARGIN = 24  # px of frame border left out of the scored positions
HALF_WINDOW = 16  # px: a position this far from the disk's outline has its whole window in one motion


def load(name: str) -> np.ndarray:
    """(H, W) float64 grey photograph from the package assets."""
    return load_asset(name).astype(np.float64)


def translation_field(xy: np.ndarray) -> np.ndarray:
    return np.broadcast_to(np.array([2.7, -1.6]), xy.shape)


def affine_field(xy: np.ndarray) -> np.ndarray:
    """Rotation 1.5 deg and zoom 1.02 about the frame centre plus a shift (3.2, -2.1) px."""
    angle = np.deg2rad(1.5)
    a = 1.02 * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    centred = xy - CENTRE
    return centred @ a.T - centred + np.array([3.2, -2.1])


def grid(step: int = 4, margin: int = MARGIN, side: int = SIDE) -> np.ndarray:
    """(N, 2) pixel positions every ``step`` px, ``margin`` px inside a side x side frame."""
    ys, xs = np.mgrid[margin : side - margin : step, margin : side - margin : step]
    return np.column_stack((xs.ravel(), ys.ravel())).astype(np.float64)


def warped_pair(field, photo: str, noise: float = 1.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(prev, cur) float32 SIDE x SIDE frames, prev(x) = cur(x + field(x)), cubic B-spline, noise std ``noise``."""
    return render_pair(load(photo), field, SIDE, noise, seed)


def field_of(prev: np.ndarray, cur: np.ndarray, settings: RobustMotionSettings) -> LocalField:
    """The stage's field on its own global fit, as the pipeline computes it."""
    prev_frame, cur_frame = Frame(0, prev.astype(np.uint8)), Frame(1, cur.astype(np.uint8))
    fit = GlobalMotion(settings).fit(prev_frame, cur_frame)
    return LocalMotion(settings).field(prev_frame, cur_frame, fit)


def rms(error: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.square(error), axis=-1))))


# --------------------------------------------------------------------------- one motion


@pytest.mark.parametrize(("field", "photo", "model"), [
    (translation_field, "gravel.png", "translation"),
    (translation_field, "camera.png", "affine"),
    (affine_field, "camera.png", "affine"),
    (affine_field, "astronaut.png", "affine"),
    (affine_field, "gravel.png", "affine"),
    (affine_field, "coffee.png", "quadratic"),
])
def test_a_global_warp_is_recovered(field, photo, model):
    """<= 0.1 px RMS where the field says its window constrains the motion; elsewhere Q_k says it does not.

    Q_k - q_floor I <= 0.01 px^2 holds at 87-100 % of the positions of these
    photographs; the others are windows of sky, coat or saucer with too little
    texture, where a window's own regression (``exact_local_motion``) strays by
    up to ~1-3 px as well and Q_k grows to cover it.
    """
    settings = RobustMotionSettings(model=model)
    prev, cur = warped_pair(field, photo)
    local = field_of(prev, cur, settings)
    xy = grid()
    error = local.displacement(xy) - field(xy)
    noise = local.noise(xy)
    constrained = np.linalg.eigvalsh(noise - settings.q_floor * np.eye(2))[:, -1] <= 0.01
    assert constrained.mean() >= 0.85, f"{photo}: only {constrained.mean():.0%} of windows constrain the motion"
    assert rms(error[constrained]) <= 0.1, f"{photo}, {model}: RMS error {rms(error[constrained]):.3f} px > 0.1 px"
    assert np.mean(np.linalg.norm(error, axis=1) < 0.5) >= 0.98
    mahalanobis = np.einsum("ni,nij,nj->n", error, np.linalg.inv(noise), error)
    assert np.mean(mahalanobis <= 9.21) >= 0.99, "Q_k should cover the errors (chi-square, 2 dof, 99 %)"


# --------------------------------------------------------------------------- two motions


class RingPair:
    """Frames k-1, k of the ring scene with the truth: U at any position of frame k-1 and its region."""

    def __init__(self, scene, k: int, disk_centre_0: np.ndarray):
        self.prev, self.cur = scene.frames[k - 1].astype(np.float32), scene.frames[k].astype(np.float32)
        self.index = k
        height, width = scene.frames.shape[1:]
        self.radius = 0.18 * min(width, height)  # synthetic.ring: radius 18 % of the smaller side
        self.steps = [compose(scene.maps[layer, k], invert(scene.maps[layer, k - 1])) for layer in (0, 1)]
        self.centres = [apply(scene.maps[1, j], disk_centre_0) for j in (k - 1, k)]

    def truth(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) true displacement (px) of positions xy (N, 2) of frame k-1."""
        on_disk = np.linalg.norm(xy - self.centres[0], axis=1) < self.radius
        return np.where(on_disk[:, None], apply(self.steps[1], xy), apply(self.steps[0], xy)) - xy

    def regions(self, xy: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
        """(N,) bool each: on the disk at least ``margin`` px inside its outline; on the background at least
        ``margin`` px outside it in frame k-1 and, moved by the truth, in frame k."""
        inside = self.radius - np.linalg.norm(xy - self.centres[0], axis=1)
        landed = np.linalg.norm(xy + self.truth(xy) - self.centres[1], axis=1) - self.radius
        return inside >= margin, (-inside >= margin) & (landed >= margin)


def apply(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    return x @ m[:, :2].T + m[:, 2]


def invert(m: np.ndarray) -> np.ndarray:
    a = np.linalg.inv(m[:, :2])
    return np.concatenate([a, (-a @ m[:, 2])[:, None]], axis=1)


def compose(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """The (2, 3) affine map x -> outer(inner(x))."""
    return np.concatenate([outer[:, :2] @ inner[:, :2], apply(outer, inner[:, 2])[:, None]], axis=1)


@pytest.fixture(scope="module")
def ring():
    scene = make_scene("ring", seed=0)
    height, width = scene.frames.shape[1:]
    frame_centre = np.array([width - 1, height - 1]) / 2

    def off_circle(unknowns: np.ndarray) -> np.ndarray:
        centres = np.stack([apply(m, unknowns[:2]) for m in scene.maps[1]])
        return np.linalg.norm(centres - frame_centre, axis=1) - unknowns[2]

    disk_centre_0 = least_squares(off_circle, [*frame_centre, 0.25 * min(width, height)]).x[:2]
    return scene, disk_centre_0


def test_an_object_moving_differently_from_the_background_is_captured(ring):
    """Windows inside one motion: >= 90 % of positions within 0.5 px of the truth, on the disk and off it."""
    scene, disk_centre_0 = ring
    settings = RobustMotionSettings()
    xy = grid(step=3, margin=16, side=scene.frames.shape[2])
    xy = xy[xy[:, 1] <= scene.frames.shape[1] - 16]
    close = {"disk": [], "background": []}
    relative = []
    for k in range(1, len(scene.frames), 4):
        pair = RingPair(scene, k, disk_centre_0)
        error = np.linalg.norm(field_of(pair.prev, pair.cur, settings).displacement(xy) - pair.truth(xy), axis=1)
        disk, background = pair.regions(xy, HALF_WINDOW)
        close["disk"].append(error[disk] < 0.5)
        close["background"].append(error[background] < 0.5)
        relative.append(np.linalg.norm(pair.truth(xy[disk]) - (apply(pair.steps[0], xy[disk]) - xy[disk]), axis=1))
    assert np.median(np.concatenate(relative)) > 5, "the disk should move well apart from the background"
    for region, hits in close.items():
        hits = np.concatenate(hits)
        assert len(hits) > 500, f"{region}: only {len(hits)} positions scored"
        assert hits.mean() >= 0.9, f"{region}: {hits.mean():.1%} of positions within 0.5 px of the truth (< 90 %)"


def test_shared_field_matches_the_exact_regression(ring):
    """The approximation (module docstring): field vs one robust regression per position, same everything else.

    Scored on windows inside one motion (>= a half window from the disk's
    outline), separately on the disk (turning: the affine terms matter) and the
    background. Near the outline the two may differ by several px; that band is
    reported by the module docstring, not asserted.
    """
    scene, disk_centre_0 = ring
    settings = RobustMotionSettings()
    rng = np.random.default_rng(0)
    height, width = scene.frames.shape[1:]
    gaps = {"disk": [], "background": []}
    noise_ratio = []
    for k in (3, 12, 21):
        pair = RingPair(scene, k, disk_centre_0)
        on_disk = pair.centres[0] + rng.uniform(-1, 1, (400, 2)) * (pair.radius - HALF_WINDOW) / np.sqrt(2)
        anywhere = rng.uniform([16, 16], [width - 17, height - 17], (200, 2))
        xy = np.concatenate((on_disk, anywhere))
        xy = xy[np.all((xy >= 16) & (xy <= [width - 17, height - 17]), axis=1)]
        exact_u, exact_q = exact_local_motion(pair.prev, pair.cur, xy, settings)
        local = field_of(pair.prev, pair.cur, settings)
        gap = np.linalg.norm(local.displacement(xy) - exact_u, axis=1)
        disk, background = pair.regions(xy, HALF_WINDOW)
        gaps["disk"].append(gap[disk])
        gaps["background"].append(gap[background])
        one_region = disk | background
        floor = 2 * settings.q_floor
        noise_ratio.append((np.trace(local.noise(xy[one_region]), axis1=1, axis2=2) - floor)
                           / (np.trace(exact_q[one_region], axis1=1, axis2=2) - floor))
    for region, tolerance in (("disk", (0.15, 0.3)), ("background", (0.02, 0.05))):
        gap = np.concatenate(gaps[region])
        assert len(gap) > 200, f"{region}: only {len(gap)} positions scored"
        median, p90 = np.median(gap), np.percentile(gap, 90)
        assert median <= tolerance[0] and p90 <= tolerance[1], (
            f"{region}: field - exact median {median:.3f} px, 90th percentile {p90:.3f} px "
            f"(tolerances {tolerance[0]}, {tolerance[1]})")
    ratio = np.concatenate(noise_ratio)
    assert 0.8 <= np.median(ratio) <= 1.25, f"Q_k - floor: field / exact median ratio {np.median(ratio):.2f}"


def test_the_field_matches_the_exact_regression_on_a_single_motion():
    prev, cur = warped_pair(affine_field, "camera.png")
    settings = RobustMotionSettings()
    xy = np.random.default_rng(1).uniform(MARGIN, SIDE - MARGIN, (300, 2))
    exact_u, _ = exact_local_motion(prev, cur, xy, settings)
    gap = np.linalg.norm(field_of(prev, cur, settings).displacement(xy) - exact_u, axis=1)
    assert np.median(gap) <= 0.02 and np.percentile(gap, 90) <= 0.05, (
        f"field - exact median {np.median(gap):.3f} px, 90th percentile {np.percentile(gap, 90):.3f} px")


def square_moving_far(xy: np.ndarray) -> np.ndarray:
    """A 160 px square at the frame centre moved (-44, 30) px; the background still."""
    inside = np.all(np.abs(xy - CENTRE) < 80, axis=1)
    return np.where(inside[:, None], [-44.0, 30.0], 0.0)


@pytest.mark.parametrize("local_search", [64, 0])
def test_a_motion_far_beyond_the_passes_capture_is_found_by_the_search(local_search):
    """The coarsest level's block matching (``local_search``) starts the square's windows near their motion.

    Scored on the 32 x 32 px at the square's centre (the coarsest windows there,
    64 px, lie inside the square). Measured when written: 94 % within 0.5 px
    with the search (85 % over the central 48 x 48 px); 0 % without it (the
    passes, from the background's motion, stop tens of px short).
    """
    prev, cur = warped_pair(square_moving_far, "gravel.png")
    xy = grid(step=4, margin=CENTRE - 16, side=SIDE)
    settings = RobustMotionSettings(local_search=local_search)
    error = np.linalg.norm(field_of(prev, cur, settings).displacement(xy) - square_moving_far(xy), axis=1)
    found = (error < 0.5).mean()
    if local_search:
        assert found >= 0.9, f"{found:.0%} of the square's centre within 0.5 px"
    else:
        assert found <= 0.1, f"without the search {found:.0%} within 0.5 px: the scene no longer needs it"


# --------------------------------------------------------------------------- state noise Q_k


def half_flat_pair() -> tuple[np.ndarray, np.ndarray]:
    """A still scene, two noisy shots (std 1 grey): gravel on the left half, flat grey at the top right,
    vertical stripes (texture along x only) at the bottom right."""
    x = np.arange(SIDE)
    base = np.where(x < SIDE // 2, load("gravel.png")[:SIDE, :SIDE], 128.0)
    base[SIDE // 2 :, SIDE // 2 :] = 128 + 60 * np.sin(2 * np.pi * x[SIDE // 2 :] / 9.0)
    rng = np.random.default_rng(3)
    return tuple(np.clip(np.round(base + rng.normal(0, 1, base.shape)), 0, 255).astype(np.float32) for _ in range(2))


def test_state_noise_is_positive_definite_and_grows_without_texture():
    prev, cur = half_flat_pair()
    settings = RobustMotionSettings()
    local = field_of(prev, cur, settings)
    xy = grid(step=20, margin=8)
    q = local.noise(xy)
    assert q.shape == (len(xy), 2, 2)
    np.testing.assert_allclose(q, q.transpose(0, 2, 1), rtol=0, atol=1e-9)
    assert np.linalg.eigvalsh(q).min() >= settings.q_floor - 1e-9
    quarter, three_quarters = SIDE / 4, 3 * SIDE / 4
    textured = local.noise(np.array([[quarter, quarter]]))[0]
    flat = local.noise(np.array([[three_quarters, quarter]]))[0]
    striped = local.noise(np.array([[three_quarters, three_quarters]]))[0]
    assert np.trace(flat) > 100 * np.trace(textured), f"flat {np.trace(flat):.2f} vs textured {np.trace(textured):.2f}"
    assert np.trace(textured) < 2 * settings.q_floor + 0.05
    # stripes constrain x only: the fit's part of Q_k is tight across them, wide along them (the noise's
    # gradients along the stripes are all that constrains y: a few 0.01 px^2, under q_floor)
    fit_part = striped - settings.q_floor * np.eye(2)
    assert fit_part[1, 1] > 100 * fit_part[0, 0], f"stripes: Q_k - floor diagonal {np.diag(fit_part)}"


# --------------------------------------------------------------------------- stage


def test_field_is_deterministic_and_read_only():
    prev_gray, cur_gray = warped_pair(translation_field, "astronaut.png")
    settings = RobustMotionSettings()
    prev, cur = Frame(0, prev_gray.astype(np.uint8)), Frame(1, cur_gray.astype(np.uint8))
    stage = LocalMotion(settings)
    local = stage.field(prev, cur, GlobalMotion(settings).fit(prev, cur))
    again = field_of(prev_gray, cur_gray, settings)  # fresh frames, a fresh stage
    np.testing.assert_array_equal(again.flow, local.flow)  # deterministic, bit for bit
    np.testing.assert_array_equal(again.cov, local.cov)
    reused = stage.field(prev, cur, GlobalMotion(settings).fit(prev, cur))  # the stage's work arrays and pyramids reused
    np.testing.assert_array_equal(reused.flow, local.flow)
    np.testing.assert_array_equal(reused.cov, local.cov)
    with pytest.raises(ValueError):
        local.flow[0, 0, 0] = 1.0


def test_sampling_keeps_the_leading_shape():
    local = field_of(*warped_pair(translation_field, "coffee.png"), RobustMotionSettings())
    xy = np.random.default_rng(2).uniform(0, SIDE - 1, (5, 7, 2))  # (points, particles, 2)
    u, q = local.displacement(xy), local.noise(xy)
    assert u.shape == (5, 7, 2) and q.shape == (5, 7, 2, 2)
    np.testing.assert_array_equal(u[3], local.displacement(xy[3]))
    assert local.displacement(np.array([200.0, 200.0])).shape == (2,)
