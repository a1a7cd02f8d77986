"""Issue 27: each row's Student-t predictive distribution (``dof``) and ``--max-std``."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

import condtrack_cli as ct
from condtrack_cli.cli import cli
from condtrack_cli.filters import calibration
from condtrack_cli.filters.calibration import (
    GROWTH_KNEE, GROWTH_MAX, GROWTH_POWER, RATIO_DRIFT, RATIO_MIN, RATIO_OWN, RATIO_WALK, ErrorModel, scale_ratio,
    tail_dof,
)
from condtrack_cli.predictive import ellipse_m2, major_std

from conftest import SAMPLES

SAMPLE = SAMPLES / "occlusion"


@pytest.fixture(scope="module")
def clf_tracks():
    return ct.track(str(SAMPLE), queries=str(SAMPLE / "queries.csv"), method="clf")


def test_major_std_is_the_root_of_the_larger_eigenvalue():
    inf, nan = np.inf, np.nan
    cov = np.array([np.diag([4.0, 1.0]), [[2.0, 1.0], [1.0, 2.0]], np.diag([inf, 1.0]), np.full((2, 2), nan)])
    np.testing.assert_allclose(major_std(cov), [2.0, np.sqrt(3.0), inf, nan], rtol=1e-12)


def test_dof_follows_the_error_model_and_stays_above_two(clf_tracks):
    """nu = 2 / (1 - rho), rho the Student-t's scale over its covariance (so that the covariance is the reported one);
    nu > 2 on every row with a state, NaN elsewhere."""
    assert tail_dof(np.array([0.5, 0.1])) == pytest.approx([4.0, 2.0 / 0.9])
    nu = tail_dof(np.array([0.25]))
    assert nu / (nu - 2) == pytest.approx(4.0)  # covariance = scale nu / (nu - 2)
    one = np.ones(1)
    # the filter's own covariance alone: rho is its ratio; with an equal walk W, the two ratios weighted by trace
    assert scale_ratio(one, 0 * one, 0 * one, 0 * one) == pytest.approx(RATIO_OWN)
    assert scale_ratio(one, 0 * one, 0 * one, 0 * one, one) == pytest.approx((RATIO_OWN + RATIO_WALK) / 2)
    dof, has_state = clf_tracks.dof, clf_tracks.result.has_state
    assert np.isnan(dof[~has_state]).all()
    assert ((dof[has_state] >= tail_dof(RATIO_MIN) - 1e-12) & (dof[has_state] <= tail_dof(0.999) + 1e-9)).all()
    stk = ct.track(str(SAMPLE), queries=str(SAMPLE / "queries.csv"), method="stk")
    assert np.isinf(stk.dof[stk.result.has_state]).all()  # no error model: Gaussian (and no covariance)


def test_a_points_own_innovations_grow_its_covariance():
    """Two groups of points found on one frame with the same prediction, gate and measurement covariance: one
    matched on its prediction (NIS 0), one with innovations of 0.3 times what S says (NIS 0.18 on average). The
    reported covariance is g (max(lambda, 1) Sigma + D), g = clip((lambda_p / GROWTH_KNEE)^GROWTH_POWER, 1,
    GROWTH_MAX): 1 for the first group (lambda_p below the knee), above 1 for most of the second."""
    rng = np.random.default_rng(0)
    n = 400
    model = ErrorModel(n, 9.21)
    index = np.arange(n)
    unit = np.repeat(np.eye(2)[None], n, 0)
    model.start(index, unit)
    zero = np.zeros((n, 2))
    z = np.where(np.arange(n)[:, None] < n // 2, 0.0, rng.normal(0.0, 0.3 * np.sqrt(2.0), (n, 2)))  # S = 2 I
    found = np.ones(n, bool)
    model.begin_frame()
    model.update(index, zero, unit, z, unit, found, zero, 0.5 * unit, ~found, zero)
    tight, loose = slice(0, n // 2), slice(n // 2, n)
    assert model.consistency[tight].max() < model.consistency[loose].mean()
    growth = np.clip((model.consistency / GROWTH_KNEE) ** GROWTH_POWER, 1.0, GROWTH_MAX)
    assert (growth[tight] == 1.0).all() and np.mean(growth[loose] > 1.0) > 0.5 and growth[loose].max() > 2.0
    own = max(model.scale, 1.0) * 0.5 * np.eye(2)
    np.testing.assert_allclose(model.reported, growth[:, None, None] * (own + model.drift), rtol=1e-12)
    assert (model.dof > 2).all()


def test_growth_leaves_the_query_row_and_the_student_t_ratio_alone(monkeypatch):
    """A point matched far off its prediction on every frame (lambda_p near 0.6) has its reported covariance grown
    about 6 times, one matched on it about 2.3 times (its lambda_p is only the pooled prior's share, 0.12); the query
    row is never grown, and the Student-t's ratio is the same as without the growth."""
    def run():
        model = ErrorModel(2, 9.21)
        index, unit, zero = np.arange(2), np.repeat(np.eye(2)[None], 2, 0), np.zeros((2, 2))
        model.start(index, unit)
        start = model.reported.copy()
        z = np.array([[0.0, 0.0], [1.2, 1.2]])  # NIS 0 and 1.44 against S = 2 I
        for _ in range(6):
            model.begin_frame()
            model.update(index, zero, unit, z, unit, np.ones(2, bool), zero, 0.5 * unit, np.zeros(2, bool), zero)
        return model, start
    grown, start = run()
    assert grown.consistency[1] == pytest.approx(0.6, abs=0.01) and grown.consistency[0] == pytest.approx(0.12, abs=0.01)
    assert grown.growth[1] == pytest.approx(6.0, abs=0.1) and grown.growth[0] == pytest.approx(2.3, abs=0.1)
    growth = grown.growth
    monkeypatch.setattr(calibration, "GROWTH_MAX", 1.0)
    plain, plain_start = run()
    assert (plain.growth == 1.0).all()
    np.testing.assert_array_equal(start, plain_start)
    np.testing.assert_allclose(grown.reported, growth[:, None, None] * plain.reported, rtol=1e-12)
    np.testing.assert_array_equal(grown.ratio, plain.ratio)


def test_a_wrong_match_term_summed_over_many_frames_has_a_wider_core():
    """n_D = (sum c_k)^2 / sum c_k^2 of the frames' shares c_k of D: among 200 points matched at NIS 1 every frame
    (they hold the pooled lambda steady, so a match's chance of being wrong is the same from frame to frame), a point
    matched far off its prediction on one frame, then as the others, sums about one share; one matched as far off on
    each of eight frames sums eight equal ones. The Student-t's ratio of D - A is RATIO_DRIFT n_D (at least RATIO_MIN
    for the row), so the second point's core is about eight times as large a part of its D."""
    one = np.ones(1)
    assert scale_ratio(0 * one, 0 * one, one, 0 * one, 0.0, 8.0 * one) == pytest.approx(8 * RATIO_DRIFT)
    assert scale_ratio(0 * one, 0 * one, one, 0 * one, 0.0, one) == pytest.approx(max(RATIO_DRIFT, RATIO_MIN))
    n = 202
    model = ErrorModel(n, 9.21)
    index, unit, zero = np.arange(n), np.repeat(np.eye(2)[None], n, 0), np.zeros((n, 2))
    model.start(index, unit)
    assert (model.drift_shares(index) == 1.0).all()  # no share yet
    for frame in range(8):
        z = np.ones((n, 2))  # NIS 1 against S = 2 I
        z[1] = 2.5  # NIS 6.25: inside the gate (9.21), likely a wrong match
        if frame == 0:
            z[0] = 2.5
        model.begin_frame()
        model.update(index, zero, unit, z, unit, np.ones(n, bool), zero, 0.5 * unit, np.zeros(n, bool), zero)
    once, always = model.drift_shares(index[:2])
    assert once < 1.2 and always == pytest.approx(8.0, rel=0.03)
    assert np.trace(model.drift[1]) > 5 * np.trace(model.drift[0])


def test_a_re_acquisition_jump_puts_the_prediction_inside_the_95_percent_ellipse():
    """J: among 200 points matched at NIS 1 every frame, a point found again by the re-acquisition 50 px from its
    prediction (``jump``) may be at either place, so its 95 % Student-t ellipse holds the prediction on every later
    frame; the same match without the jump, or a jump on a frame where the point is not found, leaves the row as it
    was. The jump joins D's bounded part A (ratio RATIO_BOUNDED), not the wrong-match shares that n_D counts."""
    n = 203
    jump = np.array([30.0, -40.0])

    def run(jumps: bool):
        model = ErrorModel(n, 9.21)
        index, unit, zero = np.arange(n), np.repeat(np.eye(2)[None], n, 0), np.zeros((n, 2))
        model.start(index, unit)
        found = np.ones(n, bool)
        found[2] = False  # point 2: not found on the jump's frame, found on the others
        for frame in range(6):
            moved = np.zeros((n, 2))
            if jumps and frame == 2:
                moved[:3] = jump  # point 0 found again there, point 1 matched as the others, point 2 not found
                moved[1] = 0.0
            model.begin_frame()
            model.update(index, zero, unit, np.ones((n, 2)), unit, found | (frame != 2), zero, 0.5 * unit,
                         np.zeros(n, bool), zero, None, moved)
        return model

    with_jump, without = run(True), run(False)
    np.testing.assert_allclose(with_jump.bounded[0], np.outer(jump, jump))
    np.testing.assert_array_equal(with_jump.reported[1:], without.reported[1:])
    np.testing.assert_array_equal(with_jump.drift_shares(np.arange(n)), without.drift_shares(np.arange(n)))
    for model, holds in ((with_jump, True), (without, False)):
        covariance, dof = model.reported[0], model.dof[0]
        m2 = jump @ np.linalg.solve(covariance, jump)  # the truth at the prediction: the find was wrong
        assert (m2 <= ellipse_m2(0.95, dof)) == holds
    assert with_jump.dof[0] > 10  # a bounded either-or, not a tail


def test_max_std_hides_the_rows_whose_major_std_exceeds_it(clf_tracks, tmp_path):
    """The API's max_std and the command line's --max-std: visible only where the filter said so and the std along the
    covariance's major axis is at most the threshold; positions unchanged; the threshold in the file's attributes."""
    std = major_std(clf_tracks.cov)
    threshold = float(np.nanmedian(std[clf_tracks.visible]))  # about half the visible rows pass
    trusted = ct.track(str(SAMPLE), queries=str(SAMPLE / "queries.csv"), method="clf", max_std=threshold)
    expected = clf_tracks.visible & (std <= threshold)
    assert 0 < expected.sum() < clf_tracks.visible.sum()
    assert np.array_equal(trusted.visible, expected)
    assert trusted.xy.tobytes() == clf_tracks.xy.tobytes() and trusted.attributes["max_std"] == threshold
    assert clf_tracks.attributes["max_std"] == np.inf
    out = tmp_path / "t.h5"
    result = CliRunner().invoke(cli, ["track", str(SAMPLE), "-p", str(SAMPLE / "queries.csv"), "-m", "clf", "-q",
                                      "--max-std", repr(threshold), "-o", str(out)])
    assert result.exit_code == 0, result.output
    with h5py.File(out) as f:
        assert f.attrs["max_std"] == threshold and np.array_equal(f["tracks/visible"][()], expected)
    result = CliRunner().invoke(cli, ["track", str(SAMPLE), "--max-std", "0", "-o", str(tmp_path / "u.csv")])
    assert result.exit_code == 2 and "--max-std" in result.output and not (tmp_path / "u.csv").exists()
