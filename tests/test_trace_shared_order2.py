"""One second-order hidden subsystem shared by two state equations (issue 8 item 2, order 2).

Plant: ``plantlib.thermal_chain_pair``: two measured bodies T1, T2 and, hidden behind
them, a chain of two thermal masses (Tm1 touches T1 and T2, Tm2 touches Tm1 only). In
the coordinates where the subsystem's gain in d_T1 is 1 (z = (g1/C1) Tm1) the true law is

    d_T1 = z + (a_11 - A_11) T1,   d_T2 = k_2 z + (a_22 - A_22) T2,
    z = sum_i (beta_1i s + beta_0i) / (s^2 + alpha_1 s + alpha_0) T_i,

poles -0.15 and -1.5 1/s, read off the true continuous model (the matrix logarithm of
the true discrete model). The first-order shared law is offered beside it; the workflow
must choose order 2 here (the first-order law ends at ~2x the true model's error, and a
second pass then adds an unstructured filter), and order 1 where one hidden mass is the
truth (``tests/test_trace_shared_state.py`` asserts it, with the order-2 law offered).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import logm

import greybox as gb
from greybox.trace.shared_order2 import SharedLaw2
from plantlib import thermal_chain_pair, thermal_chain_three, true_floor

SEEDS = (1, 2, 3)


def _true_law(nominal, true_d):
    """Poles, beta (2, 2) over (T1, T2), k_2, e_11, e_22 of the true law."""
    At = np.real(logm(np.asarray(true_d.A, dtype=float))) / true_d.dt
    A = np.asarray(nominal.A, dtype=float)
    g = At[0, 2]  # z = g Tm1: the subsystem's gain in d_T1 is 1
    H = At[2:, 2:]  # the hidden chain (Tm1, Tm2)
    # Tm1 = [1 0] (sI - H)^-1 [At[2, i]; At[3, i]] T_i: first row of adj(sI - H)
    beta = np.array([[g * At[2, i] for i in range(2)],
                     [g * (-H[1, 1] * At[2, i] + H[0, 1] * At[3, i]) for i in range(2)]])
    return {"poles": np.sort(np.linalg.eigvals(H).real)[::-1], "beta": beta,
            "k2": At[1, 2] / g, "e11": At[0, 0] - A[0, 0], "e22": At[1, 1] - A[1, 1]}


# 6000 estimation samples (the plant's default is 20000): measured on seeds 1-3, order 2
# chosen over the offered order 1 in each, SE 1.00-1.02x the true model's, the poles
# within 0.97 of their 95 % half-widths (1.40 at 20000), numerators within 0.87 and k_2
# within 0.69 of theirs, the feedthrough within 0.13 % (bound 3 %), no extra term; the
# half-widths widen by ~sqrt(3.3) and the tests compare with them.
N_EST = 6000


def _run(seed):
    nom, d, true = thermal_chain_pair(seed, n_est=N_EST)
    rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    floor = true_floor(true, d)
    return nom, true, rep, floor


def test_true_law_read_from_the_plant():
    # the oracle itself against the plant's documented values (C 1, 2, 2, 4 J/K; g 1.0,
    # 0.8, 1.0 W/K): logm of a 4x4 ZOH matrix with real positive eigenvalues is exact to
    # rounding
    nom, _, true = thermal_chain_pair(1, n_est=200)
    tl = _true_law(nom, true)
    np.testing.assert_allclose(tl["poles"], [-0.15, -1.5], rtol=1e-9)
    np.testing.assert_allclose(tl["beta"], [[0.5, 0.4], [0.125, 0.1]], rtol=1e-9)
    np.testing.assert_allclose([tl["k2"], tl["e11"], tl["e22"]], [0.4, -1.0, -0.4], rtol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("n_seeds", [1, 3])
def test_one_second_order_subsystem_in_the_pair(n_seeds):
    """The first seed, or all three in one test (each ~10-20 s at N_EST; the coverage counts
    need them all; [3] is in the extended tier, tests/conftest.py): a module fixture would
    run on every xdist worker that takes one of its tests."""
    inside_p, inside_c = np.zeros(2), 0
    for seed in SEEDS[:n_seeds]:
        nom, true, rep, floor = _run(seed)
        _one_seed(seed, nom, rep, floor)
        dl = rep.effect.dynamic_law
        tl = _true_law(nom, true)
        assert np.all(np.isreal(dl.poles)), dl.formula  # two real poles, slow one first
        inside_p += np.abs(dl.poles.real - tl["poles"]) <= dl.pole_ci
        # every pole within 3 half-widths in every seed (~6 sigma: a gross error)
        assert np.all(np.abs(dl.poles.real - tl["poles"]) <= 3 * dl.pole_ci), \
            (seed, dl.poles, dl.pole_ci)
        # the subsystem's numerators: within 3 half-widths
        order = [("T1", "T2").index(nm) for nm in dl.drivers]
        nb = int(np.count_nonzero(dl.beta))
        hb = dl.ci[2:2 + nb]
        est = dl.beta[dl.beta != 0]
        ref = tl["beta"][:, order][dl.beta != 0]
        assert np.all(np.abs(est - ref) <= 3 * hb), (seed, est, ref, hb)
        hk = dl.ci[2 + nb]
        assert abs(dl.k[1] - tl["k2"]) <= 3 * hk, (seed, dl.k, hk)
        inside_c += abs(dl.k[1] - tl["k2"]) <= hk
        # the true feedthrough terms are there, within 3 % (their intervals are ~0.3 %);
        # a spurious extra term, if any, is small against them
        feed = {(c, nm): v for c, nm, v in dl.feedthrough}
        np.testing.assert_allclose([feed[0, "T1"], feed[1, "T2"]], [tl["e11"], tl["e22"]],
                                   rtol=0.03)
        extra = [abs(v) for key, v in feed.items() if key not in {(0, "T1"), (1, "T2")}]
        assert all(v < 0.02 * abs(tl["e22"]) for v in extra), dl.formula
    # 95 % intervals: each pole inside in >= 2 of 3 seeds with probability ~0.993
    # ("inside their 95 % intervals in most seeds", issue 8 item 7)
    assert n_seeds < 3 or (np.all(inside_p >= 2) and inside_c >= 2), (inside_p, inside_c)


def _one_seed(seed, nom, rep, floor):
    assert rep.updated, rep.message
    assert rep.channel.name == "eq(T1)+eq(T2)", rep.message
    assert rep.effect.kind == "dynamic" and rep.effect.order == 2, rep.message
    dl = rep.effect.dynamic_law
    assert isinstance(dl, SharedLaw2), rep.effect.formula
    # one effect (not a first-order law plus a filter for what it left)
    assert len(rep.steps or [None]) == 1, rep.message
    assert rep.model.sys.nstates == nom.nstates + 2
    assert set(dl.drivers) == {"T1", "T2"}, dl.formula
    assert dl.reference == 0
    # the first-order shared law was offered and lost
    assert any(c.kind == "dynamic (sparse)" and c.order == 1 and c.channel == "eq(T1)+eq(T2)"
               for c in rep.candidates), (seed, rep.candidates)
    # the true model's validation SE is the floor; 1.5x as issue 8 item 7 asks
    assert rep.table["updated"].se.value <= 1.5 * floor, (seed, rep.table["updated"].se.value,
                                                          floor)
    assert "time constants" in dl.formula and "±" in dl.formula


def test_evaluate_matches_an_independent_zoh_simulation():
    # the law's d (used by the gate's BIC gain) against scipy's own ZOH simulation of the
    # subsystem (lsim with interp=False holds the input over each sample); the true law of
    # thermal_chain_pair, with a spurious Q1 feedthrough to exercise E's input columns
    from scipy.signal import lsim

    Bz = np.array([[0.5, 0.4, 0.0, 0.0], [0.125, 0.1, 0.0, 0.0]])
    E = np.array([[-1.0, 0.0, 0.3, 0.0], [0.0, -0.4, 0.0, 0.0]])
    dl = SharedLaw2(order=2, poles=np.array([-0.15, -1.5]), pole_ci=np.zeros(2),
                    taus=np.array([1 / 0.15, 1 / 1.5]), alpha=np.array([1.65, 0.225]),
                    states=("z[0]", "z[1]"), drivers=("T1", "T2"), beta=Bz[:, :2],
                    k=np.array([1.0, 0.4]), reference=0, feedthrough=(), Bz=Bz, E=E,
                    ci=np.zeros(9), npar=9, formula="", model=None, se_estimation=0.0,
                    continuous=None, dt=0.05)
    rng = np.random.default_rng(0)
    x, u = rng.standard_normal((2, 400)), rng.standard_normal((2, 400))
    w = np.vstack([x, u])
    t = np.arange(400) * dl.dt
    v = dl.Bz @ w  # (2, K): the inputs of z1' and z2'
    A = np.array([[-dl.alpha[0], 1.0], [-dl.alpha[1], 0.0]])
    _, z1, _ = lsim((A, np.eye(2), np.array([[1.0, 0.0]]), np.zeros((1, 2))), v.T, t,
                    interp=False)
    want = dl.k[:, None] * z1[None, :] + dl.E @ w
    # two exact ZOH discretizations (expm): equal to rounding
    np.testing.assert_allclose(dl.evaluate(x, u), want, rtol=1e-9, atol=1e-12)


def test_the_second_order_law_takes_part_in_the_joint_refit():
    """SharedLaw2 in the several-effects loop's joint output-error refit (greybox.trace.joint;
    before, any order-2 law made joint_effect None and the whole refit was skipped). The law
    fitted from the truth's terms, refitted jointly on its own, must stay at its optimum (one
    effect: the same output error) and come back as a SharedLaw2 with every term."""
    from greybox.trace import resolve_channel_spec
    from greybox.trace.joint import JointEffect, joint_effect, refine_jointly
    from greybox.trace.shared_order2 import _law_from, _Problem

    nom, d, true = thermal_chain_pair(1)
    tl = _true_law(nom, true)
    ch = resolve_channel_spec(nom, [("T1", "T2")])[0]
    p1, p2 = tl["poles"]
    bterms = [(0, ("x", 0)), (0, ("x", 1)), (1, ("x", 0)), (1, ("x", 1))]
    eterms = [(0, ("x", 0)), (1, ("x", 1))]
    theta = np.r_[-(p1 + p2), p1 * p2, tl["beta"][0], tl["beta"][1], tl["k2"], tl["e11"],
                  tl["e22"]]
    prob = _Problem(nom, ch, d.y, d.u, d.dt, np.zeros(2), 20, bterms, eterms, 0)
    sol = prob.fit(theta)
    law = _law_from(nom, ch, prob, sol, prob.halfwidths(sol, d.Q, d.R), d.Q, d.R)
    ef = joint_effect(nom, ch, law)
    assert isinstance(ef, JointEffect)
    jr = refine_jointly([ef], law.continuous, d.y, d.u, Q=law.model.Q, R=d.R, dt=d.dt,
                        x0=np.zeros(4), k0=20)
    assert jr.npar_before == 9 and jr.npar_after == 9, jr.dropped  # every term significant
    back = jr.laws[0]
    assert isinstance(back, SharedLaw2) and back.states == law.states
    # the same optimum: Levenberg-Marquardt's stopping tolerance (1e-8 relative) leaves
    # ~1e-5 on the coefficients; 1e-3 would be a different fit
    np.testing.assert_allclose(back.alpha, law.alpha, rtol=1e-3)
    np.testing.assert_allclose(back.beta, law.beta, rtol=1e-3)
    assert jr.se_after <= jr.se_before * (1 + 1e-6)
    # and the truth: poles within 3 of their 95 % half-widths (~6 sigma: a gross error)
    assert np.all(np.abs(back.poles.real - tl["poles"]) <= 3 * back.pole_ci), back.formula
    assert jr.model.sys.nstates == 4 and "poles" in back.formula


def test_second_order_law_beside_a_static_effect_end_to_end():
    """``plantlib.thermal_chain_three``: the hidden chain behind T1, T2 and T3's missing
    loss. Two passes, refitted jointly: the several-effects loop rebuilt the steps with
    ``parameter_notes`` for every non-dynamic law and crashed on a SharedLaw2 (only the
    refit itself was tested before). Seed 1 (~17 s)."""
    nom, d, true = thermal_chain_three(1)
    rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    assert rep.updated and len(rep.steps) == 2, rep.message
    first, second = rep.steps
    assert first.channel == "eq(T1)+eq(T2)" and first.effect.order == 2, rep.message
    dl = first.effect.dynamic_law
    assert isinstance(dl, SharedLaw2) and set(dl.drivers) == {"T1", "T2"}, first.effect.formula
    assert first.effect.formula == dl.formula  # the step shows the jointly refitted law
    # the chain's poles (those of thermal_chain_pair), within 3 half-widths
    assert np.all(np.abs(dl.poles.real - [-0.15, -1.5]) <= 3 * dl.pole_ci), dl.formula
    law = second.effect.law
    assert second.channel == "eq(T3)" and second.effect.kind == "static", rep.message
    j = [sp[0] for sp in law.spec].index("T3")
    assert [law.spec[i][0] for i in np.flatnonzero(law.coef[0])] == ["T3"], law.formula
    # the missing loss -g3/c3 = -0.1 per second, within 3 half-widths (measured +- 0.00018)
    assert abs(law.coef[0, j] + 0.1) <= 3 * law.ci[0, j], law.formula
    assert rep.model.sys.nstates == nom.nstates + 2
    # the true model's validation SE is the floor (measured 0.998x)
    assert rep.table["updated"].se.value <= 1.5 * true_floor(true, d), rep.message
