#!/usr/bin/env python
"""Filter throughput on the tape drive: greybox vs statsmodels, filterpy and a numpy loop.

Issue 2 item 10. One process, one data set, every method side by side:

* greybox ``uikf(gain="time-varying")``  - per-sample unknown-input recursion
* greybox ``uikf(gain="auto")``          - converged constant-gain fast path
* greybox ``kalman_filter`` (auto)       - the Kalman baseline (tension input dropped)
* statsmodels ``KalmanFilter.filter()``  - same model with G dropped, B u as a
  time-varying state intercept; checked against greybox's Kalman ``x_filt``
* filterpy ``KalmanFilter``              - predict/update loop
* a plain numpy per-sample loop of the same unbiased minimum-variance recursion
* greybox ``smooth_uikf`` (time-varying / auto) - fixed-interval smoother (issue 11)

A second table (issue 11) runs the delayed filter on a ZOH mass whose force is
unknown and whose position only is measured (relative degree 2, where uikf's
r = 1 estimate diverges): ``delayed_uikf`` and ``smooth_uikf`` with
``relative_degree=2``, time-varying and auto, beside statsmodels' KF on the
same mass (force dropped). Its accuracy column is the RMS error of d^ against
the two-sample mean of the true force (what the r = 2 filter estimates under
ZOH, see greybox.filters.delayed).

Per-sample Python loops (greybox time-varying, filterpy, numpy loop) run on the
first ``--loop-n`` samples only; their samples/s is measured there and is
assumed to extrapolate linearly to N (the cost per sample is constant).

Time: best of ``--repeat`` runs without tracing. Memory: a separate run under
``tracemalloc`` (numpy reports its data buffers to it), peak of the call; the
"outputs" column is the size of the arrays the method returns, so peak/outputs
near 1-2 means no per-step covariance stack.

Usage::

    python bench/filter_throughput.py            # N = 1e6
    python bench/filter_throughput.py --quick    # N = 1e4
    python bench/filter_throughput.py -N 200000 --loop-n 5000 --no-install
"""

from __future__ import annotations

import argparse
import gc
import importlib
import os
import platform
import subprocess
import sys
import time
import tracemalloc

import numpy as np

import greybox as gb

DT = 1e-4
MB = 1024.0**2


# --------------------------------------------------------------------------- peers
def _import_or_install(module: str, pip_name: str, no_install: bool):
    """Import ``module``; if absent, ``pip install pip_name`` (unless no_install)."""
    try:
        return importlib.import_module(module)
    except ImportError:
        pass
    if no_install:
        print(f"# {module} not installed (--no-install): its row is skipped")
        return None
    print(f"# installing {pip_name} ...", flush=True)
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", pip_name],
                       capture_output=True, text=True)
    if r.returncode != 0:
        print(f"# pip install {pip_name} failed: its row is skipped\n{r.stderr.strip()[-500:]}")
        return None
    importlib.invalidate_caches()
    try:
        return importlib.import_module(module)
    except ImportError as e:
        print(f"# {module} still not importable after install ({e}): its row is skipped")
        return None


# --------------------------------------------------------------------------- problem
class Problem:
    """Tape-drive data and the model pieces every method needs."""

    def __init__(self, N: int, seed: int):
        self.N = N
        self.sys = gb.tape_drive_nominal(dt=DT)
        true = gb.tape_drive_true(dt=DT)
        self.u = gb.lowpass_noise(N, dt=DT, bandwidth=20, nsignals=2, amplitude=1, rng=seed)
        self.sim = gb.simulate(true, self.u, R=gb.TAPE_DRIVE_R, rng=seed)
        self.y = self.sim.y
        self.T_true = (gb.tape_drive_tension() @ self.sim.x)[0]
        self.Q = np.asarray(gb.TAPE_DRIVE_Q, dtype=float)
        self.R = np.asarray(gb.TAPE_DRIVE_R, dtype=float)
        sp = gb.split_inputs(self.sys, "T")
        self.A, self.B = np.asarray(sp.sys.A), np.asarray(sp.sys.B)
        self.C, self.D = np.asarray(sp.sys.C), np.asarray(sp.sys.D)
        self.G = np.asarray(sp.G)
        self.n = self.A.shape[0]
        self.x0 = np.zeros(self.n)
        self.P0 = np.eye(self.n)  # greybox's default prior, used by every peer
        self.d_target = self.T_true
        self.unknown = "T"
        self.rd = 1


