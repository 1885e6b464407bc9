"""A continuous-time law integrated over each sample (greybox.hold.LawHold) against the truth.

The truth: scipy's adaptive Runge-Kutta (DOP853 at rtol 1e-12) on the continuous
model with the input held over each sample, as ZOH data are. The order of the
scheme is read off the error's ratio when the sampling period halves.
"""

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

import greybox as gb
from greybox.hold import LawHold, as_hold
from greybox.filters.delayed import first_order_hold
from greybox.nonlinear import add_law, simulate_nonlinear

# a mass on a cubic spring with a linear damper, a force input (SI units)
AC = np.array([[0.0, 1.0], [-4.0, -0.3]])
BC = np.array([[0.0], [1.0]])
GC = np.array([[0.0], [1.0]])
C3 = 6.0  # [N/m^3]


def _law(x, u):
    """(1,) for x of shape (2,), (1, K) for (2, K)."""
    return -C3 * np.asarray(x)[0:1] ** 3


def _truth(dt, u, x0):
    x, out = np.array(x0, dtype=float), []
    for k in range(u.shape[1]):
        out.append(x)
        rhs = lambda t, z, uk=u[:, k]: AC @ z + BC @ uk + GC @ _law(z[:, None], uk)[:, 0]
        x = solve_ivp(rhs, (0, dt), x, method="DOP853", rtol=1e-12, atol=1e-14).y[:, -1]
    return np.array(out).T


def _scheme(dt, u, x0, hold):
    M = expm(np.block([[AC, BC], [np.zeros((1, 3))]]) * dt)
    A, B = M[:2, :2], M[:2, 2:]
    x, out = np.array(x0, dtype=float)[:, None], []
    for k in range(u.shape[1]):
        out.append(x[:, 0])
        x = hold.step(A, x, B @ u[:, k:k + 1], lambda Z, uk=u[:, k:k + 1]: _law(Z, uk))
    return np.array(out).T


def _error(dt, make):
    T = 6.0
    N = int(round(T / dt))
    t = np.arange(N) * dt
    u = np.sin(1.3 * t)[None] * 2.0  # held over each sample
    x0 = [0.8, 0.0]
    return np.max(np.abs(_scheme(dt, u, x0, make(dt)) - _truth(dt, u, x0)))


def test_the_law_is_integrated_to_fourth_order():
    # ETDRK4: the error falls ~16x when dt halves; 10x allows the pre-asymptotic range
    # (measured 17.2x and 17.7x); the first-order hold's Heun step only ~4x (4.4x: second order)
    e = [_error(dt, lambda h: LawHold.of(AC, GC, h)) for dt in (0.2, 0.1, 0.05)]
    assert e[0] / e[1] > 10 and e[1] / e[2] > 10, e
    h = [_error(dt, lambda s: as_hold(first_order_hold(AC, GC, s))) for dt in (0.2, 0.1)]
    assert 3 < h[0] / h[1] < 6, h
    assert e[0] < h[0] / 20, (e, h)  # at the same sampling far closer to the truth (37x)


