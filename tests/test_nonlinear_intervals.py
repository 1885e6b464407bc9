"""Calibration of the nonlinear pipeline's output-error intervals (issue 12, item b).

The law's coefficients refined by output error (``workflow_nonlinear._refine_law_oe``)
get the larger of two variances: the autocorrelation-robust (HAC) one and the sandwich
under the noise model (Q, R) along the fitted simulation. With HAC alone the cubic
drag's 95 % intervals on the pendulum of ``tests/test_workflow_nonlinear.py`` were too
narrow: over seeds 0-19 the RMS error over the stated standard error was 1.45 (17/20
covered, sum of squared standardized errors 37.4 against the chi-square(20) 95 %
quantile 31.4); with the noise model's sandwich 0.94 (19/20, 17.5)
(``python bench/nonlinear_coverage.py pendulum``).
"""

from __future__ import annotations

import control as ct
import numpy as np
import pytest
from scipy.stats import chi2

import greybox as gb
from greybox.workflow_nonlinear import _state_jacobians
from test_workflow_nonlinear import C3, DT, QD, RM, pendulum, record


@pytest.mark.slow
def test_cubic_drag_intervals_are_calibrated_over_seeds():
    """Sum over seeds of ((estimate - truth) / standard error)^2 ~ chi-square(seeds).

    Seeds 0-7 (fixed): HAC alone gave 19.5 > 15.5 (the 95 % quantile), so this failed
    before; with the noise model's sandwich 8.3 (measured again 2026-11-28 on the code of
    then: 9.86, HAC alone 20.56). The truth -0.5 is the plant's own drag
    (no tolerance to choose: the interval is what is tested).
    """
    z = []
    for seed in range(8):
        est = record(3000, seed, process_noise=True)
        val = record(2000, seed + 100, process_noise=False)
        rep = gb.close_the_loop(pendulum(), est.y, est.u, val.y, val.u, Q=QD, R=RM, dt=DT)
        assert rep.updated and rep.effect.equations == ("omega",), rep.message
        law = rep.effect.law
        j = [s[0] for s in law.spec].index("omega^3")
        assert np.isfinite(law.ci[0, j]), law.formula
        z.append((law.coef[0, j] + C3) / (law.ci[0, j] / 1.96))
    stat = float(np.sum(np.square(z)))
    assert stat < chi2.ppf(0.95, len(z)), np.round(z, 2)
    # and not absurdly wide: above the chi-square's 1 % quantile (1.65 for 8)
    assert stat > chi2.ppf(0.01, len(z)), np.round(z, 2)


def test_state_jacobians_match_the_analytic_ones_batched_or_not():
    """The trajectory's dF/dx, from a batch-capable model and from a one-state-only one."""
    disc = gb.discretize_nonlinear(pendulum(C3), DT, substeps=1)
    rng = np.random.default_rng(3)
    x = rng.uniform(-1.5, 1.5, (2, 40))
    u = rng.uniform(-2, 2, (1, 40))

    def scalar_only(t, xk, uk, p):  # a MODEL.py written for one state at a time
        return np.asarray(disc.updfcn(t, np.array([float(xk[0]), float(xk[1])]),
                                      np.array([float(uk[0])]), p))

    one = ct.nlsys(scalar_only, None, states=2, inputs=1, outputs=2, dt=DT)
    A = _state_jacobians(disc, x, u)
    A1 = _state_jacobians(one, x, u)
    assert A.shape == (40, 2, 2)
    # the same numbers either way (the same central differences)
    np.testing.assert_allclose(A1, A, rtol=1e-9, atol=1e-12)
    # oracle: an independent RK4 step of the pendulum differentiated by complex step
    # (exact to rounding); the central differences' error is ~h^2 |F'''| + eps/h ~ 1e-9
    def f(xx, uu):
        return np.array([xx[1], -9.81 * np.sin(xx[0]) - 0.2 * xx[1] + uu - C3 * xx[1] ** 3])

    def rk4(xx, uu):
        k1 = f(xx, uu)
        k2 = f(xx + DT / 2 * k1, uu)
        k3 = f(xx + DT / 2 * k2, uu)
        k4 = f(xx + DT * k3, uu)
        return xx + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    for t in (0, 17, 39):
        want = np.empty((2, 2))
        for i in range(2):
            xc = x[:, t].astype(complex)
            xc[i] += 1e-30j
            want[:, i] = rk4(xc, u[0, t]).imag / 1e-30
        np.testing.assert_allclose(A[t], want, atol=1e-7)
