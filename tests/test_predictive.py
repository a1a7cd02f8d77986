"""Issue 27: each row's Student-t predictive distribution (``dof``) and ``--max-std``."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

import condtrack_cli as ct
from condtrack_cli.cli import cli
from condtrack_cli.filters.calibration import CORE_MAX, RATIO_MIN, ErrorModel, scale_ratio, tail_dof
from condtrack_cli.predictive import major_std

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
    # the filter's own covariance alone: rho is the core's ratio, min(CORE_GAIN lambda_p^CORE_POWER, CORE_MAX)
    assert scale_ratio(one, 0 * one, 0 * one, 0 * one, np.array([1e6])) == pytest.approx(CORE_MAX)
    low, high = (scale_ratio(one, 0 * one, 0 * one, 0 * one, np.array([v])) for v in (1e-3, 1e-1))
    assert 0 < low < high < CORE_MAX  # a point whose innovations are smaller has the tighter core
    dof, has_state = clf_tracks.dof, clf_tracks.result.has_state
    assert np.isnan(dof[~has_state]).all()
    assert ((dof[has_state] >= tail_dof(RATIO_MIN) - 1e-12) & (dof[has_state] <= tail_dof(0.999) + 1e-9)).all()
    stk = ct.track(str(SAMPLE), queries=str(SAMPLE / "queries.csv"), method="stk")
    assert np.isinf(stk.dof[stk.result.has_state]).all()  # no error model: Gaussian (and no covariance)


def test_a_points_own_innovations_set_its_core_not_its_covariance():
    """Two groups of points found on one frame with the same prediction, gate and measurement covariance: one
    matched on its prediction (NIS 0), one with innovations as S says (NIS 2 on average). The reported covariance
    stays max(lambda, 1) Sigma + D (lambda_p does not enter it); the first group's core is tighter (lambda_p
    smaller), so its nu is smaller."""
    rng = np.random.default_rng(0)
    n = 400
    model = ErrorModel(n, 9.21)
    index = np.arange(n)
    unit = np.repeat(np.eye(2)[None], n, 0)
    model.start(index, unit)
    zero = np.zeros((n, 2))
    z = np.where(np.arange(n)[:, None] < n // 2, 0.0, rng.normal(0.0, np.sqrt(2.0), (n, 2)))  # S = 2 I
    found = np.ones(n, bool)
    model.begin_frame()
    model.update(index, zero, unit, z, unit, found, zero, 0.5 * unit, ~found, zero)
    tight, loose = slice(0, n // 2), slice(n // 2, n)
    assert model.consistency[tight].max() < model.consistency[loose].mean()
    assert np.median(model.dof[tight]) < np.median(model.dof[loose])
    own = max(model.scale, 1.0) * 0.5 * np.eye(2)
    np.testing.assert_allclose(model.reported[tight], own + model.drift[tight], rtol=1e-12)
    assert (model.dof > 2).all()


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
