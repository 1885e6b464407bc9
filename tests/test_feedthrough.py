"""Tests of the unknown-input filter with direct feedthrough (sensor-side errors).

Oracles:

* Monte Carlo truth from the model with fixed seeds (bias, 95 % coverage,
  NEES of x^[k|k]);
* reduction: with G = 0 and H = e_i (an error on sensor i only) the states
  are those of the Kalman filter without output i, and
  d^[k] = y_i[k] - C_i x^[k|k] - D_i u[k] (R diagonal);
* the time-varying recursion for the constant-gain fast path.
"""

from __future__ import annotations

import control as ct
import numpy as np
import pytest
from scipy.stats import chi2, norm
from test_uikf import _simulate_runs

import greybox as gb
from greybox import DimensionError, RankConditionError

ALPHA = 1e-3
Z_CRIT = norm.ppf(1 - ALPHA / 2)
DT = 0.01


def _msd():
    """Mass-spring-damper (p, v), force u known; position and velocity measured."""
    Ac = np.array([[0.0, 1.0], [-40.0, -2.0]])
    sysd = ct.c2d(ct.ss(Ac, [[0.0], [1.0]], np.eye(2), 0), DT)
    return np.asarray(sysd.A), np.asarray(sysd.B)


def _sensor_plant():
    """Offset/gain error on the position sensor: H = e_0, G = 0."""
    A, B = _msd()
    return gb.named_ss(A, np.hstack([B, np.zeros((2, 1))]), np.eye(2),
                       [[0.0, 1.0], [0.0, 0.0]], DT, states=["p", "v"],
                       inputs=["u", "s"], outputs=["p_meas", "v_meas"])


Q = np.diag([1e-8, 1e-6])
R = np.diag([1e-6, 1e-4])
X0 = np.array([0.01, 0.0])
P0 = np.diag([1e-4, 1e-3])


def test_sensor_offset_and_gain_unbiased_and_covered(rng):
    """y_p = (1 + g) p + c + v: d = g p + c on output 0; the state model is right."""
    sys = _sensor_plant()
    A, B = _msd()
    nruns, N = 300, 120
    u = np.sin(np.arange(N) * DT * 7.0)[None, :]
    g, c = 0.2, 0.05
    # simulate the states with no unknown input, then add the sensor error to y_p
    x, y, _ = _simulate_runs(A, B, np.eye(2), np.zeros((2, 1)), np.zeros((2, 0)), Q, R, X0,
                             P0, u, lambda k, xx: np.zeros((0, xx.shape[1])), nruns, rng)
    d = g * x[:, 0, :] + c
    y[:, 0, :] += d
    err = np.empty((nruns, N))
    var = np.empty((nruns, N))
    nees = np.empty((nruns, N))
    for i in range(nruns):
        res = gb.feedthrough_uikf(sys, y[i], u, unknown="s", Q=Q, R=R, x0=X0, P0=P0,
                                  gain="time-varying", store_covariances=True)
        assert res.relative_degree == 0 and not np.any(np.isnan(res.d_est))
        err[i] = res.d_est[0] - d[i]
        var[i] = res.d_var[0]
        ex = res.x_filt - x[i]
        nees[i] = np.einsum("ik,ijk,jk->k", ex, np.linalg.inv(res.P_filt_history.T).T, ex)
    z = err.mean(axis=0) / (err.std(axis=0, ddof=1) / np.sqrt(nruns))
    assert np.max(np.abs(z)) < Z_CRIT + 0.6  # max of 120 |z| values
    cover = np.mean(np.abs(err) <= norm.ppf(0.975) * np.sqrt(var))
    assert 0.93 <= cover <= 0.97, cover
    # NEES averaged over runs: chi2(2 nruns) / nruns bounds at every sample, ALPHA two-sided
    lo, hi = chi2.ppf([ALPHA / 2, 1 - ALPHA / 2], 2 * nruns) / nruns
    m = nees.mean(axis=0)
    assert np.mean((m >= lo) & (m <= hi)) > 0.97  # allow ~ALPHA * 120 exceedances


