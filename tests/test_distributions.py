"""bodyspace.distributions gives scipy.stats' numbers (to the bit) without importing scipy.stats
in the library (0.5 s at every start of a command)."""

import numpy as np
import pytest
import scipy.stats

from bodyspace.distributions import chi2_cdf, norm_ppf, truncnorm_rvs


def test_norm_ppf_is_scipy_stats():
    q = np.concatenate([[0.0, 1.0, 0.5, 1e-300, 1 - 1e-16], np.random.default_rng(0).random(1000)])
    np.testing.assert_array_equal(norm_ppf(q), scipy.stats.norm.ppf(q))


@pytest.mark.parametrize("df", [1, 2, 3, 7.5])
def test_chi2_cdf_is_scipy_stats(df):
    xs = [-1.0, -1e-15, 0.0, 1e-300, 0.3, 1.0, 2.5, 30.0, 1e4, np.inf, np.nan]
    got = np.array([chi2_cdf(x, df) for x in xs])
    np.testing.assert_array_equal(got, scipy.stats.chi2.cdf(xs, df))


@pytest.mark.parametrize("lo, hi", [(-3.0, 3.0), (-np.inf, np.inf), (-2.0, 0.5), (0.0, 1.0), (1.0, 40.0),
                                    (-40.0, -1.0), (-np.inf, -8.0), (8.0, np.inf), (-0.5, -0.1), (0.2, 0.3)])
def test_truncnorm_rvs_is_scipy_stats(lo, hi):
    """Left, right and central cases of the mass, both quantile branches, far tails."""
    got = truncnorm_rvs(lo, hi, (300, 7), rng=np.random.default_rng(5))
    want = scipy.stats.truncnorm.rvs(lo, hi, size=(300, 7), random_state=np.random.default_rng(5))
    assert got.shape == (300, 7)
    np.testing.assert_array_equal(got, want)
    assert (got >= lo).all() and (got <= hi).all()


def test_truncnorm_rvs_takes_a_seed_like_every_random_function():
    np.testing.assert_array_equal(truncnorm_rvs(-3, 3, (4,), rng=11), truncnorm_rvs(-3, 3, (4,), rng=11))
