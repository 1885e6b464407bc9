"""The delayed unscented unknown-input filter (relative degree 2), against the truth.

Oracles: the linear delayed filter (``delayed_uikf``, relative degree 2,
time-varying gain) on a linear plant written as a ``NonlinearIOSystem``;
a simulated nonlinear two-tank plant whose unknown inflow enters the
unmeasured upper tank (rank(C G) = 0): Monte Carlo unbiasedness of d^ and
NEES of d^ against the reported variance in chi-square bounds.
"""

from __future__ import annotations

from types import SimpleNamespace

import control as ct
import numpy as np
import pytest
from scipy.stats import chi2

import greybox as gb
from greybox.exceptions import GreyboxError, RankConditionError
from greybox.system import named_ss
from plantlib import linear_as_nlsys


# --------------------------------------------------------------------------- plants
def mass(dt=0.05, zoh=False):
    """Mass-spring-damper, position measured, d a force (C G = 0, or small under ZOH)."""
    Ac = np.array([[0.0, 1.0], [-4.0, -0.4]])
    Bc = np.array([[0.0, 0.0], [1.0, 1.0]])  # [u, d]
    if zoh:
        sd = ct.c2d(ct.ss(Ac, Bc, [[1, 0]], [[0, 0]]), dt)
        A, B = np.asarray(sd.A), np.asarray(sd.B)
    else:  # Euler: d drives the velocity only, C G = 0 exactly
        A, B = np.eye(2) + dt * Ac, dt * Bc
    sys = named_ss(A, B, [[1, 0]], [[0, 0]], dt, states=["p", "v"], inputs=["u", "d"],
                   outputs=["p"], name="mass")
    return SimpleNamespace(sys=sys, dt=dt)


A1, A2, B4, DT = 0.5, 0.4, 0.5, 1.0


def tanks_model():
    """Discrete two tanks: x1 upper (unmeasured, unknown inflow d), y = x2."""
    def f(t, x, u, p):
        s1 = np.sqrt(np.abs(x[0]))
        return np.stack([x[0] + DT * (-A1 * s1 + B4 * u[0] + u[1]),
                         x[1] + DT * (A1 * s1 - A2 * np.sqrt(np.abs(x[1])))])

    return ct.nlsys(f, lambda t, x, u, p: x[1:], states=["x1", "x2"], inputs=["u", "d"],
                    outputs=["y"], dt=DT, name="tanks")


Q_T = np.diag([1e-6, 1e-6])
R_T = np.array([[1e-6]])
D_STD = 0.05


