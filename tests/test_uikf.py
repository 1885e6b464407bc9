"""Tests of the unbiased minimum-variance input and state filter and its Kalman baseline.

Oracles used here (STYLE.md, "Test habits"):

* statistics of Monte Carlo runs whose truth is simulated from model (5)-(6)
  with the same Q and R the filter is given (bias of d^, NEES of x^[k|k],
  coverage of the d^ intervals), judged with the filter's own covariances;
* the Riccati equation (scipy.linalg.solve_discrete_are, control.dlqe);
* a plain-numpy textbook Kalman filter written here;
* hand-derived gains for n = md (scalar case and G square);
* the constant-gain filter run with control.forced_response.
"""

from __future__ import annotations

import control as ct
import numpy as np
import pytest
import scipy.linalg as sla
from scipy.stats import chi2, norm

import greybox as gb
from greybox import (
    CovarianceError,
    DataError,
    DimensionError,
    GreyboxError,
    ModelError,
    RankConditionError,
)

# Two-sided significance of every statistical check below. With fixed seeds the
# tests are deterministic; 1e-3 per check keeps the chance that a correct filter
# lands outside a bound (for the seed chosen) small over the ~100 checks here.
ALPHA = 1e-3
Z_CRIT = norm.ppf(1 - ALPHA / 2)  # 3.29

MC_RUNS = 200
MC_STEPS = 60
# Sample indices checked in the Monte Carlo tests: the first ones lie in the
# time-varying phase of the gains (k = 0 is the plain update of the prior),
# the last ones after convergence. d_est[:, N-1] is NaN, so stop at N-2.
CHECK_STEPS = (0, 1, 2, 5, 20, 41, MC_STEPS - 2)


# --------------------------------------------------------------------------- helpers
def _matrices(sys, unknown):
    """A, B, C, D, G of a discrete model split into known inputs and unknown ones."""
    sp = gb.split_inputs(sys, unknown)
    A, B, C, D = (np.asarray(M, dtype=float) for M in (sp.sys.A, sp.sys.B, sp.sys.C, sp.sys.D))
    return A, B, C, D, sp.G


def _simulate_runs(A, B, C, D, G, Q, R, x0, P0, u, d_of, nruns, rng):
    """Monte Carlo truth of (5)-(6), all runs at once (plain numpy loop over time).

    ``x[0] ~ N(x0, P0)``, ``x[k+1] = A x + B u + G d + w``, ``y = C x + D u + v``,
    with ``d[k] = d_of(k, x[k])`` (shape (md, nruns)), so d may depend on the state.

    Returns x (nruns, n, N), y (nruns, p, N), d (nruns, md, N).
    """
    n, N = A.shape[0], u.shape[1]
    p, md = C.shape[0], G.shape[1]
    LQ = sla.cholesky(Q + 1e-300 * np.eye(n), lower=True) if np.any(Q) else np.zeros((n, n))
    LR = sla.cholesky(R, lower=True)
    LP = sla.cholesky(P0, lower=True)
    x = np.empty((N, n, nruns))
    d = np.empty((N, md, nruns))
    x[0] = x0[:, None] + LP @ rng.standard_normal((n, nruns))
    for k in range(N):
        d[k] = d_of(k, x[k])
        if k + 1 < N:
            x[k + 1] = (A @ x[k] + (B @ u[:, k])[:, None] + G @ d[k]
                        + LQ @ rng.standard_normal((n, nruns)))
    y = np.einsum("ij,kjr->kir", C, x) + (D @ u).T[:, :, None] \
        + np.einsum("ij,kjr->kir", LR, rng.standard_normal((N, p, nruns)))
    return x.transpose(2, 1, 0), y.transpose(2, 1, 0), d.transpose(2, 1, 0)


def _textbook_kf(A, B, C, D, Q, R, x0, P0, y, u):
    """Independent oracle: the Kalman filter as in any textbook, one sample at a time.

    Prior x[0] ~ N(x0, P0) is updated with y[0]; then predict / update.
    """
    n, N = A.shape[0], y.shape[1]
    xf, xp, e = np.empty((n, N)), np.empty((n, N)), np.empty((C.shape[0], N))
    Pf = np.empty((n, n, N))
    x, P = x0.copy(), P0.copy()
    for k in range(N):
        if k > 0:
            x = A @ xf[:, k - 1] + B @ u[:, k - 1]
            P = A @ Pf[:, :, k - 1] @ A.T + Q
        xp[:, k] = x
        S = C @ P @ C.T + R
        K = P @ C.T @ np.linalg.inv(S)
        e[:, k] = y[:, k] - C @ x - D @ u[:, k]
        xf[:, k] = x + K @ e[:, k]
        Pf[:, :, k] = (np.eye(n) - K @ C) @ P
    return xf, xp, e, Pf, K, P


def _ee(y, yhat):
    """Eq. (42) with the square root (PAPER_NOTES §8.3): relative RMS averaged over outputs [%]."""
    return 100 * np.mean(np.sqrt(np.sum((y - yhat) ** 2, axis=1) / np.sum(y**2, axis=1)))


