"""Larger models: chains of masses with one coupling spring missing from the model.

Chain wall-k-m1-k-m2-...-mN (k = 20 N/m, m = 1 kg, c = 0.5 N s/m), force on
mass 1; the nominal model lacks the spring between masses N/2 and N/2 + 1.
The joint equation screen must find the two equations, and the law must be
one force in the relative coordinate, d = -k (p_{i+1} - p_i), with the
validation SE within 1.5x of the true model's.
"""

from __future__ import annotations

import numpy as np
import pytest

import greybox as gb
from plantlib import LinearF, chain, draw


def _case(n_masses, measured, seed=1, n_est=20000):
    i = n_masses // 2 - 1
    true = chain(n_masses, k=20.0)
    meas = None if measured == "all" else [f"p{j + 1}" for j in range(n_masses)]
    nom = chain(n_masses, k=20.0, missing=[(i, i + 1)], measured=meas)
    A, B = np.asarray(true.A), np.asarray(true.B)
    d = draw(nom, LinearF(A, B), n_true=2 * n_masses, dt=0.01,
             rng=np.random.default_rng(seed), q_std=np.array([0.0, 1e-4] * n_masses),
             r_std=1e-3, n_est=n_est, sub=2)
    rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    true_d = gb.discretize(chain(n_masses, k=20.0, measured=meas), d.dt)
    floor = gb.validate_model(true_d, d.y_val, d.u_val, Q=d.Q, R=d.R).se.value
    return rep, (f"v{i + 1}", f"v{i + 2}"), (f"p{i + 1}", f"p{i + 2}"), floor


# 5000 estimation samples for the all-measured chains (2e4 before: 8.9 -> 5.6 s at n = 10,
# 12.2 -> 6.6 s at n = 20, alone): the same channel, the same one-term law in the relative
# coordinate, the force within 0.03 % of 20 against the 1 % asserted (0.011-0.025 % at
# 2e4), SE 1.00x the true model's. (Positions only keeps 2e4: 5000 saved no time there.)
N_CHAIN = 5000


@pytest.mark.slow
@pytest.mark.parametrize("n_masses", [5, 10], ids=["n10", "n20"])
def test_chain_all_measured_one_force_in_relative_coordinate(n_masses):
    rep, eqs, (pa, pb), floor = _case(n_masses, "all", n_est=N_CHAIN)
    assert rep.updated and rep.channel.kind == "force", rep.message
    assert set(rep.effect.equations) == set(eqs), rep.message
    # each candidate is traced once (the screen's and the pair law's force directions
    # agree within 0.5 degree here: one force channel, not two)
    traced = [(c.channel, c.kind, c.order) for c in rep.candidates]
    assert len(traced) == len(set(traced)), traced
    law = rep.effect.law
    names = [law.spec[j][0] for j in np.flatnonzero(law.coef[0])]
    assert names == [f"({pb}-{pa})"], rep.effect.formula     # one term, relative coordinate
    j = [s[0] for s in law.spec].index(f"({pb}-{pa})")
    g = np.asarray(rep.channel.G)[[rep.nominal.state_labels.index(e) for e in eqs], 0]
    # the force on the first body is c * g[0] * (pb - pa) = +20 (pb - pa): within 1 %
    # (the interval is 0.035-0.065 %; the direction is estimated to ~0.5 %)
    np.testing.assert_allclose(law.coef[0, j] * g[0], 20.0, rtol=0.01)
    assert rep.table["updated"].se.value < 1.5 * floor, (rep.table["updated"].se.value, floor)


@pytest.mark.slow
def test_chain_positions_only_right_pair():
    rep, eqs, (pa, pb), floor = _case(4, "positions")
    assert rep.updated and set(rep.effect.equations) == set(eqs), rep.message
    law = rep.effect.law
    assert law is not None, rep.effect.formula
    j = [s[0] for s in law.spec].index(f"({pb}-{pa})")
    g = np.asarray(rep.channel.G)[[rep.nominal.state_labels.index(e) for e in eqs], 0]
    # the relative coordinate carries the force: within 3 % (small proxy terms share it)
    np.testing.assert_allclose(law.coef[0, j] * g[0], 20.0, rtol=0.03)
    assert rep.table["updated"].se.value < 1.5 * floor, (rep.table["updated"].se.value, floor)