def tanks_run(rng, N):
    """One record of the true tanks: u, d (white, unknown), y; x (2, N)."""
    u = np.repeat(rng.uniform(0.6, 1.6, N // 10 + 1), 10)[None, :N]
    d = D_STD * rng.standard_normal(N)
    x = np.empty((2, N))
    xk = np.array([1.0, 1.6])
    for k in range(N):
        x[:, k] = xk
        s1 = np.sqrt(xk[0])
        xk = np.array([xk[0] + DT * (-A1 * s1 + B4 * u[0, k] + d[k]),
                       xk[1] + DT * (A1 * s1 - A2 * np.sqrt(xk[1]))])
        xk = xk + np.sqrt(np.diag(Q_T)) * rng.standard_normal(2)
    y = x[1:] + np.sqrt(R_T[0, 0]) * rng.standard_normal((1, N))
    return u, d, x, y


# --------------------------------------------------------------------------- oracles
@pytest.mark.parametrize("zoh", [False, True], ids=["euler-CG-zero", "zoh-CG-small"])
def test_linear_plant_as_nlsys_equals_the_linear_delayed_filter(zoh):
    s = mass(zoh=zoh)
    rng = np.random.default_rng(3)
    N = 300
    u = rng.standard_normal((1, N))
    dtrue = np.sin(0.05 * np.arange(N))
    sim = gb.simulate(s.sys, np.vstack([u, dtrue[None]]), rng=rng)
    Q, R = np.diag([1e-8, 1e-6]), np.array([[1e-6]])
    ref = gb.delayed_uikf(s.sys, sim.y, u, unknown="d", Q=Q, R=R, relative_degree=2,
                          gain="time-varying", store_covariances=True)
    for model in (s.sys, linear_as_nlsys(s)):
        res = gb.delayed_ui_ukf(model, sim.y, u, unknown="d", Q=Q, R=R)
        assert res.relative_degree == 2
        # the unscented transform is exact for a linear map, and F_z is the linear shifted
        # model exactly; the per-step dF_z/dd by central differences of an affine map
        # rounds at ~eps |F| / h (h = 1e-4): 1e-9 relative to the signals' scale
        ok = ~np.isnan(ref.d_est[0])
        np.testing.assert_array_equal(np.isnan(res.d_est[0]), ~ok)
        scale = np.max(np.abs(ref.d_est[:, ok]))
        np.testing.assert_allclose(res.d_est[:, ok], ref.d_est[:, ok], rtol=0, atol=1e-9 * scale)
        np.testing.assert_allclose(res.d_var[:, ok], ref.d_var[:, ok], rtol=1e-7)
        okx = ~np.isnan(ref.x_filt[0])
        np.testing.assert_allclose(res.x_filt[:, okx], ref.x_filt[:, okx], rtol=0,
                                   atol=1e-9 * np.max(np.abs(ref.x_filt[:, okx])))
        np.testing.assert_allclose(res.innovations, ref.innovations, rtol=0, atol=1e-9)
        np.testing.assert_allclose(res.G, s.sys.B[:, 1:], rtol=0, atol=1e-9)


def test_rank_one_channel_is_the_plain_unscented_filter():
    """C G of full rank: "auto" keeps r = 1, the record is ui_ukf's."""
    s = mass(zoh=False)
    A, B = np.asarray(s.sys.A), np.asarray(s.sys.B)
    both = named_ss(A, B, np.eye(2), np.zeros((2, 2)), s.dt, states=["p", "v"],
                    inputs=["u", "d"], outputs=["p", "v"])
    rng = np.random.default_rng(4)
    u = rng.standard_normal((1, 200))
    sim = gb.simulate(both, np.vstack([u, 0.3 * np.ones((1, 200))]), rng=rng)
    Q, R = np.diag([1e-8, 1e-8]), np.diag([1e-6, 1e-6])
    res = gb.delayed_ui_ukf(both, sim.y, u, unknown="d", Q=Q, R=R)
    ref = gb.ui_ukf(both, sim.y, u, unknown="d", Q=Q, R=R)
    assert res.relative_degree == 1
    # the same computation on a StateSpace turned NonlinearIOSystem: rounding only
    np.testing.assert_allclose(res.d_est[:, :-1], ref.d_est[:, :-1], rtol=0, atol=1e-9)


# --------------------------------------------------------------------------- the truth
@pytest.fixture(scope="module")
def tanks_mc():
    """Monte Carlo: 120 records of 160 samples; d^ error and reported variance at j = 60, 150."""
    rng = np.random.default_rng(2012)
    model = tanks_model()
    err, var, xerr = [], [], []
    for _ in range(120):
        u, d, x, y = tanks_run(rng, 160)
        res = gb.delayed_ui_ukf(model, y, u, unknown="d", Q=Q_T, R=R_T, x0=[1.0, 1.6],
                                P0=np.diag([1e-2, 1e-2]))
        assert res.relative_degree == 2
        j = np.array([60, 150])
        err.append(res.d_est[0, j] - d[j])
        var.append(res.d_var[0, j])
        xerr.append(res.x_filt[0, 100] - x[0, 100])
    return np.array(err), np.array(var), np.array(xerr)


def test_nonlinear_tanks_delayed_estimate_is_unbiased(tanks_mc):
    err, var, xerr = tanks_mc
    M = err.shape[0]
    # independent records: the mean error over M records has std sqrt(mean var / M); a
    # biased estimate (e.g. d[j-1] or the r = 1 filter's alternating d^) is off by ~D_STD
    z = err.mean(axis=0) / np.sqrt(var.mean(axis=0) / M)
    assert np.all(np.abs(z) < 3.5), z
    # and the estimate is informative: d[j] shows in y[j+2] through C (dF/dx) G~ ~ 0.25 (at
    # x1 ~ 1), so a second difference of the 1e-3 sensor noise alone is ~ 2.5e-3 / 0.25 =
    # 0.01; the reported std must be of that order, well below d's own 0.05
    assert 0.003 < np.sqrt(var.mean()) < 0.4 * D_STD
    # the unshifted upper-tank level x^[k|k+1] is unbiased too (state std ~ 1e-3 per step)
    assert abs(xerr.mean()) < 3.5 * xerr.std() / np.sqrt(M)


def test_nonlinear_tanks_nees_within_chi_square_bounds(tanks_mc):
    err, var, _ = tanks_mc
    M = err.shape[0]
    for c in range(err.shape[1]):  # one time index at a time: M independent terms
        nees = float(np.sum(err[:, c] ** 2 / var[:, c]))
        lo, hi = chi2.ppf([0.0005, 0.9995], M)
        assert lo < nees < hi, (c, nees / M)


def test_rk4_tanks_with_small_cg_estimate_the_input_weights_combination():
    """d held over the sample inside RK4 (C G ~ 0.11 != 0, forced r = 2, G at the mean state).

    Then, as for the linear delayed filter, d^[j] estimates ``w0 d[j] + w1 d[j+1]``
    with the weights of ``input_weights`` on the linearization (the part of d[j+1]
    that shows in y[j+1] is not modelled): unbiased for it, NEES in bounds.
    """
    def f(t, x, u, p):
        s1 = np.sqrt(np.abs(x[0]))
        return np.stack([-A1 * s1 + B4 * u[0] + u[1], A1 * s1 - A2 * np.sqrt(np.abs(x[1]))])

    cont = ct.nlsys(f, lambda t, x, u, p: x[1:], states=["x1", "x2"], inputs=["u", "d"],
                    outputs=["y"], dt=0)
    model = gb.discretize_nonlinear(cont, DT, substeps=4)
    lin = gb.linearize_at(model, [1.0, 1.56], [1.0, 0.0])
    G = np.asarray(lin.B)[:, 1:]
    w, misfit = gb.input_weights(lin, unknown="d", r=2)
    assert G[1, 0] > 0.05 and misfit < 1e-9  # C G clearly nonzero; weights exact (linear)
    rng = np.random.default_rng(7)
    err, var, M = [], [], 120
    for _ in range(M):
        N = 160
        u = np.repeat(rng.uniform(0.6, 1.6, N // 10 + 1), 10)[None, :N]
        d = D_STD * rng.standard_normal(N)
        x, xk = np.empty((2, N)), np.array([1.0, 1.56])
        for k in range(N):
            x[:, k] = xk
            xk = model.updfcn(0, xk, np.array([u[0, k], d[k]]), {}) + \
                np.sqrt(np.diag(Q_T)) * rng.standard_normal(2)
        y = x[1:] + np.sqrt(R_T[0, 0]) * rng.standard_normal((1, N))
        res = gb.delayed_ui_ukf(model, y, u, unknown="d", Q=Q_T, R=R_T, x0=[1.0, 1.56],
                                P0=np.diag([1e-2, 1e-2]), G=G, relative_degree=2)
        j = np.array([60, 150])
        err.append(res.d_est[0, j] - (w[0, 0, 0] * d[j] + w[1, 0, 0] * d[j + 1]))
        var.append(res.d_var[0, j])
    err, var = np.array(err), np.array(var)
    # measured z = 1.09, -0.80 and NEES / M = 1.09, 1.05 (bounds 0.63-1.48)
    assert np.all(np.abs(err.mean(axis=0) / np.sqrt(var.mean(axis=0) / M)) < 3.5)
    lo, hi = chi2.ppf([0.0005, 0.9995], M)
    nees = np.sum(err**2 / var, axis=0)
    assert np.all((lo < nees) & (nees < hi)), nees / M


# --------------------------------------------------------------------------- errors
def test_bad_relative_degree_is_refused():
    s = mass()
    y, u = np.zeros((1, 50)), np.zeros((1, 50))
    with pytest.raises(GreyboxError, match="relative_degree must be 'auto', 1 or 2"):
        gb.delayed_ui_ukf(s.sys, y, u, unknown="d", Q=np.eye(2), R=[[1]], relative_degree=3)
    with pytest.raises(GreyboxError, match="relative_degree must be 'auto', 1 or 2; found"):
        gb.delayed_ui_ukf(s.sys, y, u, unknown="d", Q=np.eye(2), R=[[1]], relative_degree="x")


def test_unobservable_within_two_steps_is_refused():
    """d enters the first of three integrators, only the third is measured: r = 3."""
    A = np.array([[1.0, 0, 0], [0.1, 1, 0], [0, 0.1, 1]])
    B = np.array([[1.0, 1.0], [0, 0], [0, 0]])
    sys = named_ss(A, B, [[0, 0, 1]], [[0, 0]], 0.1, states=["a", "b", "c"],
                   inputs=["u", "d"], outputs=["y"])
    y, u = np.zeros((1, 50)), np.zeros((1, 50))
    with pytest.raises(RankConditionError, match="relative degree 2 either"):
        gb.delayed_ui_ukf(sys, y, u, unknown="d", Q=np.eye(3), R=[[1]])
    with pytest.raises(RankConditionError, match=r"rank\(C @ G\) = 0"):
        gb.delayed_ui_ukf(sys, y, u, unknown="d", Q=np.eye(3), R=[[1]], relative_degree=1)


def test_steps_where_the_model_does_not_respond_to_d_give_no_estimate():
    """G = dF/dd vanishes for x <= 0 (a level that cannot go below 0): d^ NaN there only."""
    sys = ct.nlsys(lambda t, x, u, p: x + u[0] + u[1] * (x > 0), lambda t, x, u, p: x,
                   states=["h"], inputs=["u", "d"], outputs=["y"], dt=1.0)
    rng = np.random.default_rng(8)
    d = np.r_[0.1 * np.ones(10), -0.6 * np.ones(10), 0.05 * np.ones(10)]
    u = np.r_[np.zeros(16), 0.25 * np.ones(14)]  # a known refill from the 16th sample on
    h = np.empty(30)
    h[0] = 1.0
    for k in range(29):  # the same law as the model: the level drains below 0, where d
        h[k + 1] = h[k] + u[k] + d[k] * (h[k] > 0)  # no longer acts, then refills
    y = h[None] + 1e-3 * rng.standard_normal((1, 30))
    res = gb.ui_ukf(sys, y, u[None], unknown="d", Q=[[1e-6]], R=[[1e-6]], x0=[1.0],
                    P0=[[1e-4]])
    seen = np.isfinite(res.d_est[0, :-1])
    # d[k-1] is seen in y[k] only where x^[k-1] > 0: not seen at the steps below the floor
    assert not np.all(seen) and np.all(np.isinf(res.d_var[0, :-1][~seen]))
    np.testing.assert_array_equal(seen, res.x_filt[0, :-1] > 0)
    # where it is seen, the estimate is the truth within 4 sigma (sigma ~ 1.4e-3)
    err = (res.d_est[0, :-1] - d[:-1])[seen]
    assert np.all(np.abs(err) < 4 * np.sqrt(res.d_var[0, :-1][seen])), err
