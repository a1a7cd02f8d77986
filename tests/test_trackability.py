"""Trackability of queries (issue 29): each query's Shi-Tomasi score at its query frame, written to
/tracks/trackability and Tracks.trackability; a warning, --untrackable drop|keep|error; the covariance of a
query on a flat region or an edge says that the image cannot place it along the aperture."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
from scipy import ndimage

import condtrack_cli as ct
from condtrack_cli.detect import trackability
from condtrack_cli.detect.shi_tomasi import ShiTomasiSettings, scores_at, structure_tensors_at
from condtrack_cli.errors import InvalidArgument, InvalidArgumentType
from condtrack_cli.frames.readers import FrameSettings, open_frames

#: The scene's queries on frame 0: point_id -> (x, y). A corner of a bright quadrant on a flat dark card, a point
#: on its vertical edge, one in its flat inside, one on its horizontal edge, one on the texture around the card.
CORNER, EDGE_V, FLAT, EDGE_H, TEXTURE = 0, 1, 2, 3, 4
QUERY_XY = np.array([[149.5, 109.5], [149.5, 140.0], [180.0, 140.0], [180.0, 109.5], [50.0, 30.0]])
STEP = np.array([1.0, 0.5])  #: the whole scene moves by STEP px per frame
N_FRAMES = 8
WARNING = re.compile(
    r"^warning: 3 of 5 queries are untrackable \(Shi-Tomasi score below detect\.min_eigenvalue 10\.0\), "
    r"e\.g\. point 1 at frame 0 \(149\.5, 140\.0\), score 0\.\d+; tracked anyway \(--untrackable keep\)$", re.M)


def whole_frame_maps(gray: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """The whole frame's structure-tensor maps (a, b, c stacked, (3, H, W)) and Shi-Tomasi score map (H, W), by
    OpenCV's filters: Sobel / 8 (reflect-101 border), products box-averaged over ``block`` (reflected border)."""
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    a, b, c = (cv2.boxFilter(u * v, -1, (block, block), borderType=cv2.BORDER_REFLECT) for u, v in
               ((gx, gx), (gx, gy), (gy, gy)))
    return np.stack([a, b, c]), (a + c) / 2 - np.sqrt(((a - c) / 2) ** 2 + b * b)


@pytest.mark.parametrize(("height", "width", "block"), [(120, 200, 7), (6, 5, 7), (3, 3, 31), (40, 30, 9)])
def test_structure_tensors_on_point_windows_are_the_whole_frame_filters_at_the_points(height, width, block):
    """Each point's window, borders included (a window larger than the frame reflects more than once), gives
    what the whole frame's Sobel and box filter give at its nearest pixel, to float32 rounding."""
    rng = np.random.default_rng(block)
    gray = ndimage.gaussian_filter(rng.uniform(0, 255, (height, width)), 1.0).astype(np.float32)
    xy = np.vstack([[[0, 0], [width - 1, height - 1], [0, height - 1], [width - 1, 0], [-3.0, height + 2.0]],
                    np.column_stack([rng.uniform(0, width - 1, 200), rng.uniform(0, height - 1, 200)])])
    maps, score = whole_frame_maps(gray, block)
    cols = np.clip(np.rint(xy[:, 0]).astype(int), 0, width - 1)
    rows = np.clip(np.rint(xy[:, 1]).astype(int), 0, height - 1)
    tensors = structure_tensors_at(gray, xy, block)
    scale = np.abs(maps).max()
    np.testing.assert_allclose(tensors[:, [0, 0, 1], [0, 1, 1]].T, maps[:, rows, cols], rtol=0, atol=1e-6 * scale)
    np.testing.assert_allclose(tensors[:, 0, 1], tensors[:, 1, 0], rtol=0, atol=0)
    np.testing.assert_allclose(scores_at(gray, xy, block), score[rows, cols], rtol=0, atol=1e-6 * scale)


