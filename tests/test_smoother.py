"""Tests of the fixed-interval unknown-input smoother.

Oracles:

* a brute-force batch solution: generalized least squares of (x[0], d[0..N-2])
  from all outputs with the joint covariance of prior, process and
  measurement noise (short horizon), which is the minimum-variance unbiased
  estimate the smoother must reproduce, with its covariance;
* the filter at the last sample (nothing left to smooth);
* Monte Carlo truth (bias, coverage, error variance below the filter's);
* the time-varying recursion for the constant-gain fast path.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm
from test_delayed import DT, P0 as MP0, Q as MQ, R as MR, X0 as MX0, ZOH_G, _mass, _runs
from conftest import make_random_system
from test_feedthrough import P0 as SP0, Q as SQ, R as SR, X0 as SX0, _msd, _sensor_plant
from test_uikf import _simulate_runs

import greybox as gb
from greybox import CovarianceError

ALPHA = 1e-3
Z_CRIT = norm.ppf(1 - ALPHA / 2)


def _gls(A, B, C, D, G, Q, R, x0, P0, y, u, H=None):
    """Batch GLS of theta = (x[0], d[0..N-2]) (d[0..N-1] with feedthrough H); (theta, cov)."""
    n, md = G.shape
    p, N = y.shape
    nd = N if H is not None else N - 1
    nth = n + md * nd
    Phi = np.zeros((p * N, nth))
    Cw = np.zeros((p * N, n * (N - 1)))
    off = np.zeros(p * N)
    for k in range(N):
        rows = slice(p * k, p * k + p)
        Phi[rows, :n] = C @ np.linalg.matrix_power(A, k)
        off[rows] = D @ u[:, k]
        for j in range(k):
            Mj = C @ np.linalg.matrix_power(A, k - 1 - j)
            Phi[rows, n + md * j:n + md * j + md] = Mj @ G
            Cw[rows, n * j:n * j + n] = Mj
            off[rows] += Mj @ B @ u[:, j]
        if H is not None:
            Phi[rows, n + md * k:n + md * k + md] = H
    Sig = Cw @ np.kron(np.eye(N - 1), Q) @ Cw.T + np.kron(np.eye(N), R)
    Z = np.concatenate([y.T.ravel() - off, x0])
    Ph = np.vstack([Phi, np.hstack([np.eye(n), np.zeros((n, nth - n))])])
    S = np.zeros((p * N + n, p * N + n))
    S[:p * N, :p * N], S[p * N:, p * N:] = Sig, P0
    Si = np.linalg.inv(S)
    cov = np.linalg.inv(Ph.T @ Si @ Ph)
    return cov @ (Ph.T @ Si @ Z), cov


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_equals_batch_generalized_least_squares(random_system, seed):
    rng = np.random.default_rng(seed)
    rs = random_system(rng, n=3, m=1, p=2, md=1)
    Q = rs.Q + 1e-3 * np.eye(3)
    N = 12
    u = rng.standard_normal((1, N))
    y = rng.standard_normal((2, N))
    x0, P0 = rng.standard_normal(3), np.eye(3) * 0.5
    res = gb.smooth_uikf(rs.sys, y, u, unknown=rs.unknown, Q=Q, R=rs.R, x0=x0, P0=P0)
    theta, cov = _gls(rs.A, rs.B, rs.C, rs.D, rs.G, Q, rs.R, x0, P0, y, u)
    assert res.smoothed
    # both are the same linear estimator; difference is round-off of a 39x39 solve (~1e-13)
    np.testing.assert_allclose(res.d_est[0, :N - 1], theta[3:], rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(res.d_var[0, :N - 1], np.diag(cov)[3:], rtol=1e-9)
    np.testing.assert_allclose(res.x_filt[:, 0], theta[:3], rtol=1e-9, atol=1e-10)
    assert np.isnan(res.d_est[0, -1])


def test_feedthrough_equals_batch_generalized_least_squares(random_system):
    """y = C x + D u + H d + v with d also in the states: smoother = batch GLS."""
    rng = np.random.default_rng(7)
    rs = random_system(rng, n=3, m=1, p=3, md=1)
    H = rng.standard_normal((3, 1))
    sys = gb.named_ss(rs.A, np.hstack([rs.B, rs.G]), rs.C, np.hstack([rs.D, H]), rs.dt,
                      states=["a", "b", "c"], inputs=["u", "d"], outputs=["y0", "y1", "y2"])
    Q = rs.Q + 1e-3 * np.eye(3)
    N = 10
    u, y = rng.standard_normal((1, N)), rng.standard_normal((3, N))
    x0, P0 = rng.standard_normal(3), np.eye(3) * 0.5
    res = gb.smooth_uikf(sys, y, u, unknown="d", Q=Q, R=rs.R, x0=x0, P0=P0,
                         relative_degree="auto")
    theta, cov = _gls(rs.A, rs.B, rs.C, rs.D, rs.G, Q, rs.R, x0, P0, y, u, H=H)
    assert res.smoothed and res.relative_degree == 0
    # same linear estimator; round-off of a 13x13 information solve
    np.testing.assert_allclose(res.d_est[0], theta[3:], rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(res.d_var[0], np.diag(cov)[3:], rtol=1e-9)
    np.testing.assert_allclose(res.x_filt[:, 0], theta[:3], rtol=1e-9, atol=1e-10)
    f = gb.uikf(sys, y, u, unknown="d", Q=Q, R=rs.R, x0=x0, P0=P0, relative_degree="auto")
    assert f.relative_degree == 0  # "auto" sends a feedthrough model to feedthrough_uikf
    np.testing.assert_allclose(res.d_est[0, -1], f.d_est[0, -1], rtol=1e-10)


def test_smoothed_sensor_error(rng):
    """Sensor offset + gain on the position (H = e_0, G = 0): smoothing helps a lot."""
    sys = _sensor_plant()
    A, B = _msd()
    nruns, N = 300, 80
    u = np.sin(np.arange(N) * 0.07)[None, :]
    x, y, _ = _simulate_runs(A, B, np.eye(2), np.zeros((2, 1)), np.zeros((2, 0)), SQ, SR,
                             SX0, SP0, u, lambda k, xx: np.zeros((0, xx.shape[1])), nruns, rng)
    d = 0.2 * x[:, 0, :] + 0.05
    y[:, 0, :] += d
    kchk = np.arange(2, N)
    kw = dict(unknown="s", Q=SQ, R=SR, x0=SX0, P0=SP0)
    ef, es, vs = [], [], []
    for i in range(nruns):
        ef.append(gb.feedthrough_uikf(sys, y[i], u, **kw).d_est[0, kchk] - d[i, kchk])
        s = gb.smooth_uikf(sys, y[i], u, relative_degree=0, **kw)
        es.append(s.d_est[0, kchk] - d[i, kchk])
        vs.append(s.d_var[0, kchk])
    ef, es, vs = np.array(ef), np.array(es), np.array(vs)
    _check_unbiased_covered(es, vs)
    ratio = ef.var(axis=0).mean() / es.var(axis=0).mean()
    assert ratio > 1.5, ratio


def test_feedthrough_fast_path_equals_time_varying(rng):
    sys = _sensor_plant()
    N = 2000
    u, y = rng.standard_normal((1, N)), rng.standard_normal((2, N)) * 0.01
    kw = dict(unknown="s", Q=SQ, R=SR, relative_degree=0, store_covariances=True)
    a = gb.smooth_uikf(sys, y, u, **kw)
    b = gb.smooth_uikf(sys, y, u, gain="time-varying", **kw)
    assert a.period_converged is not None
    # same recursions; round-off over N steps relative to the ~1e-2 signal scale
    np.testing.assert_allclose(a.x_filt, b.x_filt, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(a.d_est, b.d_est, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(a.d_var, b.d_var, rtol=1e-8)
    # covariances ~5e-7: atol 1e-15 is 2e-9 of the largest entry (off-diagonals cross zero)
    np.testing.assert_allclose(a.P_filt_history, b.P_filt_history, rtol=1e-8, atol=1e-15)


def test_last_sample_equals_filter(random_system, rng):
    rs = random_system(rng)
    N = 50
    u, y = rng.standard_normal((1, N)), rng.standard_normal((2, N))
    f = gb.uikf(rs.sys, y, u, unknown=rs.unknown, Q=rs.Q, R=rs.R)
    s = gb.smooth_uikf(rs.sys, y, u, unknown=rs.unknown, Q=rs.Q, R=rs.R)
    # d^[N-2|N-1] is the filter's own estimate (same data): round-off only
    np.testing.assert_allclose(s.d_est[:, N - 2], f.d_est[:, N - 2], rtol=1e-10)
    np.testing.assert_allclose(s.d_var[:, N - 2], f.d_var[:, N - 2], rtol=1e-10)
    np.testing.assert_allclose(s.x_filt[:, -1], f.x_filt[:, -1], rtol=1e-12)
    np.testing.assert_array_equal(s.innovations, f.innovations)  # forward pass kept
    assert np.all(s.d_var[:, :N - 2] <= f.d_var[:, :N - 2] * (1 + 1e-12))


def _mc(sys, y, u, nruns, target, kchk, **kw):
    ef, es, vs = [], [], []
    for i in range(nruns):
        f = gb.uikf(sys, y[i], u, **kw)
        s = gb.smooth_uikf(sys, y[i], u, **kw)
        ef.append(f.d_est[0, kchk] - target[i, kchk])
        es.append(s.d_est[0, kchk] - target[i, kchk])
        vs.append(s.d_var[0, kchk])
    return np.array(ef), np.array(es), np.array(vs)


def _check_unbiased_covered(es, vs):
    nruns = es.shape[0]
    z = es.mean(axis=0) / (es.std(axis=0, ddof=1) / np.sqrt(nruns))
    assert np.max(np.abs(z)) < Z_CRIT + 0.5  # the max of ~60-70 |z| values
    cover = np.mean(np.abs(es) <= norm.ppf(0.975) * np.sqrt(vs))
    assert 0.93 <= cover <= 0.97, cover


def test_smoothed_d_beats_filter_on_partly_measured_system():
    """4 states, 2 outputs: later outputs pin the state, so d^[k|N] is far less noisy."""
    rng = np.random.default_rng(0)
    rs = make_random_system(rng, n=4, p=2, md=1)
    Q = rs.Q * 1e-2 + 1e-6 * np.eye(4)
    nruns, N = 300, 70
    u = rng.standard_normal((1, N))
    x0, P0 = np.zeros(4), np.eye(4)
    _, y, d = _simulate_runs(rs.A, rs.B, rs.C, rs.D, rs.G, Q, rs.R, x0, P0, u,
                             lambda k, x: 1.0 + np.sin(0.3 * k) + 0.5 * x[:1], nruns, rng)
    kchk = np.arange(3, N - 3)
    ef, es, vs = _mc(rs.sys, y, u, nruns, d[:, 0, :], kchk, unknown=rs.unknown, Q=Q, R=rs.R,
                     x0=x0, P0=P0)
    _check_unbiased_covered(es, vs)
    ratio = ef.var(axis=0).mean() / es.var(axis=0).mean()
    # steady-state variance ratio of this system is ~36 (filter Pd / smoothed Pd); the
    # record edges (no future at the end) lower the average: require 10
    assert ratio > 10, ratio


def test_smoothed_tape_drive_tension(rng):
    """Tape drive (C = I): unbiased, covered; nothing to gain (each output pins its state)."""
    sys = gb.tape_drive_nominal(dt=1e-4)
    sp = gb.split_inputs(sys, "T")
    A, B, C, D = (np.asarray(M) for M in (sp.sys.A, sp.sys.B, sp.sys.C, sp.sys.D))
    Q, R = gb.TAPE_DRIVE_Q * 1e-2, gb.TAPE_DRIVE_R
    nruns, N = 300, 60
    u = np.ones((2, N))
    x0, P0 = np.zeros(6), np.eye(6) * 1e-4
    _, y, d = _simulate_runs(A, B, C, D, sp.G, Q, R, x0, P0, u,
                             lambda k, x: np.full((1, x.shape[1]), 2.0 + np.sin(0.2 * k)),
                             nruns, rng)
    kchk = np.arange(2, N - 2)
    ef, es, vs = _mc(sys, y, u, nruns, d[:, 0, :], kchk, unknown="T", Q=Q, R=R, x0=x0, P0=P0)
    _check_unbiased_covered(es, vs)
    # the smoother never loses: its variance is the filter's minus a PSD term
    assert es.var(axis=0).mean() <= ef.var(axis=0).mean() * 1.001


def test_smoothed_mass_force_delayed(rng):
    """Mass, positions only (r = 2 under ZOH): unbiased and covered, and equal to the
    delayed filter: a fresh unknown force at every step leaves later outputs no
    information about d[k] beyond y[k+2] (n = 2 = p r)."""
    sys = _mass(ZOH_G)
    nruns = 300
    u, y, d = _runs(ZOH_G, rng, nruns=nruns, nsteps=80)
    target = 0.5 * (d[:, 0, :-1] + d[:, 0, 1:])
    kchk = np.arange(5, 75)
    ef, es, vs = [], [], []
    for i in range(nruns):
        kw = dict(unknown="F", Q=MQ, R=MR, x0=MX0, P0=MP0, relative_degree=2)
        ef.append(gb.delayed_uikf(sys, y[i], u, **kw).d_est[0, kchk] - target[i, kchk])
        s = gb.smooth_uikf(sys, y[i], u, **kw)
        assert s.relative_degree == 2 and s.smoothed
        es.append(s.d_est[0, kchk] - target[i, kchk])
        vs.append(s.d_var[0, kchk])
    ef, es, vs = np.array(ef), np.array(es), np.array(vs)
    _check_unbiased_covered(es, vs)
    # same estimates up to round-off of forces ~1e1 N from mm positions
    np.testing.assert_allclose(es, ef, atol=1e-6)


def test_fast_path_equals_time_varying(random_system, rng):
    rs = random_system(rng, n=4, p=2, md=1)
    N = 3000
    u, y = rng.standard_normal((1, N)), rng.standard_normal((2, N))
    kw = dict(unknown=rs.unknown, Q=rs.Q + 1e-3 * np.eye(4), R=rs.R, store_covariances=True)
    a = gb.smooth_uikf(rs.sys, y, u, **kw)
    b = gb.smooth_uikf(rs.sys, y, u, gain="time-varying", **kw)
    assert a.period_converged is not None and a.period_converged < 200
    # same recursions, forward and backward; round-off of O(N) steps, ~1e-12 relative to
    # the O(1) signals
    np.testing.assert_allclose(a.x_filt, b.x_filt, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(a.d_est, b.d_est, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(a.d_var, b.d_var, rtol=1e-9)
    np.testing.assert_allclose(a.P_filt_history, b.P_filt_history, rtol=1e-8, atol=1e-14)


def test_delayed_fast_path_equals_time_varying(rng):
    sys = _mass(ZOH_G)
    u, y, _ = _runs(ZOH_G, rng, nruns=1, nsteps=500)
    kw = dict(unknown="F", Q=MQ, R=MR, relative_degree=2)
    a = gb.smooth_uikf(sys, y[0], u, **kw)
    b = gb.smooth_uikf(sys, y[0], u, gain="time-varying", **kw)
    # forces ~1e0 N from positions ~1e-2 m at dt = 0.01 s: absolute round-off ~1e-6 N
    np.testing.assert_allclose(a.d_est, b.d_est, atol=1e-6)
    np.testing.assert_allclose(a.x_filt, b.x_filt, rtol=1e-9, atol=1e-12)
    assert DT > 0


def test_singular_prediction_covariance_is_an_error(random_system, rng):
    rs = random_system(rng)
    with pytest.raises(CovarianceError, match="singular.*positive-definite part"):
        gb.smooth_uikf(rs.sys, np.zeros((2, 10)), np.zeros((1, 10)), unknown=rs.unknown,
                       Q=np.zeros((3, 3)), R=rs.R, P0=np.zeros((3, 3)))


def test_smoothing_a_feedthrough_filter_result_equals_smooth_uikf(rng):
    """The sensor channels smooth the forward filter they already ran: the same estimate
    as smooth_uikf running it again (the same arithmetic: exact)."""
    from greybox.filters.smoother import smooth_feedthrough_of

    sys = gb.named_ss([[0.9, 0.1], [0.0, 0.8]], [[1.0, 0.0], [0.5, 0.0]],
                      [[1.0, 0.0], [0.0, 1.0]], [[0.0, 0.0], [0.0, 1.0]], 0.1,
                      states=["x1", "x2"], inputs=["u", "e"], outputs=["y1", "y2"])
    u = rng.standard_normal((1, 400))
    y = rng.standard_normal((2, 400))
    kw = dict(unknown="e", Q=1e-3 * np.eye(2), R=1e-2 * np.eye(2))
    fwd = gb.feedthrough_uikf(sys, y, u, **kw)
    a = smooth_feedthrough_of(fwd, sys, y, u, **kw)
    b = gb.smooth_uikf(sys, y, u, relative_degree=0, **kw)
    np.testing.assert_array_equal(a.x_filt, b.x_filt)
    np.testing.assert_array_equal(a.d_est, b.d_est)
    np.testing.assert_array_equal(a.d_var, b.d_var)
