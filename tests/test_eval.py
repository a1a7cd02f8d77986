"""Evaluation: TAP-Vid metrics on hand-computed tiny cases, GT readers, alignment, ``condtrack eval``."""

from __future__ import annotations

import json
import os
import pickle
import warnings

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from condtrack_cli.errors import CondtrackError
from condtrack_cli.evaluate import (
    METRIC_KEYS,
    GroundTruth,
    align,
    coverage_inside,
    load_gt_csv,
    load_gt_tapvid,
    pixels_to_tapvid,
    tapvid_metrics,
    tapvid_to_pixels,
)
from condtrack_cli.cli.eval import eval_command
from condtrack_cli.evaluate.metrics import COVERAGE_LEVELS, calibration_metrics, chi2_2dof, coverage_key
from condtrack_cli.predictive import ellipse_level, ellipse_m2
from condtrack_cli.types import Queries, Tracks
from conftest import SAMPLES

NAN, INF = np.nan, np.inf

# Two points, four frames. GT position of point p on frame f: (10 + f, 20 + 2p).
# Point 0 (query frame 0):
#   f0 query frame (never scored)         pred exact, visible
#   f1 GT occluded, pred visible  d=0.5   -> FP at every threshold, OA wrong
#   f2 GT visible, pred occluded  d=1.5   -> within 2.., not TP, OA wrong; inside cov I
#   f3 GT visible, pred visible   d=1.0   -> exactly 1: NOT within 1, within 2..; outside cov 0.01 I
# Point 1 (query frame 1, its first predicted frame):
#   f0 GT visible, no prediction          -> strided only: not within, not visible, cov not counted
#   f1 query frame                        pred exact, visible
#   f2 no GT row                          pred far (d=100) and visible: never scored
#   f3 GT visible, pred visible   d=3.0   -> within 4..; inside its infinite cov
OFFSETS = np.array([
    [[0, 0], [0.5, 0], [0, -1.5], [-1, 0]],
    [[NAN, NAN], [0, 0], [100, 0], [0, 3]],
])
PRED_VISIBLE = np.array([[1, 1, 0, 1], [0, 1, 1, 1]], bool)
GT_VISIBLE = np.array([[1, 0, 1, 1], [1, 1, 0, 1]], bool)
GT_KNOWN = np.array([[1, 1, 1, 1], [1, 1, 0, 1]], bool)
QUERY_FRAME = np.array([0, 1])

EXPECTED = {
    "first": {
        # scored: p0 f1..f3, p1 f3; GT-visible scored distances 1.5, 1.0, 3.0
        "pts_within_1": 0.0, "pts_within_2": 2 / 3, "pts_within_4": 1.0, "pts_within_8": 1.0, "pts_within_16": 1.0,
        "delta_avg": 11 / 15,
        # TP/(3 + FP): x=1: 0/(3+3); x=2: 1/(3+2); x>=4: 2/(3+1)
        "jaccard_1": 0.0, "jaccard_2": 0.2, "jaccard_4": 0.5, "jaccard_8": 0.5, "jaccard_16": 0.5, "AJ": 0.34,
        "OA": 2 / 4, "median_err": 1.5,
        # counted ellipses: p0 f2 (m2 = 2.25 under I), p0 f3 (m2 = 100 under 0.01 I), p1 f3 (infinite: inside);
        # chi2 quantiles 1.386 (50%), 4.605 (90%), 5.991 (95%), 9.210 (99%)
        "cov50": 1 / 3, "cov90": 2 / 3, "cov95": 2 / 3, "cov99": 2 / 3, "nees": (2.25 + 100) / 2, "cov_finite": 2 / 3,
        # m2 sorted 0 (infinite), 2.25, 100: k = 100 / 5.991 puts all 3 inside at 95 %; at 50 %: m2 <= 23.1 (2 of 3)
        "cov50_rescaled": 2 / 3,
        # no dof given: every row Gaussian, the two readings agree
        "cov50_gauss": 1 / 3, "cov90_gauss": 2 / 3, "cov95_gauss": 2 / 3, "cov99_gauss": 2 / 3,
        "n_points": 2, "n_frames": 4,
    },
    "strided": {
        # scored: p0 f1..f3, p1 f0 and f3; GT-visible scored distances 1.5, 1.0, (none), 3.0
        "pts_within_1": 0.0, "pts_within_2": 0.5, "pts_within_4": 0.75, "pts_within_8": 0.75, "pts_within_16": 0.75,
        "delta_avg": 0.55,
        # TP/(4 + FP): x=1: 0/(4+3); x=2: 1/(4+2); x>=4: 2/(4+1)
        "jaccard_1": 0.0, "jaccard_2": 1 / 6, "jaccard_4": 0.4, "jaccard_8": 0.4, "jaccard_16": 0.4, "AJ": 41 / 150,
        "OA": 2 / 5, "median_err": 2.25,
        # p1 f0 has no prediction: not counted, and not finite (2 finite of 4 GT-visible scored rows)
        "cov50": 1 / 3, "cov90": 2 / 3, "cov95": 2 / 3, "cov99": 2 / 3, "nees": (2.25 + 100) / 2, "cov_finite": 0.5,
        "cov50_rescaled": 2 / 3,
        # no dof given: every row Gaussian, the two readings agree
        "cov50_gauss": 1 / 3, "cov90_gauss": 2 / 3, "cov95_gauss": 2 / 3, "cov99_gauss": 2 / 3,
        "n_points": 2, "n_frames": 4,
    },
}


def gt_xy() -> np.ndarray:
    """(2, 4, 2) GT positions of the fixture."""
    frames, points = np.meshgrid(np.arange(4.0), np.arange(2.0))
    return np.stack([10 + frames, 20 + 2 * points], axis=-1)


def pred_cov() -> np.ndarray:
    """(2, 4, 2, 2) predicted covariances of the fixture."""
    cov = np.broadcast_to(np.eye(2), (2, 4, 2, 2)).copy()
    cov[0, 3] = 0.01 * np.eye(2)
    cov[1, 0] = NAN
    cov[1, 3] = np.diag([INF, INF])
    return cov


def fixture_metrics(mode: str) -> dict:
    return tapvid_metrics(gt_xy() + OFFSETS, PRED_VISIBLE, pred_cov(), gt_xy(), GT_VISIBLE, GT_KNOWN, QUERY_FRAME, mode)


@pytest.mark.parametrize("mode", ["first", "strided"])
def test_hand_computed_metrics(mode):
    result = fixture_metrics(mode)
    assert tuple(result) == METRIC_KEYS
    assert result == pytest.approx(EXPECTED[mode], abs=1e-12)
    assert isinstance(result["n_points"], int) and isinstance(result["n_frames"], int)


def test_first_and_strided_differ():
    assert fixture_metrics("first")["OA"] != fixture_metrics("strided")["OA"]


def test_inputs_not_mutated():
    pred = gt_xy() + OFFSETS
    cov = pred_cov()
    before = pred.copy(), cov.copy()
    tapvid_metrics(pred, PRED_VISIBLE, cov, gt_xy(), GT_VISIBLE, GT_KNOWN, QUERY_FRAME, "strided")
    np.testing.assert_array_equal(pred, before[0])
    np.testing.assert_array_equal(cov, before[1])


def test_distance_on_threshold_is_not_within():
    # distances exactly 2, 4 and 16 px: each is within the next threshold only
    gt = np.zeros((1, 4, 2))
    pred = np.array([[[0, 0], [0, 2], [4, 0], [0, -16]]], float)
    visible = np.ones((1, 4), bool)
    result = tapvid_metrics(pred, visible, None, gt, visible, visible, np.array([0]), "first")
    assert [result[f"pts_within_{x}"] for x in (1, 2, 4, 8, 16)] == pytest.approx([0, 0, 1 / 3, 2 / 3, 2 / 3])
    assert all(result[key] is None for key in ("cov50", "cov90", "cov95", "cov99", "nees", "cov_finite", "cov50_rescaled"))


def test_all_visible_gt_leaves_visibility_metrics_null():
    gt = np.zeros((1, 3, 2))
    pred = np.array([[[0, 0], [0.5, 0], [3, 0]]])
    ones = np.ones((1, 3), bool)
    result = tapvid_metrics(pred, ~ones, None, gt, ones, ones, np.array([0]), "first")
    assert result["OA"] is None and result["AJ"] is None
    assert all(result[f"jaccard_{x}"] is None for x in (1, 2, 4, 8, 16))
    assert result["pts_within_1"] == 0.5 and result["pts_within_4"] == 1.0
    assert result["median_err"] == pytest.approx(1.75)


def test_nothing_scored_gives_nulls():
    one = np.ones((1, 1), bool)
    result = tapvid_metrics(np.zeros((1, 1, 2)), one, None, np.zeros((1, 1, 2)), one, one, np.array([0]), "first")
    assert {k: v for k, v in result.items() if v is not None} == {"n_points": 1, "n_frames": 1}


