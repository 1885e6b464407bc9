#!/usr/bin/env python
"""EMPS: the unknown friction force from positions only, r = 1 filter vs delayed (r = 2).

Issue 11 experiment (measured data, /work/shared/data/emps). Nominal model
M q'' + Fv q' = gtau vir with the published M, Fv, gtau; the unknown input is
a force F [N] in the velocity equation (d = -(Fc sign(q') + offset) + ...),
ZOH-discretized at 1 ms; only the encoder position is measured. Noise levels
as in tests/test_measured_data.py: R from the encoder step, Q_vv from the
nominal force residual. Estimation record DATA_EMPS[0:8000].

Rows: uikf (relative degree 1) raw; its two-sample mean (the old workaround);
delayed_uikf (relative degree detected); smooth_uikf on top of it. For each:
the filter's own d^ standard deviation, the lag-1 autocorrelation of d^, and
a least-squares static law d^ ~ a tanh(v/0.005) + b v + c |v| + e on the
state estimate (Fc = -a, offset = -e, (Fv- - Fv+)/2 = c), compared with the published values
(Fc 20.39 N, offset -3.16 N; asymmetry (Fv- - Fv+)/2 = 36.9 N s/m).

Usage::

    python bench/emps_delayed.py
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

import greybox as gb

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "emps" / "DATA_EMPS.npz"
M, FV, DT = 95.1089, 203.5034, 1e-3
FC_PUB, OFFSET_PUB, ASYM_PUB = 20.3935, -3.1648, 0.5 * (240.42 - 166.71)


def _law(d, x):
    v = x[1]
    X = np.column_stack([np.tanh(v / 0.005), v, np.abs(v), np.ones_like(v)])
    coef, *_ = np.linalg.lstsq(X, d, rcond=None)
    resid = d - X @ coef
    return coef, float(np.std(resid))


def main() -> int:
    if not DATA.is_file():
        print(f"data not found: {DATA}")
        return 1
    z = np.load(DATA)
    q, vir, gtau = z["qm"], z["vir"], float(z["gtau"])
    steps = np.diff(np.unique(q))
    R = np.array([[steps[steps > 1e-12].min() ** 2 / 12]])
    v = np.gradient(q, DT)
    res = M * np.gradient(v, DT) + FV * v - gtau * vir
    Q = np.diag([0.0, np.var(res / M * DT)])
    sysc = gb.named_ss([[0, 1], [0, -FV / M]], [[0, 0], [gtau / M, 1 / M]], [[1, 0]], [[0, 0]],
                       0, states=["q", "v"], inputs=["vir", "F"], outputs=["q"])
    sysd = gb.discretize(sysc, DT)
    est = slice(0, 8000)
    y, u = q[None, est], vir[None, est]
    print(f"# load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; EMPS DATA_EMPS"
          f"[0:8000], dt = 1 ms, R = {R[0, 0]:.3g} m^2, Q_vv = {Q[1, 1]:.3g} (m/s)^2")
    rd = gb.detect_relative_degree(sysd, unknown="F", Q=Q, R=R)
    print(f"# detect_relative_degree: r = {rd.r}; steady d variance per r {rd.d_var}; "
          f"{rd.reason}")
    f1 = gb.uikf(sysd, y, u, unknown="F", Q=Q, R=R)
    fd = gb.delayed_uikf(sysd, y, u, unknown="F", Q=Q, R=R, relative_degree="auto")
    fs = gb.smooth_uikf(sysd, y, u, unknown="F", Q=Q, R=R, relative_degree="auto")
    rows = []
    k = slice(50, 7990)
    d1, x1 = f1.d_est[0, k], f1.x_filt[:, k]
    rows.append(("uikf r=1, raw d^", d1, x1, f1.d_var[0, k]))
    d2 = 0.5 * (f1.d_est[0, 50:7989] + f1.d_est[0, 51:7990])
    x2 = 0.5 * (f1.x_filt[:, 50:7989] + f1.x_filt[:, 51:7990])
    rows.append(("uikf r=1, 2-sample mean (old workaround)", d2, x2, None))
    rows.append((f"delayed_uikf r={fd.relative_degree}", fd.d_est[0, k], fd.x_filt[:, k],
                 fd.d_var[0, k]))
    rows.append((f"smooth_uikf r={fs.relative_degree}", fs.d_est[0, k], fs.x_filt[:, k],
                 fs.d_var[0, k]))
    print("\n| estimate | d^ std [N] | filter's sqrt(d_var) [N] | lag-1 autocorr | Fc [N] "
          "(pub 20.39) | offset [N] (pub -3.16) | |v| coef = (Fv- - Fv+)/2 [N s/m] (pub 36.9) "
          "| law residual std [N] |")
    print("|" + "---|" * 8)
    for name, d, x, var in rows:
        coef, rs = _law(d, x)
        ac = np.corrcoef(d[1:], d[:-1])[0, 1]
        sd = "n/a" if var is None else f"{np.sqrt(np.median(var)):.3g}"
        print(f"| {name} | {np.std(d):.3g} | {sd} | {ac:.2f} | {-coef[0]:.2f} | {-coef[3]:.2f} "
              f"| {coef[2]:.1f} | {rs:.3g} |")
    print("\nSign convention: F enters M v' = gtau vir - Fv v + F, so friction F = -(Fc "
          "sign(v) + offset + ...). The d^ of the r = 2 filter estimates the two-sample mean "
          "(F[k] + F[k+1]) / 2 (see greybox.filters.delayed).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