def write_scene(folder: Path, noise: float = 2.0, seed: int = 0) -> None:
    """8 frames 200 x 160 of a textured background with a flat card (dark, with a bright quadrant), all moving by STEP."""
    folder.mkdir()
    height, width, pad = 160, 200, 40
    rng = np.random.default_rng(seed)
    base = 128 + 400 * ndimage.gaussian_filter(rng.normal(0, 1, (height + 2 * pad, width + 2 * pad)), 2.0)
    base[100:, 140:] = 90.0  # the card: frame x >= 100, y >= 60 on frame 0
    base[150:, 190:] = 190.0  # its bright quadrant, corner at (149.5, 109.5) on frame 0
    for k in range(N_FRAMES):
        shift = np.float32([[1, 0, STEP[0] * k - pad], [0, 1, STEP[1] * k - pad]])
        image = cv2.warpAffine(base.astype(np.float32), shift, (width, height), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REFLECT)
        cv2.imwrite(str(folder / f"{k:03d}.png"),
                    np.clip(np.round(image + rng.normal(0, noise, image.shape)), 0, 255).astype(np.uint8))


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[Path, Path]:
    """(frames folder, queries CSV) of the scene, the five queries on frame 0."""
    root = tmp_path_factory.mktemp("trackability")
    write_scene(root / "frames")
    queries = root / "queries.csv"
    queries.write_text("point_id,frame,x,y\n" + "".join(f"{p},0,{x},{y}\n" for p, (x, y) in enumerate(QUERY_XY)))
    return root / "frames", queries


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", "from condtrack_cli.cli import main; main()", *args],
                          capture_output=True, text=True, timeout=300)


def test_scores_are_the_detectors_at_each_query_frame_one_call_per_frame(scene, monkeypatch):
    folder, _ = scene
    source = open_frames(FrameSettings(), folder)
    # the texture point queried on frame 0 and again on frame 3 (where the scene has moved 3 STEPs)
    queries = ct.types.Queries(np.arange(6), np.array([0, 0, 0, 0, 0, 3]),
                               np.vstack([QUERY_XY, QUERY_XY[TEXTURE] + 3 * STEP]))
    calls = []
    real = trackability.scores_at
    monkeypatch.setattr(trackability, "scores_at", lambda gray, xy, block: calls.append(len(xy)) or real(gray, xy, block))
    scores = trackability.query_scores(source, queries, block=7)
    assert calls == [5, 1]  # one call per query frame, all its points at once
    for k in (0, 3):
        _, eig = whole_frame_maps(source.read(k).astype(np.float32), 7)
        on = queries.frame == k
        cols, rows = np.rint(queries.xy[on]).astype(int).T
        np.testing.assert_allclose(scores[on], eig[rows, cols], rtol=1e-5, atol=1e-4)
    floor = ShiTomasiSettings().min_eigenvalue
    np.testing.assert_array_equal(scores > floor, [True, False, False, False, True, True])


def test_keep_warns_once_with_the_count_and_the_first_point(scene, tmp_path):
    folder, queries = scene
    out = tmp_path / "out.h5"
    result = run_cli("track", str(folder), "-p", str(queries), "-m", "stk", "-o", str(out))
    assert result.returncode == 0, result.stderr
    assert len(WARNING.findall(result.stderr)) == 1, result.stderr
    assert len([line for line in result.stderr.splitlines() if line.startswith("warning:")]) == 1
    with h5py.File(out) as f:
        assert f["tracks/point_id"][()].tolist() == [0, 1, 2, 3, 4]
        scores = f["tracks/trackability"]
        assert scores.dtype == np.float64 and scores.shape == (5,) and scores.attrs["units"] == "(grey/px)^2"
        np.testing.assert_array_equal(scores[()] > 10.0, [True, False, False, False, True])
    quiet = run_cli("track", str(folder), "-p", str(queries), "-m", "stk", "-o", str(tmp_path / "q.csv"), "-q")
    assert quiet.returncode == 0 and quiet.stderr == ""