class MassProblem(Problem):
    """ZOH mass, known force u and unknown force F, position measured (r = 2)."""

    def __init__(self, N: int, seed: int):
        dt, m = 1e-3, 2.0
        self.N = N
        A = np.array([[1.0, dt], [0.0, 1.0]])
        Bc = np.array([[dt**2 / 2], [dt]]) / m
        self.sys = gb.named_ss(A, np.hstack([Bc, Bc]), [[1.0, 0.0]], [[0.0, 0.0]], dt,
                               states=["p", "v"], inputs=["u", "F"], outputs=["p"])
        rng = np.random.default_rng(seed)
        self.u = gb.lowpass_noise(N, dt=dt, bandwidth=5, nsignals=1, amplitude=1, rng=seed)
        F = 50.0 * np.tanh(gb.lowpass_noise(N, dt=dt, bandwidth=2, rng=seed + 1)[0] * 50)
        # 1 um position noise; 50 N Coulomb-like force on a 2 kg mass
        self.Q, self.R = np.diag([1e-14, 1e-10]), np.array([[1e-12]])
        x = np.zeros(2)
        xs = np.empty((2, N))
        w = rng.standard_normal((2, N)) * np.sqrt(np.diag(self.Q))[:, None]
        for k in range(N):  # plain loop: the truth, not a greybox routine
            xs[:, k] = x
            x = A @ x + Bc[:, 0] * (self.u[0, k] + F[k]) + w[:, k]
        self.y = xs[:1] + 1e-6 * rng.standard_normal((1, N))
        self.T_true = F
        self.d_target = np.append(0.5 * (F[:-1] + F[1:]), np.nan)
        self.A, self.B, self.C, self.D, self.G = A, Bc, np.array([[1.0, 0.0]]), np.zeros((1, 1)), Bc
        self.n = 2
        self.x0, self.P0 = np.zeros(2), np.eye(2)
        self.unknown = "F"
        self.rd = 2


def _nbytes(*arrays) -> int:
    return int(sum(a.nbytes for a in arrays if isinstance(a, np.ndarray)))


# --------------------------------------------------------------------------- methods
# Each method: f(prob, n) -> (x_filt (nstates, n), d_est (md, n) or None, output_bytes)
def gb_uikf_tv(prob, n):
    r = gb.uikf(prob.sys, prob.y[:, :n], prob.u[:, :n], unknown="T", Q=prob.Q, R=prob.R,
                gain="time-varying")
    return r.x_filt, r.d_est, _gb_out_bytes(r)


_CONVERGED: dict[str, int | None] = {}


def gb_uikf_auto(prob, n):
    r = gb.uikf(prob.sys, prob.y[:, :n], prob.u[:, :n], unknown="T", Q=prob.Q, R=prob.R,
                gain="auto")
    _CONVERGED["greybox uikf auto"] = r.period_converged
    return r.x_filt, r.d_est, _gb_out_bytes(r)


def gb_kf_auto(prob, n):
    r = gb.kalman_filter(prob.sys, prob.y[:, :n], prob.u[:, :n], unknown="T", Q=prob.Q,
                         R=prob.R)
    _CONVERGED["greybox kalman_filter auto"] = r.period_converged
    return r.x_filt, None, _gb_out_bytes(r)


def gb_kf_auto_mass(prob, n):
    r = gb.kalman_filter(prob.sys, prob.y[:, :n], prob.u[:, :n], unknown=prob.unknown,
                         Q=prob.Q, R=prob.R)
    return r.x_filt, None, _gb_out_bytes(r)


def gb_uikf_r1_mass(prob, n):
    r = gb.uikf(prob.sys, prob.y[:, :n], prob.u[:, :n], unknown=prob.unknown, Q=prob.Q,
                R=prob.R)
    return r.x_filt, r.d_est, _gb_out_bytes(r)


def gb_delayed_tv(prob, n):
    r = gb.delayed_uikf(prob.sys, prob.y[:, :n], prob.u[:, :n], unknown=prob.unknown, Q=prob.Q,
                        R=prob.R, relative_degree=prob.rd, gain="time-varying")
    return r.x_filt, r.d_est, _gb_out_bytes(r)


def gb_delayed_auto(prob, n):
    r = gb.delayed_uikf(prob.sys, prob.y[:, :n], prob.u[:, :n], unknown=prob.unknown, Q=prob.Q,
                        R=prob.R, relative_degree=prob.rd)
    _CONVERGED["greybox delayed_uikf auto"] = r.period_converged
    return r.x_filt, r.d_est, _gb_out_bytes(r)


