"""Tests of delayed unknown-input estimation (relative degree r >= 2).

Oracles:

* Monte Carlo truth simulated from the model (fixed seeds), judged with the
  filter's own covariances (bias, 95 % coverage);
* exact identities: with ``C G~ = 0`` the estimate is unbiased for d[k]; for
  a ZOH double integrator it is unbiased for ``(d[k] + d[k+1]) / 2`` (the
  output is the same for both, module docstring of greybox.filters.delayed);
* the r = 1 filter on the same data (variance ratio);
* the time-varying recursion for the constant-gain fast path.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm
from test_uikf import _simulate_runs

import greybox as gb
from greybox import DataError, GreyboxError, ModelError, RankConditionError

ALPHA = 1e-3
Z_CRIT = norm.ppf(1 - ALPHA / 2)
DT = 0.01
MASS = 2.0  # [kg]
RUNS = 300
STEPS = 80


def _mass(G_force):
    """Mass with a known force u and an unknown force F (columns G_force), position measured."""
    A = np.array([[1.0, DT], [0.0, 1.0]])
    Bu = np.array([[DT**2 / 2], [DT]]) / MASS
    return gb.named_ss(A, np.hstack([Bu, G_force]), [[1.0, 0.0]], [[0.0, 0.0]], DT,
                       states=["p", "v"], inputs=["u", "F"], outputs=["p"])


ZOH_G = np.array([[DT**2 / 2], [DT]]) / MASS        # exact ZOH: C G = dt^2 / 2m != 0
VELOCITY_G = np.array([[0.0], [DT]]) / MASS         # force enters the velocity only: C G = 0
Q = np.diag([1e-12, 1e-8])  # [m^2], [(m/s)^2]
R = np.array([[1e-8]])  # (0.1 mm)^2
X0 = np.array([0.0, 0.1])
P0 = np.diag([1e-6, 1e-4])


def _force(k, x):
    t = k * DT
    return np.full((1, x.shape[1]), 1.0 + 3.0 * np.sin(2 * np.pi * 0.5 * t))


def _runs(G_true, rng, nruns=RUNS, nsteps=STEPS):
    A = np.array([[1.0, DT], [0.0, 1.0]])
    Bu = np.array([[DT**2 / 2], [DT]]) / MASS
    u = 0.5 * np.cos(np.arange(nsteps) * DT * 3.0)[None, :]
    _, y, d = _simulate_runs(A, Bu, np.array([[1.0, 0.0]]), np.zeros((1, 1)), G_true, Q, R,
                             X0, P0, u, _force, nruns, rng)
    return u, y, d


@pytest.mark.parametrize("truth", ["velocity", "zoh"])
def test_mass_position_only_unbiased_covered_and_100x_below_r1(truth, rng):
    G_true = VELOCITY_G if truth == "velocity" else ZOH_G
    sys = _mass(G_true)
    u, y, d = _runs(G_true, rng)
    # with C G~ = 0 the target is d[k]; under ZOH it is the two-sample mean (exact identity)
    target = d[:, 0, :] if truth == "velocity" else 0.5 * (d[:, 0, :-1] + d[:, 0, 1:])
    k_chk = np.arange(5, STEPS - 2)
    err = np.empty((RUNS, k_chk.size))
    var = np.empty_like(err)
    err1 = np.empty_like(err)
    for i in range(RUNS):
        res = gb.delayed_uikf(sys, y[i], u, unknown="F", Q=Q, R=R, x0=X0, P0=P0,
                              relative_degree=2)
        assert res.relative_degree == 2
        assert np.all(np.isnan(res.d_est[:, -2:])) and not np.any(np.isnan(res.d_est[:, :-2]))
        err[i] = res.d_est[0, k_chk] - target[i, k_chk]
        var[i] = res.d_var[0, k_chk]
        if truth == "zoh":  # the r = 1 filter exists only when C G != 0
            r1 = gb.uikf(sys, y[i], u, unknown="F", Q=Q, R=R, x0=X0, P0=P0)
            err1[i] = r1.d_est[0, k_chk] - d[i, 0, k_chk]
    # unbiased at every checked sample: |mean| within Z_CRIT standard errors
    z = err.mean(axis=0) / (err.std(axis=0, ddof=1) / np.sqrt(RUNS))
    assert np.max(np.abs(z)) < Z_CRIT + 0.5  # ~73 samples checked: allow the max of 73 |z|
    # the filter's variance matches the empirical one (chi-square-ish, 300 runs: +-25 %)
    np.testing.assert_allclose(err.var(axis=0, ddof=1).mean(), var.mean(), rtol=0.1)
    cover = np.mean(np.abs(err) <= norm.ppf(0.975) * np.sqrt(var))
    assert 0.93 <= cover <= 0.97, cover
    if truth == "zoh":
        ratio = err1[:, -20:].var(axis=0).mean() / err[:, -20:].var(axis=0).mean()
        assert ratio >= 100, ratio


def test_velocity_entry_fails_plain_filter_but_auto_detects_r2():
    sys = _mass(VELOCITY_G)
    with pytest.raises(RankConditionError, match=r"rank\(C @ G\) = 0 < md = 1"):
        gb.uikf(sys, np.zeros((1, 10)), np.zeros((1, 10)), unknown="F", Q=Q, R=R)
    rd = gb.detect_relative_degree(sys, unknown="F", Q=Q, R=R)
    assert rd.r == 2 and rd.candidates == (1, 2)
    assert np.isnan(rd.d_var[0]) and np.isfinite(rd.d_var[1])
    assert "rank(C G) < md" in rd.reason


def test_zoh_mass_auto_detects_r2_and_says_why(rng):
    sys = _mass(ZOH_G)
    rd = gb.detect_relative_degree(sys, unknown="F", Q=Q, R=R)
    assert rd.r == 2
    assert rd.d_var[0] == np.inf  # the r = 1 recursion diverges (zero at z = -1)
    assert "does not converge" in rd.reason
    u, y, _ = _runs(ZOH_G, rng, nruns=1, nsteps=200)
    res = gb.uikf(sys, y[0], u, unknown="F", Q=Q, R=R, relative_degree="auto")
    assert res.relative_degree == 2
    ref = gb.delayed_uikf(sys, y[0], u, unknown="F", Q=Q, R=R, relative_degree=2)
    np.testing.assert_array_equal(res.d_est, ref.d_est)  # same code path


def test_well_conditioned_systems_keep_r1(random_system, rng):
    """Default behaviour unchanged: "auto" picks r = 1 when rank(C G) = md is well conditioned."""
    rs = random_system(rng)
    rd = gb.detect_relative_degree(rs.sys, unknown=rs.unknown, Q=rs.Q, R=rs.R)
    assert rd.r == 1
    tape = gb.tape_drive_nominal(dt=1e-4)
    rd = gb.detect_relative_degree(tape, unknown="T", Q=gb.TAPE_DRIVE_Q * 1e-3,
                                   R=gb.TAPE_DRIVE_R)
    assert rd.r == 1
    sim = gb.simulate(gb.tape_drive_true(dt=1e-4), np.ones((2, 300)), rng=0)
    a = gb.uikf(tape, sim.y, sim.u, unknown="T", Q=gb.TAPE_DRIVE_Q * 1e-3, R=gb.TAPE_DRIVE_R)
    b = gb.delayed_uikf(tape, sim.y, sim.u, unknown="T", Q=gb.TAPE_DRIVE_Q * 1e-3,
                        R=gb.TAPE_DRIVE_R)
    assert b.relative_degree == 1
    np.testing.assert_array_equal(a.d_est, b.d_est)


def _triple_integrator():
    A = np.array([[1.0, DT, 0.0], [0.0, 1.0, DT], [0.0, 0.0, 1.0]])
    G = np.array([[0.0], [0.0], [DT]])
    return gb.named_ss(A, np.hstack([np.zeros((3, 1)), G]), [[1.0, 0.0, 0.0]], [[0.0, 0.0]],
                       DT, states=["p", "v", "a"], inputs=["u", "jerk"], outputs=["p"])


def test_relative_degree_three_unbiased(rng):
    sys = _triple_integrator()
    A, G = np.asarray(sys.A), np.asarray(sys.B)[:, 1:]
    Qt, Rt = np.diag([1e-12, 1e-12, 1e-10]), np.array([[1e-12]])
    rd = gb.detect_relative_degree(sys, unknown="jerk", Q=Qt, R=Rt)
    assert rd.r == 3
    nruns, N = 200, 40
    u = np.zeros((1, N))
    _, y, d = _simulate_runs(A, np.zeros((3, 1)), np.asarray(sys.C), np.zeros((1, 1)), G, Qt,
                             Rt, np.zeros(3), np.eye(3) * 1e-6, u,
                             lambda k, x: np.full((1, x.shape[1]), np.cos(0.3 * k)), nruns, rng)
    err = np.array([gb.delayed_uikf(sys, y[i], u, unknown="jerk", Q=Qt, R=Rt,
                                    P0=np.eye(3) * 1e-6, relative_degree=3).d_est[0, 5:N - 3]
                    - d[i, 0, 5:N - 3] for i in range(nruns)])
    z = err.mean(axis=0) / (err.std(axis=0, ddof=1) / np.sqrt(nruns))
    assert np.max(np.abs(z)) < Z_CRIT + 0.5


def test_x_filt_is_the_delayed_state_estimate(rng):
    """x_filt[:, k] = x^[k|k+r-1] is unbiased for x[k]; its last r-1 columns are NaN."""
    sys = _mass(VELOCITY_G)
    A = np.array([[1.0, DT], [0.0, 1.0]])
    Bu = np.array([[DT**2 / 2], [DT]]) / MASS
    nruns, N = 200, 40
    u = np.zeros((1, N))
    x, y, _ = _simulate_runs(A, Bu, np.array([[1.0, 0.0]]), np.zeros((1, 1)), VELOCITY_G, Q,
                             R, X0, P0, u, _force, nruns, rng)
    err = np.empty((nruns, 2, N - 1))
    for i in range(nruns):
        res = gb.delayed_uikf(sys, y[i], u, unknown="F", Q=Q, R=R, x0=X0, P0=P0,
                              relative_degree=2)
        assert np.all(np.isnan(res.x_filt[:, -1])) and not np.any(np.isnan(res.x_filt[:, :-1]))
        err[i] = res.x_filt[:, :-1] - x[i, :, :-1]
    z = err.mean(axis=0) / (err.std(axis=0, ddof=1) / np.sqrt(nruns))
    assert np.max(np.abs(z)) < Z_CRIT + 0.5  # 78 checks: the max of 78 |z| stays below ~3.8
    # the velocity is known to a few mm/s although only positions are measured
    assert np.sqrt(np.mean(err[:, 1, 5:] ** 2)) < 0.05


def test_fast_path_equals_time_varying(rng):
    sys = _mass(ZOH_G)
    u, y, _ = _runs(ZOH_G, rng, nruns=1, nsteps=400)
    a = gb.delayed_uikf(sys, y[0], u, unknown="F", Q=Q, R=R, relative_degree=2)
    b = gb.delayed_uikf(sys, y[0], u, unknown="F", Q=Q, R=R, relative_degree=2,
                        gain="time-varying")
    assert a.period_converged is not None and a.period_converged < 50
    # same recursion after convergence to tol = 1e-12 relative: round-off level of d (~1e3 N
    # scale of the innovations / dt^2) -> 1e-6 absolute
    np.testing.assert_allclose(a.d_est, b.d_est, atol=1e-6, rtol=0)
    # states: relative round-off accumulated over 400 steps of two different evaluation
    # orders (the fast path runs a modal recursion), ~1e-12 relative
    np.testing.assert_allclose(a.x_filt, b.x_filt, rtol=1e-10, atol=1e-12)


def test_rank_violated_at_every_delay_is_a_clear_error():
    # d drives a mode the output never sees
    sys = gb.named_ss(np.diag([0.9, 0.8]), [[1.0, 0.0], [0.0, 1.0]], [[1.0, 0.0]], [[0.0, 0.0]],
                      0.1, states=["a", "b"], inputs=["u", "d"], outputs=["y"])
    with pytest.raises(RankConditionError, match=r"not observable at any delay.*r = 1\.\.2"):
        gb.detect_relative_degree(sys, unknown="d", Q=np.eye(2), R=[[1.0]])
    with pytest.raises(RankConditionError, match="not observable at any delay"):
        gb.delayed_uikf(sys, np.zeros((1, 5)), np.zeros((1, 5)), unknown="d", Q=np.eye(2),
                        R=[[1.0]])
    with pytest.raises(RankConditionError, match="relative degree 3"):
        gb.delayed_uikf(_mass(ZOH_G), np.zeros((1, 5)), np.zeros((1, 5)), unknown="F", Q=Q,
                        R=R, relative_degree=3)


def test_bad_options_and_feedthrough():
    sys = _mass(ZOH_G)
    y, u = np.zeros((1, 5)), np.zeros((1, 5))
    with pytest.raises(GreyboxError, match="relative_degree must be 'auto'"):
        gb.delayed_uikf(sys, y, u, unknown="F", Q=Q, R=R, relative_degree="fast")
    with pytest.raises(DataError, match="relative_degree must be finite and > 0"):
        gb.delayed_uikf(sys, y, u, unknown="F", Q=Q, R=R, relative_degree=0)
    with pytest.raises(DataError, match="switch_ratio must be finite and > 0"):
        gb.detect_relative_degree(sys, unknown="F", Q=Q, R=R, switch_ratio=-1)
    ft = gb.named_ss(np.eye(2) * 0.5, [[1.0, 0.0], [0.0, 1.0]], [[1.0, 0.0]], [[0.0, 1.0]], 0.1,
                     states=["a", "b"], inputs=["u", "d"], outputs=["y"])
    with pytest.raises(ModelError, match="use feedthrough_uikf"):
        gb.delayed_uikf(ft, y, u, unknown="d", Q=np.eye(2), R=[[1.0]])
    with pytest.raises(ModelError, match="use feedthrough_uikf"):
        gb.detect_relative_degree(ft, unknown="d", Q=np.eye(2), R=[[1.0]])