# --------------------------------------------------------------------------- Monte Carlo
def _mc_case(case, make):
    """Model, prior, input and unknown-input law of one Monte Carlo case."""
    rng = np.random.default_rng({"rand-sine": 11, "rand-step": 12, "rand-walk": 13,
                                 "rand-md2": 14, "tape-drive": 15}[case])
    N = MC_STEPS
    k = np.arange(N)
    if case == "tape-drive":
        sys = gb.tape_drive_nominal(dt=gb.TAPE_DRIVE_DT)
        unknown = "T"
        Q, R = gb.TAPE_DRIVE_Q, gb.TAPE_DRIVE_R
        cT = gb.tape_drive_tension()
        # d = the tape tension itself, a feedback of the true state: "arbitrary" d
        # (correlated with the noise) still gives unbiased estimates.
        d_of = lambda kk, x: cT @ x  # noqa: E731
        u = gb.random_binary(N, nsignals=2, amplitude=1.0, hold=20, rng=rng)
        x0 = np.array([0.5, -0.5, 0.0, 1e-3, 0.0, 0.0])  # 1 mm stretch: T ~ 10 N
        P0 = np.diag([1e-4, 1e-4, 1e-8, 1e-8, 1e-2, 1e-2])
    else:
        md = 2 if case == "rand-md2" else 1
        rs = make(rng, n=4 if md == 2 else 3, m=2 if md == 2 else 1, p=3 if md == 2 else 2,
                  md=md)
        sys, unknown, Q, R = rs.sys, rs.unknown, rs.Q, rs.R
        u = rng.standard_normal((rs.m, N))
        x0 = rng.standard_normal(rs.n)
        P0 = 0.5 * np.eye(rs.n)
        sine = 5.0 * np.sin(2 * np.pi * k / 25)
        step = np.where(k >= 30, 3.0, -1.0)
        if case == "rand-sine":
            d_of = lambda kk, x: np.full((1, x.shape[1]), sine[kk])  # noqa: E731
        elif case == "rand-step":
            d_of = lambda kk, x: np.full((1, x.shape[1]), step[kk])  # noqa: E731
        elif case == "rand-walk":
            walk = 2.0 + np.cumsum(0.5 * rng.standard_normal((MC_RUNS, N)), axis=1)
            d_of = lambda kk, x: walk[None, :, kk]  # noqa: E731
        else:
            d_of = lambda kk, x: np.vstack([np.full(x.shape[1], sine[kk]),  # noqa: E731
                                            np.full(x.shape[1], step[kk])])
    A, B, C, D, G = _matrices(sys, unknown)
    return sys, unknown, Q, R, u, x0, P0, d_of, (A, B, C, D, G), rng


@pytest.fixture(scope="module", params=["rand-sine", "rand-step", "rand-walk", "rand-md2",
                                        "tape-drive"])
def mc(request, random_system):
    """Monte Carlo runs of the unknown-input filter on a truth matching Q and R.

    Memoized per case: the indirect parametrization below would otherwise
    make pytest rebuild it.
    """
    if request.param not in _MC_CACHE:
        _MC_CACHE[request.param] = _run_mc(request.param, random_system)
    return _MC_CACHE[request.param]


_MC_CACHE: dict = {}


def _run_mc(case, random_system):
    sys, unknown, Q, R, u, x0, P0, d_of, (A, B, C, D, G), rng = _mc_case(case, random_system)
    x, y, d = _simulate_runs(A, B, C, D, G, Q, R, x0, P0, u, d_of, MC_RUNS, rng)
    res = [gb.uikf(sys, y[r], u, unknown=unknown, Q=Q, R=R, x0=x0, P0=P0,
                   store_covariances=(r == 0)) for r in range(MC_RUNS)]
    return dict(
        case=case, sys=sys, unknown=unknown, Q=Q, R=R, u=u, x0=x0, P0=P0,
        x=x, y=y, d=d,
        x_filt=np.stack([r.x_filt for r in res]),
        d_est=np.stack([r.d_est for r in res]),
        d_var=res[0].d_var,  # data-independent (checked below)
        d_var_all=np.stack([r.d_var for r in res]),
        d_lower=np.stack([r.d_lower for r in res]),
        d_upper=np.stack([r.d_upper for r in res]),
        P_hist=res[0].P_filt_history,
        first=res[0],
    )


def test_mc_covariances_are_data_independent(mc):
    """d_var and the gains do not depend on the data: every run reports the same."""
    v = mc["d_var_all"]
    # exact: the covariance recursion never touches y or u
    np.testing.assert_array_equal(v, np.broadcast_to(v[0], v.shape))
    assert mc["P_hist"].shape == (mc["x"].shape[1],) * 2 + (MC_STEPS,)
    assert np.all(np.isnan(mc["d_est"][:, :, -1]))
    assert np.all(np.isfinite(mc["d_est"][:, :, :-1]))


def test_d_estimate_unbiased(mc):
    """E[d^[k] - d[k]] = 0 for any d (sine, step, random walk, state feedback)."""
    err = mc["d_est"] - mc["d"]
    for k in CHECK_STEPS:
        se = np.sqrt(mc["d_var"][:, k] / MC_RUNS)  # standard error from the filter's own Pd
        z = err[:, :, k].mean(axis=0) / se
        assert np.all(np.abs(z) < Z_CRIT), (k, z)
    # The test can fail: at some checked step the mean of d is more than
    # 10 Z_CRIT standard errors away from 0, so an estimate mis-scaled by 10 %
    # (or a filter ignoring d) would be rejected.
    power = max(np.max(np.abs(mc["d"][:, :, k].mean(axis=0))
                       / np.sqrt(mc["d_var"][:, k] / MC_RUNS)) for k in CHECK_STEPS)
    assert power > 10 * Z_CRIT, power


# (not on the step or the random walk: their increments have mean ~0, a shift is invisible)
@pytest.mark.parametrize("mc", ["rand-sine", "rand-md2", "tape-drive"], indirect=True)
def test_d_estimate_alignment_matters(mc):
    """d_est[:, j] estimates d[j], not d[j+1]: the shifted comparison is strongly biased."""
    err = mc["d_est"][:, :, :-2] - mc["d"][:, :, 1:-1]
    se = np.sqrt(mc["d_var"][:, :-2] / MC_RUNS)
    z = err.mean(axis=0) / se
    # the unbiasedness test above would reject a one-sample shift (with a 2x margin)
    assert np.max(np.abs(z)) > 2 * Z_CRIT


def test_nees_within_chi2_bounds(mc):
    """NEES of x^[k|k] with P[k|k] (store_covariances) is chi-square(n R) over R runs."""
    n = mc["x"].shape[1]
    lo, hi = chi2.ppf([ALPHA / 2, 1 - ALPHA / 2], n * MC_RUNS)
    for k in CHECK_STEPS + (MC_STEPS - 1,):
        e = mc["x"][:, :, k] - mc["x_filt"][:, :, k]
        P = mc["P_hist"][:, :, k]
        nees = np.einsum("ri,ri->", e, np.linalg.solve(P, e.T).T)
        assert lo < nees < hi, (k, nees / MC_RUNS, n)