def gb_smooth_tv(prob, n):
    r = gb.smooth_uikf(prob.sys, prob.y[:, :n], prob.u[:, :n], unknown=prob.unknown, Q=prob.Q,
                       R=prob.R, relative_degree=prob.rd, gain="time-varying")
    return r.x_filt, r.d_est, _gb_out_bytes(r)


def gb_smooth_auto(prob, n):
    r = gb.smooth_uikf(prob.sys, prob.y[:, :n], prob.u[:, :n], unknown=prob.unknown, Q=prob.Q,
                       R=prob.R, relative_degree=prob.rd)
    return r.x_filt, r.d_est, _gb_out_bytes(r)


def _gb_out_bytes(r) -> int:
    # arrays the filter computes (t, x_filt, x_pred, d_est, d_var, innovations);
    # the record also keeps its validated copies of u and y (not counted here)
    return _nbytes(r.t, r.x_filt, r.x_pred, r.d_est, r.d_var, r.innovations)


def make_statsmodels(sm_kf_mod, conserve: bool = False):
    """statsmodels' filter; ``conserve`` drops its per-step covariance/gain stacks."""
    KalmanFilter = sm_kf_mod.KalmanFilter
    flags = (sm_kf_mod.MEMORY_NO_FORECAST_COV | sm_kf_mod.MEMORY_NO_PREDICTED_COV
             | sm_kf_mod.MEMORY_NO_FILTERED_COV | sm_kf_mod.MEMORY_NO_GAIN
             | sm_kf_mod.MEMORY_NO_SMOOTHING | sm_kf_mod.MEMORY_NO_STD_FORECAST)

    def statsmodels_kf(prob, n):
        y, u = prob.y[:, :n], prob.u[:, :n]
        nx, p = prob.n, prob.C.shape[0]
        kf = KalmanFilter(k_endog=p, k_states=nx, k_posdef=nx)
        kf.bind(np.ascontiguousarray(y.T))  # (nobs, k_endog)
        kf["design"] = prob.C
        kf["transition"] = prob.A
        kf["selection"] = np.eye(nx)
        kf["state_cov"] = prob.Q
        kf["obs_cov"] = prob.R
        # x[k+1] = A x[k] + B u[k]: statsmodels' c_t enters alpha_{t+1} = c_t + T alpha_t
        kf["state_intercept"] = np.asfortranarray(prob.B @ u)
        if np.any(prob.D):
            kf["obs_intercept"] = np.asfortranarray(prob.D @ u)
        kf.initialize_known(prob.x0, prob.P0)  # a_1, P_1 = x[0|-1], P[0|-1]
        if conserve:
            kf.set_conserve_memory(flags)
        res = kf.filter()
        out = sum(v.nbytes for v in vars(res).values() if isinstance(v, np.ndarray))
        return res.filtered_state, None, int(out)

    return statsmodels_kf


def make_filterpy(fp_kalman):
    KalmanFilter = fp_kalman.KalmanFilter

    def filterpy_kf(prob, n):
        y, u = prob.y[:, :n], prob.u[:, :n]
        nx, p, m = prob.n, prob.C.shape[0], prob.B.shape[1]
        if np.any(prob.D):
            y = y - prob.D @ u  # filterpy has no feed-through term
        kf = KalmanFilter(dim_x=nx, dim_z=p, dim_u=m)
        kf.F, kf.H, kf.B = prob.A.copy(), prob.C.copy(), prob.B.copy()
        kf.Q, kf.R = prob.Q.copy(), prob.R.copy()
        kf.x = prob.x0.reshape(nx, 1).copy()
        kf.P = prob.P0.copy()
        x_filt = np.empty((nx, n))
        for k in range(n):
            kf.update(y[:, k])
            x_filt[:, k] = kf.x[:, 0]
            kf.predict(u=u[:, k:k + 1])
        return x_filt, None, x_filt.nbytes

    return filterpy_kf