@pytest.mark.slow
def test_correct_large_model_is_left_unchanged():
    true = chain(10, k=20.0)
    A, B = np.asarray(true.A), np.asarray(true.B)
    d = draw(true, LinearF(A, B), n_true=20, dt=0.01,
             rng=np.random.default_rng(3), q_std=np.array([0.0, 1e-4] * 10), r_std=1e-3,
             n_est=20000, sub=2)
    rep = gb.close_the_loop(true, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    assert not rep.updated, rep.message


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_two_effects_in_two_equations_named_with_their_coefficients(seed):
    """6-state chain, all measured: the damping of mass 1 is 1.3 N s/m (model 0.5) and a
    15 N/m spring ties mass 3 to the wall (model lacks it). The joint screen finds both
    equations; the pair law names each effect with its coefficient."""
    nom = chain(3, k=20.0)
    A, B = np.asarray(nom.A).copy(), np.asarray(nom.B)
    A[1, 1] -= 0.8
    A[5, 4] -= 15.0
    d = draw(nom, LinearF(A, B), n_true=6, dt=0.01,
             rng=np.random.default_rng(seed), q_std=np.array([0.0, 1e-4] * 3), r_std=1e-3)
    rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    assert rep.updated and set(rep.effect.equations) == {"v1", "v3"}, rep.message
    names = [s[0] for s in rep.effect.law.spec]
    law = rep.effect.law
    c = {(k, names[j]): law.coef[k, j] for k in range(2) for j in np.flatnonzero(law.coef[k])}
    # one term each: -0.8*v1 in eq(v1), -15*p3 in eq(v3), within their 95 % intervals or 1 %
    assert set(c) == {(0, "v1"), (1, "p3")}, rep.effect.formula
    np.testing.assert_allclose([c[0, "v1"], c[1, "p3"]], [-0.8, -15.0], rtol=0.01)
    import re

    pct = [float(re.search(r"\(([+-][0-9.]+)", n).group(1)) for n in rep.effect.parameter_notes
           if n.startswith("A[v1; v1]")]
    assert pct and abs(pct[0] - 160.0) < 1.6, rep.effect.parameter_notes  # damping 0.5 -> 1.3
    assert any(n.startswith("A[v3; p3]") for n in rep.effect.parameter_notes)


def _lag_and_spring(seed):
    """6-state chain: a 0.1 s actuator lag on F (F enters v1 only) and a 15 N/m spring from
    mass 3 to the wall, both missing from the model."""
    nom = chain(3, k=20.0)
    A, B = np.asarray(nom.A).copy(), np.asarray(nom.B)
    A[5, 4] -= 15.0

    def f(x, u):
        dx = np.empty(7)
        dx[:6] = A @ x[:6] + B[:, 0] * x[6]
        dx[6] = (u[0] - x[6]) / 0.1
        return dx

    d = draw(nom, f, n_true=7, dt=0.01, rng=np.random.default_rng(seed),
             q_std=np.array([0.0, 1e-4] * 3), r_std=1e-3)
    Ac = np.zeros((7, 7))
    Ac[:6, :6], Ac[:6, 6], Ac[6, 6] = A, B[:, 0], -10.0
    Bc = np.zeros((7, 1))
    Bc[6, 0] = 10.0
    true = gb.discretize(gb.named_ss(Ac, Bc, np.hstack([np.asarray(nom.C), np.zeros((6, 1))]),
                                     np.zeros((6, 1)), 0,
                                     states=list(nom.state_labels) + ["lag"],
                                     inputs=nom.input_labels, outputs=nom.output_labels), d.dt)
    floor = gb.validate_model(true, d.y_val, d.u_val, Q=np.eye(7) * 1e-8, R=d.R).se.value
    return nom, d, floor


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 2, 4])
def test_static_and_dynamic_effects_refitted_jointly(seed):
    """Pass 1 finds the spring (its law borrows part of the lag), pass 2 the lag; the joint
    output-error refit of both effects then drops the borrowed terms: the spring reads
    -15*p3 and the lag is F alone through 10/(s + 10), at the true model's error.

    Seed 4: pass 2's d^ on eq(v1) is mostly estimation noise (its variance within 1 % of
    the filter's Pd) and its regressions chose p1, v2, v3 (no F: SE 9.6 %, 24x the true
    model's); the drivers chosen by output error on y (F first) give the joint refit a law
    with F to keep."""
    nom, d, floor = _lag_and_spring(seed)
    rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    assert len(rep.steps) == 2, rep.message
    static, dyn = rep.steps[0].effect, rep.steps[1].effect
    law = static.law
    names = [s[0] for s in law.spec]
    terms = {(k, names[j]): law.coef[k, j] for k in range(law.coef.shape[0])
             for j in np.flatnonzero(law.coef[k])}
    # the lag's feedthrough -F/m1 = -1*F is one term of the model already: it is kept once
    # (in the earlier law); the spring -15*p3 within 1 % (interval ~1 %), -1*F within 10 %
    # (interval ~10 %)
    assert set(terms) == {(0, "F"), (1, "p3")}, static.formula
    np.testing.assert_allclose(terms[1, "p3"], -15.0, rtol=0.01)
    np.testing.assert_allclose(terms[0, "F"], -1.0, rtol=0.1)
    dl = dyn.dynamic_law
    assert dl.drivers == ("F",), dyn.formula
    # tau = 0.1 s within 5 % (its 95 % interval is ~12 % wide); the filtered gain 10 N/s
    # within 10 % (interval ~20 %)
    np.testing.assert_allclose(dl.tau, 0.1, rtol=0.05)
    lo, hi = 1.0 / (-dl.pole + dl.ci[0]), 1.0 / (-dl.pole - dl.ci[0])
    assert lo <= 0.1 <= hi, (lo, hi)  # the true tau inside its 95 % interval
    # ... in eq(v1)'s units: the law's b times its channel's entry in eq(v1) (1 for the
    # equation's own channel; B's for the input's, whose d is in F's units)
    np.testing.assert_allclose(dl.b[0] * np.asarray(dl.continuous.A)[1, -1], 10.0, rtol=0.1)
    assert any(n.startswith("joint refinement") for n in rep.notes), rep.notes
    se = rep.table["updated"].se.value
    assert se < 1.5 * floor, (se, floor)


