#!/usr/bin/env python
"""Monte Carlo figures of the issue-11 estimators (the numbers the tests bound).

Prints, for fixed seeds: bias (max |z| over the checked samples), 95 % coverage
and error variances of

1. delayed_uikf (r = 2) on a ZOH mass, position only, vs uikf (r = 1) on the
   same data (target: the two-sample mean of the force, see
   greybox.filters.delayed);
2. feedthrough_uikf and its smoother on a mass-spring-damper whose position
   sensor has an offset and a gain error (d = 0.2 p + 0.05);
3. smooth_uikf vs uikf on a 4-state, 2-output random system, and on the
   mass of 1 (where it equals the delayed filter).

Usage::

    python bench/unknown_input_stats.py [--runs 300]
"""

from __future__ import annotations

import argparse
import os
import sys

import control as ct
import numpy as np
from scipy.stats import norm

import greybox as gb


def simulate_runs(A, B, C, G, Q, R, x0, P0, u, d_of, nruns, rng, D=None):
    """x[k+1] = A x + B u + G d + w, y = C x + D u + v, all runs at once."""
    n, N, p = A.shape[0], u.shape[1], C.shape[0]
    LQ = np.linalg.cholesky(Q + 1e-30 * np.eye(n))
    LR = np.linalg.cholesky(R)
    x = x0[:, None] + np.linalg.cholesky(P0) @ rng.standard_normal((n, nruns))
    X, Y, Ds = [], [], []
    for k in range(N):
        d = d_of(k, x)
        X.append(x)
        Ds.append(d)
        Du = 0.0 if D is None else (D @ u[:, k])[:, None]
        Y.append(C @ x + Du + LR @ rng.standard_normal((p, nruns)))
        x = A @ x + (B @ u[:, k])[:, None] + G @ d + LQ @ rng.standard_normal((n, nruns))
    return (np.array(X).transpose(2, 1, 0), np.array(Y).transpose(2, 1, 0),
            np.array(Ds).transpose(2, 1, 0))


