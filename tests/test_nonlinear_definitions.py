"""Two ways a correct nonlinear model used to be "updated": a law in a kinematic
identity (dp/dt = v, a definition), and greybox's own RK4 discretization error read
as model error (one sub-step where the record needs two).

Truth: models whose identities are known by construction; RK4 with 8x the
sub-steps checked as the reference integrator (RK4's error falls as h^4: 4096x less).
"""

from __future__ import annotations

import control as ct
import numpy as np
import pytest

import greybox as gb
from greybox import zoo


def _model(dt=0):
    """p' = v (identity), v' = -k p - c v^3 + F, q' = 2 v (scaled: no identity),
    z' = v + 0.1 F (an input: no identity), w' = -w (own state: no identity)."""
    def f(t, x, u, par):
        p, v, q, z, w = x
        return np.array([v, -3.0 * p - 0.5 * v ** 3 + u[0], 2.0 * v, v + 0.1 * u[0], -w])

    return ct.nlsys(f, lambda t, x, u, par: x[:2], states=["p", "v", "q", "z", "w"],
                    inputs=["F"], outputs=["p", "v"], dt=dt, name="m")


def test_kinematic_identities_are_the_unscaled_input_free_rows():
    rng = np.random.default_rng(0)
    X, U = rng.normal(size=(5, 40)), rng.normal(size=(1, 40))
    assert gb.kinematic_identities(_model(), X, U) == ["p"]
    # a discrete model mixes the rows: no identity is read from it
    assert gb.kinematic_identities(_model(dt=0.1), X, U) == []


def _duffing(m, k, k3):
    def f(t, x, u, par):
        return np.array([x[1], (-k * x[0] - k3 * x[0] ** 3 - 0.3 * x[1] + u[0]) / m])

    return ct.nlsys(f, lambda t, x, u, par: x, states=["p", "v"], inputs=["F"],
                    outputs=["p", "v"], name="duffing")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_step_doubling_bounds_the_discretization_error_of_a_hardening_spring(seed):
    """A hardening spring driven to large amplitude is stiffer there than at rest, where
    the local rule looks: the count from step doubling keeps the record's RK4 error
    within its tolerance, against a 64-sub-step reference."""
    rng = np.random.default_rng(seed)
    m, k, k3 = rng.uniform(0.5, 2.0), rng.uniform(10, 20), rng.uniform(500, 800)
    dt, N = 0.03, 1000
    u = np.convolve(rng.normal(size=N), np.ones(8) / 8, mode="same")[None, :] * 8.0
    sys = _duffing(m, k, k3)
    tol = np.array([1e-4, 1e-3])
    s0 = gb.rk4_substeps(sys, dt)
    s = gb.rk4_substeps_for(sys, dt, u, x0=np.zeros(2), tol=tol, start=s0)
    # reference: 8x the sub-steps, 8^4 = 4096x less error than the count checked
    ref = gb.simulate_nonlinear(gb.discretize_nonlinear(sys, dt, substeps=8 * s), u).y_clean
    err = np.sqrt(np.mean((gb.simulate_nonlinear(
        gb.discretize_nonlinear(sys, dt, substeps=s), u).y_clean - ref) ** 2, axis=1))
    # the doubling's difference is 15/16 of the error of s sub-steps (RK4, 16x per
    # doubling) when the error is asymptotic: 10 % more allowed for the pre-asymptotic part
    assert np.all(err <= 1.1 * 16 / 15 * tol), (s, err)
    err0 = np.sqrt(np.mean((gb.simulate_nonlinear(
        gb.discretize_nonlinear(sys, dt, substeps=s0), u).y_clean - ref) ** 2, axis=1))
    assert s > s0 and np.any(err0 > tol), (s0, err0)  # the local rule alone misses it


def test_a_correct_nonlinear_model_is_not_updated():
    """A zoo draw (Duffing, p and v measured, N = 4000) that was given a law in eq(p),
    a definition, while RK4 at one sub-step left 0.4 % error: now left unchanged."""
    d = zoo.draw_class("correct_nonlinear", 1641989470, 1, n_est=4000)
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt)
    assert not rep.updated, rep.message
    assert "eq(p)" not in {c.channel for c in rep.candidates}


def test_a_viscous_term_is_named_alone_not_with_the_nominal_s_own_terms():
    """d^ is held over each sample, so it estimates the continuous law's mean over the
    sample. Fitted on the terms at the sample's start, a law -c v picked up c dt / 2 times
    the acceleration, i.e. every term of the nominal's own equation: a zoo draw (Duffing,
    omitted damping -0.445 v, dt = 0.025 s) came out as -0.441 v + 3.21 p^3 + 0.084 p -
    0.005 F (each 0.6 % = c dt / 2 of the nominal's term), SE 2.35 % against the true
    model's 0.171 %. On the midpoint state: the one true term."""
    d = zoo.draw_class("nonlinear_model", 1641989470, 0, n_est=4000)
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt)
    s = zoo.score(d, rep)
    assert rep.updated and s.right_channel and s.right_terms, (s.why, s.found)
    # the coefficient within 2 % (its interval is ~0.05 %; the zoo asks 10 %)
    law = rep.effect.law
    (j,) = np.flatnonzero(law.coef[0])
    np.testing.assert_allclose(law.coef[0, j], d.truth.effects[0].terms[0].coefficient,
                               rtol=0.02)
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)
