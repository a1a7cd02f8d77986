"""Synthetic scenes: determinism, exact ground truth (geometric and photometric), files written."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from condtrack_cli.cli import cli
from condtrack_cli.frames import synthetic
from condtrack_cli.frames.synthetic.deform import Bumps, random_bumps

PATCH = np.stack(np.meshgrid(np.arange(-3.0, 4.0), np.arange(-3.0, 4.0)), axis=-1).reshape(-1, 2)  # (49, 2) offsets


@pytest.fixture(scope="module")
def scenes() -> dict[str, synthetic.Scene]:
    return {name: synthetic.make_scene(name, seed=0) for name in synthetic.SCENES}


def invert(m: np.ndarray) -> np.ndarray:
    """Inverse of affine maps (..., 2, 3), written independently of the module under test."""
    a = np.linalg.inv(m[..., :2])
    return np.concatenate([a, -(a @ m[..., 2:])], axis=-1)


def apply(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Affine maps (..., 2, 3) applied to points (..., 2)."""
    return (m[..., :2] @ x[..., None])[..., 0] + m[..., 2]


def sample(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """OpenCV bicubic samples of ``image`` at positions xy (N, M, 2) -> (N, M), OpenCV's pixel convention."""
    xy = xy.astype(np.float32)
    return cv2.remap(image.astype(np.float32), xy[..., 0], xy[..., 1], cv2.INTER_CUBIC,
                     borderMode=cv2.BORDER_REFLECT).astype(np.float64)


def patch_differences(scene: synthetic.Scene, offset=(0.0, 0.0), normalise: bool = False):
    """Mean absolute difference between each point's query patch and its patch at the truth in frame k.

    The 7 x 7 query patch is carried to frame k by the point's layer map, so rotation
    and zoom are accounted for; ``offset`` (px) displaces the frame-k patch. Returns
    (P, F) differences, NaN on the query frame.
    """
    n_points, n_frames = scene.visible.shape
    q = scene.queries.frame
    reference = np.empty((n_points, len(PATCH)))
    for frame in np.unique(q):
        rows = q == frame
        reference[rows] = sample(scene.frames[frame], scene.queries.xy[rows, None] + PATCH)
    query_to_frame0 = invert(scene.maps[scene.layer, q])  # (P, 2, 3)
    out = np.full((n_points, n_frames), np.nan)
    for k in range(n_frames):
        linear = scene.maps[scene.layer, k, :, :2] @ query_to_frame0[..., :2]  # (P, 2, 2) query frame -> frame k
        where = scene.tracks[:, k, None] + PATCH @ linear.transpose(0, 2, 1) + offset
        target = sample(scene.frames[k], where)
        ref = reference
        if normalise:
            ref = (ref - ref.mean(1, keepdims=True)) / ref.std(1, keepdims=True)
            target = (target - target.mean(1, keepdims=True)) / (target.std(1, keepdims=True) + 1e-9)
        out[:, k] = np.where(q == k, np.nan, np.abs(ref - target).mean(axis=1))
    return out


def in_frame(scene: synthetic.Scene) -> np.ndarray:
    """(P, F) bool: the true position lies inside the frame."""
    _, h, w = scene.frames.shape
    x, y = scene.tracks[..., 0], scene.tracks[..., 1]
    return (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)


def test_same_seed_same_scene_and_different_seed_differs():
    a, b = synthetic.make_scene("occlusion", seed=3), synthetic.make_scene("occlusion", seed=3)
    for field in ("frames", "tracks", "visible", "layer", "maps"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    np.testing.assert_array_equal(a.queries.xy, b.queries.xy)
    np.testing.assert_array_equal(a.queries.frame, b.queries.frame)
    c = synthetic.make_scene("occlusion", seed=4)
    assert not np.array_equal(a.frames, c.frames)
    assert not np.array_equal(a.maps, c.maps)


@pytest.mark.parametrize("name", list(synthetic.SCENES))
def test_shapes_queries_and_visibility(scenes, name):
    scene = scenes[name]
    n_frames, h, w = scene.frames.shape
    n_points = len(scene.queries)
    assert scene.frames.dtype == np.uint8 and (w, h) == synthetic.DEFAULT_SIZE
    assert 40 <= n_points <= 80
    assert scene.tracks.shape == (n_points, n_frames, 2) and scene.visible.shape == (n_points, n_frames)
    assert scene.maps.shape == (len(scene.layer_names), n_frames, 2, 3)
    np.testing.assert_array_equal(scene.queries.point_id, np.arange(n_points))
    rows = np.arange(n_points)
    np.testing.assert_array_equal(scene.queries.xy, scene.tracks[rows, scene.queries.frame])
    assert scene.visible[rows, scene.queries.frame].all()
    margin = synthetic.BORDER_MARGIN
    assert (scene.queries.xy >= margin).all() and (scene.queries.xy <= [w - 1 - margin, h - 1 - margin]).all()
    assert not (scene.visible & ~in_frame(scene)).any()  # outside the frame is never visible


@pytest.mark.parametrize("name", [name for name in synthetic.SCENES if name != "nonrigid"])
def test_maps_carry_every_position_back_to_its_query(scenes, name):
    scene = scenes[name]
    to_frame0 = invert(scene.maps[scene.layer])  # (P, F, 2, 3)
    back = apply(to_frame0, scene.tracks)  # (P, F, 2)
    rows = np.arange(len(scene.layer))
    query_in_frame0 = back[rows, scene.queries.frame]
    np.testing.assert_allclose(back, np.broadcast_to(query_in_frame0[:, None], back.shape), rtol=0, atol=1e-9)
    np.testing.assert_allclose(scene.maps[:, 0], np.broadcast_to(np.eye(2, 3), scene.maps[:, 0].shape), atol=1e-12)


@pytest.mark.parametrize("name", ["camera_motion", "occlusion", "ring", "fast"])
def test_image_content_follows_the_truth(scenes, name):
    """Patches at the true positions match the query patches to the noise level; 2 px off they do not."""
    scene = scenes[name]
    visible_later = scene.visible & ~np.isnan(patch_differences(scene))
    at_truth = patch_differences(scene)[visible_later]
    shifted = patch_differences(scene, offset=(2.0, 0.0))[visible_later]
    # Two independent noisy samples differ by ~1.13 sigma on average; half a pixel off already gives > 10.
    assert np.median(at_truth) < 1.75 * scene.noise
    assert np.median(at_truth) < 0.2 * np.median(shifted)
    for layer in np.unique(scene.layer):  # each layer on its own, the rotating disk included
        rows = np.broadcast_to((scene.layer == layer)[:, None], scene.visible.shape)[visible_later]
        assert np.median(at_truth[rows]) < 1.75 * scene.noise


def test_image_content_follows_the_truth_under_changing_light(scenes):
    scene = scenes["illumination"]
    at_truth = patch_differences(scene, normalise=True)
    shifted = patch_differences(scene, offset=(2.0, 0.0), normalise=True)
    keep = scene.visible & ~np.isnan(at_truth)
    assert np.median(at_truth[keep]) < 0.3 * np.median(shifted[keep])
    contrast = scene.frames.reshape(len(scene.frames), -1).std(axis=1)
    assert contrast.max() > 1.4 * contrast.min()  # the light does change


@pytest.mark.parametrize("name", ["occlusion", "ring"])
def test_hidden_points_are_really_covered(scenes, name):
    """Where a point in the frame is flagged hidden, the image there is not the point's patch."""
    scene = scenes[name]
    differences = patch_differences(scene)
    hidden = ~scene.visible & in_frame(scene) & ~np.isnan(differences)
    visible = scene.visible & ~np.isnan(differences)
    assert hidden.sum() >= 30
    assert np.median(differences[hidden]) > 4 * np.median(differences[visible])


def test_occlusion_hides_points_for_several_frames_then_shows_them_again(scenes):
    scene = scenes["occlusion"]
    covered = ~scene.visible & in_frame(scene)
    returns = 0
    for p in range(len(scene.layer)):
        flags = "".join("h" if c else ("v" if v else "o") for c, v in zip(covered[p], scene.visible[p]))
        returns += bool(re.search("vh{3,}v", flags[scene.queries.frame[p]:]))
    assert returns >= 5
    assert (scene.layer == 1).sum() >= 5 and (scene.queries.frame > 0).sum() >= 3


def test_ring_object_moves_differently_from_the_background(scenes):
    scene = scenes["ring"]
    disk = scene.layer == 1
    assert disk.sum() >= 10 and (~disk).sum() >= 30
    # Where the background motion would carry the disk points, versus where they are.
    as_background = apply(scene.maps[0][None], scene.tracks[disk, :1])
    assert np.linalg.norm(as_background - scene.tracks[disk], axis=-1).max(axis=1).min() > 20
    # The disk spins on itself: the rotation angle of its map changes by degrees per frame.
    angle = np.degrees(np.arctan2(scene.maps[1, :, 1, 0], scene.maps[1, :, 0, 0]))
    assert np.abs(np.diff(np.unwrap(angle, period=360))).min() > 2
    # Disk points are never covered, background points are while the disk passes.
    assert scene.visible[disk].all()
    assert (~scene.visible[~disk] & in_frame(scene)[~disk]).any()


def test_camera_motion_changes_abruptly(scenes):
    maps = scenes["camera_motion"].maps[0]
    square = np.concatenate([maps, np.broadcast_to([[[0.0, 0.0, 1.0]]], (len(maps), 1, 3))], axis=1)
    steps = square[1:] @ np.linalg.inv(square[:-1])  # frame k-1 -> frame k
    changes = np.abs(np.diff(steps, axis=0)).max(axis=(1, 2)) > 1e-6
    assert 4 <= changes.sum() <= 10


def test_fast_scene_moves_10_to_25_pixels_per_frame(scenes):
    scene = scenes["fast"]
    step = np.linalg.norm(np.diff(scene.tracks, axis=1), axis=-1)
    assert 10 <= np.median(step) <= 25 and step.min() > 8 and step.max() < 27


def test_write_scene_files(tmp_path):
    scene = synthetic.make_scene("ring", seed=1, size=(160, 120), n_frames=6)
    n_points, n_frames = scene.visible.shape
    out = synthetic.write_scene(scene, tmp_path / "ring")
    names = sorted(p.name for p in out.iterdir())
    assert names == [f"{k:05d}.png" for k in range(n_frames)] + ["labels.csv", "queries.csv", "scene.json", "tracks.csv"]
    for k in range(n_frames):
        np.testing.assert_array_equal(cv2.imread(str(out / f"{k:05d}.png"), cv2.IMREAD_UNCHANGED), scene.frames[k])

    queries = (out / "queries.csv").read_text()
    assert queries.splitlines()[0] == "point_id,frame,x,y" and "\r" not in queries
    table = np.loadtxt(out / "queries.csv", delimiter=",", skiprows=1, ndmin=2)
    np.testing.assert_array_equal(table[:, :2], np.stack([scene.queries.point_id, scene.queries.frame], axis=1))
    np.testing.assert_allclose(table[:, 2:], scene.queries.xy, atol=5e-5)

    tracks = (out / "tracks.csv").read_text()
    lines = tracks.splitlines()
    assert lines[0] == "point_id,frame,x,y,visible" and len(lines) == 1 + n_points * n_frames
    assert re.fullmatch(r"0,0,-?\d+\.\d{4},-?\d+\.\d{4},[01]", lines[1])
    table = np.loadtxt(out / "tracks.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(table[:, 0], np.repeat(np.arange(n_points), n_frames))
    np.testing.assert_array_equal(table[:, 1], np.tile(np.arange(n_frames), n_points))
    np.testing.assert_allclose(table[:, 2:4], scene.tracks.reshape(-1, 2), atol=5e-5)
    np.testing.assert_array_equal(table[:, 4], scene.visible.ravel())

    labels = np.loadtxt(out / "labels.csv", delimiter=",", skiprows=1, dtype=int)
    assert (out / "labels.csv").read_text().startswith("point_id,layer\n")
    np.testing.assert_array_equal(labels[:, 1], scene.layer)

    first = {p.name: p.read_bytes() for p in out.iterdir()}
    synthetic.write_scene(synthetic.make_scene("ring", seed=1, size=(160, 120), n_frames=6), out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == first  # bit for bit, PNGs included

    synthetic.write_scene(synthetic.make_scene("ring", seed=1, size=(160, 120), n_frames=4), out)
    assert not (out / "00005.png").exists()  # no stale frame from the longer sequence
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="notes.txt"):
        synthetic.write_scene(scene, out)
    assert (out / "notes.txt").exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_command_line_writes_samples_and_single_scenes(tmp_path):
    runner = CliRunner()
    assert runner.invoke(cli, ["synth", str(tmp_path / "samples"), "--samples"]).exit_code == 0
    assert sorted(p.name for p in (tmp_path / "samples").iterdir()) == sorted(synthetic.SAMPLE_SEEDS)
    result = runner.invoke(cli, ["synth", str(tmp_path / "fast"), "--scene", "fast", "--size", "128x96", "--frames", "5"])
    assert result.exit_code == 0
    assert len(list((tmp_path / "fast").glob("*.png"))) == 5
    result = runner.invoke(cli, ["synth", str(tmp_path / "bad"), "--scene", "fast", "--size", "10x10"])
    assert result.exit_code == 2 and "size 10x10 is too small" in result.output
    result = runner.invoke(cli, ["synth", str(tmp_path / "bad"), "--scene", "fast", "--size", "64\u00b2x64"])
    assert result.exit_code == 2 and "expected WIDTHxHEIGHT, got '64\u00b2x64'" in result.output


def test_unknown_scene_lists_the_valid_names():
    with pytest.raises(ValueError, match="camera_motion, occlusion, ring, illumination, fast"):
        synthetic.make_scene("garden")


@pytest.mark.parametrize("seed", [0, 3])
def test_jumps_and_card_are_the_hard_cases_of_issue_31(seed):
    """jumps: the camera's step jumps between slow (< 11 px) and fast (> 16 px, beyond the default search)
    segments; card: background points are covered by the card and seen again once it has left."""
    jumps = synthetic.make_scene("jumps", seed=seed)
    step = np.median(np.linalg.norm(np.diff(jumps.tracks, axis=1), axis=2), axis=0)  # (F - 1,) px per frame
    assert step.max() > 16 and step.min() < 11 and (np.abs(np.diff(step)) > 6).sum() >= 3
    card = synthetic.make_scene("card", seed=seed)
    background = card.layer == 0
    _, h, w = card.frames.shape
    inside = (card.tracks[..., 0] >= 0) & (card.tracks[..., 0] <= w - 1) & (card.tracks[..., 1] >= 0) & (card.tracks[..., 1] <= h - 1)
    covered = background[:, None] & inside & ~card.visible
    back_again = [p for p in np.flatnonzero(covered.any(axis=1)) if card.visible[p, np.flatnonzero(covered[p]).max():].any()]
    assert len(back_again) >= 10
    assert not card.visible[card.layer == 1, 0].any()  # the card starts outside the frame


@pytest.mark.parametrize("n_frames", [2, 4, 9, 10])
def test_a_short_card_clip_is_the_start_of_the_long_one(n_frames):
    """--frames 2-9 crashed: the card's points were picked on its arrival frame (7-9) whatever the clip's length;
    at 10 the card jumped out of the frame on frame 8 (np.interp's knots out of order). Seed 0 (arrival 9, leaving
    after frame 20): the card moves as in the default 30 frames, its points picked on the clip's last frame."""
    full = synthetic.make_scene("card", seed=0, size=(64, 64))
    short = synthetic.make_scene("card", seed=0, size=(64, 64), n_frames=n_frames)
    assert short.frames.shape[0] == n_frames
    np.testing.assert_array_equal(short.maps[1], full.maps[1, :n_frames])
    assert (short.layer == 1).any() == (n_frames >= 8)  # card points from an 8-frame clip on (seed 0, 64 px)
    assert short.visible[short.layer == 1, -1].all()  # picked in place on the last frame


def test_synth_help_lists_every_scene():
    """The --scene help is written out (the command line imports no numpy for --help): it names every scene."""
    from click.testing import CliRunner

    from condtrack_cli.cli import cli
    from condtrack_cli.frames.synthetic import SCENES

    text = " ".join(CliRunner().invoke(cli, ["synth", "--help"]).output.split())
    assert f"Scene to write into OUT: {', '.join(SCENES)}." in text


def test_synth_help_gives_the_sizes_it_takes():
    """--size's help said "WIDTHxHEIGHT in pixels." while synth refuses a side under 64 px or over 4096 ("size 48x48 is
    too small (at least 64 px each way)"); it now gives the range, written out and checked here against the scenes'."""
    from condtrack_cli.frames.synthetic.scenes import MAX_SIDE

    text = " ".join(CliRunner().invoke(cli, ["synth", "--help"]).output.split())
    assert f"WIDTHxHEIGHT in pixels, {4 * synthetic.BORDER_MARGIN} to {MAX_SIDE} each way." in text
    with pytest.raises(ValueError, match=f"at least {4 * synthetic.BORDER_MARGIN} px each way"):
        synthetic.make_scene("ring", seed=0, size=(4 * synthetic.BORDER_MARGIN - 1, 64))


@pytest.mark.parametrize("seed", [0, 2])
def test_nonrigid_truth_is_exact(seed):
    """The ``nonrigid`` scene (issue 45), small and short: the renderer's own backward map carries every true
    position back to its query's frame-0 position within 1e-9 px, the frames are that renderer's output (noiseless:
    the rounded intensity at each pixel), the noiseless intensity along the truth equals the query's intensity times
    the scene's slow contrast gain within 1e-9 grey levels (1 px off it differs by >= 1 grey level on most points),
    and the motion is non-rigid: the best affine map of frame 0's true positions to frame k's misses them by > 0.3 px."""
    from condtrack_cli.frames.synthetic.scenes import _nonrigid_intensity, _nonrigid_parts, _nonrigid_source

    size, n_frames = (128, 96), 8
    scene = synthetic.make_scene("nonrigid", seed=seed, size=size, n_frames=n_frames, noise=0.0)
    _, _, layer, bumps, contrast, _ = _nonrigid_parts(seed, size, n_frames, 0.0)
    assert len(scene.queries) >= 6 and (scene.queries.frame == 0).all()
    x0 = scene.tracks[:, 0]
    grid = np.stack(np.meshgrid(np.arange(128.0), np.arange(96.0)), axis=-1).reshape(-1, 2)
    no_gain = Bumps(contrast.centres, contrast.directions, contrast.sigmas, np.zeros_like(contrast.amplitudes))
    reference = _nonrigid_intensity(layer, bumps, no_gain, x0, 0)
    misfit = []
    for k in range(n_frames):
        np.testing.assert_allclose(_nonrigid_source(layer, bumps, scene.tracks[:, k], k), x0, rtol=0, atol=1e-9)
        rendered = _nonrigid_intensity(layer, bumps, contrast, grid, k).reshape(96, 128)
        np.testing.assert_array_equal(scene.frames[k], np.clip(np.rint(rendered), 0, 255))
        along = _nonrigid_intensity(layer, bumps, no_gain, scene.tracks[:, k], k)
        np.testing.assert_allclose(along, reference, rtol=0, atol=1e-9)
        off = _nonrigid_intensity(layer, bumps, no_gain, scene.tracks[:, k] + [1.0, 0.0], k)
        assert np.median(np.abs(off - reference)) >= 1.0
        design = np.column_stack([x0, np.ones(len(x0))])
        fit, *_ = np.linalg.lstsq(design, scene.tracks[:, k], rcond=None)
        misfit.append(np.abs(design @ fit - scene.tracks[:, k]).max())
    assert max(misfit) > 0.3, misfit


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5])
def test_nonrigid_deformation_never_folds_and_its_newton_inverse_is_exact(seed):
    """Over the default frame, every frame's deformation u -> u + D(u, k) keeps a Jacobian determinant >= 0.5 (a
    diffeomorphism) and :meth:`Bumps.forward` inverts it within 1e-9 px; the displacement reaches 6 px or more."""
    from condtrack_cli.frames.synthetic.scenes import _nonrigid_parts

    _, _, _, bumps, _, _ = _nonrigid_parts(seed, synthetic.DEFAULT_SIZE, 30, 2.0)
    w, h = synthetic.DEFAULT_SIZE
    grid = np.stack(np.meshgrid(np.arange(0.0, w, 4), np.arange(0.0, h, 4)), axis=-1).reshape(-1, 2)
    largest = 0.0
    for k in range(30):
        assert np.linalg.det(bumps.jacobian(grid, k)).min() >= 0.5
        moved = grid + bumps.displacement(grid, k)
        np.testing.assert_allclose(bumps.forward(moved, k), grid, rtol=0, atol=1e-9)
        largest = max(largest, np.abs(bumps.displacement(grid, k)).max())
    assert largest >= 6.0


def test_bumps_jacobian_matches_finite_differences():
    """``Bumps.jacobian`` against central differences of ``Bumps.displacement`` (step 1e-4 px): within 1e-6."""
    rng = np.random.default_rng(7)
    bumps = random_bumps(rng, (120, 90), 5)
    u = rng.uniform(0, 100, (20, 2))
    numeric = np.stack([(bumps.displacement(u + step, 3) - bumps.displacement(u - step, 3)) / 2e-4
                        for step in ([1e-4, 0.0], [0.0, 1e-4])], axis=2) + np.eye(2)
    np.testing.assert_allclose(bumps.jacobian(u, 3), numeric, rtol=0, atol=1e-6)


def test_random_bumps_scale_down_a_deformation_that_would_fold():
    """Twenty bumps of 4-8 px peak on a 64 x 64 frame would fold it; ``random_bumps`` scales their amplitudes
    down by 0.8 at a time: the result keeps the determinant >= MIN_JACOBIAN on its 4 px grid (and > 0 on a 1 px
    one), the amplitudes one step larger do not, and the largest amplitude is under 2 x 4 px."""
    from condtrack_cli.frames.synthetic.deform import MIN_JACOBIAN

    bumps = random_bumps(np.random.default_rng(5), (64, 64), 10, count=20)
    coarse = np.stack(np.meshgrid(np.arange(-8.0, 72, 4), np.arange(-8.0, 72, 4)), axis=-1).reshape(-1, 2)
    fine = np.stack(np.meshgrid(np.arange(0.0, 64), np.arange(0.0, 64)), axis=-1).reshape(-1, 2)
    larger = Bumps(bumps.centres, bumps.directions, bumps.sigmas, bumps.amplitudes / 0.8)
    assert min(np.linalg.det(bumps.jacobian(coarse, k)).min() for k in range(10)) >= MIN_JACOBIAN
    assert min(np.linalg.det(bumps.jacobian(fine, k)).min() for k in range(10)) > 0
    assert min(np.linalg.det(larger.jacobian(coarse, k)).min() for k in range(10)) < MIN_JACOBIAN
    assert np.abs(bumps.amplitudes).max() < 8.0