def test_median_is_null_when_most_frames_have_no_prediction():
    gt = np.zeros((1, 4, 2))
    pred = np.array([[[0, 0], [1, 0], [NAN, NAN], [NAN, NAN]]])
    ones = np.ones((1, 4), bool)
    result = tapvid_metrics(pred, ones, None, gt, ones, ones, np.array([0]), "strided")
    assert result["median_err"] is None
    assert result["pts_within_2"] == pytest.approx(1 / 3)


def test_coverage_inside():
    correlated = np.array([[2.0, 1.0], [1.0, 2.0]])
    cov = np.array([correlated, correlated, np.diag([INF, INF]), np.diag([INF, 1.0]), np.full((2, 2), NAN),
                    np.zeros((2, 2)), np.array([[1.0, 2.0], [2.0, 1.0]]), np.eye(2)])
    error = np.array([[2, 2], [3, -3], [1e6, 1e6], [0, 1e3], [0, 0], [0, 0], [0, 0], [NAN, NAN]], float)
    counted, inside = coverage_inside(error, cov)
    # Mahalanobis^2: (2, 2) -> 8/3 inside; (3, -3) -> 18 outside; any infinite entry: unbounded, inside;
    # NaN cov, zero cov, indefinite cov, no prediction: no ellipse, not counted
    np.testing.assert_array_equal(counted, [1, 1, 1, 1, 0, 0, 0, 0])
    np.testing.assert_array_equal(inside, [1, 0, 1, 1, 0, 0, 0, 0])
    m2 = [e @ np.linalg.solve(correlated, e) for e in error[:2]]
    assert m2 == pytest.approx([8 / 3, 18]) and m2[0] <= chi2_2dof(0.95) < m2[1]


@pytest.mark.parametrize("dof", [2.5, 3.0, 4.0, 10.0, 1e6])
def test_student_t_ellipse_bounds_are_fisher_quantiles(dof):
    """Issue 27: with scale C (nu - 2) / nu, d^T C^-1 d nu / (2 (nu - 2)) ~ F(2, nu); ellipse_level inverts the bound."""
    from scipy import stats

    levels = np.array(COVERAGE_LEVELS)
    bound = ellipse_m2(levels, dof)
    np.testing.assert_allclose(bound, 2 * (dof - 2) / dof * stats.f.ppf(levels, 2, dof), rtol=1e-9)
    np.testing.assert_allclose(ellipse_level(bound, dof), levels, rtol=1e-12)
    np.testing.assert_allclose(ellipse_m2(levels, np.inf), chi2_2dof(levels), rtol=1e-15)
    if dof == 1e6:  # nu large: the Gaussian's bounds
        np.testing.assert_allclose(bound, chi2_2dof(levels), rtol=1e-4)


