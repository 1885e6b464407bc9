"""Where fits on a filter's result start: past its transient, never most of the record.

A force with only positions measured puts the unknown-input filter's zero
on the unit circle: its covariance converges slowly and meets the
convergence test only near the end of a long record (the EMPS data, 22000
samples: at sample 21969). The law used to be fitted from there on, on a
few dozen samples (EMPS's first 22000 samples gave ``(16.2 ± 0.95)*q^3``
instead of the Coulomb friction it gives on 20000 samples).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

import greybox as gb
from greybox.system import named_ss
from greybox.trace import resolve_channel_spec, trace_channel


def _emps_like(N=23000, seed=3):
    """A ball-screw axis in a P/P cascade (EMPS's published M, Fv, Fc, gains), encoder-quantized.

    Returns the nominal model (no friction), q, vir, Q, R and the truth -Fc/M.
    """
    M, Fv, Fc, gtau, kp, kv, dt = 95.1, 203.5, 20.4, 35.15, 160.18, 243.45, 1e-3
    t = np.arange(N) * dt
    qr = 0.1 - 0.1 * np.cos(2 * np.pi * t / 6.0) * (1 + 0.3 * np.sin(2 * np.pi * t / 17.0))
    step = 2.5e-7  # encoder step [m]
    q, vir = np.zeros(N), np.zeros(N)
    x, q_prev, h = np.zeros(2), 0.0, dt / 10
    for k in range(N):
        q[k] = np.round(x[0] / step) * step
        vf = (q[k] - q_prev) / dt if k else 0.0
        q_prev = q[k]
        vir[k] = 1e-2 * (kp * kv * (qr[k] - q[k]) - kv * vf)  # a softer loop than the rig's
        for _ in range(10):  # Euler, 10 sub-steps; Coulomb friction smoothed over 1 mm/s
            a = (gtau * vir[k] - Fv * x[1] - Fc * np.tanh(x[1] / 1e-3)) / M
            x = x + h * np.array([x[1], a])
    nom = named_ss([[0, 1], [0, -Fv / M]], [[0], [gtau / M]], [[1, 0]], [[0]], 0,
                   states=["q", "v"], inputs=["vir"], outputs=["q"])
    return nom, q, vir, np.diag([0.0, 1e-9]), np.array([[step**2 / 12]]), -Fc / M, dt


def test_settled_is_the_converged_period_or_the_settled_one_when_late():
    rng = np.random.default_rng(0)
    sys = named_ss([[0.9]], [[0.1]], [[1.0]], [[0.0]], 0.1, states=["x"], inputs=["u"],
                   outputs=["y"])
    y, u = rng.standard_normal((1, 1000)), rng.standard_normal((1, 1000))
    res = gb.kalman_filter(sys, y, u, Q=[[0.1]], R=[[0.1]])
    kc, ks = res.period_converged, res.period_settled
    # a geometric recursion: within 10 % of its converged variance well before the test
    assert kc is not None and ks is not None and 1 <= ks < kc < 20
    assert res.settled(20) == 20 and res.settled(5) == max(5, kc)
    assert replace(res, period_converged=500).settled(20) == 500
    # converged only in the second half of the record: from where P settled
    assert replace(res, period_converged=501, period_settled=40).settled(20) == 40
    assert replace(res, period_converged=900, period_settled=5).settled(20) == 20
    assert replace(res, period_converged=900, period_settled=None).settled(20) == 900
    assert replace(res, period_converged=None).settled(20) == 20


def test_a_creeping_filter_still_fits_the_law_on_the_whole_record():
    nom, q, vir, Q, R, truth, dt = _emps_like()
    ch = [c for c in resolve_channel_spec(nom, None) if c.name == "eq(v)"][0]
    tr = trace_channel(nom, ch, q[None], vir[None], Q=Q, R=R, dt=dt, max_order=0)
    # the precondition: the r = 1 filter's covariance meets the test only near the end
    # (measured at sample 21603 of 23000); without it this test could not fail
    res = tr.filter_result
    assert res.period_converged > 0.9 * q.size
    assert res.settled(20) == res.period_settled < 0.5 * q.size
    names = [s[0] for s in tr.static.spec]
    j = names.index("sign(v)")
    # the Coulomb friction, -Fc/M = -0.2145 m/s^2: measured -0.226 +- 0.005, fitted from
    # sample 8445, where the variances came within 10 % of their converged values (+5 %: the
    # simulated friction is tanh(v / 1 mm/s), the law's sign(v) a sharper tanh, and small v,
    # vir, v^3 terms share the shape); 10 % bounds it. Before the fix the law was fitted on
    # the 1397 samples after sample 21603 and read -(0.067 +- 0.016)*sign(q)
    assert tr.static.coef[0, j] < 0, tr.static.formula
    assert abs(tr.static.coef[0, j] / truth - 1) < 0.10, tr.static.formula
    assert np.count_nonzero(tr.static.coef[0, [names.index(n) for n in names
                                               if n.startswith(("sign(q)", "q^3"))]]) == 0
