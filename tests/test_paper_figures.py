"""The forward-backward round trip of ``make paper`` (condtrack_cli/evaluate/paper_figures.py), on exact truth."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from condtrack_cli.evaluate import paper_figures
from condtrack_cli.frames.synthetic import make_scene
from condtrack_cli.frames.synthetic.files import write_scene

#: A correct tracker brings a point visible on every frame of a short camera-motion clip back to where it
#: started within this many px (median), and nearly all of them within paper_figures.WITHIN (2 px).
MEDIAN_TOLERANCE = 0.5
SHARE_WITHIN = 0.9


@pytest.fixture(scope="module")
def scene_folder(tmp_path_factory):
    scene = make_scene("camera_motion", seed=1, size=(192, 144), n_frames=10)
    folder = write_scene(scene, tmp_path_factory.mktemp("paper") / "camera_motion")
    always = scene.visible.all(axis=1)
    return folder, scene.tracks[always, 0], scene.tracks[always]


@pytest.mark.parametrize("method", ["clf", "stk"])
@pytest.mark.filterwarnings("ignore:.*queries are untrackable:condtrack_cli.errors.CondtrackWarning")  # the way back starts where the forward leg ended (issue 29)
def test_round_trip_is_small_for_a_correct_tracker(scene_folder, tmp_path, method):
    folder, start, truth = scene_folder
    trip = paper_figures.round_trip(folder, start, method, tmp_path)
    assert trip.forward.xy.shape == truth.shape
    stats = paper_figures.round_trip_stats(trip)
    assert stats["points"] == len(start) >= 20
    assert stats["came_back"] == 1.0
    assert stats["median_px"] < MEDIAN_TOLERANCE
    assert stats["within"] >= SHARE_WITHIN
    # the forward leg itself is on the truth: the round trip is not small by standing still
    assert np.median(np.linalg.norm(trip.forward.xy[:, -1] - truth[:, -1], axis=-1)) < MEDIAN_TOLERANCE
    assert np.median(np.linalg.norm(np.diff(truth, axis=1), axis=-1).sum(axis=1)) > 10  # px travelled


def test_round_trip_stats_count_points_that_did_not_come_back(scene_folder, tmp_path):
    folder, start, _ = scene_folder
    trip = paper_figures.round_trip(folder, start[:4], "stk", tmp_path)
    back = trip.back.copy()
    back[0] = np.nan            # not tracked back
    back[1] = start[1] + [3, 4]  # 5 px off
    bent = dataclasses.replace(trip, back=back)
    stats = paper_figures.round_trip_stats(bent)
    assert stats["came_back"] == 0.75
    assert stats["within"] == 0.5
    assert np.isclose(bent.error[1], 5.0)


def test_reversed_folder_reverses_the_frames(scene_folder, tmp_path):
    folder, _, _ = scene_folder
    clip = paper_figures.reversed_folder(folder, tmp_path / "reversed")
    names = sorted(p.name for p in clip.iterdir())
    assert [(clip / n).resolve().name for n in names] == sorted((p.name for p in folder.glob("*.png")), reverse=True)


def test_paper_skips_without_the_shared_data(tmp_path, capsys):
    assert paper_figures.main(["--shared-data", str(tmp_path / "absent"), "--out", str(tmp_path / "out")]) == 0
    assert "absent" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_draw_writes_an_enlarged_contact_sheet_and_an_overlay(scene_folder, tmp_path):
    folder, start, _ = scene_folder
    trip = paper_figures.round_trip(folder, start[:5], "clf", tmp_path)
    paper_figures.draw(trip, folder, tmp_path / "s.sheet.png", tmp_path / "s.mp4")
    sheet = cv2.imread(str(tmp_path / "s.sheet.png"))
    scale = 3  # 192 x 144 frames are drawn 3x (MIN_DRAWN_SIDE 400 px)
    assert sheet.shape == (2 * 144 * scale, 3 * 192 * scale, 3)
    assert (tmp_path / "s.mp4").stat().st_size > 0