def test_d_normalized_error_within_chi2_bounds(mc):
    """(d^ - d)^2 / d_var summed over runs is chi-square(R) for each channel."""
    lo, hi = chi2.ppf([ALPHA / 2, 1 - ALPHA / 2], MC_RUNS)
    err = mc["d_est"] - mc["d"]
    for k in CHECK_STEPS:
        s = np.sum(err[:, :, k] ** 2, axis=0) / mc["d_var"][:, k]
        assert np.all((lo < s) & (s < hi)), (k, s / MC_RUNS)


def test_d_interval_coverage(mc):
    """The 95 % interval [d_lower, d_upper] covers the truth in 93-97 % of the samples."""
    d = mc["d"][:, :, :-1]
    inside = (mc["d_lower"][:, :, :-1] <= d) & (d <= mc["d_upper"][:, :, :-1])
    assert 0.93 <= inside.mean() <= 0.97, inside.mean()


def test_d_interval_level_option(random_system):
    """level=0.8 gives about 80 % coverage (4 binomial SDs on 6000 samples: ±0.02)."""
    sys, unknown, Q, R, u, x0, P0, d_of, mats, rng = _mc_case("rand-sine", random_system)
    x, y, d = _simulate_runs(*mats, Q, R, x0, P0, u, d_of, 50, rng)
    cover = []
    for r in range(50):
        res = gb.uikf(sys, y[r], u, unknown=unknown, Q=Q, R=R, x0=x0, P0=P0, level=0.8)
        assert res.level == 0.8
        cover.append((res.d_lower[:, :-1] <= d[r, :, :-1]) & (d[r, :, :-1] <= res.d_upper[:, :-1]))
    assert 0.78 <= np.mean(cover) <= 0.82, np.mean(cover)


def test_kalman_filter_nees_and_nis(random_system):
    """Without unknown input, the KF's NEES and NIS (innovation_cov) are chi-square."""
    rng = np.random.default_rng(21)
    rs = random_system(rng, n=3, m=1, p=2, md=1)
    A, B, C, D, G = _matrices(rs.sys, rs.unknown)
    N, nruns = 80, 300
    u = rng.standard_normal((1, N))
    x0, P0 = np.zeros(3), np.eye(3)
    x, y, _ = _simulate_runs(A, B, C, D, np.zeros((3, 0)), rs.Q, rs.R, x0, P0, u,
                             lambda k, xx: np.zeros((0, xx.shape[1])), nruns, rng)
    res = [gb.kalman_filter(rs.sys, y[r], u, unknown=rs.unknown, Q=rs.Q, R=rs.R, x0=x0,
                            P0=P0) for r in range(nruns)]
    assert res[0].converged and res[0].period_converged is not None
    k = N - 1  # after convergence: P_filt and innovation_cov are the converged ones
    e = np.stack([x[r, :, k] - res[r].x_filt[:, k] for r in range(nruns)])
    nees = np.einsum("ri,ri->", e, np.linalg.solve(res[0].P_filt, e.T).T)
    lo, hi = chi2.ppf([ALPHA / 2, 1 - ALPHA / 2], 3 * nruns)
    assert lo < nees < hi
    nu = np.stack([r.innovations[:, k] for r in res])
    nis = np.einsum("ri,ri->", nu, np.linalg.solve(res[0].innovation_cov, nu.T).T)
    lo, hi = chi2.ppf([ALPHA / 2, 1 - ALPHA / 2], 2 * nruns)
    assert lo < nis < hi


# --------------------------------------------------------------------------- fast path
@pytest.mark.parametrize("case", ["rand-md1", "rand-md2", "tape-drive"])
def test_auto_gain_equals_time_varying(case, random_system):
    """gain="auto" freezes the gains once P[k|k-1] has converged and runs an LTI filter.

    Before ``period_converged`` both modes run the same code: results are equal
    bit for bit. After it the time-varying gains still move by at most
    the convergence test (a relative change of P of at most tol = 1e-12 per
    step), and the remaining geometric tail of the recursion adds at most a
    factor 1/(1 - rho^2) ~ 10-100 for the filters here: the gains, hence the
    estimates, differ by <~1e-10 relative. The LTI recursion (Schur form) only
    adds rounding (measured: ~3e-15). Tolerance: 1e-10 of the signal scale.
    """
    rng = np.random.default_rng(31)
    N = 1500
    if case == "tape-drive":
        sys, unknown, Q, R = (gb.tape_drive_nominal(dt=gb.TAPE_DRIVE_DT), "T",
                              gb.TAPE_DRIVE_Q, gb.TAPE_DRIVE_R)
        u = gb.lowpass_noise(N, dt=gb.TAPE_DRIVE_DT, bandwidth=20, nsignals=2, rng=rng)
        sim = gb.simulate(gb.tape_drive_true(dt=gb.TAPE_DRIVE_DT), u, Q=Q, R=R, rng=rng)
        y = sim.y
    else:
        md = 2 if case == "rand-md2" else 1
        rs = random_system(rng, n=4, m=2, p=3, md=md)
        sys, unknown, Q, R = rs.sys, rs.unknown, rs.Q, rs.R
        u = rng.standard_normal((2, N))
        uu = np.vstack([u, np.cumsum(rng.standard_normal((md, N)), axis=1)])
        y = gb.simulate(sys, uu, Q=Q, R=R, rng=rng).y
    fast = gb.uikf(sys, y, u, unknown=unknown, Q=Q, R=R, gain="auto", store_covariances=True)
    slow = gb.uikf(sys, y, u, unknown=unknown, Q=Q, R=R, gain="time-varying",
                   store_covariances=True)
    kc = fast.period_converged
    assert fast.converged and slow.converged
    assert isinstance(kc, int) and 1 < kc < N // 2
    assert slow.period_converged is None
    for name in ("x_filt", "x_pred", "innovations", "d_est"):
        a, b = getattr(fast, name), getattr(slow, name)
        # identical code path before convergence
        np.testing.assert_array_equal(a[:, : kc - 1], b[:, : kc - 1])
        scale = np.max(np.abs(b[:, :-1]))
        # see docstring: gain freeze at tol=1e-12 (times the tail factor) plus rounding
        np.testing.assert_allclose(a[:, kc - 1:-1], b[:, kc - 1:-1], rtol=0, atol=1e-10 * scale,
                                   err_msg=name)
    # covariances: equal to the convergence tolerance (1e-12 relative) of P; 1e-10 leaves
    # room for the geometric tail of the recursion after the freeze
    np.testing.assert_allclose(fast.P_filt_history, slow.P_filt_history, rtol=0,
                               atol=1e-10 * np.max(np.abs(slow.P_filt_history[:, :, -1])))
    np.testing.assert_allclose(fast.d_var[:, :-1], slow.d_var[:, :-1], rtol=1e-10)
    np.testing.assert_allclose(fast.K, slow.K, rtol=0, atol=1e-10 * np.max(np.abs(slow.K)))
    np.testing.assert_allclose(fast.M, slow.M, rtol=0, atol=1e-10 * np.max(np.abs(slow.M)))


