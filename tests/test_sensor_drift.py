"""A drifting and a saturating sensor as output-channel laws (issue 11, item 2).

A mass-spring-damper with a correct state model, position and velocity
measured. In one plant the position sensor drifts, ``y_pos = pos + b0 +
r t`` (b0 = 0.05 m, r = 0.004 m/s, t from the start of the estimation
record; the validation record starts 60 s later, where the offset is 0.29
m); in the other it clips at +-1.5 m. The trace must name the sensor (an
output channel, not a state equation) and report the drift rate, or the
clipping level, inside its 95 % interval.
"""

from __future__ import annotations

from functools import lru_cache

import control as ct
import numpy as np
import pytest
from plantlib import LinearF, msd, rk4_simulate

import greybox as gb
from greybox.exceptions import ModelError
from greybox.system import discretize, named_ss
from greybox.trace import output_channel, trace_channel
from greybox.trace.laws import sensor_states

OFFSET, RATE = 0.05, 0.004  # [m], [m/s] the drifting sensor at the estimation record's start
T_VAL = 60.0  # [s] the validation record's start (the estimation record starts at 0)
LEVEL = 1.5  # [m] the saturating sensor's clipping level (the position's std is ~1.1 m)
DT, R_STD = 0.01, 1e-3


@lru_cache(maxsize=None)
def _case(rate: float = RATE, level: float = np.inf, seed: int = 5):
    """(nominal, y, u, y_val, u_val, Q, R, x_val): pos read with a drift and/or clipped.

    ``rate = 0``: no drift (nor offset). The state model is right; process
    noise on vel in the estimation record only, measurement noise 1e-3 on
    both outputs. ``x_val`` (2, nsteps): the true states of the validation record.
    """
    nom = msd()
    A, B = np.asarray(nom.A, dtype=float), np.asarray(nom.B, dtype=float)
    rng = np.random.default_rng(seed)
    off = OFFSET if rate else 0.0
    out = []
    for n, q, t0 in ((4000, np.array([0.0, 1e-3]), 0.0), (3000, None, T_VAL)):
        u = gb.lowpass_noise(n, dt=DT, bandwidth=1.0, amplitude=4.0, rng=rng).reshape(1, -1)
        x = rk4_simulate(LinearF(A, B), np.zeros(2), u, DT, q_std=q, rng=rng)
        y = x.copy()
        y[0] = np.clip(y[0], -level, level) + off + rate * (t0 + DT * np.arange(n))
        out += [y + R_STD * rng.standard_normal((2, n)), u]
    Q = np.diag([0.0, 1e-6]) + 1e-12 * np.eye(2)
    return (nom, *out, Q, R_STD**2 * np.eye(2), x)


