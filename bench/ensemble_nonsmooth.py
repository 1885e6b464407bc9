#!/usr/bin/env python
"""Ensemble unknown-input filter vs the UI-UKF on non-smooth and smooth plants (issue 10 item 3).

Paired Monte Carlo (same data for both filters in each draw): the RMS error
of d^ against the true d, per draw; the table gives the mean paired
difference (ensemble - UI-UKF) with its standard error, and the 95 % band
coverage of each filter. Plants (RK4-discretized ``control.nlsys``):

* relay: a drive velocity a (noisy sensor, R = 0.25) pushes a load b through
  ``4 sign(a)``; d enters b's equation (the test in tests/test_ukf.py)
* relay, smooth twin: ``4 tanh(a / 0.3)``
* Coulomb: one mass, ``v' = u - 2 sign(v) - 0.5 v + d``, v measured (R = 0.04),
  dt = 0.2 s: friction and d in the same equation

Usage::

    python bench/ensemble_nonsmooth.py [--draws 30] [--members 500]
"""

from __future__ import annotations

import argparse
import os

import control as ct
import numpy as np

import greybox as gb


def relay(width):
    sg = np.sign if width == 0 else (lambda v: np.tanh(v / width))

    def f(t, x, u, p):
        return np.stack([u[0] - x[0], -x[1] + 4.0 * sg(x[0]) + u[1]])

    sysc = ct.nlsys(f, lambda t, x, u, p: x, states=["a", "b"], inputs=["u", "d"],
                    outputs=["a", "b"], dt=0, name="relay")
    dt = 0.05
    return (gb.discretize_nonlinear(sysc, dt, substeps=2), np.diag([0.01 * dt, 1e-8]),
            np.diag([0.25, 1e-4]), np.array([0.0, 0.0]), np.diag([1e-2, 1e-4]), 1.0, 0.5)


def coulomb():
    def f(t, x, u, p):
        return np.stack([u[0] - 2.0 * np.sign(x[0]) - 0.5 * x[0] + u[1]])

    sysc = ct.nlsys(f, lambda t, x, u, p: x, states=["v"], inputs=["u", "d"], outputs=["v"],
                    dt=0, name="coulomb")
    return (gb.discretize_nonlinear(sysc, 0.2, substeps=4), np.diag([0.004]), np.diag([0.04]),
            np.array([0.0]), np.diag([1e-4]), 2.5, 0.2)


def run(plant, draws, members, N=200):
    sysd, Q, R, x0, P0, uamp, damp = plant
    dt = float(sysd.dt)
    t = np.arange(N) * dt
    u = uamp * np.sin(2 * np.pi * t / (N * dt / 3))
    d = damp * np.sin(2 * np.pi * t / (N * dt) + 1)
    diff, ref, cov_a, cov_e = [], [], [], []
    for seed in range(draws):
        g = np.random.default_rng(seed)
        sim = gb.simulate_nonlinear(sysd, np.vstack([u, d]), Q=Q, R=R, rng=g)
        kw = dict(unknown="d", Q=Q, R=R, x0=x0, P0=P0)
        a = gb.ui_ukf(sysd, sim.y, u, **kw)
        e = gb.ensemble_uikf(sysd, sim.y, u, nmembers=members, rng=g, **kw)
        ea, ee = a.d_est[0, :-1] - d[:-1], e.d_est[0, :-1] - d[:-1]
        diff.append(np.sqrt(np.mean(ee**2)) - np.sqrt(np.mean(ea**2)))
        ref.append(np.sqrt(np.mean(ea**2)))
        cov_a.append(np.mean(np.abs(ea) <= a.d_halfwidth[0, :-1]))
        cov_e.append(np.mean(np.abs(ee) <= e.d_halfwidth[0, :-1]))
    diff = np.array(diff)
    return (np.mean(ref), diff.mean(), diff.std(ddof=1) / np.sqrt(draws), np.mean(cov_a),
            np.mean(cov_e))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--members", type=int, default=500)
    a = ap.parse_args()
    print(f"# load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}; {a.draws} paired "
          f"draws, {a.members} members, 200 samples each")
    print(f"{'plant':<22}{'UI-UKF RMS d err':>18}{'ens - UKF':>12}{'+- se':>9}{'z':>7}"
          f"{'cover UKF':>11}{'cover ens':>11}")
    for name, plant in (("relay sign(a)", relay(0.0)), ("relay tanh(a/0.3)", relay(0.3)),
                        ("Coulomb, same eq.", coulomb())):
        ref, m, se, ca, ce = run(plant, a.draws, a.members)
        print(f"{name:<22}{ref:>18.4f}{m:>12.4f}{se:>9.4f}{m / se:>7.1f}{ca:>11.3f}{ce:>11.3f}")


if __name__ == "__main__":
    main()