def test_short_record_does_not_converge(random_system, rng):
    """On a record shorter than the transient the gains are never frozen."""
    rs = random_system(rng)
    y = rng.standard_normal((rs.p, 4))
    u = rng.standard_normal((rs.m, 4))
    res = gb.uikf(rs.sys, y, u, unknown=rs.unknown, Q=rs.Q, R=rs.R, P0=100 * np.eye(rs.n))
    assert res.period_converged is None
    assert res.converged is False


# --------------------------------------------------------------------------- Kalman filter
@pytest.fixture
def kf_case(random_system):
    rng = np.random.default_rng(41)
    rs = random_system(rng, n=4, m=2, p=2, md=1)
    N = 600
    u = rng.standard_normal((2, N))
    uu = np.vstack([u, np.sin(0.3 * np.arange(N))[None]])
    y = gb.simulate(rs.sys, uu, Q=rs.Q, R=rs.R, x0=rng.standard_normal(4), rng=rng).y
    return rs, u, y


def test_kalman_P_pred_converges_to_dare(kf_case):
    """P[k|k-1] of the KF tends to the DARE solution; gains and poles agree with dlqe.

    The recursion stops at a relative change of 1e-12 per step; the distance
    to the fixed point is then at most that times rho^2/(1 - rho^2) (rho the
    filter's contraction, <= 0.99 here), i.e. < 1e-10; DARE solvers are accurate
    to ~1e-13 here (measured distance ~1e-12). rtol = 1e-9.
    """
    rs, u, y = kf_case
    A, B, C, D, _ = _matrices(rs.sys, rs.unknown)
    P_dare = sla.solve_discrete_are(A.T, C.T, rs.Q, rs.R)
    res = gb.kalman_filter(rs.sys, y, u, unknown=rs.unknown, Q=rs.Q, R=rs.R,
                           gain="time-varying")
    assert res.converged
    np.testing.assert_allclose(res.P_pred, P_dare, rtol=1e-9, atol=1e-12)
    ss = gb.steady_state_filter(gb.split_inputs(rs.sys, rs.unknown).sys, Q=rs.Q, R=rs.R)
    np.testing.assert_allclose(ss.P_pred, P_dare, rtol=1e-9, atol=1e-12)
    L_dlqe, P_dlqe, E_dlqe = ct.dlqe(A, np.eye(4), C, rs.Q, rs.R)
    np.testing.assert_allclose(ss.P_pred, P_dlqe, rtol=1e-9, atol=1e-12)
    # dlqe returns the predictor gain A K (x[k+1|k] = A x[k|k-1] + B u + A K e)
    np.testing.assert_allclose(A @ ss.K, L_dlqe, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ss.L, ss.K, rtol=0, atol=0)  # G = 0: no compensation
    np.testing.assert_allclose(np.sort_complex(np.linalg.eigvals(ss.sys.A)),
                               np.sort_complex(E_dlqe), rtol=1e-9)
    np.testing.assert_allclose(ss.P_filt, P_dare - ss.K @ ss.innovation_cov @ ss.K.T,
                               rtol=1e-9, atol=1e-12)
    assert ss.M.shape == (0, 2) and ss.d_cov.shape == (0, 0)


@pytest.mark.parametrize("gain", ["time-varying", "auto"])
def test_kalman_filter_equals_textbook(kf_case, gain):
    """kalman_filter (unknown channel dropped) equals a plain-numpy textbook KF.

    Same arithmetic in another order (the library symmetrizes P and uses a
    Cholesky solve): with time-varying gains the differences are rounding
    (measured ~1e-14 relative): tolerance 1e-11 of the scale. The "auto" path
    freezes the gains at a 1e-12 relative change of P (measured gain
    difference 2e-12): tolerance 1e-10 (see test_auto_gain_equals_time_varying).
    """
    rs, u, y = kf_case
    A, B, C, D, _ = _matrices(rs.sys, rs.unknown)
    x0, P0 = np.array([1.0, -1.0, 0.5, 0.0]), 2.0 * np.eye(4)
    xf, xp, e, Pf, K, Pp = _textbook_kf(A, B, C, D, rs.Q, rs.R, x0, P0, y, u)
    res = gb.kalman_filter(rs.sys, y, u, unknown="d0", Q=rs.Q, R=rs.R, x0=x0, P0=P0,
                           gain=gain, store_covariances=True)
    tol = 1e-11 if gain == "time-varying" else 1e-10  # see docstring
    sc = np.max(np.abs(xf))
    np.testing.assert_allclose(res.x_filt, xf, rtol=0, atol=tol * sc)
    np.testing.assert_allclose(res.x_pred, xp, rtol=0, atol=tol * sc)
    np.testing.assert_allclose(res.innovations, e, rtol=0, atol=tol * np.max(np.abs(e)))
    np.testing.assert_allclose(res.P_filt_history, Pf, rtol=0, atol=tol * np.max(np.abs(Pf)))
    np.testing.assert_allclose(res.K, K, rtol=tol)
    np.testing.assert_allclose(res.y_pred, y - e, rtol=0, atol=tol * np.max(np.abs(y)))
    assert res.d_est.shape == (0, y.shape[1]) and res.unknown_labels == ()
    # same filter on the model without the d channel at all
    res2 = gb.kalman_filter(gb.split_inputs(rs.sys, "d0").sys, y, u, Q=rs.Q, R=rs.R, x0=x0,
                            P0=P0, gain=gain)
    np.testing.assert_array_equal(res2.x_filt, res.x_filt)  # identical inputs to _run


