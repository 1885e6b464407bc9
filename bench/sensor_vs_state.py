#!/usr/bin/env python
"""Sensor-side error vs state-equation channels: which candidate explains d^? (issue 11).

A mass-spring-damper (p, v both measured, correct state model) whose position
sensor is wrong: (a) rectifying, y_p = |p| + v; (b) slowly drifting,
y_p = p + 0.02 t / T + v. Three candidate channels, each run on the same data:

* ``out p``: ``feedthrough_uikf(with_sensor_error(sys, "p_meas"))``, d^[k] = what
  the position sensor shows beyond p[k];
* ``eq(v)``, ``eq(p)``: ``uikf`` with an unknown input in that state equation.

For each, a static law d^ ~ [p, |p|, v, |v|, 1, t] is fitted by least squares on
x^[k|k]; printed: R^2 of the law and the law residual's variance over the
filter's own mean d_var (about 1 when the law leaves only the estimation noise).
This is the evidence a trace needs to put the error on the output.

Usage::

    python bench/sensor_vs_state.py
"""

from __future__ import annotations

import os
import sys

import control as ct
import numpy as np

import greybox as gb


def main() -> int:
    dt, N = 0.01, 4000
    sd = ct.c2d(ct.ss([[0.0, 1.0], [-40.0, -2.0]], [[0.0], [1.0]], np.eye(2), 0), dt)
    A, B = np.asarray(sd.A), np.asarray(sd.B)
    base = gb.named_ss(A, B, np.eye(2), np.zeros((2, 1)), dt, states=["p", "v"],
                       inputs=["u"], outputs=["p_meas", "v_meas"])
    Q, R = np.diag([1e-8, 1e-6]), np.diag([1e-6, 1e-4])
    rng = np.random.default_rng(0)
    u = 20 * np.sin(np.arange(N) * dt * 3.0)[None] + 5 * rng.standard_normal((1, N))
    x = np.zeros(2)
    X, Y = [], []
    for k in range(N):  # the truth: a plain loop
        X.append(x)
        Y.append(x + rng.multivariate_normal([0, 0], R))
        x = A @ x + B[:, 0] * u[0, k] + rng.multivariate_normal([0, 0], Q)
    X, y = np.array(X).T, np.array(Y).T
    print(f"# load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}; N = {N}, "
          f"dt = {dt} s, seed 0")
    print("\n| sensor fault | candidate | law R^2 | law residual var / mean d_var |")
    print("|---|---|---|---|")
    t = np.arange(N) * dt
    for fault in ("rectifying abs(p)", "drift 0.02 t/T"):
        yy = y.copy()
        if fault.startswith("rect"):
            yy[0] = np.abs(X[0]) + (y[0] - X[0])
        else:
            yy[0] = y[0] + 0.02 * t / t[-1]
        cands = {"out p": gb.feedthrough_uikf(gb.with_sensor_error(base, "p_meas"), yy, u,
                                               unknown="p_meas_err", Q=Q, R=R)}
        for eq, g in (("eq(v)", [[0.0], [dt]]), ("eq(p)", [[dt], [0.0]])):
            s = gb.named_ss(A, np.hstack([B, np.asarray(g)]), np.eye(2), np.zeros((2, 2)), dt,
                            states=["p", "v"], inputs=["u", "d"],
                            outputs=["p_meas", "v_meas"])
            cands[eq] = gb.uikf(s, yy, u, unknown="d", Q=Q, R=R)
        for name, r in cands.items():
            k = slice(20, N - 2)
            d, xs = r.d_est[0, k], r.x_filt[:, k]
            T = np.column_stack([xs[0], np.abs(xs[0]), xs[1], np.abs(xs[1]), np.ones(d.size),
                                 t[k]])
            c, *_ = np.linalg.lstsq(T, d, rcond=None)
            res = d - T @ c
            print(f"| {fault} | {name} | {1 - res.var() / d.var():.3f} | "
                  f"{res.var() / np.mean(r.d_var[0, k]):.3g} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
