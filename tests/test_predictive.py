"""Issue 27: each row's Student-t predictive distribution (``dof``) and ``--max-std``."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

import condtrack_cli as ct
from condtrack_cli.cli import cli
from condtrack_cli.filters.calibration import CORE_MAX, scale_ratio, tail_dof
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
    assert (dof[has_state] > 2).all() and np.isfinite(dof[has_state]).all()
    stk = ct.track(str(SAMPLE), queries=str(SAMPLE / "queries.csv"), method="stk")
    assert np.isinf(stk.dof[stk.result.has_state]).all()  # no error model: Gaussian (and no covariance)


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
