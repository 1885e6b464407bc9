"""The fast paths of the unscented filters agree with the general ones (issue 10, item 6).

The UKF loop (greybox/filters/ukf.py) takes shortcuts for speed: md = 1 in
scalars, C = I, LAPACK Cholesky and solve with a fallback, the sigma points
as ``x + S E``; the motor-pump's f has a batch form. Each shortcut is
checked here against the path it replaces.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

import greybox as gb
from greybox.filters import MerweScaledSigmaPoints, robust_cholesky
from plantlib import linear_as_nlsys
from greybox.plants.motor_pump import MotorPumpParams, _batch_matrix, _rhs, _rhs_batch

UKF_MODULE = sys.modules["greybox.filters.ukf"]


@pytest.fixture
def lin2(rng, random_system):
    """Linear plant with two unknown inputs (the general md > 1 branch)."""
    s = random_system(rng, n=4, m=1, p=3, md=2)
    N = 200
    u = rng.standard_normal((1, N))
    t = np.arange(N)
    d = np.vstack([np.sin(t / 10), np.cos(t / 7)])
    sim = gb.simulate(s.sys, np.vstack([u, d]), Q=s.Q, R=s.R, rng=rng)
    return s, sim, u


def test_ui_ukf_with_two_unknown_inputs_equals_uikf(lin2):
    s, sim, u = lin2
    ref = gb.uikf(s.sys, sim.y, u, unknown=["d0", "d1"], Q=s.Q, R=s.R, gain="time-varying")
    for model in (s.sys, linear_as_nlsys(s)):
        res = gb.ui_ukf(model, sim.y, u, unknown=["d0", "d1"], Q=s.Q, R=s.R)
        # exact unscented transform of a linear map; the nlsys form takes G by central
        # differences (rounding ~eps |F| / h, h = 1e-4): 1e-10 as for md = 1
        np.testing.assert_allclose(res.d_est[:, :-1], ref.d_est[:, :-1], rtol=0, atol=1e-10)
        np.testing.assert_allclose(res.x_filt, ref.x_filt, rtol=0, atol=1e-10)
        np.testing.assert_allclose(res.innovations, ref.innovations, rtol=0, atol=1e-10)
        np.testing.assert_allclose(res.d_var[:, :-1], ref.d_var[:, :-1], rtol=1e-9)
        np.testing.assert_allclose(res.M, ref.M, rtol=0, atol=1e-9)  # gains: 1e-9 (|M| ~ 1)


class LoopedMerwe:
    """A strategy that is not a MerweScaledSigmaPoints: the filters call its points()."""

    def __init__(self):
        self._p = MerweScaledSigmaPoints()

    def weights(self, n):
        return self._p.weights(n)

    def points(self, x, P):
        return self._p.points(x, P)


def test_generic_point_strategy_equals_the_precomputed_offsets():
    sysd = gb.discretize_nonlinear(gb.motor_pump_nominal(), 1e-4, substeps=6)
    N = 200
    rng = np.random.default_rng(3)
    V = 10.0 + 0.2 * rng.standard_normal(N)
    x0 = np.array([5.9, 3.3, 0.9])
    sim = gb.simulate_nonlinear(sysd, np.vstack([V, np.full(N, -200.0)]), x0=x0,
                                Q=gb.MOTOR_PUMP_Q, R=gb.MOTOR_PUMP_R, rng=rng)
    kw = dict(unknown="d", Q=gb.MOTOR_PUMP_Q, R=gb.MOTOR_PUMP_R, x0=x0, P0=1e-4 * np.eye(3))
    for filt in (gb.ukf, gb.ui_ukf):
        a = filt(sysd, sim.y, V[None], **kw)
        b = filt(sysd, sim.y, V[None], points=LoopedMerwe(), **kw)
        # x + S E and the concatenated points are the same numbers (exact zeros in E):
        # only the G probes' column placement differs; 1e-12 of |x| ~ 6
        np.testing.assert_allclose(a.x_filt, b.x_filt, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.d_est, b.d_est, rtol=1e-12, atol=1e-9)
    E = MerweScaledSigmaPoints(alpha=0.5).offsets(3)
    P = np.array([[2.0, 0.3, 0.1], [0.3, 1.0, 0.2], [0.1, 0.2, 0.5]])
    x = np.array([1.0, -2.0, 3.0])
    # the documented identity, to the last bit
    np.testing.assert_array_equal(x[:, None] + robust_cholesky(P) @ E,
                                  MerweScaledSigmaPoints(alpha=0.5).points(x, P))


def test_lapack_failures_fall_back_to_the_general_path(lin2, monkeypatch):
    s, sim, u = lin2
    ref = gb.ui_ukf(s.sys, sim.y, u, unknown=["d0", "d1"], Q=s.Q, R=s.R)
    ref1 = gb.ukf(s.sys, sim.y, u, unknown=["d0", "d1"], Q=s.Q, R=s.R)
    real_potrf, real_posv = UKF_MODULE._dpotrf, UKF_MODULE._dposv

    def potrf_fails(P, **kw):
        S, _ = real_potrf(P, **kw)
        return np.full_like(S, np.nan), 1  # as if P were not positive definite

    def posv_fails(A, B, **kw):
        c, x, _ = real_posv(A, B, **kw)
        return c, np.full_like(x, np.nan), 1  # as if Rt were not: LU solve takes over

    monkeypatch.setattr(UKF_MODULE, "_dpotrf", potrf_fails)
    monkeypatch.setattr(UKF_MODULE, "_dposv", posv_fails)
    res = gb.ui_ukf(s.sys, sim.y, u, unknown=["d0", "d1"], Q=s.Q, R=s.R)
    res1 = gb.ukf(s.sys, sim.y, u, unknown=["d0", "d1"], Q=s.Q, R=s.R)
    # same filter through numpy's LU and the symmetrized Cholesky: rounding only
    np.testing.assert_allclose(res.d_est[:, :-1], ref.d_est[:, :-1], rtol=0, atol=1e-10)
    np.testing.assert_allclose(res.x_filt, ref.x_filt, rtol=0, atol=1e-10)
    np.testing.assert_allclose(res1.x_filt, ref1.x_filt, rtol=0, atol=1e-10)


def test_motor_pump_batch_form_equals_the_equations_point_by_point():
    rng = np.random.default_rng(7)
    p = MotorPumpParams()
    X = np.array([6.0, 4.0, 1.2])[:, None] * (1 + 0.2 * rng.standard_normal((3, 11)))
    V = 10.0 + rng.standard_normal(11)
    load = -200.0 + 10 * rng.standard_normal(11)
    batch = _rhs_batch(X, np.vstack([V, load]), _batch_matrix(p))
    one = np.column_stack([_rhs(X[:, j], V[j], load[j], p) for j in range(11)])
    # a matrix product sums the same terms in another order: dI/dt is a difference of
    # terms ~1e4 (V / L, R0 I / L), so rounding ~1e4 * eps ~ 2e-12 absolute; 1e-14
    # relative to the largest term
    scale = np.array([[10.0 / p.L], [p.Psi * 8 / p.theta], [p.hn * 25]])
    np.testing.assert_allclose(batch / scale, one / scale, rtol=0, atol=1e-14)
    for model in (gb.motor_pump_true(), gb.motor_pump_nominal()):
        sysd = gb.discretize_nonlinear(model, 1e-4, substeps=6)
        U = np.vstack([V, np.full(11, 150.0 if model.name.endswith("true") else -200.0)])
        Fb = sysd.updfcn(0.0, X, U, sysd.params)
        F1 = np.column_stack([sysd.updfcn(0.0, X[:, j], U[:, j], sysd.params)
                              for j in range(11)])
        # one RK4 sample (24 evaluations) of the two forms: rounding only, relative 1e-13
        np.testing.assert_allclose(Fb, F1, rtol=1e-13, atol=0)
        # one input vector for all states broadcasts like a column per state
        np.testing.assert_allclose(sysd.updfcn(0.0, X[:, :2], U[:, 0], sysd.params),
                                   np.column_stack([F1[:, 0], sysd.updfcn(
                                       0.0, X[:, 1], U[:, 0], sysd.params)]),
                                   rtol=1e-13, atol=0)
