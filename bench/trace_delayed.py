#!/usr/bin/env python
"""Accuracy of a static law traced through a delayed d^ (issue 11, positions only).

Plant: tests/plantlib.msd (k = 4, c = 0.6, m = 1) whose model lacks a
hardening spring -K3 pos^3 (K3 = 30) in eq(vel); only pos measured; dt = 0.01,
RK4 truth, lowpass input of amplitude 4, discrete process-noise std q on vel,
measurement-noise std r. For each seed, ``trace_channel(eq(vel), max_order=0)``
and the pos^3 coefficient with its 95 % half-width. The table gives, per
variant, the Monte Carlo mean and sd of the estimate, the mean half-width /
1.96 (should match the sd), the coverage of the 95 % interval, the time per
trace and the load average (the machine is shared).

Usage::

    python bench/trace_delayed.py [nseeds] [q] [r]
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from plantlib import draw, msd  # noqa: E402

from greybox.trace import resolve_channel_spec, trace_channel  # noqa: E402

K3 = 30.0


def main(nseeds=20, q=3e-3, r=3e-3, n=3000):
    nom = msd(measured=("pos",))
    A, B = np.asarray(nom.A), np.asarray(nom.B)

    def f(x, u):
        dx = A @ x + B @ u
        dx[1] -= K3 * x[0] ** 3
        return dx

    ch = [c for c in resolve_channel_spec(nom, None) if c.name == "eq(vel)"][0]
    print(f"load average {os.getloadavg()[0]:.1f}; {nseeds} seeds, N = {n}, q = {q:g}, r = {r:g}")
    print("| variant | mean K3 est. | MC sd | half-width/1.96 | coverage | other terms "
          "(runs) | s/trace |")
    print("|---|---|---|---|---|---|---|")
    for label, smooth in (("delayed + smoothed (default)", "auto"), ("delayed filter", False)):
        est, hw, extra, t = [], [], 0, time.perf_counter()
        for seed in range(nseeds):
            c = draw(nom, f, n_true=2, dt=0.01, rng=np.random.default_rng(seed),
                     q_std=np.array([0, q]), r_std=r, n_est=n, n_val=10, amplitude=4.0)
            law = trace_channel(nom, ch, c.y, c.u, Q=c.Q, R=c.R, dt=c.dt, max_order=0,
                                smooth=smooth).static
            j = [s[0] for s in law.spec].index("pos^3")
            est.append(law.coef[0, j])
            hw.append(law.ci[0, j])
            extra += int(law.npar > 1)
        dt_ = (time.perf_counter() - t) / nseeds
        est, hw = -np.array(est), np.array(hw)
        print(f"| {label} | {est.mean():.4g} | {est.std(ddof=1):.3g} | {np.mean(hw) / 1.96:.3g} "
              f"| {np.mean(np.abs(est - K3) <= hw):.2f} | {extra} | {dt_:.2f} |")


if __name__ == "__main__":
    a = sys.argv[1:]
    main(int(a[0]) if a else 20, float(a[1]) if len(a) > 1 else 3e-3,
         float(a[2]) if len(a) > 2 else 3e-3)
