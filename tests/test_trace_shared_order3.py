"""One third-order hidden subsystem shared by two state equations (issue 8 item 2, order 3).

Plant: ``plantlib.thermal_chain3_pair``: two measured bodies T1, T2 and, hidden behind
them, a chain of three thermal masses (Tm1 touches T1 and T2, Tm2 touches Tm1, Tm3 touches
Tm2 only). In the coordinates where the subsystem's gain in d_T1 is 1 (z = (g1/C1) Tm1)
the true law is

    d_T1 = z + (a_11 - A_11) T1,   d_T2 = k_2 z + (a_22 - A_22) T2,
    z = sum_i (beta_2i s^2 + beta_1i s + beta_0i) / det(sI - H) T_i,

H the hidden chain's 3x3 matrix, poles -1.525, -0.460 and -0.0401 1/s. The second-order
law (offered first) ends at ~1.6x the true model's validation error on seed 1; the
workflow must offer order 3 and choose it.
"""

from __future__ import annotations

import numpy as np
import pytest

import greybox as gb
from greybox.trace.shared_order2 import SharedLaw2, _alpha_of, _pole_coords
from plantlib import thermal_chain3_pair, true_floor

SEEDS = (1, 2, 3)


def _true_law(nominal, true_c):
    """Poles (slow first), beta (3, 2) over (T1, T2), k_2, e_11, e_22 of the true law, from
    the plant's continuous matrix ``true_c`` (5x5)."""
    At = np.asarray(true_c, dtype=float)
    A = np.asarray(nominal.A, dtype=float)
    g = At[0, 2]  # z = g Tm1: the subsystem's gain in d_T1 is 1
    H = At[2:, 2:]
    # Tm1 = e1' adj(sI - H) [At[2, i]; 0; 0] / det(sI - H) T_i: adj(sI - H)[0, 0] is the
    # determinant of the lower-right 2x2 block of sI - H
    minor = np.poly(H[1:, 1:])  # s^2 - tr s + det of that block
    beta = np.array([g * At[2, i] * minor for i in range(2)]).T
    return {"poles": np.sort(np.linalg.eigvals(H).real)[::-1], "beta": beta,
            "alpha": np.poly(H)[1:], "k2": At[1, 2] / g, "e11": At[0, 0] - A[0, 0],
            "e22": At[1, 1] - A[1, 1]}


def _plant_matrix():
    """The continuous 5x5 matrix of thermal_chain3_pair (its documented values)."""
    c1, c2, cm1, cm2, cm3 = 1.0, 2.0, 2.0, 4.0, 8.0
    l1, l2, g1, g2, g3, g4 = 0.5, 0.4, 1.0, 0.8, 1.0, 1.0
    return np.array([[-(l1 + g1) / c1, 0, g1 / c1, 0, 0], [0, -(l2 + g2) / c2, g2 / c2, 0, 0],
                     [g1 / cm1, g2 / cm1, -(g1 + g2 + g3) / cm1, g3 / cm1, 0],
                     [0, 0, g3 / cm2, -(g3 + g4) / cm2, g4 / cm2],
                     [0, 0, 0, g4 / cm3, -g4 / cm3]])


def test_true_law_read_from_the_plant():
    # the oracle against an independent route: the plant's discrete model (logm of the
    # 5x5 ZOH matrix) and the transfer function Tm1/T_i of the hidden chain
    from scipy.linalg import logm

    nom, _, true = thermal_chain3_pair(1, n_est=200)
    At = np.real(logm(np.asarray(true.A, dtype=float))) / true.dt
    np.testing.assert_allclose(At, _plant_matrix(), atol=1e-9)  # logm exact to rounding
    tl = _true_law(nom, _plant_matrix())
    np.testing.assert_allclose(tl["poles"], [-0.0401, -0.460, -1.525], rtol=2e-3)
    # numerator of T1 at s = 0.3: g * At[2, 0] * det(sI - H[1:, 1:]) against a direct
    # evaluation of e1' (sI - H)^-1 e1 det(sI - H)
    s0 = 0.3
    H = _plant_matrix()[2:, 2:]
    direct = np.linalg.inv(s0 * np.eye(3) - H)[0, 0] * np.linalg.det(s0 * np.eye(3) - H)
    np.testing.assert_allclose(np.polyval(tl["beta"][:, 0], s0), 1.0 * 0.5 * direct,
                               rtol=1e-12)


