"""Metrics and residual tests against analytic values and known statistics."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from greybox import DataError, DimensionError, metrics
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


# ------------------------------------------------------------------ the selection criterion
def _ar1(rng, n, a):
    """Unit-variance AR(1) noise, pole a (coloured like an output error under process noise)."""
    w = rng.standard_normal(n + 200)
    e = np.empty_like(w)
    e[0] = w[0]
    for k in range(1, len(w)):
        e[k] = a * e[k - 1] + np.sqrt(1 - a * a) * w[k]
    return e[200:]


def _candidates(rng, n, extra_coef):
    """y = x1 + extra_coef x2 + coloured noise; least-squares fits with x1 alone (1 par),
    x1 and x2 (2 par) and x1, x2 and four spurious slow signals (6 par)."""
    X = np.vstack([_ar1(rng, n, 0.95) for _ in range(6)])
    y = X[0] + extra_coef * X[1] + 0.3 * _ar1(rng, n, 0.9)
    fits, npars = [], []
    for k in (1, 2, 6):
        beta = np.linalg.lstsq(X[:k].T, y, rcond=None)[0]
        fits.append(metrics.output_fit(y[None], (beta @ X[:k])[None]))
        npars.append(k)
    return fits, npars


def test_criterion_keeps_only_the_terms_the_data_support():
    """Over 40 seeds of coloured noise, the criterion picks the true structure: the
    one-term model when the second regressor is absent (the larger fits only chase the
    noise: their SE is lower, never by much), the two-term one when it is there at a
    tenth of the first. 90 %: the penalty is a BIC's, whose false-inclusion rate on
    effective samples is a few % per term at these sizes, not zero."""
    rng = np.random.default_rng(20261126)
    picks_absent, picks_present = [], []
    for _ in range(40):
        fits, npars = _candidates(rng, 2000, 0.0)
        assert fits[2].se <= fits[0].se  # the larger fit is never worse on its own data
        picks_absent.append(int(np.argmin(metrics.criterion_scores(fits, npars))))
        fits, npars = _candidates(rng, 2000, 0.1)
        picks_present.append(int(np.argmin(metrics.criterion_scores(fits, npars))))
    assert np.mean(np.array(picks_absent) == 0) >= 0.9, picks_absent
    assert np.mean(np.array(picks_present) == 1) >= 0.9, picks_present


def test_criterion_on_all_samples_would_overfit_coloured_noise():
    """The effective sample count is what keeps the spurious terms out: scored on all N
    samples (as if the error were white) the six-term fit wins far more often. The
    criterion's n_eff is the best-fitting candidate's, below N for coloured errors."""
    rng = np.random.default_rng(7)
    naive = honest = 0
    for _ in range(30):
        fits, npars = _candidates(rng, 2000, 0.0)
        assert fits[2].n_eff[0] < 0.5 * 2000
        honest += int(np.argmin(metrics.criterion_scores(fits, npars)) == 2)
        naive += int(np.argmin(metrics.criterion_scores(fits, npars, n_eff=[2000.0])) == 2)
    assert naive >= honest + 5, (naive, honest)


def test_output_fit_of_a_diverged_candidate_loses():
    y = np.vstack([np.sin(np.arange(100) / 5.0)])
    bad = metrics.output_fit(y, np.full_like(y, np.nan))
    good = metrics.output_fit(y, y + 0.01)
    assert bad.se == np.inf
    scores = metrics.criterion_scores([bad, good], [1, 3])
    assert scores[0] == np.inf and np.isfinite(scores[1])
    with pytest.raises(DataError, match="parameter counts"):
        metrics.criterion_scores([good], [1, 2])


def test_independent_samples_count_a_repeated_error_once():
    """Two outputs that carry the same error hold the information of one: their counts
    are halved (participation ratio 1 of 2); two independent errors keep theirs (within
    the sampling spread of the correlation matrix, ~1/sqrt(N) = 1.4 %)."""
    rng = np.random.default_rng(3)
    a, b = _ar1(rng, 5000, 0.5), _ar1(rng, 5000, 0.5)
    alone = metrics.effective_samples(np.vstack([a, b]))
    same = metrics.independent_samples(np.vstack([a, a]))
    apart = metrics.independent_samples(np.vstack([a, b]))
    np.testing.assert_allclose(same, metrics.effective_samples(np.vstack([a, a])) / 2,
                               rtol=1e-9)
    np.testing.assert_allclose(apart, alone, rtol=0.02)
    # one output: nothing to share
    np.testing.assert_allclose(metrics.independent_samples(a[None]), alone[:1])


def test_criterion_factor_charges_each_parameter_factor_times_its_penalty():
    """``factor`` scales the penalty only: two candidates' scores move apart by exactly
    (factor - 1) * (k2 - k1) * log(sum n_eff), so a nested candidate's fit gain must beat
    ``factor`` penalties (the choice in close_the_loop uses bic_factor = 10)."""
    rng = np.random.default_rng(11)
    fits, npars = _candidates(rng, 2000, 0.1)
    n = fits[0].n_eff
    s1 = metrics.criterion_scores(fits, npars, n_eff=n)
    s10 = metrics.criterion_scores(fits, npars, n_eff=n, factor=10.0)
    logn = np.log(np.sum(n))
    np.testing.assert_allclose((s10 - s1) - (s10[0] - s1[0]),
                               9.0 * (np.array(npars) - npars[0]) * logn, rtol=1e-12)


def test_oe_criterion_factor_is_the_choices_price():
    """The prune's criterion (:func:`oe_criterion`) prices a parameter as the choice does
    (:func:`criterion_scores`): the same numbers for any factor, and the factor-1 value
    is the BIC on effective samples as before."""
    rng = np.random.default_rng(5)
    fits, npars = _candidates(rng, 2000, 0.1)
    n = fits[0].n_eff
    for f in (1.0, 10.0):
        cs = metrics.criterion_scores(fits, npars, n_eff=n, factor=f)
        for fit, k, c in zip(fits, npars, cs):
            e = np.tile((fit.per_output / 100.0)[:, None], (1, 4))  # mean square = SE^2
            assert metrics.oe_criterion(e, k, n, f) == pytest.approx(c, rel=1e-12)
    e = rng.standard_normal((1, 500))
    bic = float(np.sum(n * np.log(np.mean(e**2, axis=1))) + 3 * np.log(np.sum(n)))
    assert metrics.oe_criterion(e, 3, n) == pytest.approx(bic, rel=1e-12)


@pytest.mark.parametrize("worth, factor, kept", [(3.0, 1.0, True), (3.0, 10.0, False),
                                                 (30.0, 10.0, True)])
def test_backward_prune_keeps_a_term_only_above_its_price(worth, factor, kept):
    """A term that lowers the output error by ``worth`` BIC penalties (n_eff log of the
    mean-square ratio) is kept at a price of ``factor`` penalties only if worth > factor:
    close the loop prunes the chosen law at its bic_factor (10), the price its choice
    between candidates pays, so a tiny proxy term beside the right one (worth 3) goes."""
    from greybox.metrics import effective_samples
    from greybox.trace.oe import backward_by_criterion

    rng = np.random.default_rng(3)
    w = rng.standard_normal((1, 4000))
    ne = float(np.sum(effective_samples(w)))
    ratio = np.exp(worth * np.log(ne) / ne)  # the mean square without term 1, over with

    def resid(keep, th):
        if keep == [0, 1]:
            return w
        return w * (np.sqrt(ratio) if keep == [0] else 10.0)  # term 0 is the main one

    keep, _ = backward_by_criterion(2, np.ones(2), lambda keep, start: start, resid, 1,
                                    factor=factor)
    assert keep == ([0, 1] if kept else [0])
