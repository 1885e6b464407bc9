#!/usr/bin/env python
"""Cascaded tanks: where the 0.2 V between 0.70 V and the goal 0.5 V goes (a diagnosis).

Issue 12. Each row is a model structure fitted by output error on the
ESTIMATION record only (uEst/yEst); its test simulation RMS on uVal/yVal
(all 1024 samples, and from sample 20 as the README table) is printed under
several treatments of the test record's initial state:

* ``x0 est``    -- the initial state fitted on the estimation record, reused
  (the data README: "unknown initial state, the same for both records");
* ``x0 short``  -- fitted by output error on the test record's first 20
  samples only (what a test-only treatment can do: the upper tank is not
  measured, so 20 samples of y say little about x1);
* ``x0 test``   -- fitted by output error on the WHOLE test record with the
  parameters fixed: a floor, NOT a legitimate test figure (it uses the test
  output to fit two numbers), printed to bound what any x0 treatment can give.

Structures (RK4, 4 sub-steps of 1 s per 4 s sample, input held; the
simulator of ``bench/tanks_joint_oe.py``):

1. Torricelli, fitted where y < 9.9 V (the tutorial's nominal)
2. Torricelli, fitted on all samples
3. Torricelli + the sensor clip y = min(x2, 10 V), all samples
4. + the upper tank's saturation ``-kappa max(x1 - c, 0)`` in dx1/dt, y < 9.9 V
5. + saturation + clip, all samples
6. + overflow falling partly into the lower tank (``+gamma kappa max(x1 - c, 0)``
   in dx2/dt) + clip, all samples
7. row 1's k1..k4 kept FIXED + the hinge (x0, kappa, c fitted): the structure of
   greybox's pipeline, which adds one law to a fixed nominal
8. row 1's k1..k4 kept FIXED + hinge + gamma + clip
9. Torricelli + the level sensor's offset, y = x2 + offset (the data README: a
   raw, uncalibrated capacitive-sensor reading; a gain is absorbed by k1..k4,
   an offset is not, because of the square roots), fitted where y < 9.9 V
10.-12. rows 3, 5, 6 with the offset
13.-14. rows 7, 8 on row 9's nominal (k1..k4 and the offset FIXED)

Each row starts from the row named in ``rows``.

Usage::

    python bench/tanks_floors.py
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tanks_joint_oe import load, simulate  # noqa: E402

SKIP, W = 20, 20


def rms(e):
    return float(np.sqrt(np.mean(e ** 2)))


def fit(p, free, u, y, clip, mask, lo, hi, nfev=80):
    """Output-error fit of p[free] on (u, y)[mask]; returns the new p and the fit RMS."""
    p = p.copy()

    def resid(q):
        pp = p.copy()
        pp[free] = q
        return (simulate(pp, u, clip) - y)[mask]

    s = least_squares(resid, p[free], x_scale="jac", bounds=(lo[free], hi[free]),
                      max_nfev=nfev)
    p[free] = s.x
    return p, rms(s.fun)


NAMES = ("k1", "k2", "k3", "k4", "x1(0)", "x2(0)", "kappa", "c", "gamma", "offset")
K, X0, HINGE, GAMMA, OFF = [0, 1, 2, 3], [4, 5], [6, 7], [8], [9]


def main():
    data = load()
    if data is None:
        return
    uE, uV, yE, yV = data
    holds = yE < 9.9
    every = np.ones_like(holds)
    # kappa up to 50 (bench/tanks_joint_oe.py's bound 1 was reached by its last row); gamma is
    # a fraction of the overflow, at most 1; the sensor offset within +-10 V
    lo = np.array([1e-4] * 4 + [0, 0, 0, 0, 0, -10])
    hi = np.array([1] * 4 + [30, 30, 50.0, 40, 1.0, 10])
    p0 = np.array([0.05, 0.05, 0.05, 0.05, 5, 5, 0.0, 40.0, 0.0, 0.0])
    # (name, free, clip, fitted samples, start from row)
    rows = [("1 Torricelli, y < 9.9 V (tutorial nominal)", K + X0, False, holds, None),
            ("2 Torricelli, all samples", K + X0, False, every, 0),
            ("3 Torricelli + clip 10 V, all samples", K + X0, True, every, 1),
            ("4 + saturation hinge in x1, y < 9.9 V", K + X0 + HINGE, False, holds, 0),
            ("5 + saturation + clip, all samples", K + X0 + HINGE, True, every, 3),
            ("6 + overflow gamma into x2 + clip", K + X0 + HINGE + GAMMA, True, every, 4),
            ("7 row 1's k1..k4 FIXED + hinge, y < 9.9 V", X0 + HINGE, False, holds, 0),
            ("8 row 1's k1..k4 FIXED + hinge + gamma + clip", X0 + HINGE + GAMMA, True, every, 6),
            ("9 Torricelli + sensor offset, y < 9.9 V", K + X0 + OFF, False, holds, 0),
            ("10 + clip, all samples", K + X0 + OFF, True, every, 8),
            ("11 + saturation + clip", K + X0 + HINGE + OFF, True, every, 9),
            ("12 + overflow gamma into x2 + clip", K + X0 + HINGE + GAMMA + OFF, True, every, 10),
            ("13 row 9's k1..k4, offset FIXED + hinge", X0 + HINGE, False, holds, 8),
            ("14 row 9's FIXED + hinge + gamma + clip", X0 + HINGE + GAMMA, True, every, 12)]
    print(f"cascaded tanks, official split, fitted on uEst/yEst only; load average "
          f"{os.getloadavg()[0]:.2f}")
    print(f"{'structure (fitted on the estimation record)':46s} {'est RMS':>7s} | test RMS [V],"
          f" all samples / from sample 20")
    print(f"{'':46s} {'':7s} | {'x0 est':>13s} {'x0 short':>13s} {'x0 test*':>13s} {'time':>5s}")
    done = []
    for name, free, clip, mask, start in rows:
        p = p0.copy() if start is None else done[start].copy()
        if 6 in free and p[6] == 0.0:
            p[6], p[7] = 0.2, 10.0  # start of the hinge: a gentle slope at a mid level
        if 8 in free and p[8] == 0.0:
            p[8] = 0.3
        t0 = time.time()
        p, est = fit(p, free, uE, yE, clip, mask, lo, hi, nfev=100)
        done.append(p)
        out = []
        for how in ("est", "short", "test"):
            q = p.copy()
            if how != "est":
                n = W if how == "short" else len(yV)
                q, _ = fit(q, X0, uV[:n], yV[:n], clip, np.ones(n, bool), lo, hi, nfev=60)
            e = simulate(q, uV, clip) - yV
            out.append(f"{rms(e):.3f}/{rms(e[SKIP:]):.3f}")
        print(f"{name:46s} {est:7.3f} | {out[0]:>13s} {out[1]:>13s} {out[2]:>13s} "
              f"{time.time() - t0:4.0f}s")
        print("    " + ", ".join(f"{NAMES[i]} {p[i]:.4g}" for i in free))
    print("* x0 test: fitted on the whole test output (a floor, not a test figure)")
    print("published good models: 0.3-0.5 V test RMS")


if __name__ == "__main__":
    main()