def stats(err, var):
    z = err.mean(axis=0) / (err.std(axis=0, ddof=1) / np.sqrt(err.shape[0]))
    cover = np.mean(np.abs(err) <= norm.ppf(0.975) * np.sqrt(var)) if var is not None else None
    return float(np.max(np.abs(z))), cover, float(err.var(axis=0).mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=300)
    nruns = ap.parse_args(argv).runs
    print(f"# load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; {nruns} runs each; "
          f"max|z| is the largest bias z-score over the checked samples (3.3 = alpha 1e-3)")
    rng = np.random.default_rng(1)
    # 1. ZOH mass, position only
    dt, m = 0.01, 2.0
    A = np.array([[1.0, dt], [0.0, 1.0]])
    G = np.array([[dt**2 / 2], [dt]]) / m
    mass = gb.named_ss(A, np.hstack([G, G]), [[1.0, 0.0]], [[0.0, 0.0]], dt, states=["p", "v"],
                      inputs=["u", "F"], outputs=["p"])
    Q, R, x0, P0 = np.diag([1e-12, 1e-8]), np.array([[1e-8]]), np.array([0.0, 0.1]), \
        np.diag([1e-6, 1e-4])
    N = 80
    u = 0.5 * np.cos(np.arange(N) * dt * 3.0)[None, :]
    force = lambda k, x: np.full((1, x.shape[1]), 1 + 3 * np.sin(np.pi * k * dt))  # noqa: E731
    _, y, d = simulate_runs(A, G, np.array([[1.0, 0.0]]), G, Q, R, x0, P0, u, force, nruns, rng)
    kk = np.arange(5, N - 2)
    tgt = 0.5 * (d[:, 0, :-1] + d[:, 0, 1:])
    e2, v2, e1, es, vs = [], [], [], [], []
    for i in range(nruns):
        kw = dict(unknown="F", Q=Q, R=R, x0=x0, P0=P0)
        r2 = gb.delayed_uikf(mass, y[i], u, relative_degree=2, **kw)
        r1 = gb.uikf(mass, y[i], u, **kw)
        s2 = gb.smooth_uikf(mass, y[i], u, relative_degree=2, **kw)
        e2.append(r2.d_est[0, kk] - tgt[i, kk])
        v2.append(r2.d_var[0, kk])
        e1.append(r1.d_est[0, kk] - d[i, 0, kk])
        es.append(s2.d_est[0, kk] - tgt[i, kk])
        vs.append(s2.d_var[0, kk])
    z2, c2, var2 = stats(np.array(e2), np.array(v2))
    z1, _, var1 = stats(np.array(e1), None)
    zs, cs, vars_ = stats(np.array(es), np.array(vs))
    print("\n| estimator | plant | max abs z | 95 % coverage | error variance | ratio |")
    print("|---|---|---|---|---|---|")
    print(f"| uikf r = 1 | ZOH mass, position only | {z1:.2f} | - | {var1:.3g} N^2 | 1 |")
    print(f"| delayed_uikf r = 2 | same data | {z2:.2f} | {c2:.3f} | {var2:.3g} N^2 | "
          f"{var1 / var2:.0f}x lower |")
    print(f"| smooth_uikf r = 2 | same data | {zs:.2f} | {cs:.3f} | {vars_:.3g} N^2 | "
          f"{var2 / vars_:.3f}x vs delayed |")
    # 2. sensor offset + gain
    dts = 0.01
    sd = ct.c2d(ct.ss([[0.0, 1.0], [-40.0, -2.0]], [[0.0], [1.0]], np.eye(2), 0), dts)
    As, Bs = np.asarray(sd.A), np.asarray(sd.B)
    base = gb.named_ss(As, Bs, np.eye(2), np.zeros((2, 1)), dts, states=["p", "v"],
                       inputs=["u"], outputs=["p_meas", "v_meas"])
    aug = gb.with_sensor_error(base, "p_meas")
    Qs, Rs = np.diag([1e-8, 1e-6]), np.diag([1e-6, 1e-4])
    x0s, P0s = np.array([0.01, 0.0]), np.diag([1e-4, 1e-3])
    N = 120
    us = np.sin(np.arange(N) * dts * 7.0)[None, :]
    x, y, _ = simulate_runs(As, Bs, np.eye(2), np.zeros((2, 0)), Qs, Rs, x0s, P0s, us,
                            lambda k, xx: np.zeros((0, xx.shape[1])), nruns, rng)
    dd = 0.2 * x[:, 0, :] + 0.05
    y[:, 0, :] += dd
    ef, vf, es, vs = [], [], [], []
    for i in range(nruns):
        kw = dict(unknown="p_meas_err", Q=Qs, R=Rs, x0=x0s, P0=P0s)
        r = gb.feedthrough_uikf(aug, y[i], us, **kw)
        ef.append(r.d_est[0] - dd[i])
        vf.append(r.d_var[0])
        s = gb.smooth_uikf(aug, y[i], us, relative_degree=0, **kw)
        es.append(s.d_est[0] - dd[i])
        vs.append(s.d_var[0])
    zf, cf, varf = stats(np.array(ef), np.array(vf))
    zs, cs, vars_ = stats(np.array(es), np.array(vs))
    print(f"| feedthrough_uikf | sensor offset 0.05 m + gain 0.2 on p | {zf:.2f} | {cf:.3f} | "
          f"{varf:.3g} m^2 | 1 |")
    print(f"| smooth_uikf r = 0 | same data | {zs:.2f} | {cs:.3f} | {vars_:.3g} m^2 | "
          f"{varf / vars_:.1f}x lower |")
    # 3. smoother on a partly measured random system (conftest's make_random_system(rng(0)))
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
    from conftest import make_random_system

    rg = np.random.default_rng(0)
    rs = make_random_system(rg, n=4, p=2, md=1)
    Qr = rs.Q * 1e-2 + 1e-6 * np.eye(4)
    N = 70
    ur = rg.standard_normal((1, N))
    _, y, d = simulate_runs(rs.A, rs.B, rs.C, rs.G, Qr, rs.R, np.zeros(4), np.eye(4), ur,
                            lambda k, xx: 1.0 + np.sin(0.3 * k) + 0.5 * xx[:1], nruns, rg,
                            D=rs.D)
    kk = np.arange(3, N - 3)
    ef, es, vs = [], [], []
    for i in range(nruns):
        kw = dict(unknown=rs.unknown, Q=Qr, R=rs.R, x0=np.zeros(4), P0=np.eye(4))
        ef.append(gb.uikf(rs.sys, y[i], ur, **kw).d_est[0, kk] - d[i, 0, kk])
        s = gb.smooth_uikf(rs.sys, y[i], ur, **kw)
        es.append(s.d_est[0, kk] - d[i, 0, kk])
        vs.append(s.d_var[0, kk])
    _, _, vff = stats(np.array(ef), None)
    zs, cs, vss = stats(np.array(es), np.array(vs))
    print(f"| uikf | random 4 states, 2 outputs | - | - | {vff:.3g} | 1 |")
    print(f"| smooth_uikf | same data | {zs:.2f} | {cs:.3f} | {vss:.3g} | {vff / vss:.1f}x "
          f"lower |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