def test_coverage_of_student_t_errors_is_the_level_under_their_dof_only():
    """Errors drawn from bivariate Student-t laws (nu 3 and 6, known covariances): the coverage under each row's
    dof is the level within 0.01 (20000 rows); the Gaussian reading of the same rows holds far more than half at
    50 % and less than 99 % at 99 %."""
    from scipy import stats

    rng = np.random.default_rng(7)
    n = 20000
    cov = np.array([[4.0, 1.5], [1.5, 2.0]])
    error = np.concatenate([stats.multivariate_t(shape=cov * (nu - 2) / nu, df=nu).rvs(n // 2, random_state=rng)
                            for nu in (3.0, 6.0)])
    dof = np.repeat([3.0, 6.0], n // 2)
    out = calibration_metrics(error[None], np.broadcast_to(cov, (1, n, 2, 2)), np.ones((1, n), bool), dof[None])
    for level in COVERAGE_LEVELS:
        assert out[coverage_key(level)] == pytest.approx(level, abs=0.01), level
    assert out["cov50_gauss"] > 0.6 and out["cov99_gauss"] < 0.985


@pytest.mark.parametrize("level", [0.5, 0.9, 0.95, 0.99])
def test_chi2_quantile(level):
    # 1 - exp(-q / 2) = p, and scipy agrees
    from scipy import stats

    assert 1 - np.exp(-chi2_2dof(level) / 2) == pytest.approx(level, abs=1e-15)
    assert chi2_2dof(level) == pytest.approx(stats.chi2.ppf(level, 2), rel=1e-12)


def test_unknown_mode_refused():
    one = np.ones((1, 1), bool)
    with pytest.raises(ValueError, match="strided"):
        tapvid_metrics(np.zeros((1, 1, 2)), one, None, np.zeros((1, 1, 2)), one, one, np.array([0]), "all")


# ---------------------------------------------------------------- TAP-Vid coordinates


def test_tapvid_conversion_values_and_round_trip():
    width, height = 8, 6
    norm = np.array([[0.5 / 8, 0.5 / 6], [0.5, 0.5], [0.0, 1.0]])
    pixels = tapvid_to_pixels(norm, width, height)
    np.testing.assert_allclose(pixels, [[0, 0], [3.5, 2.5], [-0.5, 5.5]], atol=1e-12)
    np.testing.assert_allclose(pixels_to_tapvid(pixels, width, height), norm, atol=1e-15)
    xy = np.array([[[0.0, 0.0], [7.0, 5.0], [-0.5, -0.5], [1.25, 3.75]]])
    np.testing.assert_allclose(tapvid_to_pixels(pixels_to_tapvid(xy, width, height), width, height), xy, atol=1e-12)


def tapvid_video(n_points=2, n_frames=3, height=6, width=8) -> dict:
    points = np.linspace(0.1, 0.9, n_points * n_frames * 2).reshape(n_points, n_frames, 2).astype(np.float32)
    occluded = np.zeros((n_points, n_frames), bool)
    occluded[0, 1] = True
    return {"video": np.zeros((n_frames, height, width, 3), np.uint8), "points": points, "occluded": occluded}


def dump(path, data):
    path.write_bytes(pickle.dumps(data))
    return path


@pytest.mark.parametrize("wrap", ["bare", "dict", "list"])
def test_load_gt_tapvid(tmp_path, wrap):
    video = tapvid_video()
    data = {"bare": video, "dict": {"bear": video}, "list": [video]}[wrap]
    gt = load_gt_tapvid(dump(tmp_path / "gt.pkl", data))
    np.testing.assert_array_equal(gt.point_id, [0, 1])
    np.testing.assert_allclose(gt.gt_xy, video["points"].astype(float) * [8, 6] - 0.5)
    np.testing.assert_array_equal(gt.visible, ~video["occluded"])
    assert gt.known.all()


def test_load_gt_tapvid_encoded_frames(tmp_path):
    video = tapvid_video(height=5, width=7)
    png = cv2.imencode(".png", np.zeros((5, 7, 3), np.uint8))[1].tobytes()
    video["video"] = [png] * 3
    gt = load_gt_tapvid(dump(tmp_path / "gt.pkl", [video]))
    np.testing.assert_allclose(gt.gt_xy, video["points"].astype(float) * [7, 5] - 0.5)


def test_load_gt_tapvid_refuses_several_videos_and_bad_files(tmp_path):
    with pytest.raises(CondtrackError, match="holds 2 videos"):
        load_gt_tapvid(dump(tmp_path / "two.pkl", {"a": tapvid_video(), "b": tapvid_video()}))
    broken = tapvid_video()
    del broken["occluded"]
    with pytest.raises(CondtrackError, match="'occluded'"):
        load_gt_tapvid(dump(tmp_path / "broken.pkl", broken))
    (tmp_path / "junk.pkl").write_bytes(b"not a pickle")
    with pytest.raises(CondtrackError, match="junk.pkl"):
        load_gt_tapvid(tmp_path / "junk.pkl")


def test_load_gt_tapvid_refuses_decoded_frames_of_unequal_sizes(tmp_path):
    """A 'video' listing decoded frames of two sizes ended in numpy's bare ValueError ("inhomogeneous shape") when its
    frame size was read; now the error every other unreadable 'video' gets."""
    video = tapvid_video()
    video["video"] = [np.zeros((6, 8, 3), np.uint8), np.zeros((5, 7, 3), np.uint8), np.zeros((6, 8, 3), np.uint8)]
    with pytest.raises(CondtrackError, match=r"gt.pkl: 'video' is neither an \(F, H, W, 3\) array nor a list of encoded "
                                             r"frames$"):
        load_gt_tapvid(dump(tmp_path / "gt.pkl", video))
    video["video"] = [np.zeros((6, 8, 3), np.uint8)] * 3  # decoded frames of one size: an (F, H, W, 3) array
    assert load_gt_tapvid(dump(tmp_path / "gt.pkl", video)).gt_xy.shape == (2, 3, 2)


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_load_gt_tapvid_refuses_a_visible_point_without_finite_coordinates(tmp_path, value):
    """A NaN or inf on a visible frame was read and skewed the scores (and showed as a non-finite predicted
    covariance); the CSV reader refuses the same row. On an occluded frame it is no position, and is read."""
    video = tapvid_video()
    video["points"][1, 2, 0] = value
    with pytest.raises(CondtrackError, match=r"gt.pkl: point 1, frame 2: a visible point needs finite x and y"):
        load_gt_tapvid(dump(tmp_path / "gt.pkl", video))
    video = tapvid_video()
    video["points"][0, 1] = value  # point 0 is occluded on frame 1
    assert not load_gt_tapvid(dump(tmp_path / "gt.pkl", video)).visible[0, 1]


@pytest.mark.parametrize("key, value, message", [
    ("points", "abc", "'points' holds <U3 values, not numbers"),
    ("points", None, "'points' holds object values, not numbers"),
    ("points", {"x": 1}, "'points' holds object values, not numbers"),
    ("points", np.ones((2, 3, 2), complex), "'points' holds complex128 values, not numbers"),
    ("points", np.full((2, 3, 2), 1e308), r"point 0, frame 0: a visible point needs finite x and y \(got 1e\+308"),
    ("occluded", [[0, 1], [0]], r"'occluded' is not an array \(lists of unequal lengths\?\)"),
    ("occluded", np.full((2, 3), "no"), "'occluded' holds <U2 values, not numbers"),
    ("occluded", np.full((2, 3), 2), r"'occluded' holds values other than true/false \(0 or 1\)"),
])
def test_load_gt_tapvid_refuses_entries_that_are_not_numbers(tmp_path, key, value, message):
    """Text, objects or ragged lists in 'points' or 'occluded' ended in a numpy traceback ('could not convert string
    to float'); occluded strings were read as all occluded; a normalised 1e308 overflowed with a RuntimeWarning. Each
    is now one error naming the entry; 0/1 numbers still stand for false/true."""
    video = tapvid_video()
    video[key] = value
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(CondtrackError, match="gt.pkl: " + message):
            load_gt_tapvid(dump(tmp_path / "gt.pkl", video))
    video = tapvid_video()
    video["occluded"] = video["occluded"].astype(np.uint8)
    np.testing.assert_array_equal(load_gt_tapvid(dump(tmp_path / "gt.pkl", video)).visible, ~tapvid_video()["occluded"])


class _Touches:
    """Unpickled, it runs ``touch`` on a file (a crafted TAP-Vid file could run anything)."""

    def __init__(self, target):
        self.target = str(target)

    def __reduce__(self):
        return os.system, (f"touch {self.target}",)


@pytest.mark.parametrize("protocol", [0, 2, 5])
def test_a_tapvid_pickle_that_would_run_code_is_refused_without_running(tmp_path, protocol):
    """Issue 28.19: pickle.load ran whatever the truth file named."""
    target = tmp_path / "pwned"
    video = tapvid_video()
    video["extra"] = _Touches(target)
    gt = tmp_path / "gt.pkl"
    gt.write_bytes(pickle.dumps({"bear": video}, protocol=protocol))
    with pytest.raises(CondtrackError, match=r"gt.pkl: cannot read the TAP-Vid pickle \(refused: it names "
                                             r"(posix|os)\.system, neither a NumPy array nor a plain value\)"):
        load_gt_tapvid(gt)
    pred = write_pred_csv(tmp_path / "pred.csv", [0, 1], tapvid_to_pixels(video["points"], 8, 6), ~video["occluded"],
                          np.broadcast_to(np.eye(2), (2, 3, 2, 2)))
    result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--gt-format", "tapvid"])
    assert isinstance(result.exception, CondtrackError) and "refused" in str(result.exception)
    assert not target.exists()
    del video["extra"]  # the same file without it loads, and as NumPy 1 wrote it (numpy.core; names in text < 4)
    clean = pickle.dumps({"bear": video}, protocol=protocol)
    gt.write_bytes(clean.replace(b"numpy._core", b"numpy.core") if protocol < 4 else clean)
    np.testing.assert_array_equal(load_gt_tapvid(gt).visible, ~video["occluded"])


# ---------------------------------------------------------------- GT CSV


def write_gt_csv(path, rows, header="point_id,frame,x,y,visible"):
    path.write_text(header + "\n" + "".join(row + "\n" for row in rows))
    return path


def fixture_gt_rows() -> list[str]:
    xy = gt_xy()
    return [
        f"{p},{f},{xy[p, f, 0]},{xy[p, f, 1]},{int(GT_VISIBLE[p, f])}"
        for p in range(2) for f in range(4) if GT_KNOWN[p, f]
    ]


def test_load_gt_csv(tmp_path):
    gt = load_gt_csv(write_gt_csv(tmp_path / "gt.csv", fixture_gt_rows()))
    np.testing.assert_array_equal(gt.point_id, [0, 1])
    np.testing.assert_array_equal(gt.known, GT_KNOWN)
    np.testing.assert_array_equal(gt.visible, GT_VISIBLE & GT_KNOWN)
    np.testing.assert_array_equal(gt.gt_xy[GT_KNOWN], gt_xy()[GT_KNOWN])
    assert np.isnan(gt.gt_xy[~GT_KNOWN]).all()


def test_load_gt_csv_column_order_extra_columns_and_nan_when_occluded(tmp_path):
    path = write_gt_csv(tmp_path / "gt.csv", ["0,7,0,nan,nan,a", "1,7,1,4.5,5.5,b"], "visible,point_id,frame,x,y,note")
    gt = load_gt_csv(path)
    np.testing.assert_array_equal(gt.point_id, [7])
    np.testing.assert_array_equal(gt.known, [[1, 1]])
    np.testing.assert_array_equal(gt.visible, [[0, 1]])
    np.testing.assert_array_equal(gt.gt_xy[0, 1], [4.5, 5.5])


@pytest.mark.parametrize(
    ("rows", "header", "message"),
    [
        (["0,0,1,2,1"], "point_id,frame,x,visible", "column\\(s\\) y missing"),
        (["0,0,1,2,1", "0,1,abc,2,1"], None, "line 3, column 'x': 'abc' is not a number"),
        (["0,0,1,2,2"], None, "line 2: visible is not 0 or 1"),
        (["0,0.5,1,2,1"], None, "line 2: frame is not a non-negative integer"),
        (["0,-1,1,2,1"], None, "line 2: frame is not a non-negative integer"),
        (["0.5,0,1,2,1"], None, "line 2: point_id is not an integer"),
        (["0,0,nan,2,1"], None, "line 2: a visible row needs finite x and y"),
        (["0,0,inf,2,0"], None, "line 2: x or y is infinite"),
        (["0,0,1,2,1", "1,0,1,2,1", "0,0,1,2,1"], None, "line 4: a second row for the same point_id and frame"),
        (["0,0,1,2"], None, "line 2 has 4 fields"),
        ([], None, "no ground-truth rows"),
    ],
)
def test_load_gt_csv_errors(tmp_path, rows, header, message):
    path = write_gt_csv(tmp_path / "gt.csv", rows, header or "point_id,frame,x,y,visible")
    with pytest.raises(CondtrackError, match=message) as error:
        load_gt_csv(path)
    assert "gt.csv" in str(error.value)


@pytest.mark.parametrize("cell, column", [("1e30", "frame"), ("1e19", "frame"), ("-1e19", "point_id")])
def test_a_frame_or_point_id_beyond_64_bits_is_refused_naming_the_line(tmp_path, cell, column):
    """A frame of 1e30 (or 1e19) was read as a float and cast to int64: numpy's 'invalid value encountered in cast'
    and a ValueError traceback ('negative dimensions are not allowed'); now one error naming the line and value."""
    row = {"frame": f"0,{cell},1,2,1", "point_id": f"{cell},0,1,2,1"}[column]
    with pytest.raises(CondtrackError, match=rf"gt.csv: line 3: {column} is not .*integer: '{cell}' is outside the "
                                             r"64-bit integer range"):
        load_gt_csv(write_gt_csv(tmp_path / "gt.csv", ["0,0,1,2,1", row]))


def test_point_ids_above_2_53_are_read_exactly(tmp_path):
    """Ids were read through float64: 2^53 + 1 became 2^53, so two points were refused as one point's second row
    (or a prediction's point 2^53 + 1 went unscored); now read as exact 64-bit integers, whole decimals still taken."""
    big = 2**53
    gt = load_gt_csv(write_gt_csv(tmp_path / "gt.csv", [f"{big},0,1,2,1", f"{big + 1},0,3,4,1", f"{2**63 - 1},1.0,5,6,0"]))
    assert gt.point_id.tolist() == [big, big + 1, 2**63 - 1] and gt.known.shape == (3, 2)
    np.testing.assert_array_equal(gt.gt_xy[:, 0], [[1, 2], [3, 4], [np.nan, np.nan]])


def test_a_byte_order_mark_before_the_header_is_ignored(tmp_path):
    """A truth saved by a spreadsheet as "CSV UTF-8" starts with a byte-order mark, which was read as part of the first
    column's name: 'ground-truth column(s) point_id missing from the header'; it is now skipped, as in a queries file."""
    path = tmp_path / "gt.csv"
    path.write_bytes("\ufeffpoint_id,frame,x,y,visible\n0,0,1,2,1\n".encode("utf-8"))
    gt = load_gt_csv(path)
    assert gt.point_id.tolist() == [0] and gt.gt_xy[0, 0].tolist() == [1.0, 2.0]


def test_a_binary_ground_truth_is_named_as_not_a_text_csv(tmp_path):
    """`eval X.h5 X.h5` (a track file given as the truth) said "cannot read the ground truth ('utf-8' codec can't decode
    byte 0x89 in position 0: invalid start byte)"; it now says what the truth must be."""
    path = tmp_path / "tracks.h5"
    path.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(64))
    with pytest.raises(CondtrackError, match=r"^\S*tracks.h5: not a text CSV; the ground truth is a CSV with the columns "
                                             r"point_id,frame,x,y,visible \(or a TAP-Vid pickle, with --gt-format tapvid\)$"):
        load_gt_csv(path)


def test_load_gt_csv_missing_file(tmp_path):
    with pytest.raises(CondtrackError, match="nope.csv"):
        load_gt_csv(tmp_path / "nope.csv")


# ---------------------------------------------------------------- alignment


def make_tracks(point_id, xy, visible, cov=None) -> Tracks:
    xy = np.asarray(xy, float)
    n_points, n_frames = xy.shape[:2]
    has = np.isfinite(xy).all(axis=-1)
    first = has.argmax(axis=1)
    cov = np.broadcast_to(np.eye(2), (n_points, n_frames, 2, 2)).copy() if cov is None else cov
    queries = Queries(np.asarray(point_id, np.int64), first, xy[np.arange(n_points), first])
    return Tracks(queries, xy, cov, np.where(has, np.inf, np.nan), np.asarray(visible, bool),
                  np.where(has, 2, -1).astype(np.int8),
                  np.full_like(xy, NAN), np.full_like(cov, NAN))


def test_align_matches_ids_and_pads_frames():
    # pred: ids 5, 9 (not in GT), 2 (no position at all: absent), 3 frames
    pred_xy = np.full((3, 3, 2), NAN)
    pred_xy[0, 1:] = [[1, 1], [2, 2]]
    pred_xy[1] = 0.0
    pred = make_tracks([5, 9, 2], pred_xy, np.isfinite(pred_xy[..., 0]))
    # GT: ids 2, 5, 7 over 4 frames
    gt_arr = np.arange(3 * 4 * 2, dtype=float).reshape(3, 4, 2)
    gt = GroundTruth(np.array([2, 5, 7]), gt_arr, np.ones((3, 4), bool), np.ones((3, 4), bool))
    data = align(pred, gt)
    np.testing.assert_array_equal(data.point_id, [5])
    np.testing.assert_array_equal(data.missing_ids, [2, 7])
    np.testing.assert_array_equal(data.unscored_ids, [9])
    np.testing.assert_array_equal(data.query_frame, [1])
    assert data.pred_xy.shape == (1, 4, 2) and np.isnan(data.pred_xy[0, [0, 3]]).all()
    np.testing.assert_array_equal(data.pred_visible, [[0, 1, 1, 0]])
    assert np.isnan(data.pred_cov[0, 3]).all()
    np.testing.assert_array_equal(data.gt_xy, gt_arr[[1]])


def test_align_pads_gt_beyond_its_frames():
    pred = make_tracks([0], np.zeros((1, 3, 2)), np.ones((1, 3), bool))
    gt = GroundTruth(np.array([0]), np.zeros((1, 2, 2)), np.ones((1, 2), bool), np.ones((1, 2), bool))
    data = align(pred, gt)
    np.testing.assert_array_equal(data.gt_known, [[1, 1, 0]])
    np.testing.assert_array_equal(data.gt_visible, [[1, 1, 0]])


def test_align_errors():
    gt = GroundTruth(np.array([0]), np.zeros((1, 2, 2)), np.ones((1, 2), bool), np.ones((1, 2), bool))
    with pytest.raises(CondtrackError, match="no point_id in common"):
        align(make_tracks([4], np.zeros((1, 2, 2)), np.ones((1, 2), bool)), gt)
    with pytest.raises(CondtrackError, match="repeated point_id"):
        align(make_tracks([0, 0], np.zeros((2, 2, 2)), np.ones((2, 2), bool)), gt)


# ---------------------------------------------------------------- command line


def write_pred_csv(path, point_id, xy, visible, cov):
    """A condtrack CSV in the documented layout (docs/schema.md), one row per frame with a position."""
    lines = ["point_id,frame,x,y,cov_xx,cov_xy,cov_yy,visible,method"]
    for p, f in zip(*np.nonzero(np.isfinite(xy).all(axis=-1))):
        c = cov[p, f]
        lines.append(f"{point_id[p]},{f},{float(xy[p, f, 0])!r},{float(xy[p, f, 1])!r},{c[0, 0]},{c[0, 1]},{c[1, 1]},"
                     f"{int(visible[p, f])},clf")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def files(tmp_path):
    pred = write_pred_csv(tmp_path / "pred.csv", [0, 1], gt_xy() + OFFSETS, PRED_VISIBLE, pred_cov())
    gt = write_gt_csv(tmp_path / "gt.csv", fixture_gt_rows())
    return pred, gt


@pytest.mark.parametrize("mode", ["first", "strided"])
def test_cli_json(files, mode):
    pred, gt = files
    result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--json", "--query-mode", mode])
    assert result.exit_code == 0, result.output
    values = json.loads(result.stdout)
    assert list(values) == list(METRIC_KEYS)
    assert values == pytest.approx(EXPECTED[mode], abs=1e-12)
    assert result.stderr == ""


def test_cli_table_and_missing_points(files, tmp_path):
    pred, _ = files
    gt = write_gt_csv(tmp_path / "gt_more.csv", fixture_gt_rows() + ["8,0,1,1,1", "8,5,1,1,0"])
    result = CliRunner().invoke(eval_command, [str(pred), str(gt)])
    assert result.exit_code == 0, result.output
    assert "delta_avg" in result.stdout and "cov95" in result.stdout
    assert "1 GT point(s) missing" in result.stdout
    assert "the GT has 6 frames" in result.stdout


def test_cli_json_notes_on_stderr(files, tmp_path):
    pred, _ = files
    gt = write_gt_csv(tmp_path / "gt_more.csv", fixture_gt_rows() + ["8,0,1,1,1"])
    result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout) == pytest.approx(EXPECTED["first"], abs=1e-12)
    assert "1 GT point(s) missing" in result.stderr