def test_reduction_to_kalman_filter_without_the_sensor(rng):
    sys = _sensor_plant()
    A, B = _msd()
    N = 300
    u = rng.standard_normal((1, N))
    y = rng.standard_normal((2, N)) * 0.01
    res = gb.feedthrough_uikf(sys, y, u, unknown="s", Q=Q, R=R, x0=X0, P0=P0)
    kf_sys = gb.named_ss(A, B, [[0.0, 1.0]], [[0.0]], DT, states=["p", "v"], inputs=["u"],
                         outputs=["v_meas"])
    # the KF's k = 0 step updates the prior; so does the feedthrough filter
    kf = gb.kalman_filter(kf_sys, y[1:], u, Q=Q, R=R[1:, 1:], x0=X0, P0=P0)
    # same estimator through different algebra (gains from a 2x2 vs a 1x1 solve):
    # agreement to round-off of the state scale
    np.testing.assert_allclose(res.x_filt, kf.x_filt, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res.d_est[0], y[0] - res.x_filt[0], rtol=1e-9, atol=1e-12)


def test_state_and_output_channel_random_system(random_system, rng):
    """d drives the states (G) and the outputs (H): unbiased d^, variance as predicted."""
    rs = random_system(rng, n=3, m=1, p=3, md=1)
    H = rng.standard_normal((3, 1))
    sys = gb.named_ss(rs.A, np.hstack([rs.B, rs.G]), rs.C, np.hstack([rs.D, H]), rs.dt,
                      states=["a", "b", "c"], inputs=["u", "d"], outputs=["y0", "y1", "y2"])
    nruns, N = 300, 40
    u = rng.standard_normal((1, N))
    x0, P0 = np.zeros(3), np.eye(3)
    x, y, d = _simulate_runs(rs.A, rs.B, rs.C, rs.D, rs.G, rs.Q, rs.R, x0, P0, u,
                             lambda k, xx: 2.0 + np.sin(0.4 * k) + 0.5 * xx[:1], nruns, rng)
    y = y + H[None, :, :] * d  # the feedthrough part of the truth
    err = np.empty((nruns, N))
    var = np.empty((nruns, N))
    for i in range(nruns):
        res = gb.feedthrough_uikf(sys, y[i], u, unknown="d", Q=rs.Q, R=rs.R)
        err[i], var[i] = res.d_est[0] - d[i, 0], res.d_var[0]
    z = err.mean(axis=0) / (err.std(axis=0, ddof=1) / np.sqrt(nruns))
    assert np.max(np.abs(z)) < Z_CRIT + 0.5
    cover = np.mean(np.abs(err) <= norm.ppf(0.975) * np.sqrt(var))
    assert 0.93 <= cover <= 0.97, cover


def test_rectifying_sensor_is_recovered_as_an_output_law(rng):
    """y_p = |p| + v with a correct state model: d^ on the output channel follows |p| - p."""
    sys = _sensor_plant()
    A, B = _msd()
    N = 3000
    u = 20.0 * np.sin(np.arange(N) * DT * 3.0)[None, :]
    x, y, _ = _simulate_runs(A, B, np.eye(2), np.zeros((2, 1)), np.zeros((2, 0)), Q, R, X0,
                             P0, u, lambda k, xx: np.zeros((0, xx.shape[1])), 1, rng)
    y = y[0]
    y[0] += np.abs(x[0, 0]) - x[0, 0]
    res = gb.feedthrough_uikf(sys, y, u, unknown="s", Q=Q, R=R, x0=X0, P0=P0)
    p_hat = res.x_filt[0]
    coef = np.linalg.lstsq((np.abs(p_hat) - p_hat)[:, None], res.d_est[0], rcond=None)[0]
    # least-squares slope on 3000 samples with ~1e-3 noise on a ~0.4 m swing: within 2 %
    np.testing.assert_allclose(coef, [1.0], rtol=0.02)