def test_pole_coordinates_round_trip():
    # the chain rule of the pole intervals rests on alpha(phi): one real pole and a complex
    # pair, and three real poles, back to the same denominator to rounding
    for poles in ([-0.5, complex(-0.2, 1.5), complex(-0.2, -1.5)], [-0.04, -0.46, -1.5]):
        alpha = np.real(np.poly(poles))[1:]
        p, phi, nreal = _pole_coords(alpha)
        np.testing.assert_allclose(_alpha_of(phi, nreal), alpha, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(np.sort_complex(p), np.sort_complex(np.asarray(poles)),
                                   rtol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("n_seeds", [1, 3])
def test_one_third_order_subsystem_in_the_pair(n_seeds):
    """The first seed, or all three in one test (each ~30 s; the coverage count needs them
    all; [3] is in the extended tier, tests/conftest.py): a module fixture would run on
    every xdist worker that takes one of its tests."""
    inside = np.zeros(3)
    for seed in SEEDS[:n_seeds]:
        nom, d, true = thermal_chain3_pair(seed)
        rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                                delta=False)
        floor = true_floor(true, d)
        assert rep.updated and rep.channel.name == "eq(T1)+eq(T2)", (seed, rep.message)
        assert rep.effect.kind == "dynamic" and rep.effect.order == 3, (seed, rep.message)
        dl = rep.effect.dynamic_law
        assert isinstance(dl, SharedLaw2) and dl.order == 3, rep.effect.formula
        assert len(rep.steps or [None]) == 1, rep.message  # one effect, nothing after it
        assert rep.model.sys.nstates == nom.nstates + 3
        assert set(dl.drivers) == {"T1", "T2"}, dl.formula  # the bodies, no proxy input
        # the second-order law was offered and lost
        assert any(c.kind == "dynamic (sparse)" and c.order == 2 for c in rep.candidates)
        # the true model's validation SE is the floor; 1.5x as issue 8 item 7 asks
        assert rep.table["updated"].se.value <= 1.5 * floor, (seed, rep.table, floor)
        tl = _true_law(nom, _plant_matrix())
        assert np.all(np.isreal(dl.poles)), dl.formula
        err = np.abs(dl.poles.real - tl["poles"])
        # every pole within 3 half-widths in every seed (~6 sigma: a gross error)
        assert np.all(err <= 3 * dl.pole_ci), (seed, dl.poles, dl.pole_ci)
        inside += err <= dl.pole_ci
        # the numerators: within 3 half-widths (their order in dl.drivers may differ)
        order = [("T1", "T2").index(nm) for nm in dl.drivers]
        nb = int(np.count_nonzero(dl.beta))
        est, ref = dl.beta[dl.beta != 0], tl["beta"][:, order][dl.beta != 0]
        assert np.all(np.abs(est - ref) <= 3 * dl.ci[3:3 + nb]), (seed, est, ref)
        # the true feedthrough terms, within 2 % (intervals ~0.2 %)
        feed = {(c, nm): v for c, nm, v in dl.feedthrough}
        np.testing.assert_allclose([feed[0, "T1"], feed[1, "T2"]], [tl["e11"], tl["e22"]],
                                   rtol=0.02)
        np.testing.assert_allclose(dl.k[1], tl["k2"], rtol=0.02)
        assert "third-order" in dl.formula and "time constants" in dl.formula
    # each pole inside its 95 % interval in >= 2 of 3 seeds (probability ~0.993 each)
    assert n_seeds < 3 or np.all(inside >= 2), inside


def test_third_order_law_evaluates_as_its_subsystem():
    # SharedLaw2.evaluate (order 3) against scipy's ZOH simulation of the same transfer
    # functions (lsim with interp=False holds the input over each sample)
    from scipy.signal import lsim

    tl = _true_law(thermal_chain3_pair(1, n_est=200)[0], _plant_matrix())
    alpha = tl["alpha"]
    Bz = np.zeros((3, 4))
    Bz[:, :2] = tl["beta"]
    E = np.array([[tl["e11"], 0, 0, 0], [0, tl["e22"], 0, 0]])
    law = SharedLaw2(order=3, poles=tl["poles"], pole_ci=np.zeros(3), taus=-1 / tl["poles"],
                     alpha=alpha, states=("z[0]", "z[1]", "z[2]"), drivers=("T1", "T2"),
                     beta=tl["beta"], k=np.array([1.0, tl["k2"]]), reference=0,
                     feedthrough=((0, "T1", tl["e11"]), (1, "T2", tl["e22"])), Bz=Bz, E=E,
                     ci=np.zeros(12), npar=12, formula="", model=None, se_estimation=0.0,
                     continuous=None, dt=0.05)
    rng = np.random.default_rng(0)
    x, u = rng.standard_normal((2, 400)), rng.standard_normal((2, 400))
    d = law.evaluate(x, u)
    t = 0.05 * np.arange(400)
    z = sum(lsim((tl["beta"][:, i], np.r_[1.0, alpha]), x[i], t, interp=False)[1]
            for i in range(2))
    np.testing.assert_allclose(d[0], z + tl["e11"] * x[0], atol=1e-10)
    np.testing.assert_allclose(d[1], tl["k2"] * z + tl["e22"] * x[1], atol=1e-10)