def _true_drift_model():
    """The drifting truth as a discrete StateSpace (pos, vel, offset, rate) and its Q."""
    nom = msd()
    A = np.zeros((4, 4))
    A[:2, :2], A[2, 3] = np.asarray(nom.A, dtype=float), 1.0
    B = np.vstack([np.asarray(nom.B, dtype=float), np.zeros((2, 1))])
    C = np.array([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
    sys = named_ss(A, B, C, np.zeros((2, 1)), 0, states=["pos", "vel", "b", "r"],
                   inputs=["F"], outputs=["pos", "vel"])
    return discretize(sys, DT), np.diag([0.0, 1e-6, 1e-14, 1e-14]) + 1e-12 * np.eye(4)


def _terms(law):
    """The kinds of the selected terms of a law."""
    return [sp[1] for j, sp in enumerate(law.spec) if law.coef[0, j]]


def test_drifting_sensor_is_traced_to_the_output():
    nom, y, u, yv, uv, Q, R, _ = _case()
    rep = gb.close_the_loop(nom, y, u, yv, uv, Q=Q, R=R, dt=DT, delta=False)
    assert rep.updated and rep.channel.kind == "output" and rep.channel.output == "pos", \
        rep.message
    assert not rep.channel.equations  # not a state equation
    assert rep.effect.kind == "sensor" and rep.effect.order == 2, rep.effect
    assert "a drifting sensor" in rep.message, rep.message
    law = rep.effect.law
    assert _terms(law) == ["const", "drift"], law.formula
    (b0, rate), (hb, hr) = law.coef[0], law.ci[0]
    # the 95 % intervals cover the truth and are informative
    # (measured: rate 0.00396 +- 6.9e-05 m/s, offset 0.0509 +- 0.0016 m)
    assert abs(rate - RATE) <= hr and hr < 0.05 * RATE, (rate, hr)
    assert abs(b0 - OFFSET) <= hb and hb < 0.1 * OFFSET, (b0, hb)
    assert any("drifts at" in s for s in rep.effect.parameter_notes)
    assert list(rep.model.sys.state_labels) == ["pos", "vel", "pos_offset", "pos_drift"]
    # the validation record has its own offset (0.29 m at its start, not the estimation
    # record's 0.05 m): a state of the updated model, estimated with its initial state
    # (from 50 samples of 1e-3 m noise; 0.01 m is ten times that estimate's spread)
    x0 = gb.estimate_initial_state(rep.model.sys, yv, uv)
    np.testing.assert_allclose(x0[2], OFFSET + RATE * T_VAL, atol=0.01)
    # validation SE against the truth's own structure, its initial state estimated alike
    true, Qt = _true_drift_model()
    se_true = gb.validate_model(true, yv, uv, Q=Qt, R=R, x0="estimate", name="true").se.value
    se0, se1 = rep.table["nominal"].se.value, rep.table["updated"].se.value
    assert se1 <= 1.5 * se_true, (se1, se_true)  # measured 0.193 % vs 0.193 %
    assert se0 > 20 * se1, (se0, se1)  # measured 16.7 % -> 0.193 %
    # the output channel's notes are listed once (it was traced twice)
    out = [s for s in rep.notes if s.startswith("output(")]
    assert len(out) == len(set(out)), out


def test_a_right_sensor_gets_no_drift_nor_saturation():
    """The same plant without drift: no drift term, no clip, no sensor state."""
    nom, y, u, _, _, Q, R, _ = _case(rate=0.0)
    tr = trace_channel(nom, output_channel(nom, "pos"), y, u, Q=Q, R=R, dt=DT, max_order=0)
    kinds = _terms(tr.static)
    assert "drift" not in kinds and "yhat_sat" not in kinds, tr.static.formula
    assert tr.static_model.sys.nstates == 2
    # and the drifting plant's other (correct) sensor gets none either
    nom, y, u, _, _, Q, R, _ = _case()
    tr = trace_channel(nom, output_channel(nom, "vel"), y, u, Q=Q, R=R, dt=DT, max_order=0)
    kinds = _terms(tr.static)
    assert "drift" not in kinds and "yhat_sat" not in kinds, tr.static.formula


def test_a_drift_law_is_not_evaluated_pointwise():
    nom, y, u, _, _, Q, R, _ = _case()
    tr = trace_channel(nom, output_channel(nom, "pos"), y, u, Q=Q, R=R, dt=DT, max_order=0)
    assert sensor_states(tr.static) == 2
    with pytest.raises(ModelError, match="a sensor drift is not a function of the current"):
        tr.static.evaluate(np.zeros((2, 3)), np.zeros((1, 3)))


def test_saturating_sensor_is_traced_to_the_output():
    nom, y, u, yv, uv, Q, R, xv = _case(rate=0.0, level=LEVEL)
    rep = gb.close_the_loop(nom, y, u, yv, uv, Q=Q, R=R, dt=DT, delta=False)
    assert rep.updated and rep.channel.kind == "output" and rep.channel.output == "pos", \
        rep.message
    law = rep.effect.law
    assert _terms(law) == ["yhat_sat"] and law.nonlinear, law.formula
    assert rep.effect.kind == "static"  # a static (nonlinear) sensor law: no sensor state
    j = [sp[1] for sp in law.spec].index("yhat_sat")
    L, half = law.coef[0, j], law.ci[0, j]
    # the 95 % interval covers the truth and is informative (measured 1.5 +- 5.6e-05 m:
    # the clipped samples read L plus 1e-3 m noise; 30 seeds: 28 covered, the spread of
    # L^ 0.88 of the reported sigma)
    assert abs(L - LEVEL) <= half and half < 1e-3 * LEVEL, (L, half)
    assert any("saturates at" in s for s in rep.effect.parameter_notes)
    # the law simulates the clip: validation SE near the truth's floor (its exact
    # noise-free output from its exact initial state)
    y_true = np.vstack([np.clip(xv[0], -LEVEL, LEVEL), xv[1]])
    se_true = gb.relative_error(yv, y_true, skip=20).value
    se0, se1 = rep.table["nominal"].se.value, rep.table["updated"].se.value
    assert se1 <= 1.5 * se_true, (se1, se_true)  # measured 0.0854 % vs 0.0792 %
    assert se0 > 20 * se1, (se0, se1)  # measured 14.9 % -> 0.0854 %
    # the report's NonlinearIOSystem clips the output too: it simulates the 'updated' row
    # from the row's start, the better (over the first samples) of the linear part's
    # estimate over the short window (slow_modes=False) and least squares through C on
    # the first sample, as for every non-affine law
    fsys = rep.trace.filter_result.sys
    C, D = np.asarray(fsys.C, dtype=float), np.asarray(fsys.D, dtype=float)
    starts = (gb.estimate_initial_state(rep.model.sys, yv, uv, slow_modes=False),
              np.linalg.lstsq(C, yv[:, 0] - D @ uv[:, 0], rcond=None)[0])
    sims = [ct.input_output_response(rep.nonlinear.model, DT * np.arange(uv.shape[1]), uv,
                                     X0=x0).outputs for x0 in starts]
    # the same discrete recursion from one of the two starts: rounding only
    assert any(np.allclose(s, rep.table["updated"].y_sim, rtol=1e-9, atol=1e-12)
               for s in sims)


@pytest.mark.slow
def test_rate_and_level_interval_coverage_over_seeds():
    """Five seeds each: the 95 % intervals cover the drift rate and the clipping level;
    three right sensors get no drift (seed 101's rate is 2.1 sigma from 0: a 95 % test
    alone would keep it; the drift must pass BIC's z^2 > ln N under the robust variance).

    (bench/sensor_laws.py, 40 seeds: the rate's interval covered 37, the spread of r^
    equal to the reported sigma, 3.5e-05 m/s; L's covered 38.)
    """
    hits_r, hits_l = 0, 0
    for seed in range(20, 25):
        nom, y, u, _, _, Q, R, _ = _case(RATE, np.inf, seed)
        law = trace_channel(nom, output_channel(nom, "pos"), y, u, Q=Q, R=R, dt=DT,
                            max_order=0).static
        assert _terms(law) == ["const", "drift"], law.formula
        hits_r += abs(law.coef[0, -1] - RATE) <= law.ci[0, -1]
        nom, y, u, _, _, Q, R, _ = _case(0.0, LEVEL, seed)
        law = trace_channel(nom, output_channel(nom, "pos"), y, u, Q=Q, R=R, dt=DT,
                            max_order=0).static
        assert _terms(law) == ["yhat_sat"], law.formula
        hits_l += abs(law.coef[0, -1] - LEVEL) <= law.ci[0, -1]
    # P(>= 4 of 5) = 0.977 for an exact 95 % interval
    assert hits_r >= 4 and hits_l >= 4, (hits_r, hits_l)
    for seed in (100, 101, 102):
        nom, y, u, _, _, Q, R, _ = _case(0.0, np.inf, seed)
        law = trace_channel(nom, output_channel(nom, "pos"), y, u, Q=Q, R=R, dt=DT,
                            max_order=0).static
        assert not {"drift", "yhat_sat"} & set(_terms(law)), (seed, law.formula)


@pytest.mark.parametrize("rate, level", [(RATE, np.inf), (0.0, LEVEL)], ids=["drift", "clip"])
def test_discrete_nominal_model(rate, level):
    """A discrete nominal: the same drift rate, or clipping level, within its interval."""
    nom, y, u, _, _, Q, R, _ = _case(rate, level)
    nd = discretize(nom, DT)
    law = trace_channel(nd, output_channel(nd, "pos"), y, u, Q=Q, R=R, max_order=0).static
    truth = RATE if rate else LEVEL
    assert _terms(law)[-1] == ("drift" if rate else "yhat_sat"), law.formula
    assert abs(law.coef[0, -1] - truth) <= law.ci[0, -1], law.formula


def test_a_ramp_no_input_drives_is_told_from_a_driven_one():
    """greybox.validate.has_free_ramp: a drift's (offset, rate) block is a Jordan chain at 1
    that no input reaches; its initial state then takes the longest window."""
    from greybox.validate import has_free_ramp

    h = 0.1
    drift = np.array([[1.0, h], [0.0, 1.0]])
    plant, Bp = np.array([[0.9, 0.1], [0.0, 0.8]]), np.array([[1.0], [0.5]])
    A = np.block([[plant, np.zeros((2, 2))], [np.zeros((2, 2)), drift]])
    assert has_free_ramp(A, np.vstack([Bp, np.zeros((2, 1))]))
    # a double integrator the input drives (a mass alone) is not one, with or without an
    # offset state beside it; with a drift beside it, it is
    Bdi = np.array([[h * h / 2], [h]])
    assert not has_free_ramp(drift, Bdi)
    A3 = np.block([[drift, np.zeros((2, 1))], [np.zeros((1, 2)), np.eye(1)]])
    assert not has_free_ramp(A3, np.vstack([Bdi, [[0.0]]]))
    A4 = np.block([[drift, np.zeros((2, 2))], [np.zeros((2, 2)), drift]])
    assert has_free_ramp(A4, np.vstack([Bdi, np.zeros((2, 1))]))
    # an offset alone (eigenvalue 1, no chain) is seen in the first samples; no input at all
    assert not has_free_ramp(np.diag([0.9, 1.0]), np.array([[1.0], [0.0]]))
    assert has_free_ramp(drift, np.zeros((2, 0)))


def test_a_slow_drift_s_rate_is_estimated_over_a_long_window():
    """Zoo sensor_drift 2020699907 #1 (a row of 2 thermal bodies, the sensor of T1 drifting
    6.6e-5 /s from 0.366): the drift law was fitted right, but its candidate was scored
    from an initial state estimated on 60 samples, where the rate came out 1.2e-5, and
    simulated at 3.14 % against the true model's 0.39 %; a constant in both state
    equations won (2.23 %). Over the longest window (has_free_ramp) the sensor is named,
    its offset and rate within 10 % and inside their intervals, at the true model's error."""
    from greybox import zoo

    d = zoo.draw_class("sensor_drift", 2020699907, 1)
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    s = zoo.score(d, rep)
    assert rep.updated and s.right and s.covered == s.n_coefficients == 2, (s.why, s.found)
    assert s.error_updated <= 1.1 * s.error_true, (s.error_updated, s.error_true)
