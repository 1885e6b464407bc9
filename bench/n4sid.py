"""Benchmark: greybox.ident.n4sid against SIPPY, nfoursid and SLICOT (Octave).

System: random stable order-4 model, 8 inputs, 1 output, D = 0, white output
noise (std 0.1 against unit-variance white inputs); horizon (block rows) 10;
fixed order 4 for every method (SLICOT's default tolerance breaks automatic
order selection). Each method runs in its own process, which loads the same
raw binary data file; we report identification time (data loading excluded),
peak resident memory of that process (/usr/bin/time %M, for every method;
"RSS above data" is that peak minus the RSS after imports and data loading,
Python methods only), the largest pole error (optimal matching) and the validation
fit 100 (1 - |y - y_sim| / |y - mean(y)|) [%] of the simulated model on a
fresh 5000-sample record.

BLAS threads are pinned on both sides (``--blas-threads``, default 1):
every method's process gets OMP/OPENBLAS/MKL/VECLIB thread limits in its
environment, Octave included, so that a busy second core does not stall one
side's multithreaded BLAS (issue 13: Octave took 72 s instead of 2.3 s with
two threads and the other core busy). Each (method, N) runs ``--repeat``
times (default 3); the table keeps the fastest run and prints the load
average before and after.

Usage::

    python bench/n4sid.py                 # installs peers if missing, runs all
    python bench/n4sid.py --skip-install  # only what is already installed
    python bench/n4sid.py --sizes 1e4 1e5 --timeout 300

Peers: ``pip install sippy-unipi nfoursid``; Debian ``octave octave-control``
(``apt-get update`` first). A peer that is missing is skipped.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

NIN, NOUT, ORDER, HORIZON, SIGMA, SEED = 8, 1, 4, 10, 0.1, 2024
NVAL = 5000
HERE = Path(__file__).resolve().parent

# Peers that form the whole block Hankel matrix: limits from their measured runs
# (issue 13: SIPPY finishes N = 1e6 in ~54 s with ~5.3 GB, so it runs up to 1e6)
PEER_CAP = {"nfoursid": 1e4, "sippy": 1e6}
PEER_CAP_WHY = {
    "nfoursid": "skipped: 1.6 GB peak RSS at N=1e4, grows ~linearly (~16 GB at 1e5)",
    "sippy": "skipped: ~5.3 GB peak RSS at N=1e6, grows ~linearly",
}
BLAS_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
             "VECLIB_MAXIMUM_THREADS", "BLIS_NUM_THREADS")


def pinned_env(threads: int) -> dict:
    """The environment of a benchmarked process, with its BLAS thread count pinned."""
    return dict(os.environ, **{v: str(threads) for v in BLAS_VARS})


def load_average() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


# ---------------------------------------------------------------------------
# data
# ---------------------------------------------------------------------------


def true_system():
    rng = np.random.default_rng(SEED)
    poles = [0.85 * np.exp(0.4j), 0.6 * np.exp(1.8j)]
    A = np.zeros((4, 4))
    for k, p in enumerate(poles):
        A[2 * k:2 * k + 2, 2 * k:2 * k + 2] = [[p.real, p.imag], [-p.imag, p.real]]
    B = rng.standard_normal((4, NIN))
    C = rng.standard_normal((NOUT, 4))
    return A, B, C, np.zeros((NOUT, NIN))


def simulate(A, B, C, D, u):
    """y = C (qI - A)^-1 B u + D u via lfilter per input (fast for long records)."""
    from scipy.signal import lfilter, ss2tf

    y = np.zeros((C.shape[0], u.shape[1]))
    for j in range(u.shape[0]):
        num, den = ss2tf(A, B, C, D, input=j)
        for i in range(C.shape[0]):
            y[i] += lfilter(num[i], den, u[j])
    return y


def write_data(path: Path, N: int, seed: int):
    """Raw float64, sample-major: [u_0..u_7, y] per sample (Octave: fread [9, N])."""
    A, B, C, D = true_system()
    rng = np.random.default_rng(seed)
    chunk = 1_000_000
    with open(path, "wb") as f:
        # simulate in one go per chunk with carried state via full record for simplicity
        u = rng.standard_normal((NIN, N))
        y = simulate(A, B, C, D, u) + SIGMA * rng.standard_normal((NOUT, N))
        for c0 in range(0, N, chunk):
            np.vstack([u[:, c0:c0 + chunk], y[:, c0:c0 + chunk]]).T.astype("<f8").tofile(f)


def load(path: Path, N: int):
    z = np.fromfile(path, dtype="<f8").reshape(N, NIN + NOUT).T  # (9, N) view
    return z[NIN:], z[:NIN]


# ---------------------------------------------------------------------------
# worker (one method, one process)
# ---------------------------------------------------------------------------


def pole_error(est, true):
    from scipy.optimize import linear_sum_assignment

    est, true = np.asarray(est), np.asarray(true)
    if est.size != true.size:
        return float("inf")
    cost = np.abs(est[:, None] - true[None, :])
    r, c = linear_sum_assignment(cost)
    return float(cost[r, c].max())


def score(A, B, C, D, valpath: Path):
    At, Bt, Ct, Dt = true_system()
    yv, uv = load(valpath, NVAL)
    ysim = simulate(np.asarray(A), np.asarray(B), np.asarray(C), np.asarray(D), uv)
    fit = 100 * (1 - np.linalg.norm(yv - ysim) / np.linalg.norm(yv - yv.mean()))
    return pole_error(np.linalg.eigvals(A), np.linalg.eigvals(At)), float(fit)


def rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def worker(method: str, path: Path, N: int, valpath: Path):
    y, u = load(path, N)
    if method == "greybox":
        from greybox.ident import n4sid
    elif method == "sippy":
        from sippy_unipi import system_identification
    elif method == "nfoursid":
        import pandas as pd
        from nfoursid.nfoursid import NFourSID
    base = rss_mb()
    t0 = time.perf_counter()
    if method == "greybox":
        r = n4sid(y, u, order=ORDER, horizon=HORIZON)
        A, B, C, D = r.sys.A, r.sys.B, r.sys.C, r.sys.D
    elif method == "sippy":
        r = system_identification(y, u, "N4SID", SS_fixed_order=ORDER, SS_f=HORIZON,
                                  SS_p=HORIZON)
        A, B, C, D = r.A, r.B, r.C, r.D
    elif method == "nfoursid":
        cols = {f"u{j}": u[j] for j in range(NIN)} | {"y": y[0]}
        df = pd.DataFrame(cols)
        m = NFourSID(df, output_columns=["y"], input_columns=[f"u{j}" for j in range(NIN)],
                     num_block_rows=HORIZON)
        m.subspace_identification()
        ss, _ = m.system_identification(rank=ORDER)
        A, B, C, D = ss.a, ss.b, ss.c, ss.d
    else:
        raise ValueError(method)
    t = time.perf_counter() - t0
    peak = rss_mb()
    err, fit = score(A, B, C, D, valpath)
    print(json.dumps({"time": t, "peak_mb": peak, "base_mb": base, "pole_err": err, "fit": fit}))


OCTAVE_SCRIPT = r"""
pkg load control
fid = fopen('{path}', 'r'); Z = fread(fid, [{nz}, {N}], 'double'); fclose(fid);
dat = iddata(Z({nz}, :)', Z(1:{nin}, :)', 1); clear Z;
t0 = tic; sys = n4sid(dat, {order}, 's', {horizon}); t = toc(t0);
[a, b, c, d] = ssdata(sys);
fid = fopen('{out}', 'w'); fprintf(fid, '%.17g\n', t, a(:), b(:), c(:), d(:)); fclose(fid);
"""


def run_octave(path: Path, N: int, valpath: Path, timeout: float, env=None):
    out = path.with_suffix(".oct.txt")
    script = path.with_suffix(".m")
    script.write_text(OCTAVE_SCRIPT.format(path=path, nz=NIN + NOUT, N=N, nin=NIN, order=ORDER,
                                           horizon=HORIZON, out=out))
    timef = path.with_suffix(".time")
    cmd = ["/usr/bin/time", "-f", "%M", "-o", str(timef), "octave", "--no-gui", "-q",
           "--no-window-system", str(script)]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    if p.returncode != 0 or not out.exists():
        raise RuntimeError(p.stderr.strip()[-500:])
    vals = np.array([float(v) for v in out.read_text().split()])
    t = vals[0]
    k = 1
    A = vals[k:k + 16].reshape(4, 4, order="F"); k += 16
    B = vals[k:k + 4 * NIN].reshape(4, NIN, order="F"); k += 4 * NIN
    C = vals[k:k + 4].reshape(1, 4, order="F"); k += 4
    D = vals[k:k + NIN].reshape(1, NIN, order="F")
    peak = float(timef.read_text().strip().splitlines()[-1]) / 1024.0
    err, fit = score(A, B, C, D, valpath)
    return {"time": t, "peak_mb": peak, "base_mb": float("nan"), "pole_err": err, "fit": fit}


# ---------------------------------------------------------------------------
# driver
# ---------------------------------------------------------------------------


def have_module(name):
    return subprocess.run([sys.executable, "-c", f"import {name}"], capture_output=True).returncode == 0


def install(skip: bool):
    notes = {}
    for mod, pkg in (("sippy_unipi", "sippy-unipi"), ("nfoursid", "nfoursid")):
        if not have_module(mod) and not skip:
            p = subprocess.run([sys.executable, "-m", "pip", "install", "-q", pkg],
                               capture_output=True, text=True)
            if p.returncode:
                notes[mod] = f"pip install {pkg} failed: {p.stderr.strip()[-300:]}"
    octave_ok = shutil.which("octave") and subprocess.run(
        ["octave", "--no-gui", "-q", "--eval", "pkg load control"], capture_output=True
    ).returncode == 0
    if not octave_ok and not skip:
        env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
        for cmd in (["apt-get", "update", "-q"],
                    ["apt-get", "install", "-y", "-q", "octave", "octave-control", "time"]):
            p = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if p.returncode:
                notes["octave"] = f"{' '.join(cmd)} failed: {p.stderr.strip()[-300:]}"
                break
    return notes


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", type=float, default=[1e4, 1e5, 1e6, 1e7])
    ap.add_argument("--peers-max", type=float, default=1e6, help="largest N run for the peers")
    ap.add_argument("--skip-install", action="store_true")
    ap.add_argument("--timeout", type=float, default=900.0, help="per method and size [s]")
    ap.add_argument("--methods", nargs="+", default=["greybox", "slicot", "sippy", "nfoursid"])
    ap.add_argument("--out", type=Path, default=HERE / "RESULTS_n4sid.md")
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="BLAS threads of every benchmarked process (both sides)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per method and size (best)")
    ap.add_argument("--worker", nargs=4, metavar=("METHOD", "PATH", "N", "VALPATH"),
                    help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        m, p, n, v = args.worker
        worker(m, Path(p), int(n), Path(v))
        return
    notes = install(args.skip_install)
    avail = {
        "greybox": True,
        "sippy": have_module("sippy_unipi"),
        "nfoursid": have_module("nfoursid"),
        "slicot": bool(shutil.which("octave")) and Path("/usr/bin/time").exists(),
    }
    rows = []
    env = pinned_env(args.blas_threads)
    load_before = load_average()
    with tempfile.TemporaryDirectory(prefix="bench_n4sid_") as tmp:
        tmp = Path(tmp)
        valpath = tmp / "val.bin"
        write_data(valpath, NVAL, SEED + 1)
        for Nf in args.sizes:
            N = int(Nf)
            path = tmp / f"data_{N}.bin"
            write_data(path, N, SEED + 2)
            for meth in args.methods:
                if meth != "greybox" and N > args.peers_max:
                    continue
                if N > PEER_CAP.get(meth, float("inf")):
                    rows.append({"method": meth, "N": N, "status": PEER_CAP_WHY[meth]})
                    print(json.dumps(rows[-1]), flush=True)
                    continue
                if not avail.get(meth):
                    res = {"status": notes.get(meth if meth != "slicot" else "octave", "not installed")}
                else:
                    res = best_of(args.repeat, lambda: _run_one(meth, path, N, valpath, args,
                                                                env))
                res.update(method=meth, N=N)
                rows.append(res)
                print(json.dumps(res), flush=True)
            path.unlink()
    load_after = load_average()
    table = format_table(rows)
    header = (f"BLAS threads pinned to {args.blas_threads} in every process; best of "
              f"{args.repeat} runs; load average before {load_before}, after {load_after} "
              f"({os.cpu_count()} CPUs)")
    print(header)
    print(table)
    args.out.write_text(
        "# N4SID benchmark\n\n" + __doc__.split("Usage::")[0].strip() + "\n\n"
        + f"Machine: {os.cpu_count()} CPUs; command: `python bench/n4sid.py "
        + " ".join(sys.argv[1:]) + "`\n\n" + header + "\n\n" + table + "\n"
    )


def best_of(k: int, run) -> dict:
    """The fastest of ``k`` runs (a failed or timed-out run ends the series)."""
    best = None
    for _ in range(max(1, k)):
        res = run()
        if "time" not in res:
            return res if best is None else best
        if best is None or res["time"] < best["time"]:
            best = res
    return best


def _run_one(meth, path, N, valpath, args, env) -> dict:
    """One run of one method in its own process (BLAS threads pinned by ``env``)."""
    try:
        if meth == "slicot":
            return run_octave(path, N, valpath, args.timeout, env)
        # /usr/bin/time measures a process forked from a small parent: a child
        # forked from this (large) driver would inherit its RSS in ru_maxrss
        timef = path.with_suffix(".ptime")
        p = subprocess.run(
            ["/usr/bin/time", "-f", "%M", "-o", str(timef), sys.executable,
             __file__, "--worker", meth, str(path), str(N), str(valpath)],
            capture_output=True, text=True, timeout=args.timeout, env=env)
        if p.returncode:
            raise RuntimeError(p.stderr.strip().splitlines()[-1][:200])
        res = json.loads(p.stdout.strip().splitlines()[-1])
        res["peak_mb"] = float(timef.read_text().split()[-1]) / 1024.0
        return res
    except subprocess.TimeoutExpired:
        return {"status": f"timeout > {args.timeout:.0f} s"}
    except Exception as e:  # report and go on with the other peers
        return {"status": f"failed: {e}"}


def format_table(rows):
    ref = {r["N"]: r for r in rows if r["method"] == "slicot" and "time" in r}
    hdr = ("| N | method | time [s] | peak RSS [MB] | RSS above data [MB] | time / SLICOT | "
           "RSS / SLICOT | max pole error | val. fit [%] |")
    lines = [hdr, "|" + "---|" * 9]
    for r in rows:
        if "time" not in r:
            lines.append(f"| {r['N']:.0e} | {r['method']} | {r['status']} | | | | | | |")
            continue
        s = ref.get(r["N"])
        tr = f"{r['time'] / s['time']:.2f}" if s else "-"
        mr = f"{r['peak_mb'] / s['peak_mb']:.3f}" if s else "-"
        above = "-" if np.isnan(r["base_mb"]) else f"{r['peak_mb'] - r['base_mb']:.0f}"
        lines.append(
            f"| {r['N']:.0e} | {r['method']} | {r['time']:.2f} | {r['peak_mb']:.0f} | {above} | "
            f"{tr} | {mr} | {r['pole_err']:.2e} | {r['fit']:.2f} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
