"""Tracing an error that shows first in the second next output (positions only measured).

A mass-spring-damper whose model lacks a hardening spring ``-K3 pos^3`` in
its velocity equation, with only the position measured: C G ~ dt^2/2, so the
r = 1 filter's d^ alternates in sign (a ZOH zero near z = -1). The trace
detects relative degree 2, fits the law on the delayed, smoothed d^ with the
law's terms weighted as that d^ sees them (first-order hold of a
continuous-time law: [1/6, 2/3, 1/6]) and by GLS (its noise is coloured).
"""

from __future__ import annotations

import numpy as np
import pytest
from plantlib import draw, msd

import greybox as gb
from greybox.exceptions import DataError, DimensionError, RankConditionError
from greybox.trace import resolve_channel_spec, trace_channel

K3 = 30.0
DT = 0.01


def _case(seed, q=3e-3, r=3e-3, n=3000):
    nom = msd(measured=("pos",))
    A, B = np.asarray(nom.A), np.asarray(nom.B)

    def f(x, u):
        dx = A @ x + B @ u
        dx[1] -= K3 * x[0] ** 3
        return dx

    c = draw(nom, f, n_true=2, dt=DT, rng=np.random.default_rng(seed), q_std=np.array([0, q]),
             r_std=r, n_est=n, n_val=10, amplitude=4.0)
    ch = [ch for ch in resolve_channel_spec(nom, None) if ch.name == "eq(vel)"][0]
    return nom, ch, c


def _k3(tr):
    law = tr.static
    j = [s[0] for s in law.spec].index("pos^3")
    return law.coef[0, j], law.ci[0, j]


def test_positions_only_uses_relative_degree_2_and_finds_the_cubic_alone():
    nom, ch, c = _case(0)
    tr = trace_channel(nom, ch, c.y, c.u, Q=c.Q, R=c.R, dt=DT, max_order=0)
    assert tr.relative_degree == 2 and tr.law_estimate.smoothed
    assert tr.law_estimate.relative_degree == 2
    # the r = 1 filter's d^ alternates (the old workaround's trigger); the law's d^ does not
    d1 = tr.filter_result.d_est[0, 50:-2]
    assert np.corrcoef(d1[1:], d1[:-1])[0, 1] < -0.9
    assert not any("alternates" in s for s in tr.notes)
    law = tr.static
    # one term: with a ZOH alignment a spurious -0.1*vel (a half-sample shift) came with it
    assert law.npar == 1, law.formula
    k, h = _k3(tr)
    # 1 %: far wider than the Monte Carlo spread (0.035) and bias (0.08) measured below
    np.testing.assert_allclose(k, -K3, rtol=0.01)
    assert 0 < h < 0.01 * K3
    assert "d[j+2]" in " ".join(tr.notes)  # the weights are reported


def test_filter_instead_of_smoother_and_bad_smooth_flag():
    nom, ch, c = _case(1, n=1500)
    tr = trace_channel(nom, ch, c.y, c.u, Q=c.Q, R=c.R, dt=DT, max_order=0, smooth=False)
    assert tr.relative_degree == 2 and not tr.law_estimate.smoothed
    np.testing.assert_allclose(_k3(tr)[0], -K3, rtol=0.01)  # as above
    with pytest.raises(DataError, match="smooth must be"):
        trace_channel(nom, ch, c.y, c.u, Q=c.Q, R=c.R, dt=DT, smooth="yes")


@pytest.fixture(scope="module")
def monte_carlo():
    """(k, half-width) of pos^3 on 20 records (seeds 100-119, 2000 samples): the spread
    test and the coverage limit ask the very same traces, so they share one run."""
    ks, hs = [], []
    for seed in range(20):
        nom, ch, c = _case(100 + seed, n=2000)
        k, h = _k3(trace_channel(nom, ch, c.y, c.u, Q=c.Q, R=c.R, dt=DT, max_order=0))
        ks.append(k)
        hs.append(h)
    return np.array(ks), np.array(hs)


@pytest.mark.slow
def test_cubic_coefficient_monte_carlo_spread_and_interval_width(monte_carlo):
    """20 records: the 95 % half-width matches the Monte Carlo spread; the bias is small."""
    ks, hs = monte_carlo
    sd = ks.std(ddof=1)
    # the HAC interval of the GLS fit describes the spread: half-width / 1.96 within
    # [0.6, 1.7] x the Monte Carlo sd (20 draws: the sd itself is known to +-32 % at 95 %)
    assert 0.6 < np.mean(hs) / 1.96 / sd < 1.7, (np.mean(hs), sd)
    # bias: measured -0.08 (0.3 %, ~2 sd here) from the correlation of the x^ and d^
    # errors (errors in variables; see test_cubic_interval_coverage_limit); 1 % bounds it
    assert abs(ks.mean() + K3) < 0.01 * K3, ks.mean()


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="known limit: the d^ regression of a nonlinear law is "
                   "biased by ~0.3 % (x^ and d^ estimation errors are correlated), which the "
                   "interval does not cover when the noise is this small; coverage 0.80 "
                   "measured 2026-11-28 (~45 % when first written)")
def test_cubic_interval_coverage_limit(monte_carlo):
    ks, hs = monte_carlo
    cover = [abs(k + K3) <= h for k, h in zip(ks, hs)]
    assert np.mean(cover) >= 0.85


def test_input_weights_zoh_and_first_order_hold():
    dt = 1e-3
    mass = gb.named_ss([[1, dt], [0, 1]], [[0, dt**2 / 2], [0, dt]], [[1, 0]], [[0, 0]], dt,
                       states=["p", "v"], inputs=["u", "F"], outputs=["p"])
    w, mis = gb.input_weights(mass, unknown="F", r=2)
    # exact: a held force seen through positions only: d^[j] ~ (d[j] + d[j+1]) / 2
    np.testing.assert_allclose(w[:, 0, 0], [0.5, 0.5], atol=1e-12)
    assert mis < 1e-12
    w, mis = gb.input_weights(mass, unknown="F", r=2, continuous=([[0, 1], [0, 0]], [[0], [1]]))
    # exact: a continuous force, linear between samples: the cubic B-spline weights
    np.testing.assert_allclose(w[:, 0, 0], [1 / 6, 2 / 3, 1 / 6], atol=1e-9)
    w1, _ = gb.input_weights(mass, unknown="F", r=1)
    np.testing.assert_array_equal(w1, [[[1.0]]])
    with pytest.raises(DimensionError, match="continuous: A of shape"):
        gb.input_weights(mass, unknown="F", r=2, continuous=(np.eye(3), [[0], [1]]))
    # the force drives a second, unmeasured mass only: no delay makes it visible
    two = gb.named_ss(np.eye(4), np.c_[np.zeros((4, 1)), [0, 0, 0, dt]], [[1, 0, 0, 0]],
                      [[0, 0]], dt, states=["p1", "v1", "p2", "v2"], inputs=["u", "F"],
                      outputs=["p1"])
    with pytest.raises(RankConditionError, match="not observable with relative degree 2"):
        gb.input_weights(two, unknown="F", r=2)
