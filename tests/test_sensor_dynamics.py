"""First-order sensor dynamics as an output-channel law (issue 11, item 2).

A mass-spring-damper with a correct state model, position and velocity
measured; the position sensor reads the position through a first-order lag
``1/(tau s + 1)`` (tau = 0.1 s). The trace must name the sensor (an output
channel, not a state equation) and report tau with its 95 % interval.
"""

from __future__ import annotations

import json
from functools import lru_cache

import numpy as np
import pytest
from plantlib import msd, rk4_simulate

import greybox as gb
from greybox.exceptions import ModelError
from greybox.system import discretize, named_ss
from greybox.trace import output_channel, trace_channel

TAU = 0.1  # [s] the position sensor's time constant


@lru_cache(maxsize=None)
def _lag_case(tau: float = TAU, seed: int = 3, n_val: int = 3000):
    """(nominal, y, u, y_val, u_val, Q, R, dt): pos read through 1/(tau s + 1); vel exact.

    ``tau = 0``: the sensor reads pos itself (the model is right). The truth
    has a third state, the sensor's reading z: dz/dt = (pos - z)/tau.
    Process noise on vel only (estimation data), measurement noise 1e-3 on both.
    ``n_val``: validation samples, drawn after the estimation record (which they leave
    unchanged); the tests that trace the estimation record alone take 10 (cheaper).
    """
    nom = msd()
    A, B = np.asarray(nom.A, dtype=float), np.asarray(nom.B, dtype=float)
    rng = np.random.default_rng(seed)
    dt, r_std = 0.01, 1e-3

    def f(x, u):
        return np.r_[A @ x[:2] + B @ u, (x[0] - x[2]) / (tau or 1.0)]

    out = []
    for n, q in ((4000, np.array([0.0, 1e-3])), (n_val, None)):
        u = gb.lowpass_noise(n, dt=dt, bandwidth=1.0, amplitude=4.0, rng=rng).reshape(1, -1)
        x = rk4_simulate(f, np.zeros(3), u, dt, q_std=q, rng=rng)
        y = x[[2 if tau else 0, 1]] + r_std * rng.standard_normal((2, n))
        out += [y, u]
    Q = np.diag([0.0, 1e-6]) + 1e-12 * np.eye(2)
    R = r_std**2 * np.eye(2)
    return (nom, *out, Q, R, dt)


def _true_model(tau: float, dt: float):
    """The truth as a discrete StateSpace (states pos, vel, reading) with its Q."""
    nom = msd()
    A = np.zeros((3, 3))
    A[:2, :2] = np.asarray(nom.A, dtype=float)
    A[2, 0], A[2, 2] = 1.0 / tau, -1.0 / tau
    B = np.vstack([np.asarray(nom.B, dtype=float), [[0.0]]])
    C = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    sys = named_ss(A, B, C, np.zeros((2, 1)), 0, states=["pos", "vel", "z"], inputs=["F"],
                   outputs=["pos", "vel"])
    return discretize(sys, dt), np.diag([0.0, 1e-6, 0.0]) + 1e-12 * np.eye(3)


def _lag(tr):
    """(tau, 95 % half-width) of a trace whose sensor law is a lag; fails otherwise."""
    law = tr.static
    assert [s[1] for s in law.spec] == ["yhat_lag"], law.formula
    return float(law.coef[0, 0]), float(law.ci[0, 0])