def test_cli_notes_the_predicted_points_the_gt_does_not_have(files, tmp_path):
    """A predicted point absent from the GT was left out of every metric without a word (a GT point absent from the
    prediction has its note); now it has one too, and the metrics are those of the points both files have."""
    pred, _ = files
    gt = write_gt_csv(tmp_path / "gt_less.csv", [row for row in fixture_gt_rows() if not row.startswith("1,")])
    result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["n_points"] == 1
    assert result.stderr == f"note: 1 point(s) of {pred} not in the GT, not scored: 1\n"


def test_cli_all_visible_gt_prints_null(tmp_path):
    pred = write_pred_csv(tmp_path / "pred.csv", [3], np.zeros((1, 3, 2)), np.ones((1, 3), bool),
                          np.broadcast_to(np.eye(2), (1, 3, 2, 2)))
    gt = write_gt_csv(tmp_path / "gt.csv", ["3,0,0,0,1", "3,1,0,0.5,1", "3,2,0,0,1"])
    result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--json"])
    values = json.loads(result.stdout)
    assert values["OA"] is None and values["AJ"] is None and values["jaccard_4"] is None
    assert values["pts_within_1"] == 1.0 and values["cov95"] == 1.0
    assert "null" in result.stdout


def test_cli_json_nees_beyond_the_float_range_is_the_string_inf(tmp_path):
    """A truth 1e200 px from its prediction (a hand-edited file) printed 'warning: RuntimeWarning: overflow encountered
    in multiply' and '"nees": Infinity', which is not JSON; d^T C^-1 d is now inf without a warning (the truth outside
    every ellipse) and --json writes it as compare --json does, the string "inf"."""
    pred = write_pred_csv(tmp_path / "pred.csv", [3], np.zeros((1, 3, 2)), np.ones((1, 3), bool),
                          np.broadcast_to(np.eye(2), (1, 3, 2, 2)))
    gt = write_gt_csv(tmp_path / "gt.csv", ["3,0,0,0,1", "3,1,0,1e200,1", "3,2,0,0,0"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--json"])
    assert result.exit_code == 0 and result.stderr == "", result.output
    values = json.loads(result.stdout, parse_constant=lambda name: pytest.fail(f"not JSON: {name}"))
    assert values["nees"] == "inf" and values["cov99"] == 0.0 and values["pts_within_16"] == 0.0


def test_cli_tapvid(tmp_path):
    video = tapvid_video()
    gt_path = dump(tmp_path / "gt.pkl", {"bear": video})
    xy = tapvid_to_pixels(video["points"], 8, 6)
    pred = write_pred_csv(tmp_path / "pred.csv", [0, 1], xy, ~video["occluded"], np.broadcast_to(np.eye(2), (2, 3, 2, 2)))
    result = CliRunner().invoke(eval_command, [str(pred), str(gt_path), "--gt-format", "tapvid", "--json"])
    assert result.exit_code == 0, result.output
    values = json.loads(result.stdout)
    assert values["delta_avg"] == 1.0 and values["OA"] == 1.0 and values["AJ"] == 1.0


def test_cli_errors_name_the_file(files, tmp_path):
    pred, gt = files
    bad_gt = write_gt_csv(tmp_path / "bad.csv", ["0,0,1,1"], "point_id,frame,x,y")
    result = CliRunner().invoke(eval_command, [str(pred), str(bad_gt)])
    assert isinstance(result.exception, CondtrackError)
    assert "bad.csv" in str(result.exception) and "visible" in str(result.exception)
    result = CliRunner().invoke(eval_command, [str(tmp_path / "none.csv"), str(gt)])
    assert isinstance(result.exception, CondtrackError) and "none.csv" in str(result.exception)
    result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--query-mode", "all"])
    assert result.exit_code == 2


def test_cli_hdf5_prediction(files, tmp_path):
    import h5py

    from condtrack_cli import SCHEMA_VERSION

    _, gt = files
    xy = gt_xy() + OFFSETS
    has = np.isfinite(xy).all(axis=-1)
    first = has.argmax(axis=1)
    path = tmp_path / "pred.h5"
    with h5py.File(path, "w") as f:
        f.attrs["schema_version"] = SCHEMA_VERSION
        f["tracks/point_id"] = np.array([0, 1], np.int64)
        f["tracks/xy"] = xy
        f["tracks/cov"] = pred_cov()
        f["tracks/visible"] = PRED_VISIBLE
        f["tracks/method_code"] = np.where(has, 2, -1).astype(np.int8)
        f["tracks/dof"] = np.where(has, np.inf, np.nan)  # Gaussian rows
        f["tracks/trackability"] = np.full(2, np.nan)
        f["queries"] = np.column_stack([first, xy[[0, 1], first]]).astype(float)
    result = CliRunner().invoke(eval_command, [str(path), str(gt), "--json", "--query-mode", "strided"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout) == pytest.approx(EXPECTED["strided"], abs=1e-12)


def test_calibrated_gaussian_errors_give_nominal_coverage_and_nees():
    # errors drawn from their own (correlated, varying) covariance: coverage p at every level, NEES 2
    rng = np.random.default_rng(3)
    n = 20000
    scale = rng.uniform(0.2, 5.0, n)
    cov = scale[:, None, None] * np.array([[2.0, 0.8], [0.8, 1.0]])
    error = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.standard_normal((n, 2)))
    gt = np.zeros((1, n + 1, 2))
    pred = np.concatenate([np.zeros((1, 1, 2)), error[None]], axis=1)
    pred_cov = np.concatenate([np.eye(2)[None, None], cov[None]], axis=1)
    ones = np.ones((1, n + 1), bool)
    result = tapvid_metrics(pred, ones, pred_cov, gt, ones, ones, np.array([0]), "first")
    for level in (0.5, 0.9, 0.95, 0.99):  # binomial std at n = 20000: at most 0.0035
        assert result[f"cov{round(100 * level)}"] == pytest.approx(level, abs=0.012)
    assert result["nees"] == pytest.approx(2.0, abs=0.08)  # std of the mean of chi2(2): 2 / sqrt(n) = 0.014
    assert result["cov_finite"] == 1.0
    assert result["cov50_rescaled"] == pytest.approx(0.5, abs=0.015)


def test_cov50_rescaled_tells_a_wrong_scale_from_a_heavy_tail():
    """``cov50_rescaled``: 0.5 for Gaussian errors under covariances 4x too wide (only the scale is off), above
    0.5 for a mixture with the same second moment: 90 % of the errors 1/4 as wide, 10 % 6.75x as wide.

    Once scaled so that 95 % of the frames lie in their 95 % ellipse, the scale is set by the wide tenth and the
    narrow core falls inside the 50 % ellipse (expected values from the chi-square CDF, 2 dof: 1 - exp(-q / 2)).
    """
    from scipy.optimize import brentq

    rng = np.random.default_rng(5)
    n = 40000
    cov = np.repeat(np.eye(2)[None], n, 0)
    ones = np.ones((1, n + 1), bool)

    def metrics(error):
        pred = np.concatenate([np.zeros((1, 1, 2)), error[None]], axis=1)
        pred_cov = np.concatenate([np.eye(2)[None, None], cov[None]], axis=1)
        return tapvid_metrics(pred, ones, pred_cov, np.zeros((1, n + 1, 2)), ones, ones, np.array([0]), "first")

    too_wide = metrics(0.5 * rng.standard_normal((n, 2)))  # error cov I / 4 under a reported I
    # m2 = chi2 / 4: P(chi2 <= 4 x 2 ln 2) = 1 - 2^-4 = 0.9375, not calibrated
    assert too_wide["cov50"] == pytest.approx(1 - 2.0**-4, abs=0.01)
    assert too_wide["cov50_rescaled"] == pytest.approx(0.5, abs=0.012)  # binomial std 0.0025
    wide = rng.random(n) < 0.1
    heavy = rng.standard_normal((n, 2)) * np.where(wide, np.sqrt(6.75), 0.5)[:, None]  # second moment 0.9/4 + 0.675
    result = metrics(heavy)
    # m2 is the mixture 0.9 chi2 x 0.25 + 0.1 chi2 x 6.75, of CDF 0.9 (1 - exp(-q / 0.5)) + 0.1 (1 - exp(-q / 13.5));
    # q95 its 95 % quantile, and the 50 % ellipse at that scale is q95 chi2(0.5) / chi2(0.95).
    cdf = lambda q: 0.9 * -np.expm1(-q / 0.5) + 0.1 * -np.expm1(-q / 13.5)  # noqa: E731
    q95 = brentq(lambda q: cdf(q) - 0.95, 0.0, 100.0, xtol=1e-12)
    expected = cdf(q95 * np.log(2.0) / -np.log(0.05))
    assert result["cov50_rescaled"] == pytest.approx(expected, abs=0.012)
    assert expected > 0.7


def test_cli_plot_writes_png(files, tmp_path):
    pred, gt = files
    out = tmp_path / "calibration.png"
    result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--json", "--plot", str(out)])
    assert result.exit_code == 0, result.output
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = cv2.imread(str(out))
    assert image is not None and image.shape[1] > image.shape[0] > 100
    assert json.loads(result.stdout) == pytest.approx(EXPECTED["first"], abs=1e-12)


def test_cli_plot_into_the_frame_folder_of_the_truth_is_refused(files, tmp_path):
    """`eval t.h5 CLIP/tracks.csv --plot CLIP/plot.png` wrote the picture among CLIP's frames: the next `track CLIP`
    read it as one more frame. A picture in GT's folder, where that folder holds as many images as GT has frames, is
    refused before the plot is drawn."""
    pred, gt = files
    for k in range(len(gt_xy()[0])):  # GT's folder is its sequence's frame folder
        cv2.imwrite(str(gt.parent / f"{k:05d}.png"), np.zeros((8, 8), np.uint8))
    out = gt.parent / "plot.png"
    result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--plot", str(out)])
    assert result.exit_code != 0 and not out.exists()
    assert str(result.exception) == (f"--plot {out}: an image in the frame folder of GT {gt.parent}; writing it would "
                                     "replace or add a frame of the input")


def test_cli_plots_again_into_a_working_folder_that_holds_the_truth(files, tmp_path):
    """A working folder holding the GT CSV and the plots of earlier runs is not a frame folder: a second `eval --plot`
    there is drawn (probe helper round 12: it was refused once the first plot had made the folder hold an image)."""
    pytest.importorskip("matplotlib")
    pred, gt = files
    for name in ("cal.png", "cal2.png"):
        result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--plot", str(gt.parent / name)])
        assert result.exit_code == 0, result.output
        assert (gt.parent / name).stat().st_size > 0


def test_cli_plot_without_matplotlib_is_one_error_line(files, tmp_path, monkeypatch):
    import sys

    pred, gt = files
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now raises ImportError
    out = tmp_path / "calibration.png"
    result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--plot", str(out)])
    assert result.exit_code != 0
    assert isinstance(result.exception, CondtrackError) and "condtrack[plot]" in str(result.exception)
    assert result.stdout == "" and not out.exists()


def test_bench_coverage_table_lists_every_reading_per_set_and_method():
    """The bench's coverage table (``bench/versus_lk.py``): one row per set and covariance method that ran, the
    Student-t and the Gaussian readings; a failed run says so; no check (``group_tables`` checks the bands)."""
    from condtrack_cli.evaluate.bench.versus_lk import coverage_table

    calibrated = {"cov50": 0.5, "cov90": 0.9, "cov95": 0.95, "cov99": 0.99, "cov50_gauss": 0.7, "cov90_gauss": 0.93,
                  "cov95_gauss": 0.96, "cov99_gauss": 0.98, "cov_finite": 1.0, "nees": 2.0, "cov50_rescaled": 0.5}
    per_set = {"a": {m: (calibrated, 1.0) for m in ("auto", "clf", "cnlf")},
               "b": {"auto": (calibrated, 1.0), "cnlf": (None, "exit 1")}}
    lines = coverage_table(per_set, "set")
    assert "| a | clf | 0.500 | 0.900 | 0.950 | 0.990 | 0.700 | 0.930 | 0.960 | 0.980 | 1.000 | 2.000 | 0.500 |" in lines
    assert "| b | cnlf | failed |" in lines
    assert not any(line.startswith("| b | clf") for line in lines)  # not run on b
    assert len(lines) == 2 + 3 + 2 and not any(line.startswith("- [") for line in lines)


def _coverage(cov50: float, cov90: float, cov95: float, cov99: float, delta: float = 0.8) -> dict:
    return {"delta_avg": delta, "cov50": cov50, "cov90": cov90, "cov95": cov95, "cov99": cov99, "cov_finite": 1.0}


def test_bench_group_tables_check_issue_45_group_and_set_bands():
    """``group_tables``: one table per group of sets (its members by glob, the rest as "other"), δ_avg of each
    column that ran and the four Student-t levels of each covariance method, the group's mean row; the group bands
    are checked on the mean, the set bands (50 % in [0.35, 0.75], 95 % in [0.85, 0.99]) on every set.

    Face: two clips whose mean is in every band, but clip b's 50 % (0.30) is outside the set band. KITTI: one clip,
    95 % 0.99 outside the group band [0.90, 0.98] but inside the set band."""
    from condtrack_cli.evaluate.bench.versus_lk import group_tables

    lk = ({"delta_avg": 0.7, "cov50": None, "cov90": None, "cov95": None, "cov99": None, "cov_finite": None}, 1.0)
    per_set = {
        "dudek_a": {"lk": lk, "auto": (_coverage(0.70, 0.92, 0.96, 0.99), 1.0)},
        "dudek_b": {"lk": lk, "auto": (_coverage(0.30, 0.88, 0.92, 0.98, 0.6), 1.0)},
        "kt3dmoseg_x": {"lk": lk, "auto": (_coverage(0.50, 0.90, 0.99, 1.0), 1.0)},
        "elsewhere": {"lk": lk, "auto": (_coverage(0.50, 0.90, 0.95, 0.99), 1.0)},
    }
    points = {name: 7 for name in per_set}
    lines = group_tables(per_set, points, (("KITTI", "kt3dmoseg_*"), ("face", "dudek_*")))
    assert [line for line in lines if line.startswith("### ")] == ["### KITTI", "### face", "### other"]
    face = lines[lines.index("### face"):lines.index("### other")]
    assert "| set | points | lk | auto | auto cov50 / 90 / 95 / 99 |" in face
    assert "| dudek_b | 7 | 0.700 | 0.600 | 0.30 / 0.88 / 0.92 / 0.98 |" in face
    assert "| face mean |  | 0.700 | 0.700 | 0.50 / 0.90 / 0.94 / 0.98 |" in face
    checks = [line for line in face if line.startswith("- [")]
    assert checks[:4] == ["- [x] pass: face mean cov50 of auto 0.500 in [0.42, 0.62]",
                          "- [x] pass: face mean cov90 of auto 0.900 in [0.85, 0.95]",
                          "- [x] pass: face mean cov95 of auto 0.940 in [0.90, 0.98]",
                          "- [x] pass: face mean cov99 of auto 0.985 in [0.97, 1.00]"]
    assert "- [ ] FAIL: cov50 of auto in [0.35, 0.75] on 1 of 2 sets; not on: dudek_b 0.300" in checks
    assert "- [x] pass: cov95 of auto in [0.85, 0.99] on 2 of 2 sets" in checks
    kitti = lines[lines.index("### KITTI"):lines.index("### face")]
    assert "- [ ] FAIL: KITTI mean cov95 of auto 0.990 in [0.90, 0.98]" in kitti
    assert "- [x] pass: cov95 of auto in [0.85, 0.99] on 1 of 1 sets" in kitti


def test_bench_set_globs_pick_sets_and_scenes():
    """``--sets`` globs (``selected``): any matching glob keeps a name, in the names' order; None keeps all. The
    synthetic table's rows are the five scenes at seed 0, then nonrigid at its reporting seeds, never a tuning one."""
    from condtrack_cli.evaluate.bench.versus_lk import NONRIGID_TUNE_SEEDS, selected, synthetic_scenes

    names = ["badja_camel", "dudek_00", "dudek_01", "kt3dmoseg_seq005_clip01", "nonrigid_0"]
    assert selected(names, ("dudek_*", "nonrigid_*")) == ["dudek_00", "dudek_01", "nonrigid_0"]
    assert selected(names, ("dudek_01",)) == ["dudek_01"]
    assert selected(names, None) == names
    rows = synthetic_scenes()
    assert [row[0] for row in rows] == ["camera_motion", "occlusion", "ring", "illumination", "fast",
                                        "nonrigid_0", "nonrigid_4", "nonrigid_5"]
    assert not {seed for _, scene, seed in rows if scene == "nonrigid"} & set(NONRIGID_TUNE_SEEDS)


def test_bench_versus_lk_refuses_an_unknown_method(tmp_path):
    """``--methods`` names columns of the section; a misspelt one is a usage error (exit 2) naming the valid ones."""
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "condtrack_cli.evaluate.bench", "--versus-lk", "--methods",
                             "lk,dsi", "--work", str(tmp_path)], capture_output=True, text=True)
    assert result.returncode == 2 and result.stdout == ""
    assert "--methods: unknown column 'dsi'; valid: lk, dis, auto, clf, cnlf, stk" in result.stderr


