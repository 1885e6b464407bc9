"""One hidden state shared by two state equations along no fixed direction (issue 8 item 2).

Plant: ``plantlib.thermal_pair``: two measured bodies T1, T2 and a hidden
thermal mass Tm the model lacks, coupled to both. The true law, in the
coordinates where the state's gain in d_T1 is 1 (z = (g1/C1) Tm), is

    d_T1 = z + (a_11 - A_11) T1,   d_T2 = k_2 z + (a_22 - A_22) T2,
    dz/dt = a z + b_1 T1 + b_2 T2,

six coefficients, read off the true continuous model (the matrix logarithm
of the true discrete model that ``thermal_pair`` returns).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import logm

import greybox as gb
from greybox.trace.dynamic import SharedLaw
from plantlib import thermal_pair, true_floor

SEEDS = (1, 2, 3)


def _true_law(nominal, true_d):
    """(a, b over (T1, T2), k_2, e_11, e_22) of the true law, from the true model."""
    At = np.real(logm(np.asarray(true_d.A, dtype=float))) / true_d.dt
    A = np.asarray(nominal.A, dtype=float)
    g = At[0, 2]  # z = g Tm: the state's gain in d_T1 is 1
    return {"a": At[2, 2], "b": g * At[2, :2], "k2": At[1, 2] / g,
            "e11": At[0, 0] - A[0, 0], "e22": At[1, 1] - A[1, 1]}


@pytest.fixture(scope="module")
def runs():
    out = {}
    for seed in SEEDS:
        nom, d, true = thermal_pair(seed, n_est=20000)
        rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                                delta=False)
        floor = true_floor(true, d)
        out[seed] = (nom, true, rep, floor)
    return out


def test_true_law_read_from_the_plant(runs):
    # the oracle itself: the plant's documented values (C 1, 2, 4 J/K; g 1.0, 0.8 W/K)
    nom, true, _, _ = runs[SEEDS[0]]
    tl = _true_law(nom, true)
    # logm of a 3x3 ZOH matrix with real positive eigenvalues: exact to rounding
    np.testing.assert_allclose([tl["a"], *tl["b"], tl["k2"], tl["e11"], tl["e22"]],
                               [-0.45, 0.25, 0.2, 0.4, -1.0, -0.4], rtol=1e-9)


@pytest.mark.parametrize("seed", SEEDS, ids=[f"seed{s}" for s in SEEDS])
def test_one_shared_state_in_the_pair(runs, seed):
    nom, true, rep, floor = runs[seed]
    assert rep.updated
    assert rep.channel.name == "eq(T1)+eq(T2)"
    assert rep.effect.kind == "dynamic" and rep.effect.order == 1
    dl = rep.effect.dynamic_law
    assert isinstance(dl, SharedLaw)
    assert not dl.one_direction  # d_T1 carries T1, d_T2 carries T2: no fixed direction
    assert rep.model.sys.nstates == nom.nstates + 1  # one state, shared by both equations
    # the second-order shared law (greybox.trace.shared_order2) was offered beside it and
    # lost, or ended undetermined, or was not tried because the first-order law already
    # leaves white innovations: order 2 is not chosen where order 1 is the truth
    assert any(c.kind == "dynamic (sparse)" and c.order == 2 and c.status == "ok"
               for c in rep.candidates) or \
        "eq(T1)+eq(T2): no second-order shared law" in " ".join(rep.notes), rep.notes
    assert dl.npar <= 8, dl.formula  # the true law has 6; the unstructured pair filter 24
    # the true model's validation SE is the floor; 1.5x as issue 8 item 7 asks
    assert rep.table["updated"].se.value <= 1.5 * floor
    assert "time constant" in dl.formula and "±" in dl.formula


def test_shared_state_drivers_and_gains_are_the_true_ones(runs):
    for seed in SEEDS:
        nom, true, rep, _ = runs[seed]
        dl = rep.effect.dynamic_law
        tl = _true_law(nom, true)
        assert set(dl.drivers) == {"T1", "T2"}, dl.formula
        assert dl.reference == 0
        assert {(c, nm) for c, nm, _ in dl.feedthrough} == {(0, "T1"), (1, "T2")}, dl.formula
        # coefficients within 3 of their 95 % half-widths in every seed (~6 sigma: a gross
        # error, not the calibration, which the next test checks)
        est = np.r_[dl.pole, dl.b, dl.k[1], [v for _, _, v in dl.feedthrough]]
        ref = np.r_[tl["a"], tl["b"][[("T1", "T2").index(n) for n in dl.drivers]], tl["k2"],
                    tl["e11"], tl["e22"]]
        assert np.all(np.abs(est - ref) <= 3 * dl.ci), (seed, est, ref, dl.ci)


def test_time_constant_inside_its_interval_in_most_seeds(runs):
    inside = 0
    for seed in SEEDS:
        nom, true, rep, _ = runs[seed]
        dl = rep.effect.dynamic_law
        tau_true = -1.0 / _true_law(nom, true)["a"]  # Cm / (g1 + g2) = 2.22 s
        lo, hi = 1.0 / (-dl.pole + dl.ci[0]), 1.0 / (-dl.pole - dl.ci[0])
        inside += lo <= tau_true <= hi
    # 95 % intervals: all three seeds inside with probability ~0.86, two or more ~0.993
    # ("inside their 95 % intervals in most seeds", issue 8 item 7)
    assert inside >= 2


def test_sparsest_realization_is_the_same_law_with_the_true_terms():
    # the true law written in the coordinates z~ = z - 0.2 T1 (7 terms, pole -0.25 1/s; found
    # by output error on seed 1 before the search): the search must return the true 6-term
    # realization, with the same transfer function from u to y (an exact similarity)
    from greybox.trace.dynamic import _SharedProblem, _sparsest_realization

    nom, _, _ = thermal_pair(1, n_est=200)
    A, B = np.asarray(nom.A, dtype=float), np.asarray(nom.B, dtype=float)
    C, D = np.asarray(nom.C, dtype=float), np.asarray(nom.D, dtype=float)
    y, u = np.zeros((2, 200)), np.zeros((2, 200))
    prob = _SharedProblem(A, B, np.eye(2), C, D, 0.05, y, u, np.zeros(2), 20,
                          [("x", 1), ("u", 0)], [(0, ("x", 0)), (1, ("x", 0)), (1, ("x", 1))], 0)
    theta = np.array([-0.25, 0.2, 0.2, 0.4, -1.2, -0.08, -0.4])
    bdrv, eterms, theta1 = _sparsest_realization(prob, theta, np.ones(4))
    assert bdrv == [("x", 0), ("x", 1)]
    assert eterms == [(0, ("x", 0)), (1, ("x", 1))]
    # rounding only (a root of a quadratic in c)
    np.testing.assert_allclose(theta1, [-0.45, 0.25, 0.2, 0.4, -1.0, -0.4], rtol=1e-12)
    prob1 = _SharedProblem(A, B, np.eye(2), C, D, 0.05, y, u, np.zeros(2), 20, bdrv, eterms, 0)
    Ca = np.hstack([C, np.zeros((2, 1))])
    for s in (0.0, 0.1j, 1j, 10j):
        h = [Ca @ np.linalg.solve(s * np.eye(3) - Aa, Ba) for Aa, Ba in
             (prob.cont(theta), prob1.cont(theta1))]
        np.testing.assert_allclose(h[1], h[0], rtol=1e-12, atol=1e-12)
