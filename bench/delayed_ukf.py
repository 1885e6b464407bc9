#!/usr/bin/env python
"""Delayed unscented unknown-input filter: cost and accuracy beside its peers.

Issue 12 (cascaded tanks). One process, one data set, every method side by
side on the discrete two-tank plant of ``tests/test_ukf_delayed.py`` (the
upper tank x1 gets the unknown inflow d, only the lower tank x2 is measured:
rank(C G) = 0, relative degree 2; f written for a batch of states):

* greybox ``delayed_ui_ukf``  - the unscented unknown-input filter on the shifted
  state z = x - G~ d[k-1] (d[k-2] from y[k], no prior on d)
* greybox ``ui_ukf``, both tanks measured - the r = 1 filter on the same plant
  with x1 measured too (the per-sample cost of the undelayed filter; its d^ is
  the better one since it sees x1)
* filterpy ``UnscentedKalmanFilter`` on the augmented state [x1, x2, d] with
  a random-walk d (the common practice for an unknown input: it needs a
  prior on d's variation, here its true per-sample variance, an advantage the
  unknown-input filters do not get); its d after y[k] is taken as the estimate
  of d[k-2], the latest d that y[k] sees (compared with d[k-1], the d that
  moved x to x[k], its RMS error is 6x larger)

Time: best of ``--repeat`` runs, single BLAS thread. Memory: a separate run
under ``tracemalloc`` (peak of the call). Accuracy: RMS of d^ - d against the
true d (white, std 0.05) and the mean NEES of d^ with the filter's own
variance (1 = consistent).

Usage::

    python bench/delayed_ukf.py           # N = 3000
    python bench/delayed_ukf.py --quick   # N = 500
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")  # every row single-threaded (before numpy loads)

import argparse
import sys
import time
import tracemalloc
from pathlib import Path

import control as ct
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import greybox as gb  # noqa: E402
from test_ukf_delayed import A1, A2, B4, DT, D_STD, Q_T, R_T, tanks_model, tanks_run  # noqa: E402


def both_measured():
    """The same tanks with y = [x1, x2] (rank(C G) = 1)."""
    m = tanks_model()
    return ct.nlsys(m.updfcn, lambda t, x, u, p: x, states=["x1", "x2"], inputs=["u", "d"],
                    outputs=["y1", "y2"], dt=DT, name="tanks_both")


def filterpy_augmented(y, u):
    """filterpy UKF on [x1, x2, d] with a random-walk d of variance D_STD^2 per sample."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    def fx(s, dt, uk):
        s1 = np.sqrt(abs(s[0]))
        return np.array([s[0] + DT * (-A1 * s1 + B4 * uk + s[2]),
                         s[1] + DT * (A1 * s1 - A2 * np.sqrt(abs(s[1]))), s[2]])

    pts = MerweScaledSigmaPoints(3, alpha=1.0, beta=2.0, kappa=0.0)
    f = UnscentedKalmanFilter(3, 1, DT, hx=lambda s: s[1:2], fx=fx, points=pts)
    f.x = np.array([1.0, 1.6, 0.0])
    f.P = np.diag([1e-2, 1e-2, D_STD**2])
    f.Q = np.diag([Q_T[0, 0], Q_T[1, 1], D_STD**2])
    f.R = R_T
    N = y.shape[1]
    d, var = np.full(N, np.nan), np.full(N, np.nan)
    for k in range(1, N):
        f.predict(uk=u[0, k - 1])
        f.update(y[:, k])
        if k >= 2:  # y[k] sees d up to d[k-2] (relative degree 2)
            d[k - 2], var[k - 2] = f.x[2], f.P[2, 2]
    return d, var


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="N = 500 instead of 3000")
    ap.add_argument("--repeat", type=int, default=3, help="timing runs per row (best of)")
    a = ap.parse_args()
    N = 500 if a.quick else 3000
    rng = np.random.default_rng(12)
    u, d, x, y = tanks_run(rng, N)
    y2 = x + np.sqrt(R_T[0, 0]) * rng.standard_normal((2, N))
    model, model2 = tanks_model(), both_measured()
    kw = dict(unknown="d", Q=Q_T, x0=[1.0, 1.6], P0=np.diag([1e-2, 1e-2]))
    rows = [
        ("greybox delayed_ui_ukf (y = x2)",
         lambda: gb.delayed_ui_ukf(model, y, u, R=R_T, **kw)),
        ("greybox ui_ukf (y = x1, x2)",
         lambda: gb.ui_ukf(model2, y2, u, R=R_T[0, 0] * np.eye(2), **kw)),
        ("filterpy UKF, [x; d] random walk", lambda: filterpy_augmented(y, u)),
    ]
    load = os.getloadavg()[0]
    print(f"two tanks, N = {N}, d white (std {D_STD}), load average {load:.2f}, "
          f"numpy {np.__version__}, best of {a.repeat}")
    print(f"{'method':36s} {'time [ms]':>10s} {'us/sample':>10s} {'ratio':>7s} "
          f"{'peak MB':>8s} {'RMS(d^-d)':>10s} {'NEES':>6s}")
    base = None
    for name, fn in rows:
        best = np.inf
        for _ in range(a.repeat):
            t0 = time.perf_counter()
            out = fn()
            best = min(best, time.perf_counter() - t0)
        tracemalloc.start()
        fn()
        peak = tracemalloc.get_traced_memory()[1] / 1e6
        tracemalloc.stop()
        if isinstance(out, tuple):
            dh, dv = out
        else:
            dh, dv = out.d_est[0], out.d_var[0]
        ok = np.isfinite(dh) & np.isfinite(dv)
        ok[:50] = False  # the filters' transient
        e = dh[ok] - d[ok]
        base = best if base is None else base
        print(f"{name:36s} {1e3 * best:10.1f} {1e6 * best / N:10.1f} {best / base:7.2f} "
              f"{peak:8.2f} {np.sqrt(np.mean(e**2)):10.4f} {np.mean(e**2 / dv[ok]):6.2f}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
