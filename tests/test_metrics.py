"""Metrics and residual tests against analytic values and known statistics."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from greybox import DataError, DimensionError
from greybox.metrics import (
    autocorrelation,
    correlation_band,
    cross_correlation,
    relative_error,
    whiteness_test,
)


def test_relative_error_analytic():
    # y = 1 everywhere, y_hat = 0.9: sqrt form gives exactly 10 %, squared 1 %.
    y = np.ones((2, 100))
    yh = np.vstack([0.9 * np.ones(100), np.ones(100)])
    e = relative_error(y, yh)
    np.testing.assert_allclose(e.per_output, [10.0, 0.0], atol=1e-12)  # exact arithmetic
    np.testing.assert_allclose(e.value, 5.0, atol=1e-12)
    es = relative_error(y, yh, squared=True)
    np.testing.assert_allclose(es.per_output, [1.0, 0.0], atol=1e-12)
    assert float(e) == e.value


def test_relative_error_skip_and_errors():
    y = np.ones((1, 10))
    yh = np.ones((1, 10))
    yh[0, 0] = 100.0
    assert relative_error(y, yh, skip=1).value == 0.0
    with pytest.raises(DimensionError, match="y_hat has shape"):
        relative_error(y, np.ones((2, 10)))
    with pytest.raises(DataError, match="identically zero"):
        relative_error(np.zeros((1, 10)), yh)
    with pytest.raises(DataError, match="NaN"):
        relative_error(y, np.full((1, 10), np.nan))


def test_autocorrelation_of_ar1_matches_theory():
    # AR(1) with coefficient a has autocorrelation a^lag; with N = 2e5 the sample
    # estimate has standard error ~ 1/sqrt(N) * O(1) ~ 0.005: tolerance 0.02.
    rng = np.random.default_rng(1)
    a, N = 0.7, 200_000
    from scipy.signal import lfilter

    x = lfilter([1.0], [1.0, -a], rng.standard_normal(N))
    r = autocorrelation(x, 5)
    np.testing.assert_allclose(r[0], a ** np.arange(6), atol=0.02)


def test_cross_correlation_finds_delay():
    # e[k] = u[k-3]: the cross-correlation peaks (at 1) at lag +3 only.
    rng = np.random.default_rng(2)
    u = rng.standard_normal((1, 5000))
    e = np.roll(u, 3, axis=1)
    c = cross_correlation(u, e, 5)
    assert c.shape == (1, 1, 11)
    assert np.argmax(c[0, 0]) == 5 + 3
    np.testing.assert_allclose(c[0, 0, 8], 1.0, atol=2e-3)  # 3 wrapped samples of 5000
    assert np.max(np.abs(np.delete(c[0, 0], 8))) < 4 * correlation_band(5000, 0.99)


def test_whiteness_test_size_and_power():
    # Under H0 (white noise) the Ljung-Box p-values are ~uniform: the rejection
    # rate at 5 % over 400 independent series must lie in a 99.9 % binomial
    # interval around 0.05 (about 0.018..0.093).
    rng = np.random.default_rng(3)
    e = rng.standard_normal((400, 2000))
    t = whiteness_test(e, 20, alpha=0.05)
    rate = np.mean(~t.white)
    assert 0.018 < rate < 0.093
    # Under H1 (AR(1) with a = 0.2) every series is rejected at 1e-3.
    from scipy.signal import lfilter

    x = lfilter([1.0], [1.0, -0.2], rng.standard_normal((5, 2000)), axis=1)
    t1 = whiteness_test(x, 20)
    assert not t1.all_white and np.all(t1.pvalue < 1e-3)
    # statistic follows chi2(20): its mean over H0 series is 20 within 3 standard errors
    se = np.sqrt(2 * 20 / 400)
    assert abs(t.statistic.mean() - 20) < 3 * se * 1.2  # 1.2: small-sample excess of LB
    assert np.isclose(chi2.sf(t.statistic[0], 20), t.pvalue[0])


def test_whiteness_needs_enough_samples():
    with pytest.raises(DataError, match="needs at least 41 samples"):
        whiteness_test(np.zeros((1, 30)), 20)
