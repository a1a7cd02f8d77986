"""The ``paper`` preset (configs/paper.yaml, issue 29) and its per-point regression motion stage (``regression``).

Measured when written:
- regression stage, a 320 x 320 crop of camera.png warped by rotation 1.5 deg, zoom 1.02 and
  shift (3.2, -2.1) px, the regression started from a zero global motion (so that the window
  alone must find the motion), 225 windows every 16 px: median error 0.024 px, 95th percentile
  0.19 px, 95 % within 0.2 px (the worst, 17 px, on the sky's flat windows);
- the preset end to end on a synthetic camera-motion scene (10 frames, 12 queries, exact truth):
  clf <delta_avg 1.000 (median error 0.03 px), cnlf 1.000 (0.11 px).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from condtrack_cli import pipeline
from condtrack_cli.config import load_config
from condtrack_cli.evaluate.groundtruth import load_gt_csv
from condtrack_cli.frames.readers import FrameSettings, open_frames
from condtrack_cli.frames.synthetic import make_scene
from condtrack_cli.frames.synthetic.files import write_scene
from condtrack_cli.evaluate.score import score_tracks
from condtrack_cli.motion.local import local_levels
from condtrack_cli.motion.pyramid import build_pyramid
from condtrack_cli.motion.regression import RegressionField, RegressionSettings
from condtrack_cli.motion.robust import fit_of
from condtrack_cli.queries import read_queries
from condtrack_cli import registry

from conftest import load_asset, render_pair

PAPER = Path(__file__).resolve().parents[1] / "configs" / "paper.yaml"
SIDE = 320
CENTRE = (SIDE - 1) / 2


def affine_field(xy: np.ndarray) -> np.ndarray:
    """Rotation 1.5 deg and zoom 1.02 about the frame centre plus a shift (3.2, -2.1) px."""
    angle = np.deg2rad(1.5)
    a = 1.02 * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    centred = xy - CENTRE
    return centred @ a.T - centred + np.array([3.2, -2.1])


def test_the_preset_is_the_papers_method():
    config = load_config(PAPER).to_dict()
    motion, measure, filters = config["motion"], config["measure"], config["filter"]
    assert motion["name"] == "regression" and motion["model"] == "affine" and motion["local_window"] == 32
    assert motion["q_misfit"] == 0 and motion["search_radius"] == 0
    assert measure["cost"] == "ssd" and measure["c_rule"] == "unit_sum" and measure["uniform_test"] == "pearson"
    assert measure["ambiguity_ratio"] is None and measure["search_max"] == 32 and measure["r_floor"] <= 0.001
    assert filters["clf"]["dynamics"] == "global"
    cnlf = filters["cnlf"]
    assert cnlf["particles"] == 100 and cnlf["ess_fraction"] == 1.0 and cnlf["path_lag"] is None
    assert cnlf["layer_jump"] is None
    for line in PAPER.read_text(encoding="utf-8").splitlines():  # every key says what the paper says
        if line.strip() and not line.lstrip().startswith("#") and ":" in line:
            assert "#" in line, f"paper.yaml: no comment on {line.strip()!r}"


def test_the_regression_stage_is_registered():
    assert "regression" in registry.names("motion")


def test_the_regression_stage_recovers_an_affine_motion():
    """Each window's regression alone (global motion zero) finds the affine warp: median error <= 0.05 px,
    >= 90 % of the windows within 0.2 px (measured 0.024 px and 95 %).

    Positions every 16 px, 40 px inside the frame. Windows without texture (sky) may
    stray; the 95 % bound leaves room for them.
    """
    prev, cur = render_pair(load_asset("camera.png").astype(np.float64), affine_field, SIDE, 1.0, 0)
    settings = RegressionSettings(model="affine")
    depth = local_levels(prev.shape, settings.levels)
    prev_pyramid, cur_pyramid = build_pyramid(prev, depth), build_pyramid(cur, depth)
    still = fit_of(prev_pyramid, cur_pyramid, np.zeros(6), settings)  # no help from the global fit
    ys, xs = np.mgrid[40 : SIDE - 40 : 16, 40 : SIDE - 40 : 16]
    xy = np.column_stack((xs.ravel(), ys.ravel())).astype(np.float64)
    field = RegressionField(prev_pyramid, cur_pyramid, still, settings)
    error = np.linalg.norm(field.displacement(xy) - affine_field(xy), axis=1)
    assert np.median(error) <= 0.05, f"median error {np.median(error):.3f} px"
    assert np.mean(error <= 0.2) >= 0.90, f"only {np.mean(error <= 0.2):.0%} within 0.2 px"
    noise = field.noise(xy)
    assert noise.shape == (len(xy), 2, 2)
    assert np.all(np.linalg.eigvalsh(noise) >= settings.q_floor - 1e-9)
    # a batch and the same positions asked one by one agree (nothing shared between windows)
    np.testing.assert_allclose(RegressionField(prev_pyramid, cur_pyramid, still, settings).displacement(xy[:3]),
                               field.displacement(xy)[:3], atol=1e-9)


@pytest.fixture(scope="module")
def camera_scene(tmp_path_factory):
    """A synthetic camera-motion scene, 10 frames, the first 12 queries (exact truth)."""
    folder = write_scene(make_scene("camera_motion", seed=0, n_frames=10), tmp_path_factory.mktemp("paper") / "scene")
    lines = (folder / "queries.csv").read_text().splitlines()
    (folder / "queries.csv").write_text("\n".join(lines[:13]) + "\n")
    return folder


@pytest.mark.parametrize("method", ["clf", "cnlf"])
def test_the_paper_preset_tracks_a_synthetic_scene(camera_scene, method):
    """The camera scene's motion is one affine map per frame: both filters follow it, <delta_avg >= 0.95
    and median error <= 0.3 px (measured 1.000 and 0.03 / 0.11 px)."""
    source = open_frames(FrameSettings(), camera_scene)
    queries = read_queries(camera_scene / "queries.csv", source.info)
    truth = load_gt_csv(camera_scene / "tracks.csv")
    tracks = pipeline.run(source, source.info, load_config(PAPER, method=method), queries)
    metrics, _ = score_tracks(tracks, truth)
    assert metrics["delta_avg"] >= 0.95, f"{method}: <delta_avg {metrics['delta_avg']:.3f}"
    assert metrics["median_err"] <= 0.3, f"{method}: median error {metrics['median_err']:.3f} px"


def test_the_papers_uniform_test_and_no_one_peak_test():
    """Pearson's statistic and the G form agree on a sharp peak and a flat surface; with ``ambiguity_ratio``
    null two equal peaks 3 px apart are no longer refused by a one-peak test."""
    from condtrack_cli.measure.response import SSDSettings, response

    grid = np.arange(7) - 3
    sharp = (100.0 + 50.0 * (grid[None, :] ** 2 + grid[:, None] ** 2))[None].astype(float)
    flat = np.full((1, 7, 7), 1000.0)
    for form in ("g", "pearson"):
        settings = SSDSettings(uniform_test=form, equalise_alpha=None)
        assert response(sharp, 2.0, 121, settings, np.zeros((1, 2)))[1][0]
        assert not response(flat, 2.0, 121, settings, np.zeros((1, 2)))[1][0]
    two = np.full((1, 7, 7), 5000.0)
    two[0, 3, 3] = two[0, 3, 6] = 100.0
    assert not response(two, 2.0, 121, SSDSettings(equalise_alpha=None), np.zeros((1, 2)))[1][0]
    R, informative, _ = response(two, 2.0, 121, SSDSettings(equalise_alpha=None, ambiguity_ratio=None,
                                                            uniform_test="pearson"), np.zeros((1, 2)))
    assert R[0, 0, 0] > R[0, 1, 1]  # the second peak widens R_k along x, the paper's eq. (9)


def test_mdr_can_move_points_by_the_local_motion():
    """``filter.mdr.dynamics: local`` asks for the local field and moves points with it (ring sample's disk)."""
    from conftest import sample_inputs

    source, queries, truth = sample_inputs("ring")
    scores = {}
    for dynamics in ("global", "local"):
        config = load_config(None, method="mdr", overrides=[f"filter.mdr.dynamics={dynamics}"])
        scores[dynamics] = score_tracks(pipeline.run(source, source.info, config, queries), truth)[0]["delta_avg"]
    assert scores["local"] > scores["global"] + 0.05, scores


def test_the_bench_reports_the_paper_preset_beside_the_defaults():
    """The coverage table of the bench's section against LK has the paper preset's rows after the defaults'."""
    from condtrack_cli.evaluate.bench.versus_lk import coverage_table, paper_columns

    calibrated = {"cov50": 0.5, "cov90": 0.9, "cov95": 0.95, "cov99": 0.99, "cov50_gauss": 0.7, "cov90_gauss": 0.93,
                  "cov95_gauss": 0.96, "cov99_gauss": 0.98, "cov_finite": 1.0, "nees": 2.0, "cov50_rescaled": 0.5}
    results = {m: (calibrated, 1.0) for m in ("auto", "clf", "cnlf")}
    results.update({column: (dict(calibrated, cov50=0.9), 9.0) for column in paper_columns(("clf", "cnlf"))})
    lines = coverage_table({"a": results}, "set", ("clf", "cnlf"))
    assert "| a | paper cnlf | 0.900 | 0.900 | 0.950 | 0.990 | 0.700 | 0.930 | 0.960 | 0.980 | 1.000 | 2.000 | 0.500 |" in lines
    assert lines.index("| a | paper cnlf | 0.900 | 0.900 | 0.950 | 0.990 | 0.700 | 0.930 | 0.960 | 0.980 | 1.000 | 2.000 | 0.500 |") == 6
