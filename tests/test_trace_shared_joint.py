"""A shared-state law among several effects, refitted jointly (issue 8 items 2 and 5).

Plant: ``plantlib.thermal_three``: the hidden thermal mass of ``thermal_pair``
shared by eq(T1) and eq(T2), and an independent missing conductance of a third
body to ambient (0.15 W/K on 1.5 J/K: d_T3 = -0.1 T3). Both must be found over
the several-effects loop, the shared law must take part in the joint output-error
refit (greybox.trace.joint), and the final model must hold both.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import logm

import greybox as gb
from greybox.trace import resolve_channel_spec
from greybox.trace.dynamic import SharedLaw
from greybox.trace.joint import JointEffect, _params, joint_effect
from plantlib import thermal_three, true_floor

SEEDS = (1, 2, 3)


@pytest.fixture(scope="module")
def runs():
    out = {}
    for seed in SEEDS:
        nom, d, true = thermal_three(seed)
        rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                                delta=False)
        floor = true_floor(true, d)
        out[seed] = (nom, true, rep, floor)
    return out


def _by_kind(rep):
    shared = [st for st in rep.steps if isinstance(st.effect.dynamic_law, SharedLaw)]
    static = [st for st in rep.steps if st.effect.kind == "static"]
    return shared, static


@pytest.mark.slow
@pytest.mark.parametrize("seed", SEEDS, ids=[f"seed{s}" for s in SEEDS])
def test_both_effects_found_and_held_by_the_final_model(runs, seed):
    _check_both(*runs[seed])


@pytest.mark.slow
def test_both_effects_found_with_half_the_data():
    """Seed 3 at N = 1e4: the second effect spoils both pair fits (unstructured 22.9 %,
    static 24.5 %), so the shared law was not offered (it needed a 20 % margin) and an
    18-term nonlinear static pair law was chosen (validation SE 29 %, 51x the true
    model's); offered, its d^ starts ended in an 8-term realization (drivers Q1, Q2). Now
    offered whenever the unstructured fit is better, with the touching-bodies start
    always refined."""
    nom, d, true = thermal_three(3, n_est=10000)
    rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    floor = true_floor(true, d)
    _check_both(nom, true, rep, floor)


def _check_both(nom, true, rep, floor):
    """Both effects named with their true terms, refitted jointly, at the floor."""
    assert rep.updated and len(rep.steps) == 2, rep.message
    shared, static = _by_kind(rep)
    assert len(shared) == 1 and shared[0].channel == "eq(T1)+eq(T2)", rep.message
    assert len(static) == 1 and static[0].channel == "eq(T3)", rep.message
    dl = shared[0].effect.dynamic_law
    assert set(dl.drivers) == {"T1", "T2"}, dl.formula
    assert {(c, nm) for c, nm, _ in dl.feedthrough} == {(0, "T1"), (1, "T2")}, dl.formula
    law = static[0].effect.law
    names = [law.spec[j][0] for j in np.flatnonzero(law.coef[0])]
    assert names == ["T3"], law.formula
    # the shared law took part in the joint refit (it was skipped before: joint_effect None)
    assert any("joint refinement of the 2 effects" in nt for nt in rep.notes), rep.notes
    # the final model holds both: 3 + 1 states, and its poles are the true plant's (a
    # similarity invariant; the laws' intervals are ~0.1-0.5 %: 2 % is a gross error)
    assert rep.model.sys.nstates == 4
    lam = np.sort(np.linalg.eigvals(np.asarray(rep.model.sys.A, dtype=float)).real)
    lam_true = np.sort(np.linalg.eigvals(np.asarray(true.A, dtype=float)).real)
    np.testing.assert_allclose(lam, lam_true, rtol=2e-2)
    # the true model's validation SE is the floor; 1.5x as issue 8 item 7 asks
    assert rep.table["updated"].se.value <= 1.5 * floor


@pytest.mark.slow
def test_coefficients_inside_their_intervals_in_most_seeds(runs):
    inside = 0
    total = 0
    for seed in SEEDS:
        nom, true, rep, _ = runs[seed]
        shared, static = _by_kind(rep)
        At = np.real(logm(np.asarray(true.A, dtype=float))) / true.dt
        g = At[0, 3]
        dl = shared[0].effect.dynamic_law
        est = np.r_[dl.pole, dl.b, dl.k[1], [v for _, _, v in dl.feedthrough]]
        ref = np.r_[At[3, 3], g * At[3, [("T1", "T2").index(nm) for nm in dl.drivers]],
                    At[1, 3] / g, -1.0, -0.4]
        law = static[0].effect.law
        j = int(np.flatnonzero(law.coef[0])[0])
        est, ref = np.r_[est, law.coef[0, j]], np.r_[ref, -0.1]
        half = np.r_[dl.ci, law.ci[0, j]]
        # within 3 half-widths in every seed (~6 sigma: a gross error) ...
        assert np.all(np.abs(est - ref) <= 3 * half), (seed, est, ref, half)
        inside += int(np.sum(np.abs(est - ref) <= half))
        total += est.size
    # ... and inside their 95 % intervals in most cases (21 intervals: >= 15 inside has
    # probability > 0.999 if they are calibrated)
    assert inside >= 15, (inside, total)


def test_a_shared_law_is_affine_in_its_coefficients(runs):
    # the joint refit's parametrization A0 + sum theta_q dA_q must rebuild the law's own
    # continuous model exactly (to rounding); A0 holds the reference component's fixed
    # gain 1 (the scale of z), which is not a coefficient
    nom, _, rep, _ = runs[SEEDS[0]]
    shared, _ = _by_kind(rep)
    dl = shared[0].effect.dynamic_law
    ch = resolve_channel_spec(nom, [("T1", "T2")])[0]
    ef = joint_effect(nom, ch, dl)
    assert isinstance(ef, JointEffect)
    ps = _params([ef], 4, 3)
    A = np.zeros((4, 4))
    A[:3, :3] = np.asarray(nom.A, dtype=float)
    A[:3, 3] = np.asarray(ch.G, dtype=float)[:, dl.reference]
    B = np.vstack([np.asarray(nom.B, dtype=float), np.zeros((1, 3))])
    A += sum(p.value * p.dA for p in ps)
    B += sum(p.value * p.dB for p in ps)
    np.testing.assert_allclose(A, np.asarray(dl.continuous.A, dtype=float), atol=1e-12)
    np.testing.assert_allclose(B, np.asarray(dl.continuous.B, dtype=float), atol=1e-12)
    assert len(ps) == dl.npar  # a, b (2), k_2, e (2)