def test_lagging_sensor_is_traced_to_the_output():
    nom, y, u, yv, uv, Q, R, dt = _lag_case()
    rep = gb.close_the_loop(nom, y, u, yv, uv, Q=Q, R=R, dt=dt, delta=False)
    assert rep.updated and rep.channel.kind == "output" and rep.channel.output == "pos", \
        rep.message
    assert not rep.channel.equations  # not a state equation
    assert "sensor dynamics, a first-order lag" in rep.message, rep.message
    assert rep.effect.kind == "sensor" and rep.effect.order == 1, rep.effect  # one sensor state
    doc = json.loads(json.dumps(rep.as_dict()))  # the --json document says so too
    assert doc["effect"]["kind"] == "sensor" and doc["effect"]["order"] == 1
    tau, half = _lag(rep.trace)
    # the 95 % interval covers the truth and is informative (measured 0.1000 +- 0.00096 s)
    assert abs(tau - TAU) <= half and half < 0.05 * TAU, (tau, half)
    assert any("first-order lag" in s for s in rep.effect.parameter_notes)
    assert list(rep.model.sys.state_labels) == ["pos", "vel", "pos_sensor"]
    # validation SE of the truth itself (same data, same initial-state estimate)
    true, Qt = _true_model(TAU, dt)
    se_true = gb.validate_model(true, yv, uv, Q=Qt, R=R, x0="estimate", name="true").se.value
    se0, se1 = rep.table["nominal"].se.value, rep.table["updated"].se.value
    assert se1 <= 1.5 * se_true, (se1, se_true)  # measured 0.0731 % vs 0.0734 %
    assert se0 > 20 * se1, (se0, se1)  # measured 9.37 % -> 0.0731 %
    # a cheaper state-equation explanation is not near: every state-equation candidate
    # within 10x of the sensor law's estimation SE needs over 10x its parameters (with
    # eq(pos), a kinematic identity, a candidate: 0.56 % with 20 parameters; without it
    # the best is eq(vel), 10.8 % with 4: not near)
    se_law = rep.gate["se_estimation_updated"]
    state = [c for c in rep.candidates if not c.channel.startswith("output")]
    near = [c for c in state if c.se_estimation <= 10 * se_law]
    assert all(c.npar > 10 * rep.effect.law.npar for c in near), near
    assert min(c.se_estimation for c in state) > se_law, state


@pytest.mark.parametrize("tau", [0.05, 0.2])
def test_tau_within_its_interval(tau):
    nom, y, u, _, _, Q, R, dt = _lag_case(tau, n_val=10)
    tr = trace_channel(nom, output_channel(nom, "pos"), y, u, Q=Q, R=R, dt=dt, max_order=0)
    got, half = _lag(tr)
    assert abs(got - tau) <= half and half < 0.05 * tau, (got, half)
    # the updated model holds the lag exactly: its pos output, simulated, is the truth's
    true, _ = _true_model(tau, dt)
    upd = tr.static_model.sys
    np.testing.assert_allclose(np.asarray(upd.A)[2, 2], np.asarray(true.A)[2, 2],
                               rtol=1.1 * dt / tau * half / tau)  # da/a = dt/tau^2 dtau


def test_discrete_nominal_model_first_order_hold():
    """A discrete nominal: the lag sees c x linear between samples; same tau within its interval."""
    nom, y, u, _, _, Q, R, dt = _lag_case()
    nd = discretize(nom, dt)
    tr = trace_channel(nd, output_channel(nd, "pos"), y, u, Q=Q, R=R, max_order=0)
    got, half = _lag(tr)
    assert abs(got - TAU) <= half and half < 0.05 * TAU, (got, half)


def test_a_right_sensor_gets_no_lag():
    nom, y, u, _, _, Q, R, dt = _lag_case(0.0, n_val=10)
    tr = trace_channel(nom, output_channel(nom, "pos"), y, u, Q=Q, R=R, dt=dt, max_order=0)
    assert "yhat_lag" not in [s[1] for s in tr.static.spec if tr.static.npar], tr.static.formula
    assert tr.static_model.sys.nstates == 2


def test_a_lag_law_is_not_evaluated_pointwise():
    nom, y, u, _, _, Q, R, dt = _lag_case()
    tr = trace_channel(nom, output_channel(nom, "pos"), y, u, Q=Q, R=R, dt=dt, max_order=0)
    with pytest.raises(ModelError, match="not a function of the current sample"):
        tr.static.evaluate(np.zeros((2, 3)), np.zeros((1, 3)))


@pytest.mark.slow
def test_tau_interval_coverage_over_seeds():
    """Eight seeds: the 95 % intervals cover tau (measured: 20/20 at tau = 0.05, 0.1, 0.2;
    the spread of tau^ is ~0.85 of the reported sigma: the interval is conservative)."""
    hits, err = 0, []
    for seed in range(10, 18):
        nom, y, u, _, _, Q, R, dt = _lag_case(TAU, seed, n_val=10)
        tr = trace_channel(nom, output_channel(nom, "pos"), y, u, Q=Q, R=R, dt=dt, max_order=0)
        got, half = _lag(tr)
        hits += abs(got - TAU) <= half
        err.append(got - TAU)
    assert hits >= 7, hits  # P(>= 7 of 8) = 0.94 for an exact 95 % interval
    # unbiased: the mean error within 3 standard errors of 0
    assert abs(np.mean(err)) <= 3 * np.std(err) / np.sqrt(len(err)), err