def test_bench_meter_reads_the_command_s_own_peak_memory():
    """``run_process`` (``bench/peak.py``): a command's peak RSS excludes the benchmark's memory at the fork.

    While this process holds 300 MiB, a bare interpreter run through the meter
    reads under 60 MiB, one that fills 200 MiB reads 200 MiB or more, and the
    exit code and the last line of stderr come back.
    """
    import sys

    from condtrack_cli.evaluate.bench.common import run_process

    held = np.ones(300 * 2**20 // 8)  # pages touched: resident in this process until the test returns
    _, bare, code, _ = run_process([sys.executable, "-c", "pass"])
    assert code == 0 and bare < 60, bare
    _, filled, _, _ = run_process([sys.executable, "-c", "import numpy; a = numpy.ones(200 * 2**20 // 8)"])
    assert filled >= 200, filled
    _, _, code, message = run_process([sys.executable, "-c", "import sys; sys.exit('Error: no frame')"])
    assert code == 1 and message == "Error: no frame"


def test_bench_meter_reads_the_command_s_cpu_time():
    """``run_metered`` (``bench/peak.py``) reads the command's user + system CPU time: a second of sleep costs next
    to none, a busy loop about its wall time (one thread: never much more than its wall time)."""
    import sys

    from condtrack_cli.evaluate.bench.common import run_metered

    asleep = run_metered([sys.executable, "-c", "import time; time.sleep(1.0)"])
    assert asleep.code == 0 and asleep.seconds >= 1.0 and asleep.cpu_seconds < 0.5, asleep
    busy = run_metered([sys.executable, "-c", "x = 0\nfor i in range(3_000_000): x += i"])
    assert busy.code == 0 and 0.05 < busy.cpu_seconds <= busy.seconds * 1.1 + 0.05, busy


def test_bench_versus_row_takes_the_ratio_within_each_round():
    """``versus_row`` (``bench --speed-versus``): the bound is checked on the median of the rounds' own ratios, so a
    round where the whole machine ran slow does not tip it; the median walls and the ratios to the script are shown."""
    from condtrack_cli.evaluate.bench.common import Metered
    from condtrack_cli.evaluate.bench.speed import VERSUS_BOUND, versus_row

    def runs(*seconds):
        return [Metered(wall, wall / 2, 100.0, 0, "") for wall in seconds]

    # round 2 ran twice as slow for both; this tree takes 1.1x the earlier commit's time in every round
    row = versus_row("auto", runs(4.0, 8.0, 4.0), runs(4.4, 8.8, 4.4), 1.0)
    assert row == "| auto | 4.00 | 4.40 | 1.100 (1.10-1.10) | 1.100 | 4.00 / 4.40 | pass (<= 1.15x) |"
    slower = versus_row("clf", runs(2.0, 2.0, 2.0), runs(2.4, 2.2, 2.6), 0.5)
    assert slower.endswith(f"| 4.00 / 4.80 | FAIL (<= {VERSUS_BOUND:g}x) |") and "1.200 (1.10-1.30)" in slower


def test_bench_speed_versus_refuses_what_names_no_commit(tmp_path):
    """``--speed-versus`` reads the earlier commit from this checkout's history: a name git does not know is a
    one-line ``Error:`` (exit 1, nothing on stdout), as is a checkout without git; ``--rounds`` must be positive."""
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "condtrack_cli.evaluate.bench", "--speed-versus", "no-such-commit",
                             "--work", str(tmp_path)], capture_output=True, text=True)
    assert result.returncode == 1 and result.stdout == ""
    assert result.stderr.startswith("Error: --speed-versus") and result.stderr.count("\n") == 1, result.stderr
    result = subprocess.run([sys.executable, "-m", "condtrack_cli.evaluate.bench", "--speed-versus", "HEAD",
                             "--rounds", "0", "--work", str(tmp_path)], capture_output=True, text=True)
    assert result.returncode == 2 and "--rounds: expected a positive integer, got 0" in result.stderr