# --------------------------------------------------------------------------- analytic cases
def test_scalar_gains_by_hand(rng):
    """n = p = md = 1: the UMV gains in closed form.

    With F = c g, M = 1/(c g) and the combined gain L = G M + K (1 - F M) = 1/c,
    so x^[k|k] = y[k]/c for k >= 1 and, with R~ = c^2 P[k|k-1] + r,
    P[k|k] = P[k|k-1] - K^2 R~ + (g - K c g)^2 R~/(c g)^2 = r / c^2.
    Then P[k|k-1] = a^2 r/c^2 + q from k = 2 on, Pd = R~/(c g)^2 and
    d^[k-1] = (y[k]/c - a x^[k-1|k-1] - b u[k-1]) / g. k = 0 is the plain
    update of the prior: K0 = P0 c/(c^2 P0 + r).
    All checks are a few flops away from the formulas: rtol = 1e-12.
    """
    a, b, c, g, q, r = 0.8, 0.5, 2.0, 1.5, 0.3, 0.2
    x0, P0 = 1.0, 4.0
    sys = gb.named_ss([[a]], [[b, g]], [[c]], [[0.0, 0.0]], 1.0, states=["x"],
                      inputs=["u", "d"], outputs=["y"])
    N = 30
    y = rng.standard_normal((1, N))
    u = rng.standard_normal((1, N))
    for gain in ("time-varying", "auto"):
        res = gb.uikf(sys, y, u, unknown="d", Q=q, R=r, x0=[x0], P0=[[P0]], gain=gain,
                      store_covariances=True)
        K0 = P0 * c / (c**2 * P0 + r)
        np.testing.assert_allclose(res.x_filt[0, 0], x0 + K0 * (y[0, 0] - c * x0), rtol=1e-12)
        np.testing.assert_allclose(res.P_filt_history[0, 0, 0], P0 * r / (c**2 * P0 + r),
                                   rtol=1e-12)
        np.testing.assert_allclose(res.x_filt[0, 1:], y[0, 1:] / c, rtol=1e-12)
        np.testing.assert_allclose(res.P_filt_history[0, 0, 1:], r / c**2, rtol=1e-12)
        Pp = np.r_[a**2 * P0 * r / (c**2 * P0 + r) + q, np.full(N - 2, a**2 * r / c**2 + q)]
        Pd = (c**2 * Pp + r) / (c * g) ** 2
        np.testing.assert_allclose(res.d_var[0, :-1], Pd, rtol=1e-12)
        d_hand = (y[0, 1:] / c - a * res.x_filt[0, :-1] - b * u[0, :-1]) / g
        np.testing.assert_allclose(res.d_est[0, :-1], d_hand, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(res.M, [[1 / (c * g)]], rtol=1e-12)
        Pp_end = a**2 * r / c**2 + q
        np.testing.assert_allclose(res.K, [[Pp_end * c / (c**2 * Pp_end + r)]], rtol=1e-12)
        np.testing.assert_allclose(res.P_pred, [[Pp_end]], rtol=1e-12)
        np.testing.assert_allclose(res.d_cov, [[(c**2 * Pp_end + r) / (c * g) ** 2]],
                                   rtol=1e-12)


@pytest.mark.parametrize("n,p", [(1, 2), (2, 2), (2, 3)], ids=["n1-p2", "n2-p2", "n2-p3"])
def test_square_G_gives_weighted_least_squares(n, p, rng):
    """G square and invertible (md = n): d absorbs any prior, so x^[k|k] is the BLUE from y[k].

    Unbiasedness for every d forces L C = I; the minimum variance such L is the
    Gauss-Markov estimator L = (C' R^-1 C)^-1 C' R^-1, with P[k|k] = (C' R^-1 C)^-1
    whatever A and Q are. Closed form vs a few solves: rtol = 1e-10.
    """
    A = 0.5 * rng.standard_normal((n, n))
    B = rng.standard_normal((n, 1))
    C = rng.standard_normal((p, n))
    G = rng.standard_normal((n, n)) + 2 * np.eye(n)
    V = rng.standard_normal((p, p))
    R = V @ V.T + 0.1 * np.eye(p)
    sys = gb.named_ss(A, np.hstack([B, G]), C, np.zeros((p, n + 1)), 0.5,
                      states=[f"x{i}" for i in range(n)],
                      inputs=["u"] + [f"d{i}" for i in range(n)],
                      outputs=[f"y{i}" for i in range(p)])
    y = rng.standard_normal((p, 40))
    u = rng.standard_normal((1, 40))
    res = gb.uikf(sys, y, u, unknown=[f"d{i}" for i in range(n)], Q=0.3 * np.eye(n), R=R,
                  store_covariances=True)
    Ri = np.linalg.inv(R)
    Pw = np.linalg.inv(C.T @ Ri @ C)
    np.testing.assert_allclose(res.x_filt[:, 1:], Pw @ C.T @ Ri @ y[:, 1:], rtol=1e-10,
                               atol=1e-12)
    np.testing.assert_allclose(res.P_filt_history[:, :, 1:],
                               np.broadcast_to(Pw[:, :, None], (n, n, 39)), rtol=1e-10,
                               atol=1e-14)


@pytest.mark.parametrize("n,p", [(1, 2), (2, 1), (2, 2)], ids=["n1-p2", "n2-p1", "n2-p2"])
def test_model_without_known_inputs(n, p, rng):
    """A model whose only inputs are unknown (no u) can be filtered for n, p >= 2.

    For n = 1 or p = 1 python-control reshapes the empty (1, 0) matrices of a
    0-input model to (0, 0) and cannot build it: greybox then raises a
    ModelError naming the limitation and the workaround (a zero input).
    """
    C = np.ones((p, n))
    sys = gb.named_ss(0.5 * np.eye(n), np.ones((n, 1)), C, np.zeros((p, 1)), 0.1,
                      states=[f"x{i}" for i in range(n)], inputs=["d"],
                      outputs=[f"y{i}" for i in range(p)])
    if n == 1 or p == 1:
        with pytest.raises(gb.ModelError, match="add a known input channel with zero gain"):
            gb.uikf(sys, rng.standard_normal((p, 20)), unknown="d", Q=np.eye(n), R=np.eye(p))
        return
    res = gb.uikf(sys, rng.standard_normal((p, 20)), unknown="d", Q=np.eye(n), R=np.eye(p))
    assert res.d_est.shape == (1, 20)
    assert res.sys.ninputs == 0


# --------------------------------------------------------------------------- steady state
@pytest.mark.parametrize("case", ["rand-md1", "rand-md2-kf", "tape-drive"])
def test_steady_state_filter_sys_reproduces_uikf(case, random_system):
    """steady_state_filter(...).sys run by control.forced_response from the state
    x^[kc|kc-1] reproduces x^[k|k] (and d^[k-1]) of uikf after convergence.

    The two routines converge P from different starts (P0 vs Q), each to a
    relative change of 1e-12 per step; with the tail factor 1/(1 - rho^2) the
    gains agree to <~1e-10 relative (measured: <= 2e-12). Tolerance: 1e-10 of
    the scale of each signal or matrix.
    """
    rng = np.random.default_rng(51)
    N = 800
    if case == "tape-drive":
        sys, unknown, Q, R = (gb.tape_drive_nominal(dt=gb.TAPE_DRIVE_DT), "T",
                              gb.TAPE_DRIVE_Q, gb.TAPE_DRIVE_R)
        u = gb.lowpass_noise(N, dt=gb.TAPE_DRIVE_DT, bandwidth=20, nsignals=2, rng=rng)
        y = gb.simulate(gb.tape_drive_true(dt=gb.TAPE_DRIVE_DT), u, Q=Q, R=R, rng=rng).y
        run = lambda: gb.uikf(sys, y, u, unknown=unknown, Q=Q, R=R)  # noqa: E731
    else:
        md = 2 if case == "rand-md2-kf" else 1
        rs = random_system(rng, n=4, m=2, p=3, md=md)
        sys, Q, R = rs.sys, rs.Q, rs.R
        u = rng.standard_normal((2, N))
        uu = np.vstack([u, rng.standard_normal((md, N)).cumsum(axis=1)])
        y = gb.simulate(sys, uu, Q=Q, R=R, rng=rng).y
        if case == "rand-md2-kf":  # the Kalman filter: md = 0
            sys = gb.split_inputs(sys, rs.unknown).sys
            unknown = None
            run = lambda: gb.kalman_filter(sys, y, u, Q=Q, R=R)  # noqa: E731
        else:
            unknown = rs.unknown
            run = lambda: gb.uikf(sys, y, u, unknown=unknown, Q=Q, R=R)  # noqa: E731
    res = run()
    ss = gb.steady_state_filter(sys, Q=Q, R=R, unknown=unknown)
    kc = res.period_converged
    n, md = res.x_filt.shape[0], res.d_est.shape[0]
    assert ss.sys.ninputs == u.shape[0] + y.shape[0]
    assert ss.sys.noutputs == n + md
    assert ss.sys.isdtime(strict=True) and ss.sys.dt == sys.dt
    assert list(ss.sys.output_labels[:n]) == [f"{s}_hat" for s in sys.state_labels]
    resp = ct.forced_response(ss.sys, inputs=np.vstack([u, y])[:, kc:],
                              initial_state=res.x_pred[:, kc])
    out = np.asarray(resp.outputs).reshape(n + md, -1)
    sx = np.max(np.abs(res.x_filt))
    np.testing.assert_allclose(out[:n], res.x_filt[:, kc:], rtol=0, atol=1e-10 * sx)
    if md:
        # output at step k estimates d[k-1]
        sd = np.max(np.abs(res.d_est[:, :-1]))
        np.testing.assert_allclose(out[n:], res.d_est[:, kc - 1:-1], rtol=0, atol=1e-10 * sd)
        np.testing.assert_allclose(ss.d_cov, res.d_cov, rtol=1e-10)
        np.testing.assert_allclose(ss.M, res.M, rtol=0, atol=1e-10 * np.max(np.abs(ss.M)))
    np.testing.assert_allclose(ss.P_filt, res.P_filt, rtol=0,
                               atol=1e-10 * np.max(np.abs(ss.P_filt)))


# --------------------------------------------------------------------------- tape drive
def test_tape_drive_uikf_beats_kalman_filter():
    """On the tape drive (truth: the true model with tension, noise Q and R) the
    unknown-input filter recovers the tension to about its own sqrt(Pd), far
    better than the Kalman filter of the nominal model, and has a lower EE.

    Thresholds: the UIF's tension error must be within 20 % of sqrt(Pd) (its
    theoretical level; the rest is the discretization mismatch between the true
    model and nominal + G T), at most 1/10 of the error of the KF's implicit
    estimate (zero), and at most 1/3 of the error of c_T x^ from the KF.
    """
    dt, N = gb.TAPE_DRIVE_DT, 5000
    rng = np.random.default_rng(61)
    Q, R = gb.TAPE_DRIVE_Q, gb.TAPE_DRIVE_R
    u = gb.lowpass_noise(N, dt=dt, bandwidth=20, nsignals=2, amplitude=1.0, rng=rng)
    sim = gb.simulate(gb.tape_drive_true(dt=dt), u, Q=Q, R=R, rng=rng)
    T = (gb.tape_drive_tension() @ sim.x)[0]
    nom = gb.tape_drive_nominal(dt=dt)
    uif = gb.uikf(nom, sim.y, u, unknown="T", Q=Q, R=R)
    kf = gb.kalman_filter(nom, sim.y, u, unknown="T", Q=Q, R=R)
    w = slice(100, N - 1)  # after the transient; last d_est is NaN
    rms = lambda z: np.sqrt(np.mean(z**2))  # noqa: E731
    err_uif = rms(uif.d_est[0, w] - T[w])
    err_kf_zero = rms(T[w])
    err_kf_law = rms((gb.tape_drive_tension() @ kf.x_filt)[0, w] - T[w])
    sd = np.sqrt(uif.d_cov[0, 0])
    assert err_uif < 1.2 * sd, (err_uif, sd)
    assert err_uif < 0.1 * err_kf_zero, (err_uif, err_kf_zero)
    assert err_uif < err_kf_law / 3, (err_uif, err_kf_law)
    ee_uif, ee_kf = _ee(sim.y, uif.y_filt), _ee(sim.y, kf.y_filt)
    assert ee_uif < ee_kf / 2, (ee_uif, ee_kf)


# --------------------------------------------------------------------------- error paths
@pytest.fixture
def base(random_system, rng):
    """A valid call of uikf: (sys, kwargs) on a random 3-state model with md = 1."""
    rs = random_system(rng, n=3, m=1, p=2, md=1)
    N = 50
    kw = dict(y=rng.standard_normal((2, N)), u=rng.standard_normal((1, N)), unknown="d0",
              Q=rs.Q, R=rs.R, x0=np.zeros(3), P0=np.eye(3))
    return rs, kw


def _bad_sym(n):
    M = np.eye(n)
    M[0, 1] = 0.5
    return M


def _indefinite(n):
    M = np.eye(n)
    M[0, 0] = -1.0
    return M


def _nan_at(shape, i, k, value=np.nan):
    a = np.ones(shape)
    a[i, k] = value
    return a


ERROR_CASES = [
    # (id, changes to the valid kwargs, exception, match)
    ("y-rows", dict(y=np.ones((1, 50))), DimensionError,
     r"y has shape \(1, 50\); expected \(2, nsteps\)"),
    ("y-transposed", dict(y=np.ones((50, 2))), DimensionError,
     r"expected \(2, nsteps\).*transpose"),
    ("y-3d", dict(y=np.ones((2, 50, 1))), DimensionError, r"y has shape \(2, 50, 1\)"),
    ("y-too-short", dict(y=np.ones((2, 1)), u=np.ones((1, 1))), DataError, r"y has 1 samples"),
    ("u-rows", dict(u=np.ones((2, 50))), DimensionError,
     r"u has shape \(2, 50\); expected \(1, nsteps\)"),
    ("u-length", dict(u=np.ones((1, 49))), DimensionError,
     r"different numbers of samples.*y: 50, u: 49"),
    ("u-missing", dict(u=None), DimensionError, r"1 known inputs.*pass u with shape \(1, nsteps\)"),
    ("Q-shape", dict(Q=np.eye(2)), DimensionError, r"Q has shape \(2, 2\); expected \(3, 3\)"),
    ("R-shape", dict(R=np.eye(3)), DimensionError, r"R has shape \(3, 3\); expected \(2, 2\)"),
    ("P0-shape", dict(P0=np.eye(4)), DimensionError, r"P0 has shape \(4, 4\); expected \(3, 3\)"),
    ("x0-shape", dict(x0=np.zeros(2)), DimensionError, r"x0 has 2 entries; expected nstates = 3"),
    ("x0-nan", dict(x0=[0.0, np.nan, 0.0]), DataError, r"x0 contains NaN"),
    ("y-nan", dict(y=_nan_at((2, 50), 1, 7)), DataError,
     r"y contains NaN or inf \(first at signal 1, sample 7\)"),
    ("y-inf", dict(y=_nan_at((2, 50), 0, 3, np.inf)), DataError, r"y contains NaN or inf"),
    ("u-nan", dict(u=_nan_at((1, 50), 0, 9)), DataError,
     r"u contains NaN or inf \(first at signal 0, sample 9\)"),
    ("u-inf", dict(u=_nan_at((1, 50), 0, 0, -np.inf)), DataError, r"u contains NaN or inf"),
    ("Q-nan", dict(Q=_nan_at((3, 3), 0, 0)), DataError, r"Q contains NaN or inf"),
    ("Q-nonsymmetric", dict(Q=_bad_sym(3)), CovarianceError, r"Q is not symmetric"),
    ("Q-indefinite", dict(Q=_indefinite(3)), CovarianceError, r"Q is not positive semidefinite"),
    ("R-nonsymmetric", dict(R=_bad_sym(2)), CovarianceError, r"R is not symmetric"),
    ("R-indefinite", dict(R=_indefinite(2)), CovarianceError, r"R is not positive definite"),
    ("R-singular", dict(R=np.diag([1.0, 0.0])), CovarianceError, r"R is not positive definite"),
    ("P0-nonsymmetric", dict(P0=_bad_sym(3)), CovarianceError, r"P0 is not symmetric"),
    ("P0-indefinite", dict(P0=_indefinite(3)), CovarianceError,
     r"P0 is not positive semidefinite"),
    ("unknown-label", dict(unknown="tension"), DimensionError,
     r"unknown: no signal named 'tension'; available: \['u0', 'd0'\]"),
    ("unknown-index", dict(unknown=5), DimensionError, r"unknown: index 5 out of range"),
    ("unknown-repeated", dict(unknown=["d0", 1]), DimensionError, r"repeated"),
    ("unknown-empty", dict(unknown=[]), DimensionError, r"name at least one unknown-input"),
    ("unknown-none", dict(unknown=None), DimensionError, r"name at least one unknown-input"),
    ("level-one", dict(level=1.0), DimensionError, r"level must be in \(0, 1\); found 1.0"),
    ("level-above", dict(level=1.5), DimensionError, r"level must be in \(0, 1\)"),
    ("level-zero", dict(level=0.0), DataError, r"level must be finite and > 0"),
    ("level-negative", dict(level=-0.5), DataError, r"level must be finite and > 0"),
    ("level-nan", dict(level=np.nan), DataError, r"level must be finite"),
    ("gain-bad", dict(gain="steady"), DimensionError,
     r"gain must be 'auto' or 'time-varying'; found 'steady'"),
    ("tol-zero", dict(tol=0.0), DataError, r"tol must be finite and > 0"),
]


@pytest.mark.parametrize("changes,exc,match", [c[1:] for c in ERROR_CASES],
                         ids=[c[0] for c in ERROR_CASES])
def test_uikf_error_paths(base, changes, exc, match):
    rs, kw = base
    kw = {**kw, **changes}
    y = kw.pop("y")
    u = kw.pop("u")
    with pytest.raises(exc, match=match):
        gb.uikf(rs.sys, y, u, **kw)


@pytest.mark.parametrize("changes,exc,match", [
    (dict(y=np.ones((3, 50))), DimensionError, r"y has shape \(3, 50\); expected \(2, nsteps\)"),
    (dict(Q=np.eye(4)), DimensionError, r"Q has shape \(4, 4\); expected \(3, 3\)"),
    (dict(R=_indefinite(2)), CovarianceError, r"R is not positive definite"),
    (dict(y=_nan_at((2, 50), 0, 4)), DataError, r"y contains NaN"),
    (dict(gain="fixed"), DimensionError, r"gain must be 'auto' or 'time-varying'"),
    (dict(unknown="nope"), DimensionError, r"no signal named 'nope'"),
], ids=["y-rows", "Q-shape", "R-indefinite", "y-nan", "gain-bad", "unknown-label"])
def test_kalman_filter_error_paths(base, changes, exc, match):
    rs, kw = base
    kw = {**kw, **changes}
    y, u = kw.pop("y"), kw.pop("u")
    with pytest.raises(exc, match=match):
        gb.kalman_filter(rs.sys, y, u, **kw)


def test_continuous_time_model_rejected(base):
    rs, kw = base
    cont = gb.named_ss(rs.A, np.hstack([rs.B, rs.G]), rs.C, np.zeros((2, 2)), 0,
                       states=["a", "b", "c"], inputs=["u0", "d0"], outputs=["y0", "y1"])
    y, u = kw.pop("y"), kw.pop("u")
    with pytest.raises(ModelError, match=r"continuous-time model \(dt=0\).*discretize"):
        gb.uikf(cont, y, u, **kw)
    with pytest.raises(ModelError, match=r"continuous-time"):
        gb.kalman_filter(cont, y, u, Q=kw["Q"], R=kw["R"], unknown="d0")
    with pytest.raises(ModelError, match=r"continuous-time"):
        gb.steady_state_filter(cont, Q=kw["Q"], R=kw["R"], unknown="d0")
    unspecified = ct.ss(rs.A, np.hstack([rs.B, rs.G]), rs.C, np.zeros((2, 2)), True)
    with pytest.raises(ModelError, match=r"unspecified sampling period"):
        gb.uikf(unspecified, y, u, **{**kw, "unknown": 1})


def test_not_a_statespace_rejected(base):
    rs, kw = base
    y, u = kw.pop("y"), kw.pop("u")
    with pytest.raises(ModelError, match=r"must be a control.StateSpace; found TransferFunction"):
        gb.uikf(ct.tf([1], [1, 0.5], 0.1), y, u, **kw)


def test_unknown_input_feedthrough_rejected(base):
    rs, kw = base
    sys = gb.named_ss(rs.A, np.hstack([rs.B, rs.G]), rs.C,
                      np.hstack([rs.D, [[0.0], [1.0]]]), rs.dt, states=["a", "b", "c"],
                      inputs=["u0", "d0"], outputs=["y0", "y1"])
    y, u = kw.pop("y"), kw.pop("u")
    with pytest.raises(ModelError, match=r"unknown inputs \['d0'\] feed through"):
        gb.uikf(sys, y, u, **kw)


def _rank_case(kind, rng):
    """Models violating (17): returns (sys, unknown, match)."""
    n, p = 3, 2
    A = 0.5 * np.eye(n)
    C = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    if kind == "CG-zero-column":
        G = np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])  # d1 drives x2, not measured
        match = (r"rank\(C @ G\) = 1 < md = 2 \(17\); channel\(s\) \['d1'\] do not reach "
                 r"any output")
    elif kind == "CG-not-separable":
        G = np.array([[1.0, 1.0], [0.0, 0.0], [0.0, 1.0]])  # both reach only y0
        match = r"rank\(C @ G\) = 1 < md = 2 \(17\); channels \['d0', 'd1'\] are not separable"
    elif kind == "G-dependent":
        G = np.array([[1.0, 2.0], [1.0, 2.0], [0.0, 0.0]])
        match = r"rank\(G\) = 1 < md = 2.*\['d0', 'd1'\].*\(17\)"
    else:  # more unknown inputs than outputs
        G = np.eye(3)
        match = r"3 unknown inputs \['d0', 'd1', 'd2'\] but only 2 outputs.*\(17\)"
    md = G.shape[1]
    sys = gb.named_ss(A, G, C, np.zeros((p, md)), 0.1, states=["a", "b", "c"],
                      inputs=[f"d{j}" for j in range(md)], outputs=["y0", "y1"])
    return sys, list(range(md)), match


