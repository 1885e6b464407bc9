"""One-step prediction error of a model with a nonlinear static law (issue 12, drives).

The validation table's PE of an updated model with a nonlinear law comes from
:func:`greybox.trace.ekf_predict_with_law`, an extended Kalman filter whose
gain follows the law's local slope. Before, a constant gain designed on the
law's linear stand-in was used: for a rectifying sensor (|.|) the stand-in's
slope has the wrong sign for half of the samples, the predictor diverged and
the report printed a PE of ~1e28 %.
"""

from __future__ import annotations

import numpy as np
import pytest

import greybox as gb
from greybox.system import named_ss
from greybox.trace import (
    StaticLaw,
    ekf_predict_with_law,
    law_terms,
    output_terms,
    predict_with_law,
)
from greybox.validate import ModelValidation, undefined_error
from greybox.metrics import WhitenessTest

DT = 0.05


@pytest.fixture
def rng():
    return np.random.default_rng(12)


def oscillator():
    """Discrete lightly damped oscillator, position measured (states p, v)."""
    sc = named_ss([[0.0, 1.0], [-4.0, -0.4]], [[0.0], [1.0]], [[1.0, 0.0]], [[0.0]], 0,
                  states=["p", "v"], inputs=["F"], outputs=["p"])
    return gb.discretize(sc, DT)


def make_law(spec, eps, coef, output=None):
    coef = np.atleast_2d(np.asarray(coef, dtype=float))
    return StaticLaw(spec=tuple(spec), eps=eps, coef=coef, Ddx=np.zeros((1, 2)),
                     Ddu=np.zeros((1, 1)), nonlinear=True, residual_var=np.zeros(1),
                     bic_gain=0.0, npar=int(np.count_nonzero(coef)), formula="",
                     output=output)


def test_ekf_predictor_of_a_linear_law_is_the_time_varying_kalman_filter(rng):
    """Reduction: a law linear in x is a linear model; the EKF is then the KF."""
    nd = oscillator()
    A, B, C, D = (np.asarray(m) for m in (nd.A, nd.B, nd.C, nd.D))
    G = np.array([[0.0], [DT]])
    _, spec, eps = law_terms(rng.standard_normal((2, 20)), rng.standard_normal((1, 20)),
                             ["p", "v"], ["F"])
    names = [s[0] for s in spec]
    coef = np.zeros((1, len(spec)))
    coef[0, names.index("p")], coef[0, names.index("v")] = -2.0, -0.5
    law = make_law(spec, eps, coef)
    Ab = A + G @ coef[:, :2]
    u = rng.standard_normal((1, 400))
    Q, R = np.diag([1e-8, 1e-5]), np.array([[1e-4]])
    x, y = np.zeros(2), np.empty((1, 400))
    for k in range(400):
        y[:, k] = C @ x + 1e-2 * rng.standard_normal(1)
        x = Ab @ x + B[:, 0] * u[0, k] + rng.multivariate_normal(np.zeros(2), Q)
    x0, P0 = np.array([0.01, 0.0]), 0.1 * np.eye(2)
    yp = ekf_predict_with_law(nd, G, law, y, u, x0, Q=Q, R=R, P0=P0)
    lin = named_ss(Ab, B, C, D, DT, states=["p", "v"], inputs=["F"], outputs=["p"])
    kf = gb.kalman_filter(lin, y, u, Q=Q, R=R, x0=x0, P0=P0, gain="time-varying")
    # the EKF's slopes are forward differences of a linear map: exact up to round-off
    # relative to the step (~1e-16 / 1e-7); 1e-6 of the output's scale covers it
    np.testing.assert_allclose(yp, kf.y_pred, rtol=0, atol=1e-6 * np.abs(y).max())


def rectifier_data(rng, N=2000):
    """Oscillator driven by noise; the sensor reads |p| (a rectifier) plus white noise."""
    nd = oscillator()
    A, B = np.asarray(nd.A), np.asarray(nd.B)
    u = gb.lowpass_noise(N, dt=DT, bandwidth=1.0, amplitude=3.0, rng=rng)
    x, p = np.zeros(2), np.empty(N)
    for k in range(N):
        p[k] = x[0]
        x = A @ x + B[:, 0] * u[0, k]
    sigma = 0.02 * np.std(p)
    y = np.abs(p)[None] + sigma * rng.standard_normal((1, N))
    return nd, u, y, p, sigma