def test_bench_speed_versus_runs_the_commit_s_own_package(tmp_path):
    """``extract_revision`` puts the commit's ``condtrack_cli`` in a folder of its own, its files those of git's
    history; with ``PYTHONPATH`` on that folder, ``python -m condtrack_cli`` imports it, not this tree's."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    from condtrack_cli.evaluate.bench.common import REPO
    from condtrack_cli.evaluate.bench.speed import extract_revision

    if shutil.which("git") is None or subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"],
                                                     capture_output=True).returncode:
        pytest.skip(f"git is missing or {REPO} is not a git checkout")
    label, folder = extract_revision("HEAD", tmp_path)
    committed = subprocess.run(["git", "-C", str(REPO), "show", "HEAD:condtrack_cli/types.py"], capture_output=True,
                               check=True).stdout
    assert (folder / "condtrack_cli" / "types.py").read_bytes() == committed and folder.parent == tmp_path
    found = subprocess.run([sys.executable, "-c", "import condtrack_cli; print(condtrack_cli.__file__)"],
                           env={**os.environ, "PYTHONPATH": str(folder)}, cwd=tmp_path, capture_output=True, text=True,
                           check=True).stdout.strip()
    assert Path(found) == folder / "condtrack_cli" / "__init__.py" and len(label) == 12


def test_check_queries_tolerance_and_frames_without_visible_truth():
    """Issue 28.2: a query within 1 px of the truth on its frame passes, 1.2 px away is refused; frames where the
    truth is not visible (or past its end) are not checked."""
    from condtrack_cli.evaluate.groundtruth import check_queries

    truth = GroundTruth(np.array([0, 1]), gt_xy(), np.array([[1, 1, 1, 1], [0, 1, 1, 1]], bool), np.ones((2, 4), bool))
    near = gt_xy()
    near[0, 0] += [0.6, 0.6]  # 0.85 px
    near[1, 0] += [50, 0]  # point 1's query frame 0: truth occluded there
    check_queries(make_tracks([0, 1], near, np.ones((2, 4), bool)), truth)
    late = np.full((1, 6, 2), NAN)
    late[0, 5] = [0, 0]  # query frame 5: beyond the truth's 4 frames
    check_queries(make_tracks([0], late, np.ones((1, 6), bool)), truth)
    far = gt_xy()
    far[1, 0] += [50, 0]
    far[1, 1] += [1.2, 0]
    far[1, 0] = NAN  # point 1 now queried on frame 1, where its truth is visible
    with pytest.raises(CondtrackError, match=r"point_id 1: the prediction's query on frame 1 .* 1.20 px"):
        check_queries(make_tracks([0, 1], far, np.ones((2, 4), bool)), truth)


@pytest.mark.parametrize("suffix", [".h5", ".csv"])
def test_eval_refuses_detected_points_scored_by_coinciding_ids(tmp_path, suffix):
    """Issue 28.2: points detected without -p are numbered 0.. like the truth's; eval refuses to score them."""
    from conftest import SAMPLES
    from test_cli import run_cli

    sample = SAMPLES / "ring"
    detected, queried = tmp_path / f"detected{suffix}", tmp_path / f"queried{suffix}"
    assert run_cli("track", str(sample), "-m", "stk", "-o", str(detected), "-q").returncode == 0
    assert run_cli("track", str(sample), "-p", str(sample / "queries.csv"), "-m", "stk", "-o", str(queried),
                   "-q").returncode == 0
    result = run_cli("eval", str(detected), str(sample / "tracks.csv"), "--json")
    assert result.returncode == 1 and result.stdout == ""
    assert result.stderr.startswith("Error: point_id 2: the prediction's query on frame 0") and result.stderr.count("\n") == 1
    result = run_cli("eval", str(queried), str(sample / "tracks.csv"), "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["delta_avg"] > 0.5


def test_a_two_way_run_s_csv_is_scored_though_its_first_row_is_not_its_query(tmp_path):
    """A CSV holds no queries: a point queried on frame 2 and tracked backward starts on frame 0, 1.5 px off its truth
    there. That row is no query: the point passes on its query row (exact), while a point with no row on its truth is
    still refused."""
    xy = gt_xy()
    xy[1, 0] += [1.5, 0]  # point 1, queried on frame 2: its backward pass's frame 0
    visible = np.ones((2, 4), bool)
    cov = np.broadcast_to(np.eye(2), (2, 4, 2, 2))
    gt = write_gt_csv(tmp_path / "gt.csv", [f"{p},{f},{10 + f},{20 + 2 * p},1" for p in (0, 1) for f in range(4)])
    pred = write_pred_csv(tmp_path / "pred.csv", [0, 1], xy, visible, cov)
    result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["delta_avg"] == 1.0  # scored after its first row, frame 0, the only one off
    xy[1] = gt_xy()[1] + [1.5, 0]  # every row of point 1 off its truth: tracked from other queries
    pred = write_pred_csv(tmp_path / "other.csv", [0, 1], xy, visible, cov)
    result = CliRunner().invoke(eval_command, [str(pred), str(gt), "--json"])
    assert result.exit_code == 1 and str(result.exception).startswith(
        "point_id 1: the prediction's query on frame 0 (11.50, 22.00) is 1.50 px from the ground truth (10.00, 22.00), "
        "more than 1 px, as are its other rows: track from")


def test_bench_synthetic_checks_average_aj_and_oa_over_the_scenes_that_have_them():
    """A scene without occluded truth (nonrigid's) has AJ and OA n/a: the means are over the other scenes, not NaN
    (a check that could never pass)."""
    from condtrack_cli.evaluate.bench.versus_lk import _synthetic_checks

    def scene(aj: float | None) -> dict:
        return {"auto": ({"delta_avg": 0.95, "AJ": aj, "OA": None if aj is None else 0.95}, 1.0)}

    checks = _synthetic_checks({"occlusion": scene(0.80), "fast": scene(0.90), "nonrigid_0": scene(None)}, ("auto",))
    assert checks == ["- [x] pass: auto mean <δ_avg 0.950 >= 0.88", "- [x] pass: auto mean AJ 0.850 >= 0.75 (2 scenes)",
                      "- [x] pass: auto mean OA 0.950 >= 0.90 (2 scenes)"]


def test_bench_seed_spread_means_the_seeds_and_keeps_a_missing_metric_missing():
    """``--seeds``' aggregation (``bench/seeds.py``): each metric's mean over the seeds, None where any seed has
    none (a check on it then does not pass by a partial mean); a cell is 'mean (min-max)'."""
    from condtrack_cli.evaluate.bench.seeds import mean_metrics, spread_cell

    runs = [{"delta_avg": 0.80, "cov95": 0.90, "AJ": None}, {"delta_avg": 0.70, "cov95": 0.80, "AJ": 0.5}]
    assert mean_metrics(runs) == pytest.approx({"delta_avg": 0.75, "cov95": 0.85, "AJ": None})
    assert mean_metrics(runs)["AJ"] is None
    assert spread_cell([0.841, 0.786, 0.836]) == "0.821 (0.786-0.841)"


def test_bench_seed_spread_runs_each_seed_and_judges_the_checks_on_the_mean(tmp_path):
    """``seed_spread_table`` on a one-set shared folder (the shipped occlusion sample, named as a face clip): LK,
    chained DIS and clf once, auto and cnlf once per seed with that seed (their track files differ, the CLF has
    none per seed), and issue 45's face checks and calibration bands on the means; ``--seeds 0`` is a usage error."""
    import shutil
    import subprocess
    import sys

    import h5py

    from condtrack_cli.evaluate.bench.seeds import seed_spread_table

    shared = tmp_path / "shared"
    shutil.copytree(SAMPLES / "occlusion", shared / "dudek_zz")
    work = tmp_path / "work"
    work.mkdir()
    lines = seed_spread_table(work, shared, 2, max_points=6)
    row = next(line for line in lines if line.startswith("| dudek_zz |"))
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert cells[1] == "6" and len(cells) == 7
    for cell in cells[5:]:  # auto, cnlf: mean (min-max) of two seeds
        mean, low, high = (float(v) for v in cell.replace("(", " ").replace(")", " ").replace("-", " ").split())
        assert low <= mean <= high and mean == pytest.approx((low + high) / 2, abs=1e-3)
    with h5py.File(work / "seeds_dudek_zz.s0.cnlf.h5") as first, h5py.File(work / "seeds_dudek_zz.s1.cnlf.h5") as second:
        assert not np.array_equal(first["tracks/xy"][...], second["tracks/xy"][...], equal_nan=True)
    assert (work / "seeds_dudek_zz.clf.h5").is_file() and not (work / "seeds_dudek_zz.s0.clf.h5").exists()
    checks = [line for line in lines if line.startswith("- [")]
    assert any("dudek_zz: auto" in line and ">= LK" in line for line in checks)
    assert any(line.endswith("+ 0.06") and "face mean of auto" in line for line in checks)
    # the calibration bands on the means: the face group's table, its mean row the set's mean over the seeds
    group = lines[lines.index("### face"):]
    mean_row = next(line for line in group if line.startswith("| face mean |"))
    auto_mean = float(cells[5].split()[0])
    assert float(mean_row.strip("|").split("|")[6]) == pytest.approx(auto_mean, abs=1e-3)  # lk dis clf cnlf auto
    assert any(line.startswith("- [") and "face mean cov90 of auto" in line for line in group)
    result = subprocess.run([sys.executable, "-m", "condtrack_cli.evaluate.bench", "--seeds", "0", "--work",
                             str(tmp_path / "x")], capture_output=True, text=True)
    assert result.returncode == 2 and "--seeds: expected a positive integer, got 0" in result.stderr


#: Metrics computed from positions or covariances, which a CSV rounds (``%.6f``, ``%.6e``): equal to about 1e-7.
ROUNDED_METRICS = ("median_err", "nees")


@pytest.fixture(scope="module")
def late_queries(tmp_path_factory):
    """The occlusion sample tracked two-way from queries on frame 5 (its truth there): the queries file, the run's
    CSV and HDF5 files, and the truth."""
    import condtrack_cli as ct

    folder, truth = tmp_path_factory.mktemp("late"), SAMPLES / "occlusion" / "tracks.csv"
    rows = [line.split(",") for line in truth.read_text().splitlines()[1:]]
    queries = folder / "queries.csv"
    queries.write_text("point_id,frame,x,y\n" + "".join(f"{p},5,{x},{y}\n" for p, f, x, y, v in rows
                                                         if f == "5" and v == "1"))
    tracks = ct.track(str(SAMPLES / "occlusion"), queries=str(queries), method="clf", progress=False)
    tracks.to_csv(folder / "run.csv")
    tracks.to_hdf5(folder / "run.h5")
    return queries, folder / "run.csv", folder / "run.h5", truth


def eval_json(*args) -> dict:
    """``condtrack eval ARGS --json``'s metrics."""
    result = CliRunner().invoke(eval_command, [*map(str, args), "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def assert_same_scores(scores: dict, expected: dict) -> None:
    """Equal but for the metrics a CSV's rounding moves (``ROUNDED_METRICS``)."""
    for key in ROUNDED_METRICS:
        assert scores.pop(key) == pytest.approx(expected.pop(key), rel=1e-5)
    assert scores == expected


def test_eval_queries_score_a_two_way_csv_as_its_hdf5(late_queries):
    """A CSV's point queried on frame 5 starts on frame 0 (the backward pass); ``--queries`` scores it from frame 5,
    as the HDF5 of the same run, where without it the CSV scores from frame 0."""
    queries, csv_path, h5_path, truth = late_queries
    hdf5 = eval_json(h5_path, truth)
    assert eval_json(csv_path, truth)["AJ"] != hdf5["AJ"]
    assert_same_scores(eval_json(csv_path, truth, "--queries", queries), dict(hdf5))
    assert_same_scores(eval_json(csv_path, truth, "--queries", queries, "--query-mode", "strided"),
                       eval_json(h5_path, truth, "--query-mode", "strided"))
    assert eval_json(h5_path, truth, "--queries", queries) == hdf5


def test_eval_queries_refuses_an_hdf5_whose_stored_queries_disagree(late_queries, tmp_path):
    from test_cli import run_cli

    queries, _, h5_path, truth = late_queries
    lines = queries.read_text().splitlines()
    point, frame, x, y = lines[2].split(",")
    for name, row in (("moved", f"{point},{frame},{float(x) + 1e-4},{y}"), ("late", f"{point},6,{x},{y}")):
        other = tmp_path / f"{name}.csv"
        other.write_text("\n".join([*lines[:2], row, *lines[3:]]) + "\n")
        result = run_cli("eval", str(h5_path), str(truth), "--queries", str(other))
        assert result.returncode == 1 and result.stdout == ""
        assert result.stderr.startswith(f"Error: {other}: point_id {point}: the query, frame ") and \
            "disagrees with the tracks' own, frame 5" in result.stderr and result.stderr.count("\n") == 1


@pytest.mark.parametrize("suffix", [".csv", ".h5"])
def test_eval_queries_refuses_a_tracked_point_missing_from_the_file(late_queries, tmp_path, suffix):
    queries, csv_path, h5_path, truth = late_queries
    pred = csv_path if suffix == ".csv" else h5_path
    header, first, *rest = queries.read_text().splitlines()
    fewer = tmp_path / "fewer.csv"
    fewer.write_text("\n".join([header, *rest]) + "\n")
    result = CliRunner().invoke(eval_command, [str(pred), str(truth), "--queries", str(fewer)])
    assert result.exit_code == 1 and str(result.exception) == (
        f"{fewer}: point_id {first.split(',')[0]} is in the tracks but not in the queries file")


@pytest.mark.parametrize("suffix", [".csv", ".h5"])
def test_eval_queries_takes_the_p_file_of_a_run_that_dropped_untrackable_points(late_queries, tmp_path, suffix):
    """`track --untrackable drop` tracks only some of the -p file's points; eval --queries refused that very file
    ("point_id 999 is in the queries file but not in the tracks"). Its untracked points are ignored now."""
    import condtrack_cli as ct

    queries, _, _, truth = late_queries
    more = tmp_path / "more.csv"
    more.write_text(queries.read_text() + "999,5,5,5\n")  # a flat corner: untrackable
    with pytest.warns(ct.CondtrackWarning, match="untrackable"):
        tracks = ct.track(str(SAMPLES / "occlusion"), queries=str(more), method="clf", untrackable="drop")
    assert 999 not in tracks.queries.point_id
    pred = tmp_path / f"run{suffix}"
    (tracks.to_csv if suffix == ".csv" else tracks.to_hdf5)(pred)
    assert eval_json(pred, truth, "--queries", more) == eval_json(pred, truth, "--queries", queries)


def test_score_tracks_takes_the_queries_file(late_queries):
    """The Python function under ``eval``: ``queries=`` as ``--queries``."""
    from condtrack_cli.evaluate.score import score_tracks
    from condtrack_cli.io.read import read_tracks

    queries, csv_path, h5_path, truth_path = late_queries
    truth = load_gt_csv(truth_path)
    hdf5, data = score_tracks(read_tracks(h5_path)[0], truth)
    scores, csv_data = score_tracks(read_tracks(csv_path)[0], truth, from_csv=True, queries=queries)
    assert_same_scores(scores, hdf5)
    np.testing.assert_array_equal(csv_data.query_frame, data.query_frame)
    assert set(data.query_frame) == {5}


def test_eval_queries_are_checked_against_the_track_file_s_frames(late_queries, tmp_path):
    """The queries file is read as ``track -p`` reads it, against the track file's frames (its frame size unknown to
    a CSV: a position need only be finite)."""
    queries, csv_path, _, truth = late_queries
    header, first, *rest = queries.read_text().splitlines()
    point, _, x, y = first.split(",")
    for name, row, message in (("past", f"{point},30,{x},{y}", "row 2: frame 30 is outside the sequence (0..29)"),
                               ("nan", f"{point},5,nan,{y}", f"row 2: point (nan, {float(y):g}) is not finite")):
        path = tmp_path / f"{name}.csv"
        path.write_text("\n".join([header, row, *rest]) + "\n")
        result = CliRunner().invoke(eval_command, [str(csv_path), str(truth), "--queries", str(path)])
        assert result.exit_code == 1 and str(result.exception) == f"{path}: {message}"