def test_a_dense_single_equation_law_is_chosen_by_output_error_not_refined_term_by_term():
    """32-state chain, positions only: eq(v8) alone cannot hold the missing spring (the
    force acts on v5 too), so its d^ law collects noise proxies. A linear law of more than 8
    terms per component is not refined term by term (31 terms at n = 32 cost 72 s and
    ended empty) but chosen by output error among its best-correlated terms: at most 4."""
    from greybox.trace import resolve_channel_spec, trace_channel

    n_masses = 16
    meas = [f"p{j + 1}" for j in range(n_masses)]
    true = chain(n_masses, k=20.0)
    nom = chain(n_masses, k=20.0, missing=[(7, 8)], measured=meas)
    A, B = np.asarray(true.A), np.asarray(true.B)
    d = draw(nom, LinearF(A, B), n_true=2 * n_masses, dt=0.01,
             rng=np.random.default_rng(1), q_std=np.array([0.0, 1e-4] * n_masses),
             r_std=1e-3, n_est=50000, n_val=10, sub=2)
    ch = resolve_channel_spec(nom, ["v8"])[0]
    tr = trace_channel(nom, ch, d.y, d.u, Q=d.Q, R=d.R, dt=d.dt, max_order=0)
    dense = [s for s in tr.notes if "d^ law is not sparse" in s]
    assert dense, tr.notes
    assert int(dense[0].split("(")[1].split(" terms")[0]) > 8, dense
    assert tr.static.npar <= 4, tr.static.formula   # _select_static_oe's max_terms


def test_static_is_enough_accepts_a_sensor_law_with_its_own_states():
    """Regression (lag + spring, seed 4, pass 3): the best static candidate was a sensor lag,
    whose model has one more state than the pass's Q; the whiteness check then raised
    "Q has shape (7, 7); expected (8, 8)" and ended the several-effects loop. Its Q is now
    the pass's Q beside the law's own block for the sensor state."""
    from types import SimpleNamespace
    from greybox.records import Candidate
    from greybox.workflow import _static_is_enough

    # a first-order plant read through a 0.2 s sensor lag: states (x, y_lag), one output
    lagged = gb.discretize(gb.named_ss([[-1.0, 0.0], [5.0, -5.0]], [[1.0], [0.0]],
                                       [[0.0, 1.0]], [[0.0]], 0, states=["x", "y_lag"],
                                       inputs=["u"], outputs=["y"]), 0.1)
    u = np.random.default_rng(0).standard_normal((1, 2000))
    y = gb.simulate(lagged, u, R=np.array([[1e-6]]), rng=1).y
    Q = np.array([[1e-8]])  # the pass's Q: one state
    law_model = SimpleNamespace(sys=lagged, Q=np.diag([1e-8, 1e-8]))
    scored = [Candidate(1.0, 1, SimpleNamespace(static_model=law_model), "static")]
    # the lagged model is the true one: its innovations are white
    assert _static_is_enough(scored, y, u, Q, np.array([[1e-6]]), 20, 10, 0.01)
    # and a sensor law with the wrong lag (2 s) leaves coloured innovations
    slow = gb.discretize(gb.named_ss([[-1.0, 0.0], [0.5, -0.5]], [[1.0], [0.0]],
                                     [[0.0, 1.0]], [[0.0]], 0, states=["x", "y_lag"],
                                     inputs=["u"], outputs=["y"]), 0.1)
    wrong = SimpleNamespace(sys=slow, Q=np.diag([1e-8, 1e-8]))
    assert not _static_is_enough([Candidate(1.0, 1, SimpleNamespace(static_model=wrong),
                                            "static")],
                                 y, u, Q, np.array([[1e-6]]), 20, 10, 0.01)