def test_drop_leaves_the_untrackable_queries_out_and_keeps_the_others_ids(scene, tmp_path):
    folder, queries = scene
    h5, csv = tmp_path / "out.h5", tmp_path / "out.csv"
    for out in (h5, csv):
        result = run_cli("track", str(folder), "-p", str(queries), "-m", "stk", "-o", str(out), "--untrackable", "drop")
        assert result.returncode == 0, result.stderr
        assert "3 of 5 queries are untrackable" in result.stderr and "; not tracked (--untrackable drop)" in result.stderr
    back = ct.read_tracks(h5)
    assert back.queries.point_id.tolist() == [CORNER, TEXTURE] and back.xy.shape == (2, N_FRAMES, 2)
    assert (back.trackability > 10.0).all()
    assert sorted({int(line.split(",")[0]) for line in csv.read_text().splitlines()[1:]}) == [CORNER, TEXTURE]


def test_error_stops_before_any_output_with_one_line(scene, tmp_path):
    folder, queries = scene
    out = tmp_path / "out.h5"
    result = run_cli("track", str(folder), "-p", str(queries), "-o", str(out), "--untrackable", "error")
    assert result.returncode == 1 and result.stdout == ""
    assert result.stderr.count("\n") == 1 and result.stderr.startswith(
        "Error: 3 of 5 queries are untrackable (Shi-Tomasi score below detect.min_eigenvalue 10.0), "
        "e.g. point 1 at frame 0 (149.5, 140.0), score 0.")
    assert "--untrackable error" in result.stderr
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_the_config_key_is_the_option_and_drop_of_every_query_is_an_error(scene, tmp_path):
    folder, queries = scene
    flat = tmp_path / "flat.csv"
    flat.write_text(f"frame,x,y\n0,{QUERY_XY[FLAT][0]},{QUERY_XY[FLAT][1]}\n")
    result = run_cli("track", str(folder), "-p", str(flat), "-o", str(tmp_path / "out.h5"),
                     "--set", "detect.untrackable=drop")
    assert result.returncode == 1
    assert result.stderr.startswith("Error: 1 of 1 queries are untrackable") and "no query left to track" in result.stderr
    bad = run_cli("track", str(folder), "-p", str(flat), "--untrackable", "maybe")
    assert bad.returncode == 2 and "'maybe' is not one of 'keep', 'drop', 'error'" in bad.stderr


def test_api_attribute_argument_and_warning(scene):
    folder, queries = scene
    with pytest.warns(ct.CondtrackWarning, match=r"3 of 5 queries are untrackable .*; tracked anyway"):
        kept = ct.track(folder, queries=queries, method="stk")
    assert kept.trackability.shape == (5,)
    np.testing.assert_array_equal(kept.trackability > 10.0, [True, False, False, False, True])
    rows = np.column_stack([np.zeros(5), QUERY_XY])
    with pytest.warns(ct.CondtrackWarning, match="not tracked"):
        dropped = ct.track(folder, queries=rows, method="stk", untrackable="drop")
    assert dropped.queries.point_id.tolist() == [CORNER, TEXTURE]
    np.testing.assert_array_equal(dropped.trackability, kept.trackability[[CORNER, TEXTURE]])
    with pytest.raises(ct.CondtrackError, match="3 of 5 queries are untrackable"):
        ct.track(folder, queries=rows, method="stk", config={"detect": {"untrackable": "error"}})
    with pytest.raises(InvalidArgument, match="untrackable: 'skip' is not one of keep, drop, error"):
        ct.track(folder, queries=rows, untrackable="skip")
    with pytest.raises(InvalidArgumentType, match="untrackable: expected one of keep, drop, error, got bool"):
        ct.track(folder, queries=rows, untrackable=True)


def test_detected_points_carry_their_score(scene):
    folder, _ = scene
    tracks = ct.track(folder, method="stk")
    source = open_frames(FrameSettings(), folder)
    _, eig = whole_frame_maps(source.read(0).astype(np.float32), ShiTomasiSettings().block)
    cols, rows = np.rint(tracks.queries.xy).astype(int).T
    np.testing.assert_allclose(tracks.trackability, eig[rows, cols], rtol=1e-5, atol=1e-4)
    assert (tracks.trackability > ShiTomasiSettings().min_eigenvalue).all()