def test_first_order_hold_weights_are_the_holds():
    hold = LawHold.of(AC, GC, 0.1)
    G0, G1 = first_order_hold(AC, GC, 0.1)
    np.testing.assert_allclose(hold.G0, G0, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(hold.G1, G1, rtol=1e-12, atol=1e-15)
    # a constant law over the sample enters as the ZOH input matrix: G0 + G1 = int e^(A s) ds G
    Gd = expm(np.block([[AC, GC], [np.zeros((1, 3))]]) * 0.1)[:2, 2:]
    np.testing.assert_allclose(hold.G0 + hold.G1, Gd, rtol=1e-12, atol=1e-15)


def test_add_law_simulates_the_law_as_the_trace_does():
    dt = 0.1
    sys = gb.discretize(gb.named_ss(AC, BC, np.eye(2), np.zeros((2, 1)), 0, states=["p", "v"],
                                    inputs=["F"], outputs=["p", "v"]), dt)
    hold = LawHold.of(AC, GC, dt)
    u = np.sin(1.3 * np.arange(60) * dt)[None] * 2.0
    x0 = np.array([0.8, 0.0])
    model = add_law(sys, np.zeros((2, 1)), _law, hold=hold)
    y = simulate_nonlinear(model, u, x0=x0).y_clean
    np.testing.assert_allclose(y, _scheme(dt, u, x0, hold), rtol=1e-12, atol=1e-14)
    # a (Gamma0, Gamma1) pair (1-D for one law component) is the first-order hold's Heun step
    pair = add_law(sys, np.zeros((2, 1)), _law,
                   hold=(hold.G0[:, 0], hold.G1[:, 0]))
    y2 = simulate_nonlinear(pair, u, x0=x0).y_clean
    np.testing.assert_allclose(y2, _scheme(dt, u, x0, as_hold((hold.G0, hold.G1))), rtol=1e-12,
                               atol=1e-14)
    with pytest.raises(ValueError, match="nstates, K"):
        hold.step(sys.A, x0, np.zeros((2, 1)), lambda Z: _law(Z, u[:, :1]))
    with pytest.raises(gb.ModelError, match="StateSpace"):
        add_law(gb.as_nonlinear(sys), np.zeros((2, 1)), _law, hold=hold)


# Coulomb friction on the same mass, smoothed over a narrow width: the law is faster than a
# sample (its slope FC / EPS = 200 1/s against dt = 0.02 s: rate * dt = 4, past ETDRK4's
# explicit stability near 2.8)
FC, EPS = 2.0, 0.01


def _friction(x, u):
    return -FC * np.tanh(np.asarray(x)[1:2] / EPS)


def _stiff_error(hold, dt=0.02, T=3.0):
    N = int(round(T / dt))
    u = (3.0 * np.sign(np.sin(2.1 * np.arange(N) * dt)))[None]
    x0 = np.array([0.5, 0.0])
    M = expm(np.block([[AC, BC], [np.zeros((1, 3))]]) * dt)
    A, B = M[:2, :2], M[:2, 2:]
    x, ref, out = x0[:, None], x0.copy(), []
    for k in range(N):
        out.append(np.abs(x[:, 0] - ref).max())
        x = hold.step(A, x, B @ u[:, k:k + 1], lambda Z: _friction(Z, None))
        rhs = lambda t, z, uk=u[:, k]: AC @ z + BC @ uk + GC @ _friction(z, None)
        ref = solve_ivp(rhs, (0, dt), ref, method="LSODA", rtol=1e-10, atol=1e-12).y[:, -1]
    return max(out)


def test_a_law_faster_than_a_sample_is_stepped_finely_enough():
    dt = 0.02
    one = LawHold.of(AC, GC, dt)
    rate = FC / EPS  # the law's steepest slope times its weight (GC's column: 1)
    s = one.substeps_for(rate)
    assert s == int(np.ceil(rate * dt / 0.5))  # rate * h <= STEP_RATE (8 sub-steps here)
    fine = one.with_substeps(s)
    assert fine.substeps == s and fine.G0 is not None
    np.testing.assert_allclose(fine.G0, one.G0, rtol=1e-12)  # the sample's own hold kept
    # one step per sample is unstable or far off on this law; the sub-steps follow the
    # truth within 1e-3 of the states' scale (0.5 m; measured 9e-7 with 8 sub-steps, 6e-3 with one)
    e1, es = _stiff_error(one), _stiff_error(fine)
    assert es < 1e-3 and not e1 < 100 * es, (e1, es)
    # the sub-steps' input effect adds up to the sample's: a constant input, no law
    M = expm(np.block([[AC, BC], [np.zeros((1, 3))]]) * dt)
    z = fine.step(M[:2, :2], np.zeros((2, 1)), M[:2, 2:] @ [[1.0]], lambda Z: 0 * Z[:1])
    np.testing.assert_allclose(z[:, 0], M[:2, 2], rtol=1e-12, atol=1e-15)


def test_a_law_takes_the_sub_steps_its_own_rate_needs():
    from greybox.trace.laws import StaticLaw

    dt = 0.02
    spec = (("v", "x", 1), ("sign(v)", "sign", 1))

    def law(coef, eps):
        return StaticLaw(spec=spec, eps=np.array([1.0, eps]), coef=np.array([coef]),
                         Ddx=np.zeros((1, 2)), Ddu=np.zeros((1, 1)), nonlinear=True,
                         residual_var=np.zeros(1), bic_gain=0.0, npar=2, formula="",
                         hold=LawHold.of(AC, GC, dt))

    assert law([-0.3, -FC], EPS).hold.substeps == 8  # 200 1/s * 0.02 s / 0.5
    assert law([-0.3, -FC], 0.1).hold.substeps == 1  # 20 1/s: one step is enough
    assert law([-0.3, 0.0], EPS).hold.substeps == 1  # no sign term: a linear term's slope
    assert law([-0.3, -1e4], EPS).hold.substeps == 32  # at most MAX_SUBSTEPS