def numpy_umv_loop(prob, n):
    """Gillijns & De Moor (7)-(18), one sample at a time, plain numpy (no scipy)."""
    A, B, C, D, G, Q, R = prob.A, prob.B, prob.C, prob.D, prob.G, prob.Q, prob.R
    y, u = prob.y[:, :n], prob.u[:, :n]
    nx, md = A.shape[0], G.shape[1]
    x_filt = np.empty((nx, n))
    d_est = np.full((md, n), np.nan)
    F = C @ G
    Ct, At = C.T, A.T
    Bu, Du = B @ u, D @ u
    # k = 0: measurement update of the prior
    P = prob.P0
    Rt = C @ P @ Ct + R
    K = np.linalg.solve(Rt, C @ P).T
    x = prob.x0 + K @ (y[:, 0] - C @ prob.x0 - Du[:, 0])
    P = P - K @ Rt @ K.T
    x_filt[:, 0] = x
    for k in range(1, n):
        xp = A @ x + Bu[:, k - 1]
        Pp = A @ P @ At + Q
        Rt = C @ Pp @ Ct + R
        Rti = np.linalg.inv(Rt)
        RiF = Rti @ F
        Pd = np.linalg.inv(F.T @ RiF)
        M = Pd @ RiF.T
        d = M @ (y[:, k] - C @ xp - Du[:, k])
        xs = xp + G @ d
        K = Pp @ Ct @ Rti
        x = xs + K @ (y[:, k] - C @ xs - Du[:, k])
        GKF = G - K @ F
        P = Pp - K @ Rt @ K.T + GKF @ Pd @ GKF.T
        P = 0.5 * (P + P.T)
        x_filt[:, k] = x
        d_est[:, k - 1] = d
    return x_filt, d_est, _nbytes(x_filt, d_est)


# --------------------------------------------------------------------------- harness
def _time(f, prob, n, repeat):
    best, out = np.inf, None
    for _ in range(repeat):
        out = None
        gc.collect()
        t0 = time.perf_counter()
        out = f(prob, n)
        best = min(best, time.perf_counter() - t0)
    return best, out


def _peak(f, prob, n):
    gc.collect()
    tracemalloc.start()
    tracemalloc.reset_peak()
    try:
        out = f(prob, n)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    del out
    return peak


def _blas_info() -> str:
    try:
        from threadpoolctl import threadpool_info
        info = [f"{d.get('internal_api')} {d.get('version')} ({d.get('architecture')}, "
                f"{d.get('num_threads')} threads)" for d in threadpool_info()
                if d.get("user_api") == "blas"]
        return "; ".join(info) or "unknown"
    except Exception:  # threadpoolctl absent
        return "unknown (threadpoolctl not installed)"


def _section(methods, prob, args, N, nloop):
    """Time every method (round-robin), trace its memory, print the table; return d_est's."""
    # pass 1: one timed run per method, with the accuracy checks
    rows, ref_x, uif_d = [], None, {}
    for label, f, n, kind in methods:
        t, (x_filt, d_est, out_bytes) = _time(f, prob, n, 1)
        if kind == "ref":
            ref_x = x_filt
            acc = "reference for KF peers"
        elif kind in ("uif", "uif1"):
            target = prob.T_true if kind == "uif1" else prob.d_target  # r = 1 targets d[k]
            ok = ~np.isnan(d_est[0]) & ~np.isnan(target[:n])
            rms = float(np.sqrt(np.mean((d_est[0, ok] - target[:n][ok]) ** 2)))
            acc = f"d RMS err {rms:.3g} N"
            uif_d[label] = d_est[0]
        else:
            dx = np.abs(x_filt - ref_x[:, :n])
            scale = np.max(np.abs(ref_x[:, :n]), axis=1)
            rel = float(np.max(np.max(dx, axis=1) / scale))
            verdict = "OK" if rel <= args.kf_rtol else "FAIL"
            acc = (f"x_filt max abs diff {dx.max():.2g} (rel {rel:.1g} <= {args.kf_rtol:g}: "
                   f"{verdict})")
        del x_filt, d_est
        rows.append(dict(label=label, f=f, n=n, times=[t], out=out_bytes / MB, acc=acc,
                         extrap=n < N))
        print(f"#   {label}: {t:.3f} s on {n} samples", flush=True)
    ref_x = None
    # passes 2..repeat: round-robin over the methods, so a change of machine load hits all
    for _ in range(args.repeat - 1):
        for r in rows:
            r["times"].append(_time(r["f"], prob, r["n"], 1)[0])
    for r in rows:
        r["t"] = min(r["times"])
        r["sps"] = r["n"] / r["t"]
        print(f"#   {r['label']}: best {r['t']:.3f} s, worst {max(r['times']):.3f} s "
              f"over {len(r['times'])} runs", flush=True)
    # memory: one traced run each
    for r in rows:
        r["peak"] = np.nan if args.no_memory else _peak(r["f"], prob, r["n"]) / MB

    sm = next((r for r in rows if r["label"] == "statsmodels KalmanFilter"), None)
    hdr = ("| method | N | time [s] | samples/s | vs statsmodels KF | peak mem [MB] "
           "| outputs [MB] | peak/outputs | accuracy |")  # MB = 2**20 bytes
    print()
    print(hdr)
    print("|" + "---|" * 9)
    for r in rows:
        ratio = f"{r['sps'] / sm['sps']:.2f}x" if sm else "n/a"
        ntxt = f"{r['n']:,}" + (" (*)" if r["extrap"] else "")
        pk = "n/a" if np.isnan(r["peak"]) else f"{r['peak']:.1f}"
        po = "n/a" if np.isnan(r["peak"]) else f"{r['peak'] / r['out']:.1f}"
        print(f"| {r['label']} | {ntxt} | {r['t']:.3f} | {r['sps']:,.0f} | {ratio} | {pk} "
              f"| {r['out']:.1f} | {po} | {r['acc']} |")
    if any(r["extrap"] for r in rows):
        print(f"\n(*) per-sample loop timed on the first {nloop:,} of N = {N:,} samples; "
              f"samples/s extrapolated to N (constant cost per sample), memory at that length.")
    if any("(**)" in r["label"] for r in rows):
        print("(**) statsmodels with set_conserve_memory(MEMORY_NO_FORECAST_COV | "
              "MEMORY_NO_PREDICTED_COV | MEMORY_NO_FILTERED_COV | MEMORY_NO_GAIN | "
              "MEMORY_NO_SMOOTHING | MEMORY_NO_STD_FORECAST); filtered_state kept.")
    print("peak mem: tracemalloc peak of the call (numpy buffers included); outputs: arrays "
          "the method returns (greybox: t, x_filt, x_pred, d_est, d_var, innovations; "
          "statsmodels: every array of its FilterResults; loops: x_filt [+ d_est]). "
          "MB = 2**20 bytes.")

    return uif_d, rows