@pytest.mark.parametrize("kind", ["CG-zero-column", "CG-not-separable", "G-dependent",
                                  "md-above-p"])
def test_rank_condition_violated(kind, rng):
    sys, unknown, match = _rank_case(kind, rng)
    y = rng.standard_normal((2, 20))
    with pytest.raises(RankConditionError, match=match):
        gb.uikf(sys, y, unknown=unknown, Q=np.eye(3), R=np.eye(2))
    with pytest.raises(RankConditionError, match=match):
        gb.steady_state_filter(sys, Q=np.eye(3), R=np.eye(2), unknown=unknown)
    # the Kalman filter ignores d: no rank condition
    res = gb.kalman_filter(sys, y, unknown=unknown, Q=np.eye(3), R=np.eye(2))
    assert res.d_est.shape == (0, 20)


def test_check_rank_condition_passes_and_names_labels():
    C = np.eye(2)
    gb.check_rank_condition(C, np.array([[1.0], [2.0]]))  # returns None: no error
    gb.check_rank_condition(C, np.zeros((2, 0)))  # md = 0: nothing to check
    with pytest.raises(RankConditionError, match=r"\['tension'\] do not reach any output"):
        gb.check_rank_condition(np.array([[1.0, 0.0]]), np.array([[0.0], [1.0]]),
                                labels=["tension"])


def test_steady_state_filter_not_converging():
    """(A, C) not detectable with Q > 0 on the unstable mode: P grows without bound."""
    sys = gb.named_ss(np.diag([2.0, 0.5]), np.zeros((2, 1)), [[0.0, 1.0]], [[0.0]], 1.0,
                      states=["a", "b"], inputs=["u"], outputs=["y"])
    with pytest.raises(GreyboxError, match=r"did not converge in 50 iterations.*detectable"):
        gb.steady_state_filter(sys, Q=np.eye(2), R=[[1.0]], maxiter=50)


def test_unknown_keyword_rejected(base):
    rs, kw = base
    y, u = kw.pop("y"), kw.pop("u")
    with pytest.raises(TypeError, match=r"unexpected keyword argument 'G'"):
        gb.uikf(rs.sys, y, u, G=rs.G, **kw)
