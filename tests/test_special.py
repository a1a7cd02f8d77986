"""condtrack_cli.special against scipy.special (a test dependency, no longer imported by ``track``)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import special as scipy_special

from condtrack_cli import special


@pytest.mark.parametrize("p", [0.5, 0.9, 0.95, 0.99, 0.999])
def test_chi2_quantiles_equal_scipys_for_every_support_size(p):
    """Every dof the uniform test of W(z_k) can ask for (1 .. 224, support up to 15 x 15), to 1e-11 relative."""
    dof = np.arange(1, 225)
    want = 2.0 * scipy_special.gammaincinv(dof / 2.0, p)
    np.testing.assert_allclose(special.chi2_quantiles(p, dof), want, rtol=1e-11)
    assert special.chi2_quantile(0.99, 2) == pytest.approx(9.21034037, abs=1e-8)  # the gate's gamma


def test_logsumexp_expit_xlogx_and_the_normal_quantile_equal_scipys():
    rng = np.random.default_rng(3)
    values = rng.normal(0.0, 40.0, (6, 7, 7))
    values[0] = -np.inf  # all -inf: -inf
    values[1, 2, 3] = -np.inf
    for axis, keep in (((1, 2), True), (2, False)):
        np.testing.assert_allclose(special.logsumexp(values, axis=axis, keepdims=keep),
                                   scipy_special.logsumexp(values, axis=axis, keepdims=keep), rtol=1e-14)
    x = np.array([-np.inf, -800.0, -30.0, -1.0, 0.0, 2.5, 40.0, 800.0, np.inf])
    np.testing.assert_allclose(special.expit(x), scipy_special.expit(x), rtol=1e-14, atol=1e-300)
    d = np.array([0.0, 1e-300, 0.25, 1.0, 3.0])
    np.testing.assert_allclose(special.xlogx(d), scipy_special.xlogy(d, d), rtol=1e-15)
    for p in (0.6, 0.75, 0.95, 0.999):
        assert special.normal_quantile(p) == pytest.approx(scipy_special.ndtri(p), rel=1e-14)


@pytest.mark.parametrize("dof", [1, 2, 3, 48, 224])
def test_chi2_quantiles_at_extreme_levels_are_finite_and_match_scipy(dof):
    """Any level in (0, 1) a config may give (``measure.uniform_alpha``): tails to 1e-9 relative (1e-7 at 1e-9), 1e-5 at
    1 - 1e-12 (the upper tail is 1 - P, rounded to 1e-16; the closed forms in log space neither overflow nor
    stall), and a level below what 1 - a sum resolves (1e-300) ends at a finite bracket below the 1e-6 quantile
    instead of bisecting forever."""
    # the closed forms are 1 - a sum or erf - a sum: where either is near 1 the difference keeps 1e-16 absolute
    for p, rel in ((1e-9, 1e-7), (1e-6, 1e-9), (1 - 1e-6, 1e-9), (1 - 1e-12, 1e-5)):
        want = 2.0 * scipy_special.gammaincinv(dof / 2.0, p)
        assert special.chi2_quantile(p, dof) == pytest.approx(want, rel=rel), p
    assert 0.0 <= special.chi2_quantile(1e-300, dof) < special.chi2_quantile(1e-6, dof)  # bounded, if not exact
    assert np.isfinite(special.chi2_quantile(1 - 1e-16, dof))
    assert special.chi2_quantile(1 - 1e-20, dof) == np.inf  # the level rounds to 1, as scipy's gammaincinv


def test_normal_quantile_of_a_level_that_rounds_to_0_or_1_is_infinite_as_scipys():
    """``measure.equalise_alpha`` = 1e-20 asks for the quantile at 1 - 1e-20 = 1.0: inf (no threshold), not an error."""
    for p in (0.0, 1.0 - 1e-20):
        assert special.normal_quantile(p) == scipy_special.ndtri(p)