def test_hdf5_round_trip_and_a_schema_1_0_file_without_scores(scene, tmp_path):
    folder, queries = scene
    with pytest.warns(ct.CondtrackWarning):
        tracks = ct.track(folder, queries=queries, method="stk")
    h5 = tmp_path / "out.h5"
    tracks.to_hdf5(h5)
    np.testing.assert_array_equal(ct.read_tracks(h5).trackability, tracks.trackability)
    with h5py.File(h5, "r+") as f:  # what condtrack wrote before schema 2.0
        del f["tracks/trackability"], f["tracks/dof"]
        f.attrs["schema_version"] = "1.0"
    old = ct.read_tracks(h5)
    assert old.trackability.shape == (5,) and np.isnan(old.trackability).all()
    np.testing.assert_array_equal(old.xy, tracks.xy)
    csv = tmp_path / "out.csv"
    tracks.to_csv(csv)
    assert csv.read_text().splitlines()[0] == "point_id,frame,x,y,cov_xx,cov_xy,cov_yy,dof,visible,method"
    assert np.isnan(ct.read_tracks(csv).trackability).all()


def _axes(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (..., 2) ascending and the major axis (..., 2) of covariances (..., 2, 2)."""
    values, vectors = np.linalg.eigh(cov)
    return values, vectors[..., :, 1]


@pytest.mark.parametrize("method", ["clf", "cnlf", "auto"])
def test_flat_and_edge_queries_carry_a_covariance_wide_along_the_aperture(scene, method):
    """Issue 29's done-when: a flat query is reported untrackable, warned about, and carries a wider covariance
    than a corner query; an edge query's covariance is longest along the edge, and longer there than the corner's;
    from the query frame on, and the true point stays in their 95 % ellipses."""
    folder, queries = scene
    with pytest.warns(ct.CondtrackWarning, match=r"3 of 5 queries are untrackable"):
        tracks = ct.track(folder, queries=queries, method=method)
    assert not (tracks.trackability[[FLAT, EDGE_V, EDGE_H]] > 10.0).any()
    values, major = _axes(tracks.cov)  # every frame, the query frame 0 included
    corner_largest = values[CORNER, :, 1]
    assert (values[FLAT, :, 0] > 3 * corner_largest).all()  # wider in every direction
    for edge, along in ((EDGE_V, np.array([0.0, 1.0])), (EDGE_H, np.array([1.0, 0.0]))):
        assert (values[edge, :, 1] > 3 * corner_largest).all()
        assert (np.abs(major[edge] @ along) > np.cos(np.deg2rad(20))).all()  # longest along the edge
    truth = QUERY_XY[:, None] + np.arange(N_FRAMES)[None, :, None] * STEP
    error = tracks.xy - truth
    nis = np.einsum("pfi,pfi->pf", error, np.linalg.solve(tracks.cov, error[..., None])[..., 0])
    assert (nis[[FLAT, EDGE_V, EDGE_H]] <= 5.991).all()  # chi-square 2 dof, 95 %


def test_the_aperture_offset_is_zero_where_the_test_passes_and_follows_the_edge():
    """``Aperture.offset``: nothing for a corner; along the edge only for an edge; both directions on a flat region."""
    image = np.full((64, 64), 60.0, np.float32)
    image[32:, 32:] = 200.0
    image += np.random.default_rng(0).normal(0, 1.0, image.shape).astype(np.float32)
    points = np.array([[32.0, 32.0], [31.5, 50.0], [10.0, 10.0]])  # corner, vertical edge, flat
    sigma = np.repeat(0.25 * np.eye(2)[None], 3, axis=0)
    offset = trackability.Aperture(block=7, floor=10.0).offset(image, points, sigma)
    np.testing.assert_array_equal(offset[0], 0.0)
    values, vectors = np.linalg.eigh(offset[1])
    assert values[0] < 1e-9 and values[1] > 10 * 0.25 and abs(vectors[1, 1]) > 0.99  # along y, the edge
    assert np.linalg.eigvalsh(offset[2]).min() > 10 * 0.25
    assert np.linalg.eigvalsh(offset[2]).max() <= 0.25 * (trackability.MAX_APERTURE_RATIO - 1) + 1e-9