_PINNED = []  # the active thread limit (kept alive for the whole run)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-N", type=float, default=1e6, help="samples (default 1e6)")
    ap.add_argument("--quick", action="store_true", help="N = 1e4")
    ap.add_argument("--loop-n", type=int, default=20_000,
                    help="samples for the per-sample Python loops (default 20000, <= N)")
    ap.add_argument("--repeat", type=int, default=5,
                    help="timed runs of every method, round-robin, best kept (default 5)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-install", action="store_true",
                    help="do not pip-install missing peers (statsmodels, filterpy); skip them")
    ap.add_argument("--no-memory", action="store_true", help="skip the tracemalloc runs")
    ap.add_argument("--kf-rtol", type=float, default=1e-6,
                    help="tolerance of the KF-peer check: max|dx| <= rtol * max|x| per state")
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="BLAS threads for every method alike (default 1; 0: leave as is)")
    args = ap.parse_args(argv)
    if args.blas_threads > 0:
        # every method runs in this one process: pinning here pins both sides equally (a
        # multithreaded BLAS beside a busy core stalls, which would decide the ratios)
        try:
            from threadpoolctl import threadpool_limits

            _PINNED.append(threadpool_limits(limits=args.blas_threads, user_api="blas"))
        except ImportError:
            print("# threadpoolctl missing: BLAS threads not pinned")
    N = int(1e4) if args.quick else int(args.N)
    nloop = min(args.loop_n, N)

    sm_mod = _import_or_install("statsmodels.tsa.statespace.kalman_filter", "statsmodels",
                                args.no_install)
    fp_mod = _import_or_install("filterpy.kalman", "filterpy", args.no_install)

    print(f"# python {platform.python_version()}, numpy {np.__version__}, "
          f"greybox {gb.__version__}, {os.cpu_count()} cpus; BLAS: {_blas_info()}")
    print(f"# OPENBLAS_CORETYPE={os.environ.get('OPENBLAS_CORETYPE', '(unset)')}; load average "
          f"at start {' '.join(f'{x:.2f}' for x in os.getloadavg())} (shared machine: "
          f"timings are noisy when it is not ~0)")
    if sm_mod is not None:
        import statsmodels
        print(f"# statsmodels {statsmodels.__version__}")
    if fp_mod is not None:
        import filterpy
        print(f"# filterpy {filterpy.__version__}")
    print(f"# tape drive dt={DT}, N={N}, per-sample loops on the first {nloop} samples, "
          f"seed={args.seed}, best of {args.repeat} round-robin runs")

    t0 = time.perf_counter()
    prob = Problem(N, args.seed)
    print(f"# data: lowpass_noise + simulate(tape_drive_true, R=TAPE_DRIVE_R) in "
          f"{time.perf_counter() - t0:.2f} s; true tension RMS "
          f"{np.sqrt(np.mean(prob.T_true ** 2)):.3g} N", flush=True)

    # (label, function, n, kind) kind: "uif" -> tension error, "kf" -> x_filt vs greybox KF
    methods = [
        ("greybox uikf time-varying", gb_uikf_tv, nloop, "uif"),
        ("greybox uikf auto", gb_uikf_auto, N, "uif"),
        ("greybox kalman_filter auto", gb_kf_auto, N, "ref"),
    ]
    if sm_mod is not None:
        methods.append(("statsmodels KalmanFilter", make_statsmodels(sm_mod), N, "kf"))
        methods.append(("statsmodels KalmanFilter, no cov stacks (**)",
                        make_statsmodels(sm_mod, conserve=True), N, "kf"))
    if fp_mod is not None:
        methods.append(("filterpy KalmanFilter loop", make_filterpy(fp_mod), nloop, "kf"))
    methods.append(("numpy per-sample UMV loop", numpy_umv_loop, nloop, "uif"))

    methods.insert(2, ("greybox smooth_uikf time-varying", gb_smooth_tv, nloop, "uif"))
    methods.insert(3, ("greybox smooth_uikf auto", gb_smooth_auto, N, "uif"))
    uif_d, rows = _section(methods, prob, args, N, nloop)
    sm = next((r for r in rows if r["label"] == "statsmodels KalmanFilter"), None)

    # cross-checks among the unknown-input filters (same first nloop samples)
    a = uif_d.get("greybox uikf time-varying")
    for other in ("greybox uikf auto", "numpy per-sample UMV loop"):
        b = uif_d.get(other)
        if a is not None and b is not None:
            m = min(a.size, b.size)
            ok = ~np.isnan(a[:m]) & ~np.isnan(b[:m])
            print(f"d_est max abs diff {other} vs greybox time-varying (first {m:,} samples): "
                  f"{np.max(np.abs(a[:m][ok] - b[:m][ok])):.2g} N")
    for k, v in _CONVERGED.items():
        print(f"{k}: per-sample recursion for the first {v} samples, constant gain after")
    if sm:
        for r in rows:
            if r["label"].startswith("greybox uikf auto"):
                verdict = "meets" if r["sps"] >= 10 * sm["sps"] else "MISSES"
                print(f"goal: greybox uikf auto at {r['sps'] / sm['sps']:.1f}x statsmodels "
                      f"KF throughput ({verdict} >= 10x)")

    print(f"\n## delayed unknown-input estimation (relative degree 2): ZOH mass, position "
          f"only, dt = 1e-3 s, N = {N:,}; accuracy: d^ vs the two-sample mean of the force")
    mprob = MassProblem(N, args.seed)
    mmethods = [
        ("greybox uikf (r = 1, diverging gains) auto", gb_uikf_r1_mass, nloop, "uif1"),
        ("greybox delayed_uikf time-varying", gb_delayed_tv, nloop, "uif"),
        ("greybox delayed_uikf auto", gb_delayed_auto, N, "uif"),
        ("greybox kalman_filter auto (force dropped)", gb_kf_auto_mass, N, "ref"),
        ("greybox smooth_uikf r=2 time-varying", gb_smooth_tv, nloop, "uif"),
        ("greybox smooth_uikf r=2 auto", gb_smooth_auto, N, "uif"),
    ]
    if sm_mod is not None:
        mmethods.append(("statsmodels KalmanFilter", make_statsmodels(sm_mod), N, "kf"))
    md, _ = _section(mmethods, mprob, args, N, nloop)
    a = md.get("greybox delayed_uikf time-varying")
    b = md.get("greybox delayed_uikf auto")
    if a is not None and b is not None:
        ok = ~np.isnan(a) & ~np.isnan(b[:a.size])
        print(f"d_est max abs diff delayed auto vs time-varying (first {a.size:,} samples): "
              f"{np.max(np.abs(a[ok] - b[:a.size][ok])):.2g} N")
    print(f"greybox delayed_uikf auto: per-sample recursion for the first "
          f"{_CONVERGED.get('greybox delayed_uikf auto')} samples, constant gain after")
    print(f"# load average at the end {' '.join(f'{x:.2f}' for x in os.getloadavg())}; BLAS: "
          f"{_blas_info()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