def test_ekf_predictor_of_a_rectifying_sensor_stays_at_the_noise_floor(rng):
    """A |.| sensor law: the EKF predicts at the noise level; the stand-in's constant gain
    diverges (the drives' PE of ~1e28 %)."""
    nd, u, y, p, sigma = rectifier_data(rng)
    C, D = np.asarray(nd.C), np.asarray(nd.D)
    x = np.zeros((2, y.shape[1]))
    terms, spec, eps = output_terms(x + 1.0, u, C[0], D[0], "p")
    names = [s[0] for s in spec]
    coef = np.zeros((1, len(spec)))
    coef[0, names.index("p_model")], coef[0, names.index("|p_model|")] = -1.0, 1.0  # |p| - p
    law = make_law(spec, eps, coef, output=0)
    G = np.zeros((2, 1))
    # Q = R I: process noise of the sensor noise's order, tutorial 08's rule for the drives
    Q, R = sigma**2 * np.eye(2), np.array([[sigma**2]])
    x0 = np.zeros(2)
    yp = ekf_predict_with_law(nd, G, law, y, u, x0, Q=Q, R=R)
    e = (y - yp)[0, 50:]
    # the true model: the innovations are the sensor noise plus the state uncertainty the
    # overstated Q keeps (measured 1.22 sigma; 1.0 with Q ~ 0); [0.9, 1.5] sigma: a
    # predictor that loses the sign of p is off by ~|p| ~ 50 sigma
    rms = float(np.sqrt(np.mean(e**2)))
    assert 0.9 * sigma < rms < 1.5 * sigma, (rms, sigma)
    # the old predictor: a constant gain designed on a linear stand-in (here the nominal
    # sensor, slope +1); the true slope is -1 whenever p < 0, the correction then has the
    # wrong sign and the predictor diverges (measured: to 1e100 and NaN)
    K = gb.kalman_filter(nd, y, u, Q=Q, R=R).K
    yc = predict_with_law(nd, G, law, y, u, K, x0)
    ec = (y - yc)[0, 50:]
    assert not np.all(np.isfinite(ec)) or np.sqrt(np.mean(ec**2)) > 10 * rms, \
        (np.sqrt(np.mean(ec**2)), rms)


def test_validation_row_with_an_undefined_pe_says_why():
    """A diverged predictor: PE NaN, ``pe_defined`` False, JSON null with the reason."""
    nan = np.full(1, np.nan)
    v = ModelValidation(name="updated", order=2, se=gb.relative_error([[1.0, 2.0]], [[1.0, 2.1]]),
                        pe=undefined_error(1),
                        whiteness=WhitenessTest(statistic=nan, pvalue=nan, lags=5, alpha=1e-3,
                                                white=np.zeros(1, bool)),
                        autocorr=np.full((1, 6), np.nan), crosscorr=np.zeros((0, 1, 11)),
                        band=0.1, y_sim=np.ones((1, 2)), y_pred=np.full((1, 2), np.nan),
                        residuals=np.full((1, 2), np.nan),
                        pe_reason="the one-step predictor (extended Kalman filter) diverged")
    assert not v.pe_defined and v.se_defined
    d = v.as_dict()
    assert d["pe"] is None and d["pe_per_output"] is None and "diverged" in d["pe_reason"]


def test_ekf_predictor_stops_where_the_innovation_covariance_is_singular(rng):
    """A filter whose innovation covariance S = H P H' + R becomes singular has diverged:
    the predictions are NaN from that sample on (the docstring's contract), where before
    ``numpy.linalg.solve`` raised out of the validation of an updated model (zoo
    cubic_force 1176755609 #1 ended in a traceback). Built here with P0 = 0 and R = 0:
    S = 0 at the first sample."""
    nd = oscillator()
    _, spec, eps = law_terms(rng.standard_normal((2, 20)), rng.standard_normal((1, 20)),
                             ["p", "v"], ["F"])
    coef = np.zeros((1, len(spec)))
    coef[0, [s[0] for s in spec].index("p")] = -1.0
    law = make_law(spec, eps, coef)
    y, u = rng.standard_normal((1, 50)), rng.standard_normal((1, 50))
    yp = ekf_predict_with_law(nd, np.array([[0.0], [DT]]), law, y, u, np.zeros(2),
                              Q=np.zeros((2, 2)), R=np.zeros((1, 1)), P0=np.zeros((2, 2)))
    assert yp.shape == (1, 50) and np.isnan(yp).all()