def test_fast_path_equals_time_varying(rng):
    sys = _sensor_plant()
    N = 2000
    u = rng.standard_normal((1, N))
    y = rng.standard_normal((2, N)) * 0.01
    a = gb.feedthrough_uikf(sys, y, u, unknown="s", Q=Q, R=R)
    b = gb.feedthrough_uikf(sys, y, u, unknown="s", Q=Q, R=R, gain="time-varying")
    assert a.period_converged is not None and a.converged and b.converged
    # recursions agree to the round-off accumulated over N steps: atol 1e-11 is ~1e-9 of
    # the signal scale (~0.02), rtol 1e-9 for samples away from zero crossings
    np.testing.assert_allclose(a.x_filt, b.x_filt, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(a.d_est, b.d_est, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(a.innovations, b.innovations, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(a.d_var, b.d_var, rtol=1e-9)


def test_errors():
    sys = _sensor_plant()
    y, u = np.zeros((2, 5)), np.zeros((1, 5))
    nofeed = gb.named_ss(np.eye(2) * 0.5, np.eye(2), np.eye(2), np.zeros((2, 2)), DT,
                         states=["a", "b"], inputs=["u", "d"], outputs=["y0", "y1"])
    with pytest.raises(RankConditionError, match=r"rank\(H\) < md = 1.*Use uikf"):
        gb.feedthrough_uikf(nofeed, y, u, unknown="d", Q=Q, R=R)
    two = gb.named_ss(np.eye(2) * 0.5, np.hstack([np.eye(2), np.zeros((2, 2))]), np.eye(2),
                      [[0, 0, 1.0, 2.0], [0, 0, 1.0, 2.0]], DT, states=["a", "b"],
                      inputs=["u0", "u1", "d0", "d1"], outputs=["y0", "y1"])
    with pytest.raises(RankConditionError, match=r"rank\(H\) < md = 2"):
        gb.feedthrough_uikf(two, y, np.zeros((2, 5)), unknown=["d0", "d1"], Q=Q, R=R)
    with pytest.raises(DimensionError, match="gain must be"):
        gb.feedthrough_uikf(sys, y, u, unknown="s", Q=Q, R=R, gain="steady")
    with pytest.raises(DimensionError, match="y"):
        gb.feedthrough_uikf(sys, np.zeros((3, 5)), u, unknown="s", Q=Q, R=R)


def test_with_sensor_error_builds_the_output_channel(rng):
    A, B = _msd()
    base = gb.named_ss(A, B, np.eye(2), np.zeros((2, 1)), DT, states=["p", "v"],
                       inputs=["u"], outputs=["p_meas", "v_meas"])
    aug = gb.with_sensor_error(base, "p_meas")
    assert aug.input_labels == ["u", "p_meas_err"]
    np.testing.assert_array_equal(np.asarray(aug.D)[:, 1], [1.0, 0.0])
    np.testing.assert_array_equal(np.asarray(aug.B)[:, 1], [0.0, 0.0])
    N = 200
    u, y = rng.standard_normal((1, N)), rng.standard_normal((2, N)) * 0.01
    a = gb.feedthrough_uikf(aug, y, u, unknown="p_meas_err", Q=Q, R=R)
    b = gb.feedthrough_uikf(_sensor_plant(), y, u, unknown="s", Q=Q, R=R)
    np.testing.assert_array_equal(a.d_est, b.d_est)  # the same model, built two ways
    with pytest.raises(DimensionError, match="no signal named 'q'"):
        gb.with_sensor_error(base, "q")
    with pytest.raises(DimensionError, match="already inputs"):
        gb.with_sensor_error(base, "p_meas", names=["u"])
    with pytest.raises(DimensionError, match="expected 1"):
        gb.with_sensor_error(base, "p_meas", names=["a", "b"])
