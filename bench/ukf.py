#!/usr/bin/env python
"""UKF throughput: greybox vs filterpy's UnscentedKalmanFilter, on two 3-state models.

Issue 10 item 6. One process, one data set per model, every method side by side:

* greybox ``ukf``             - UKF ignoring the load (sigma points through F in one call)
* greybox ``ukf``, f looped   - the same UKF on the same f wrapped to refuse a batch
  of states (the filters then call it once per sigma point): the gain of
  the vectorized propagation alone
* greybox ``ui_ukf``          - unknown-input UKF (sigma points + the two G probes in one call)
* filterpy ``UnscentedKalmanFilter`` - predict/update loop, ``fx`` called once per
  sigma point; same sigma points (Merwe, alpha=1, beta=2, kappa=0), redrawn
  from (x^[k|k-1], P[k|k-1]) before each update (filterpy's default reuses the
  propagated points, which leaves Q out of the cross-covariance P_xz: another
  filter, different estimates ~1e-3 apart here); same F (the model with
  d = 0), same Q, R, x0, P0; its ``x`` after each update is checked against
  greybox ``ukf``'s ``x_filt``
* greybox ``ensemble_uikf`` at 100 and 1000 members

Models (both 3 states, all measured, d entering one state equation):

1. **motor-pump**: ``discretize_nonlinear(motor_pump_nominal(), 1e-4)``, RK4 with
   6 sub-steps (24 evaluations of f per sample, PAPER_NOTES §8.9); data: the
   Table V setting (``reproduce.MotorPumpSetting``), first ``-N`` samples.
   F dominates every filter here: the bench prints the time of F alone and
   the bound it puts on the ratio.
2. **cheap map**: a motor driving a pendulum, already discrete (hand-written
   Euler step at dt = 10 ms, defined directly as ``ct.nlsys`` with dt, no
   RK4), F = one matrix product plus one sine: what is compared is the
   filters' own per-sample cost.

Both models' f are written for batches (a matrix product; the motor-pump's f
switches to that form for 2-D input and keeps the scalar equations for one
state), and filterpy's row calls the same F: the same user code for every row.

Time: best of ``--repeat`` runs, single BLAS thread (set below, before numpy
loads). Memory: a separate run under ``tracemalloc``, peak of the call.
Accuracy: max |x_filt - x_filt(greybox ukf)| relative to max |x|, and for the
unknown-input filters the RMS error of d^ against the true d.

Usage::

    python bench/ukf.py              # N = 3000 per model
    python bench/ukf.py --quick      # N = 500
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")  # both sides single-threaded (before numpy loads)

import argparse
import gc
import platform
import time
import tracemalloc

import control as ct
import numpy as np

import greybox as gb
from greybox.nonlinear import discretize_nonlinear, simulate_nonlinear
from greybox.plants import MOTOR_PUMP_X_OP
from greybox.reproduce import MotorPumpSetting

MB = 1024.0**2


def _looped(nl, name):
    """The same model with f refusing a batch: the filters call it once per point."""
    f_batch = nl.updfcn

    def f_one(t, x, u, prm):
        if np.ndim(x) != 1:
            raise TypeError("one state at a time")
        return f_batch(t, x, u, prm)

    return ct.nlsys(f_one, nl.outfcn, states=list(nl.state_labels),
                    inputs=list(nl.input_labels), outputs=list(nl.output_labels),
                    dt=nl.dt, params=dict(nl.params or {}), name=name)


class MotorPump:
    """The Table V setting, first N samples; F = RK4 (6 sub-steps) of the nominal model."""

    title = "motor-pump (RK4, 6 sub-steps = 24 evaluations of f per sample)"

    def __init__(self, N: int):
        s = MotorPumpSetting(nsteps=N)
        rng = np.random.default_rng(s.seed)
        hr = s.load()
        V = s.voltage + gb.lowpass_noise(N, dt=s.dt, bandwidth=s.bandwidth,
                                         amplitude=s.voltage_std, rng=rng)
        self.V = np.asarray(V, float).reshape(1, N)
        true = discretize_nonlinear(gb.motor_pump_true(), s.dt, substeps=s.truth_substeps)
        self.sys = discretize_nonlinear(gb.motor_pump_nominal(), s.dt, x_op=MOTOR_PUMP_X_OP,
                                        u_op=[s.voltage, -s.load_mean * MOTOR_PUMP_X_OP[2]**2])
        one = _looped(gb.motor_pump_nominal(), "motor_pump_one_point")
        self.sys_loop = discretize_nonlinear(one, s.dt, substeps=int(self.sys.name.split("x")[-1]))
        self.f_cont = gb.motor_pump_nominal().updfcn  # the continuous f inside F
        self.f_calls = 4 * int(self.sys.name.split("x")[-1])
        self.x0 = np.array([5.9, 3.3, 0.9])
        sim = simulate_nonlinear(true, np.vstack([self.V[0], hr]), x0=self.x0,
                                 Q=gb.MOTOR_PUMP_Q, R=gb.MOTOR_PUMP_R, rng=rng)
        self.y = sim.y
        self.d = -hr * sim.x[2] ** 2
        self.Q, self.R = gb.MOTOR_PUMP_Q, gb.MOTOR_PUMP_R
        self.P0 = 1e-4 * np.eye(3)
        self.N = N


CHEAP_DT = 1e-2
"""Sampling period [s] of the cheap-map model."""
_A = np.eye(3) + CHEAP_DT * np.array([[0.0, 1.0, 0.0], [0.0, -0.5, 2.0], [0.0, -1.0, -5.0]])
_B = CHEAP_DT * np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
_GRAV = CHEAP_DT * 9.81


def cheap_update(t, x, u, params):
    """One Euler step of a motor (current i, input V) driving a pendulum (theta, omega).

    ``x = [theta, omega, i]``, ``u = [V, d]`` (d a torque on the pendulum);
    x of shape (3,) or (3, npoints), u (2,) or (2, npoints).
    """
    out = _A @ x + _B @ u
    out[1] -= _GRAV * np.sin(x[0])
    return out


class CheapMap:
    """A 3-state discrete nonlinear model whose F costs one matrix product and one sine."""

    title = f"cheap map (discrete pendulum + motor, dt = {CHEAP_DT:g} s, no RK4)"

    def __init__(self, N: int):
        names = dict(states=["theta", "omega", "i"], inputs=["V", "d"],
                     outputs=["theta", "omega", "i"])
        nl = ct.nlsys(cheap_update, lambda t, x, u, p: x, dt=CHEAP_DT, name="pendulum_motor",
                      **names)
        self.sys, self.sys_loop = nl, _looped(nl, "pendulum_motor_one_point")
        rng = np.random.default_rng(10)
        t = np.arange(N) * CHEAP_DT
        V = 3.0 * np.sin(2 * np.pi * 0.15 * t) + np.asarray(gb.lowpass_noise(
            N, dt=CHEAP_DT, bandwidth=2.0, amplitude=0.5, rng=rng), float).reshape(N)
        self.d = 0.5 * np.sign(np.sin(2 * np.pi * 0.05 * t))
        self.Q = np.diag([1e-10, 1e-8, 1e-8])
        self.R = np.diag([1e-6, 1e-6, 1e-6])
        self.x0 = np.array([0.1, 0.0, 0.0])
        sim = simulate_nonlinear(nl, np.vstack([V, self.d]), x0=self.x0, Q=self.Q, R=self.R,
                                 rng=rng)
        self.y, self.V = sim.y, V[None]
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
FP = "filterpy UnscentedKalmanFilter"


def run_table(pb, rep):
    """Time, memory and accuracy of every method on one problem; prints the table."""
    N = pb.N
    print(f"\n## {pb.title}: N = {N} samples, model {pb.sys.name} (3 states)")
    best, res, peak = {}, {}, {}
    methods = []
    for name, fn in METHODS:
        try:
            res[name] = fn(pb)
            methods.append((name, fn))
        except ImportError:
            continue
    # F alone, timed in the same round-robin as the filters (a separate timing would see
    # another load): the discrete map on one state (filterpy calls it 7 times per sample)
    # and on the 7 / 9 points ukf / ui_ukf propagate at once; for an RK4 model also the
    # continuous f alone (24 calls per F)
    F, par = pb.sys.updfcn, pb.sys.params
    x1 = pb.x0.copy()
    u1 = np.array([pb.V[0, 0], 0.0])
    X9, U9 = np.repeat(x1[:, None], 9, axis=1), np.repeat(u1[:, None], 9, axis=1)
    X7, U7 = X9[:, :7].copy(), U9[:, :7].copy()
    nF = min(N, 500)  # calls per timing; scaled to per call
    parts = {"F 1": lambda: [F(0, x1, u1, par) for _ in range(nF)],
             "F 7": lambda: [F(0, X7, U7, par) for _ in range(nF)],
             "F 9": lambda: [F(0, X9, U9, par) for _ in range(nF)]}
    f_cont = getattr(pb, "f_cont", None)
    if f_cont is not None:
        parts["f 1"] = lambda: [f_cont(0, x1, u1, par) for _ in range(nF)]
        parts["f 9"] = lambda: [f_cont(0, X9, U9, par) for _ in range(nF)]
    tp = {}
    for _ in range(rep):
        for name, fn in methods:
            gc.collect()
            t0 = time.perf_counter()
            fn(pb)
            dtm = time.perf_counter() - t0
            best[name] = min(best.get(name, np.inf), dtm)
        for key, fn in parts.items():
            t0 = time.perf_counter()
            fn()
            tp[key] = min(tp.get(key, np.inf), (time.perf_counter() - t0) / nF)
    for name, fn in methods:
        gc.collect()
        tracemalloc.start()
        fn(pb)
        peak[name] = tracemalloc.get_traced_memory()[1] / MB
        tracemalloc.stop()
    ref_x = res["greybox ukf"][0]
    scale = np.max(np.abs(ref_x))
    print(f"{'method':<32}{'time [s]':>10}{'samples/s':>12}{'vs filterpy':>13}"
          f"{'peak [MB]':>11}{'max|dx|/max|x| vs gb ukf':>27}{'d^ RMS error':>14}")
    for name, _ in methods:
        x, d = res[name]
        dx = np.max(np.abs(x - ref_x)) / scale if x.shape == ref_x.shape else np.nan
        derr = np.sqrt(np.mean((d[0, 100:-1] - pb.d[100:-1]) ** 2)) if d is not None else None
        ratio = best[FP] / best[name] if FP in best else np.nan
        print(f"{name:<32}{best[name]:>10.3f}{N / best[name]:>12.0f}{ratio:>12.1f}x"
              f"{peak[name]:>11.2f}{dx:>27.2e}"
              f"{(f'{derr:.3f}' if derr is not None else '-'):>14}")
    print(f"# one call of the discrete F: {1e6 * tp['F 1']:.2f} us on one state, "
          f"{1e6 * tp['F 7']:.2f} us on 7 points, {1e6 * tp['F 9']:.2f} us on 9 points at "
          f"once; filterpy calls it 7 times per sample")
    if f_cont is not None:
        ns = pb.f_calls
        print(f"# of which f ({ns} calls): {1e6 * ns * tp['f 1']:.2f} us on one state, "
              f"{1e6 * ns * tp['f 9']:.2f} us on 9 points; the rest is the RK4 stage "
              f"arithmetic")
    if FP in best:
        tf = 7 * tp["F 1"]
        print(f"# F alone (one batched call of 7 points per sample) takes "
              f"{N * tp['F 7']:.3f} s for N = {N}: a filter with no other cost would be at "
              f"most {best[FP] / (N * tp['F 7']):.1f}x filterpy; filterpy spends "
              f"{N * tf:.3f} s of its {best[FP]:.3f} s in F")
        for name, tF, npt in (("greybox ukf", tp["F 7"], 7), ("greybox ui_ukf", tp["F 9"], 9)):
            if name in best:
                print(f"# {name}: {1e6 * best[name] / N:.1f} us per sample = F on {npt} "
                      f"points {1e6 * tF:.1f} us + the filter's own work "
                      f"{1e6 * (best[name] / N - tF):.1f} us; filterpy: "
                      f"{1e6 * best[FP] / N:.1f} us = F {1e6 * tf:.1f} us + "
                      f"{1e6 * (best[FP] / N - tf):.1f} us")
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-N", type=int, default=3000, help="samples")
    ap.add_argument("--quick", action="store_true", help="N = 500, 2 repeats")
    ap.add_argument("--repeat", type=int, default=3, help="timing repeats (best kept)")
    ap.add_argument("--model", choices=["both", "motor-pump", "cheap"], default="both",
                    help="which model's table to print")
    a = ap.parse_args()
    N, rep = (500, 2) if a.quick else (a.N, a.repeat)
    print(f"# python {platform.python_version()}, numpy {np.__version__}, greybox "
          f"{gb.__version__}, {os.cpu_count()} cpus, OMP/OPENBLAS threads "
          f"{os.environ.get('OMP_NUM_THREADS')}/{os.environ.get('OPENBLAS_NUM_THREADS')}")
    print(f"# load average at start {' '.join(f'{v:.2f}' for v in os.getloadavg())} "
          f"(shared machine: timings are noisy when it is not ~0)")
    try:
        import filterpy

        print(f"# filterpy {filterpy.__version__}")
    except ImportError:
        print("# filterpy not installed (pip install filterpy): its row is skipped")
    models = {"motor-pump": [MotorPump], "cheap": [CheapMap],
              "both": [MotorPump, CheapMap]}[a.model]
    for cls in models:
        run_table(cls(N), rep)
    print(f"\n# load average at end {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print("# 'vs filterpy' = filterpy time / method time (higher is faster); the UKF rows "
          "compare like with like, ui_ukf and the ensemble do more work per sample")


if __name__ == "__main__":
    main()
