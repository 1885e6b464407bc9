"""A constant sensor offset: detected (the innovations' mean, not only their colour),
nominated among many outputs (its DC signature in the innovations), and scored from
an initial state that does not absorb it.

Truth: simulated models with a known offset on one sensor.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

import greybox as gb
from greybox import zoo
from greybox.filters import kalman_filter
from greybox.metrics import effective_samples
from greybox.trace.screen import screen_sensors


def test_the_mean_test_sees_an_offset_the_ljung_box_test_cannot():
    rng = np.random.default_rng(0)
    e = rng.normal(size=(1, 4000))
    # 0.15 sigma of offset: t = 0.15 sqrt(4000) = 9.5; a constant leaves the autocorrelation
    # around the mean unchanged, so Ljung-Box is the same test on e and on e + offset
    lb = gb.whiteness_test(e + 0.15)
    full = gb.innovation_test(e + 0.15)
    assert lb.all_white and not full.all_white and full.mean_pvalue[0] < 1e-12


def test_the_joint_test_keeps_its_level_on_white_noise():
    """Rejections of zero-mean white noise at alpha = 0.05 over 400 series, by the mean
    alone and by the joint test (Ljung-Box + mean): each within the binomial 99.9 % band
    of 20 (7-36). Two tests at alpha each would reject ~39."""
    rng = np.random.default_rng(1)
    tests = [gb.innovation_test(rng.normal(size=(1, 500)), alpha=0.05) for _ in range(400)]
    by_mean = sum(t.mean_pvalue[0] < 0.05 for t in tests)
    joint = sum(not t.all_white for t in tests)
    assert 7 <= by_mean <= 36 and 7 <= joint <= 36, (by_mean, joint)


def _plant(rng, n, p):
    """A random stable discrete model, n states, p outputs (random mixtures of states)."""
    while True:
        A = rng.normal(size=(n, n)) / np.sqrt(n)
        A *= rng.uniform(0.8, 0.97) / np.max(np.abs(np.linalg.eigvals(A)))
        B, C = rng.normal(size=(n, 1)), rng.normal(size=(p, n))
        if np.linalg.matrix_rank(C) == min(n, p):
            return gb.named_ss(A, B, C, np.zeros((p, 1)), 1.0,
                               states=[f"x{i + 1}" for i in range(n)], inputs=["u"],
                               outputs=[f"y{i + 1}" for i in range(p)], name="plant")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_sensor_screen_names_the_offset_sensor_and_its_offset(seed):
    rng = np.random.default_rng(seed)
    n, p, N = int(rng.integers(4, 9)), int(rng.integers(7, 11)), 4000
    sys = _plant(rng, n, p)
    Q, R = 1e-3 * np.eye(n), 1e-2 * np.eye(p)
    sim = gb.simulate(sys, rng.normal(size=(1, N)), Q=Q, R=R, rng=rng)
    j, b = int(rng.integers(p)), rng.choice([-1.0, 1.0]) * rng.uniform(0.05, 0.3)
    y = sim.y.copy()
    y[j] += b
    kf = kalman_filter(sys, y, sim.u, Q=Q, R=R)
    e = kf.innovations[:, 50:]
    scr = screen_sensors(sys, kf.K, e, effective_samples(e))
    assert scr.outputs[0] == f"y{j + 1}", (scr.outputs[:3], scr.misfit[:3])
    # the offset's standard error is ~ sqrt(R_jj / N) = 0.0016; 10 % of b >= 0.005 is > 3 SE
    assert abs(scr.offset[0] - b) < 0.1 * abs(b), (scr.offset[0], b)
    # its misfit is chi-square on p - 1 degrees of freedom; the next sensor's is far above
    assert scr.misfit[0] < chi2.isf(1e-3, p - 1) < scr.misfit[1]


@pytest.mark.parametrize("cls,seed,i", [("sensor_gain_offset", 1641989470, 0),
                                        ("sensor_gain_offset", 1641989470, 1),
                                        ("sensor_drift", 431401745, 0)])
def test_close_the_loop_names_a_sensor_offset_with_its_value(cls, seed, i):
    """Zoo draws that were left unchanged (Ljung-Box blind to the offset; no sensor
    channel above 6 outputs), or named as laws in two state equations: a 9-mass chain
    (positions only, 9 sensors), a 4-body thermal row (2 sensors, the sensor candidate
    scored 1.5 % from an initial state that absorbed the offset) and a 7-mass chain whose
    p7 sensor drifts (7 sensors; innovations far from white, their mean on each output
    not significant alone: the screen's evidence is the offsets' joint fit)."""
    d = zoo.draw_class(cls, seed, i, n_est=4000)
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    s = zoo.score(d, rep)
    assert rep.updated and s.right_channel and s.right_kind and s.right_terms, (s.why, s.found)
    assert s.coefficients_within, s.found
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)
