#!/usr/bin/env python
"""UKF throughput on the motor-pump: greybox vs filterpy's UnscentedKalmanFilter.

Issue 10 item 6. One process, one data set, every method side by side:

* greybox ``ukf``             - UKF ignoring the load (sigma points through F in one call)
* greybox ``ukf``, f looped   - the same UKF on the same f wrapped to refuse a batch
  of states (the filters then call it once per sigma point): the gain of
  the vectorized propagation alone
* greybox ``ui_ukf``          - unknown-input UKF (sigma points + the two G probes in one call)
* filterpy ``UnscentedKalmanFilter`` - predict/update loop, ``fx`` called once per
  sigma point; same sigma points (Merwe, alpha=1, beta=2, kappa=0), redrawn
  from (x^[k|k-1], P[k|k-1]) before each update (filterpy's default reuses the
  propagated points, which leaves Q out of the cross-covariance P_xz: another
  filter, different estimates ~1e-3 apart here); same F
  (the RK4-discretized nominal model with d = 0), same Q, R, x0, P0; its
  ``x`` after each update is checked against greybox ``ukf``'s ``x_filt``
* greybox ``ensemble_uikf`` at 100 and 1000 members

Model: ``discretize_nonlinear(motor_pump_nominal(), 1e-4)`` (3 states, RK4 with
the sub-steps chosen from the fastest local time constant); data: the Table V
setting (``reproduce.MotorPumpSetting``), first ``-N`` samples.

Time: best of ``--repeat`` runs. Memory: a separate run under ``tracemalloc``,
peak of the call. Accuracy: max |x_filt - x_filt(greybox ukf)| relative to
max |x|, and for the unknown-input filters the RMS error of d^ against the
true d = -h_r Mdot^2.

Usage::

    python bench/ukf.py              # N = 3000
    python bench/ukf.py --quick      # N = 500
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import time
import timeit
import tracemalloc

import control as ct
import numpy as np

import greybox as gb
from greybox.nonlinear import discretize_nonlinear, simulate_nonlinear
from greybox.plants import MOTOR_PUMP_X_OP
from greybox.reproduce import MotorPumpSetting

MB = 1024.0**2


class Problem:
    def __init__(self, N: int):
        s = MotorPumpSetting(nsteps=N)
        rng = np.random.default_rng(s.seed)
        self.hr = s.load()
        self.V = s.voltage + gb.lowpass_noise(N, dt=s.dt, bandwidth=s.bandwidth,
                                              amplitude=s.voltage_std, rng=rng)
        true = discretize_nonlinear(gb.motor_pump_true(), s.dt, substeps=s.truth_substeps)
        self.sys = discretize_nonlinear(gb.motor_pump_nominal(), s.dt, x_op=MOTOR_PUMP_X_OP,
                                        u_op=[s.voltage, -s.load_mean * MOTOR_PUMP_X_OP[2]**2])
        f_batch = gb.motor_pump_nominal().updfcn

        def f_one(t, x, u, prm):  # the same f, refusing a batch: the filters loop per point
            if np.ndim(x) != 1:
                raise TypeError("one state at a time")
            return f_batch(t, x, u, prm)

        nl = gb.motor_pump_nominal()
        one = ct.nlsys(f_one, nl.outfcn, states=list(nl.state_labels),
                       inputs=list(nl.input_labels), outputs=list(nl.output_labels),
                       name="motor_pump_one_point")
        self.sys_loop = discretize_nonlinear(one, s.dt, substeps=int(self.sys.name.split("x")[-1]))
        self.x0 = np.array([5.9, 3.3, 0.9])
        sim = simulate_nonlinear(true, np.vstack([self.V, self.hr]), x0=self.x0,
                                 Q=gb.MOTOR_PUMP_Q, R=gb.MOTOR_PUMP_R, rng=rng)
        self.y, self.x = sim.y, sim.x
        self.d = -self.hr * sim.x[2] ** 2
        self.Q, self.R = gb.MOTOR_PUMP_Q, gb.MOTOR_PUMP_R
        self.P0 = 1e-4 * np.eye(3)
        self.N = N


def gb_ukf(pb):
    r = gb.ukf(pb.sys, pb.y, pb.V, unknown="d", Q=pb.Q, R=pb.R, x0=pb.x0, P0=pb.P0)
    return r.x_filt, None


def gb_ukf_loop(pb):
    r = gb.ukf(pb.sys_loop, pb.y, pb.V, unknown="d", Q=pb.Q, R=pb.R, x0=pb.x0, P0=pb.P0)
    return r.x_filt, None


def gb_ui_ukf(pb):
    r = gb.ui_ukf(pb.sys, pb.y, pb.V, unknown="d", Q=pb.Q, R=pb.R, x0=pb.x0, P0=pb.P0)
    return r.x_filt, r.d_est


def gb_ens(nm):
    def run(pb):
        r = gb.ensemble_uikf(pb.sys, pb.y, pb.V, unknown="d", Q=pb.Q, R=pb.R, x0=pb.x0,
                             P0=pb.P0, nmembers=nm, rng=1)
        return r.x_filt, r.d_est
    return run


def filterpy_ukf(pb):
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    upd, par = pb.sys.updfcn, pb.sys.params
    dt = float(pb.sys.dt)

    def fx(x, dt_, V=0.0):
        return upd(0.0, x, np.array([V, 0.0]), par)

    def hx(x):
        return x

    pts = MerweScaledSigmaPoints(3, alpha=1.0, beta=2.0, kappa=0.0)
    f = UnscentedKalmanFilter(dim_x=3, dim_z=3, dt=dt, hx=hx, fx=fx, points=pts)
    f.x, f.P, f.Q, f.R = pb.x0.copy(), pb.P0.copy(), pb.Q.copy(), pb.R.copy()
    out = np.empty((3, pb.N))
    f.sigmas_f = pts.sigma_points(f.x, f.P)  # update() of the prior uses these points
    f.update(pb.y[:, 0])
    out[:, 0] = f.x
    for k in range(1, pb.N):
        f.predict(V=pb.V[0, k - 1])
        f.sigmas_f = pts.sigma_points(f.x, f.P)  # redraw: Q enters P_xz (see docstring)
        f.update(pb.y[:, k])
        out[:, k] = f.x
    return out, None


METHODS = [("greybox ukf", gb_ukf), ("greybox ukf, f looped per point", gb_ukf_loop),
           ("greybox ui_ukf", gb_ui_ukf),
           ("filterpy UnscentedKalmanFilter", filterpy_ukf),
           ("greybox ensemble_uikf 100", gb_ens(100)),
           ("greybox ensemble_uikf 1000", gb_ens(1000))]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-N", type=int, default=3000, help="samples")
    ap.add_argument("--quick", action="store_true", help="N = 500, 2 repeats")
    ap.add_argument("--repeat", type=int, default=3, help="timing repeats (best kept)")
    a = ap.parse_args()
    N, rep = (500, 2) if a.quick else (a.N, a.repeat)
    print(f"# python {platform.python_version()}, numpy {np.__version__}, greybox "
          f"{gb.__version__}, {os.cpu_count()} cpus")
    print(f"# load average at start {' '.join(f'{v:.2f}' for v in os.getloadavg())} "
          f"(shared machine: timings are noisy when it is not ~0)")
    try:
        import filterpy

        print(f"# filterpy {filterpy.__version__}")
    except ImportError:
        print("# filterpy not installed (pip install filterpy): its row is skipped")
    pb = Problem(N)
    print(f"# motor-pump, N = {N} samples, model {pb.sys.name} (3 states)")
    best, res, peak = {}, {}, {}
    methods = []
    for name, fn in METHODS:
        try:
            res[name] = fn(pb)
            methods.append((name, fn))
        except ImportError:
            continue
    for _ in range(rep):
        for name, fn in methods:
            gc.collect()
            t0 = time.perf_counter()
            fn(pb)
            dtm = time.perf_counter() - t0
            best[name] = min(best.get(name, np.inf), dtm)
    for name, fn in methods:
        gc.collect()
        tracemalloc.start()
        fn(pb)
        peak[name] = tracemalloc.get_traced_memory()[1] / MB
        tracemalloc.stop()
    ref_x = res["greybox ukf"][0]
    scale = np.max(np.abs(ref_x))
    fp = "filterpy UnscentedKalmanFilter"
    print(f"{'method':<32}{'time [s]':>10}{'samples/s':>12}{'vs filterpy':>13}"
          f"{'peak [MB]':>11}{'max|dx|/max|x| vs gb ukf':>27}{'d^ RMS error':>14}")
    for name, _ in methods:
        x, d = res[name]
        dx = np.max(np.abs(x - ref_x)) / scale if x.shape == ref_x.shape else np.nan
        derr = np.sqrt(np.mean((d[0, 100:-1] - pb.d[100:-1]) ** 2)) if d is not None else None
        ratio = best[fp] / best[name] if fp in best else np.nan
        print(f"{name:<32}{best[name]:>10.3f}{N / best[name]:>12.0f}{ratio:>12.1f}x"
              f"{peak[name]:>11.2f}{dx:>27.2e}"
              f"{(f'{derr:.3f}' if derr is not None else '-'):>14}")
    f, par = gb.motor_pump_nominal().updfcn, {}
    x1, u1 = np.array([6.0, 4.0, 1.2]), np.array([10.0, -216.0])
    x7, u7 = np.repeat(x1[:, None], 7, axis=1), np.repeat(u1[:, None], 7, axis=1)
    reps = 20000
    t1 = min(timeit.repeat(lambda: f(0, x1, u1, par), number=reps, repeat=3)) / reps
    t7 = min(timeit.repeat(lambda: f(0, x7, u7, par), number=reps, repeat=3)) / reps
    print(f"# one call of the continuous f: {1e6 * t1:.2f} us on one state, {1e6 * t7:.2f} us "
          f"on 7 sigma points at once ({t7 / t1:.1f}x); 24 calls per sample (6 RK4 sub-steps)")
    if fp in best:
        f_only = 24 * N * t7
        print(f"# f alone (24 batched calls per sample) takes {f_only:.3f} s for N = {N}: even a "
              f"filter with no other cost would be at most {best[fp] / f_only:.1f}x filterpy "
              f"(numpy's per-operation overhead makes a 7-column f cost about as much as 7 "
              f"one-point calls)")
    print(f"# load average at end {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print("# 'vs filterpy' = filterpy time / method time (higher is faster); the UKF rows "
          "compare like with like, ui_ukf and the ensemble do more work per sample")


if __name__ == "__main__":
    main()
