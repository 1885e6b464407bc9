"""One hidden state shared by three equations of a model above 4 states (issue 8 item 2).

Plant: ``plantlib.thermal_row``: six bodies in a row (T1..T6, all measured,
heaters on T1, T3, T5) and a hidden thermal mass Tm the model lacks, coupled
to T2, T3 and T4 (1.0, 0.8, 0.6 W/K). Above SCREEN_ABOVE = 4 states the
workflow screens the equations jointly and offers the shared-state law for
the screen's group. In the coordinates where the state's gain in d_T2 is 1
(z = g_2 Tm / C_2) the true law is

    d_Ti = k_i z - (g_i / C_i) Ti  (i = 2, 3, 4),   dz/dt = a z + b_2 T2 + b_3 T3 + b_4 T4,

nine coefficients, read off the true continuous model.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import logm

import greybox as gb
from greybox.trace.dynamic import SharedLaw
from plantlib import thermal_row, true_floor

SEEDS = (1, 2, 3)
GROUP = ("T2", "T3", "T4")


def _true_law(nominal, true_d):
    """(a, b over T2..T4, k_3, k_4, e over T2..T4) of the true law, from the true model."""
    At = np.real(logm(np.asarray(true_d.A, dtype=float))) / true_d.dt
    A = np.asarray(nominal.A, dtype=float)
    idx = [1, 2, 3]
    g = At[1, 6]  # z = g Tm: the state's gain in d_T2 is 1
    return {"a": At[6, 6], "b": g * At[6, idx], "k": At[idx, 6] / g,
            "e": np.array([At[i, i] - A[i, i] for i in idx])}


# 5000 estimation samples: the output-error fits' cost grows with the record up to their
# window, and at 5000 the assertions below held on seeds 1-8 (the three tested and five
# more: right group, 9 parameters, within 1.5x the true model's error, every coefficient
# within 3 half-widths); the half-widths widen by sqrt(2) against 10000, and the tests
# compare with them, not with fixed tolerances.
N_EST = 5000


@pytest.fixture(scope="module")
def runs():
    out = {}
    for seed in SEEDS:
        nom, d, true = thermal_row(seed, n_est=N_EST)
        rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                                delta=False)
        out[seed] = (nom, true, rep, true_floor(true, d))
    return out


def test_true_law_read_from_the_plant():
    # the oracle: capacities 1.5, 2, 1 J/K for T2..T4, Tm 4 J/K, couplings 1.0, 0.8, 0.6 W/K
    nom, _, true = thermal_row(1, n_est=400)
    tl = _true_law(nom, true)
    # logm of a 7x7 ZOH matrix with real negative continuous eigenvalues: exact to rounding
    np.testing.assert_allclose(np.r_[tl["a"], tl["b"], tl["k"][1:], tl["e"]],
                               np.r_[-0.6, np.array([1.0, 0.8, 0.6]) / 1.5 / 4, 0.6, 0.9,
                                     -1 / 1.5, -0.4, -0.6], rtol=1e-8)


@pytest.mark.slow
@pytest.mark.parametrize("seed", SEEDS, ids=[f"seed{s}" for s in SEEDS])
def test_one_state_shared_by_the_right_three_equations(runs, seed):
    nom, true, rep, floor = runs[seed]
    assert rep.updated
    assert rep.channel.equations == GROUP, rep.message
    dl = rep.effect.dynamic_law
    assert isinstance(dl, SharedLaw)
    assert rep.model.sys.nstates == nom.nstates + 1  # one state for three equations
    assert set(dl.drivers) == set(GROUP), dl.formula  # the bodies the mass touches
    assert {(c, nm) for c, nm, _ in dl.feedthrough} == {(0, "T2"), (1, "T3"), (2, "T4")}, \
        dl.formula
    assert dl.npar == 9, dl.formula  # the true law's count; the unstructured one ~60
    # the true model's validation SE is the floor; 1.5x as issue 8 item 7 asks
    assert rep.table["updated"].se.value <= 1.5 * floor
    assert "±" in dl.formula and "time constant" in dl.formula


@pytest.mark.slow
def test_coefficients_and_time_constant_against_the_truth(runs):
    inside = 0
    for seed in SEEDS:
        nom, true, rep, _ = runs[seed]
        dl = rep.effect.dynamic_law
        tl = _true_law(nom, true)
        assert dl.reference == 0
        order = [GROUP.index(nm) for nm in dl.drivers]
        est = np.r_[dl.pole, dl.b, dl.k[1:], [v for _, _, v in dl.feedthrough]]
        ref = np.r_[tl["a"], tl["b"][order], tl["k"][1:], tl["e"]]
        # within 3 of their 95 % half-widths in every seed (~6 sigma: a gross error)
        assert np.all(np.abs(est - ref) <= 3 * dl.ci), (seed, est, ref, dl.ci)
        tau = -1.0 / tl["a"]  # Cm / (g2 + g3 + g4) = 1.67 s
        inside += 1.0 / (-dl.pole + dl.ci[0]) <= tau <= 1.0 / (-dl.pole - dl.ci[0])
    # 95 % intervals: all three seeds inside with probability ~0.86, two or more ~0.993
    assert inside >= 2


def test_a_correct_model_of_six_states_stays_unchanged():
    nom, d, _ = thermal_row(1, hidden=())
    rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    assert not rep.updated and not rep.model_error_detected, rep.message
    assert rep.model.kind == "nominal" and rep.model.sys.nstates == nom.nstates
    # the nominal model itself, discretized (ZOH), unchanged
    np.testing.assert_array_equal(np.asarray(rep.model.sys.A),
                                  np.asarray(gb.discretize(nom, d.dt).A))
