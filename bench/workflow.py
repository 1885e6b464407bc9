"""Time close_the_loop on 1e5 samples of a 6-state model (issue 5 goal: < 10 s).

``python bench/workflow.py csv [nsteps]``: the whole ``greybox update`` on a 1e6-row
CSV of a 2-state model and the CSV readers side by side (issue 13).

``python bench/workflow.py stages [nsteps]``: the same run in a fresh process, one row
per progress record (time per stage and the peak RSS so far).

``--whole-record`` (after ``csv`` or ``stages``): the same run with the search on the
whole estimation record (``greybox.workflow.SEARCH_WINDOW`` raised above its length, as
before issue 13's search window), to compare results and cost.

``python bench/workflow.py chains [nsteps] [n ...]``: chains of n/2 masses with
the coupling spring between the two middle masses missing from the model, all
states measured and positions only (issue 8): time, peak memory (RSS of a
fresh process per case), whether the right pair and a one-term law in the
relative coordinate were found, and the validation SE against the true
model's (the floor). An n written ``32:all`` or ``32:positions`` runs that case
only; wall and CPU time are both printed (CPU time is the fairer figure on a
loaded machine). The whole update runs, the parallel delta baseline included;
``--no-baseline`` skips it.

Three-mass chain (states p1 v1 p2 v2 p3 v3, force on mass 1, dt = 0.01 s),
the nominal model misses a 15 N/m spring from mass 3 to the wall. Run:
``python bench/workflow.py [nsteps ...]`` (default 1e4 and 1e5).
"""

import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

import greybox as gb
from greybox.system import named_ss
from greybox.workflow import close_the_loop


def chain3(k3=0.0):
    k, c = 20.0, 0.5
    A = np.zeros((6, 6))
    for i in range(3):
        A[2 * i, 2 * i + 1] = 1.0
        A[2 * i + 1, 2 * i + 1] = -c
    K = np.array([[2 * k, -k, 0], [-k, 2 * k, -k], [0, -k, k + k3]])
    for i in range(3):
        for j in range(3):
            A[2 * i + 1, 2 * j] = -K[i, j]
    B = np.zeros((6, 1))
    B[1, 0] = 1.0
    states = ["p1", "v1", "p2", "v2", "p3", "v3"]
    return named_ss(A, B, np.eye(6), np.zeros((6, 1)), 0, states=states, inputs=["F"],
                    outputs=states, name="chain3")


def run(N, rng_seed=0):
    """One timed close_the_loop run; returns a table row."""
    dt = 0.01
    rng = np.random.default_rng(rng_seed)
    truth = gb.discretize(chain3(k3=15.0), dt)
    Q = np.diag([0, 1e-8] * 3)
    R = 1e-6 * np.eye(6)
    u = gb.lowpass_noise(N, dt=dt, bandwidth=1.0, amplitude=2.0, rng=rng)
    uv = gb.lowpass_noise(max(N // 4, 2000), dt=dt, bandwidth=1.0, amplitude=2.0, rng=rng)
    y = gb.simulate(truth, u, Q=Q, R=R, rng=rng).y
    yv = gb.simulate(truth, uv, R=R, rng=rng).y
    args = (chain3(), y, u, yv, uv)
    kw = dict(Q=Q + 1e-12 * np.eye(6), R=R, dt=dt)
    t = time.perf_counter()
    rep = close_the_loop(*args, **kw)
    el = time.perf_counter() - t
    # memory in a second run: tracemalloc slows Python-heavy code several-fold
    tracemalloc.start()
    close_the_loop(*args, **kw)
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    se0 = rep.table["nominal"].se.value
    se1 = rep.table["updated"].se.value
    return dict(N=N, time=el, rate=N / el, peak=peak, data=(y.nbytes + u.nbytes) / 2**20,
                found=f"{','.join(rep.effect.equations)} {rep.effect.kind}", se0=se0, se1=se1,
                formula=rep.effect.formula)


def main(sizes=(10_000, 100_000)):
    rows = [run(N) for N in sizes]
    print("close_the_loop on a 6-state chain with a missing 15 N/m spring on mass 3 "
          "(goal: 1e5 samples in < 10 s)")
    hdr = (f"{'N':>8} {'time [s]':>9} {'samples/s':>10} {'peak [MB]':>10} {'data [MB]':>10} "
           f"{'found':>10} {'SE before [%]':>14} {'SE after [%]':>13}")
    print(hdr)
    for r in rows:
        print(f"{r['N']:>8d} {r['time']:>9.2f} {r['rate']:>10.0f} {r['peak']:>10.1f} "
              f"{r['data']:>10.1f} {r['found']:>10} {r['se0']:>14.1f} {r['se1']:>13.3f}")
    print("law found at the largest N:", rows[-1]["formula"])
    print("(time: one untraced run; peak: tracemalloc peak of a second, traced run)")




# --------------------------------------------------------------------------- 1e6-sample CSV
# ``python bench/workflow.py csv [nsteps]``: the whole ``greybox update`` run on CSV files
# of a 2-state model (issue 13 goal at 1e6 samples: <= 10 s and <= 500 MB), and the CSV
# reader alone against numpy.loadtxt, the csv module and pandas (if installed), side by side
# in one process (goal: >= 5e6 values/s, peak <= 2x the numbers).

def _osc(k=4.0):
    A = np.array([[0.0, 1.0], [-k, -0.8]])
    return named_ss(A, [[0.0], [1.0]], np.eye(2), np.zeros((2, 1)), 0, states=["x", "v"],
                    inputs=["F"], outputs=["x", "v"], name="osc")


def write_csv_case(folder, N, seed=0):
    """MODEL.json (spring 4 N/m; the truth has 6 N/m) and est/val CSVs with time column."""
    import json
    from pathlib import Path

    from greybox.model_io import model_to_dict

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    dt = 0.01
    rng = np.random.default_rng(seed)
    truth = gb.discretize(_osc(6.0), dt)
    Q, R = np.diag([0.0, 1e-8]), 1e-6 * np.eye(2)
    (folder / "model.json").write_text(json.dumps(model_to_dict(_osc(), Q + 1e-12 * np.eye(2),
                                                                R, Ts=dt)))
    for name, n in (("est.csv", N), ("val.csv", max(N // 4, 2000))):
        u = gb.lowpass_noise(n, dt=dt, bandwidth=1.0, amplitude=2.0, rng=rng)
        y = gb.simulate(truth, u, Q=Q if name == "est.csv" else None, R=R, rng=rng).y
        data = np.vstack([np.arange(n) * dt, u, y]).T
        np.savetxt(folder / name, data, delimiter=",", header="time,F,x,v", comments="",
                   fmt="%.10g")
    return folder


def _peak_of(fn):
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def bench_readers(path, repeat=3):
    """Rows: reader, best time, values/s, peak / numbers, ratio to greybox."""
    import csv

    from greybox.model_io import read_csv

    def greybox_reader():
        return read_csv(path, inputs=["F"], outputs=["x", "v"], Ts=0.01)

    def numpy_loadtxt():
        return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)

    def csv_module():  # the reader greybox had before issue 13
        with open(path, newline="") as f:
            rows = list(csv.reader(f))[1:]
        return np.array([[float(c) for c in r] for r in rows])

    readers = [("greybox.read_csv", greybox_reader), ("numpy.loadtxt", numpy_loadtxt),
               ("csv module + float()", csv_module)]
    try:
        import pandas as pd

        readers.append(("pandas.read_csv (C engine)",
                        lambda: pd.read_csv(path).to_numpy(dtype=float)))
    except ImportError:
        pass
    arr = numpy_loadtxt()
    nvalues, nbytes = arr.size, arr.nbytes
    rows = []
    for name, fn in readers:
        best = np.inf
        for _ in range(repeat):
            t = time.perf_counter()
            fn()
            best = min(best, time.perf_counter() - t)
        rows.append((name, best, nvalues / best, _peak_of(fn) / nbytes))
    return rows, nvalues, nbytes


# The child reports its own peak RSS (VmHWM of its address space). ru_maxrss of
# RUSAGE_CHILDREN is no good here: a forked child's high-water mark starts at the
# parent's RSS at fork time (this benchmark's, ~2 GB after the CSV readers), which is how
# the README once quoted 2054 MB for a run that peaked at ~830 MB.
# It also reports its CPU time (user + system, all threads): on the shared 2-core machine
# the wall time swings 3x with the other sessions' load, the CPU time much less.
_CLI_CHILD = """
import os, resource, sys
import greybox.workflow
from greybox.cli import main
if os.environ.get("BENCH_WHOLE_RECORD"):
    greybox.workflow.SEARCH_WINDOW = 10**12
try:
    rc = main(sys.argv[1:])
finally:
    with open("/proc/self/status") as f:
        hwm = [ln.split()[1] for ln in f if ln.startswith("VmHWM")]
    r = resource.getrusage(resource.RUSAGE_SELF)
    sys.stderr.write("\\nBENCH_VMHWM_KB " + (hwm[0] if hwm else "nan") + "\\n")
    sys.stderr.write("BENCH_CPU_S " + repr(r.ru_utime + r.ru_stime) + "\\n")
sys.exit(rc)
"""


def bench_cli(folder, whole=False):
    """The whole ``greybox update`` in a child process: wall time, peak RSS [MB], result."""
    import json
    import os
    import subprocess

    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    if whole:
        env["BENCH_WHOLE_RECORD"] = "1"
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", _CLI_CHILD, "update", f"{folder}/model.json",
                        f"{folder}/est.csv", "--validate", f"{folder}/val.csv", "--out",
                        f"{folder}/report", "--force", "--no-plots", "--json", "--quiet"],
                       capture_output=True, text=True, env=env)
    el = time.perf_counter() - t
    if p.returncode:
        raise SystemExit(f"greybox update failed ({p.returncode}): {p.stderr}")
    kb = [ln.split()[1] for ln in p.stderr.splitlines() if ln.startswith("BENCH_VMHWM_KB")]
    rss = float(kb[-1]) / 1024 if kb and kb[-1] != "nan" else float("nan")
    cpu = [float(ln.split()[1]) for ln in p.stderr.splitlines() if ln.startswith("BENCH_CPU_S")]
    return el, rss, json.loads(p.stdout), (cpu[-1] if cpu else float("nan"))


def _stage_profile(folder, whole=False):
    """In this (fresh) process: close_the_loop on the CSV case, one row per progress record.

    Prints the stage, wall time since the start, the time since the previous record, the
    process's CPU time (user + system) in that step, its RSS at the record and its peak
    RSS so far (ru_maxrss: the high-water mark, it never drops).
    """
    import os
    import resource

    import greybox.workflow
    from greybox.model_io import read_csv, read_model

    if whole:
        greybox.workflow.SEARCH_WINDOW = 10**12

    def peak():
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    def rss():
        with open("/proc/self/status") as f:
            return float(next(ln.split()[1] for ln in f if ln.startswith("VmRSS"))) / 1024

    t0 = time.perf_counter()
    spec = read_model(f"{folder}/model.json")
    ins, outs = list(spec.sys.input_labels), list(spec.sys.output_labels)
    y, u = read_csv(f"{folder}/est.csv", inputs=ins, outputs=outs, Ts=spec.Ts)
    yv, uv = read_csv(f"{folder}/val.csv", inputs=ins, outputs=outs, Ts=spec.Ts, min_steps=100)
    print(f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())} (2 cores shared)")
    print("| stage (progress record) | at [s] | step [s] | step CPU [s] | RSS [MB] | "
          "peak RSS so far [MB] |")
    print("|---|---|---|---|---|---|")
    print(f"| imports + read_model + read_csv (est, val) | {time.perf_counter() - t0:.2f} | "
          f"{time.perf_counter() - t0:.2f} | {time.process_time():.2f} | {rss():.0f} | "
          f"{peak():.0f} |")
    last = [time.perf_counter(), time.process_time()]

    def cb(p):
        now, cpu = time.perf_counter(), time.process_time()
        print(f"| {p.stage} {p.k}/{p.K} | {now - t0:.2f} | {now - last[0]:.2f} | "
              f"{cpu - last[1]:.2f} | {rss():.0f} | {peak():.0f} |", flush=True)
        last[:] = [now, cpu]

    close_the_loop(spec.sys, y, u, yv, uv, Q=spec.Q, R=spec.R, dt=spec.Ts,
                   channels=spec.channels, progress=cb)
    print(f"total {time.perf_counter() - t0:.2f} s wall, {time.process_time():.2f} s CPU, "
          f"peak RSS {peak():.0f} MB; load average "
          f"{' '.join(f'{v:.2f}' for v in os.getloadavg())}")


def main_stages(N=1_000_000, whole=False):
    """``python bench/workflow.py stages [nsteps]``: where the 1e6-sample run spends."""
    import os
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory(dir=os.environ.get("TMPDIR")) as tmp:
        folder = write_csv_case(tmp, N)
        subprocess.run([sys.executable, __file__, "_stages", str(folder)] +
                       (["--whole-record"] if whole else []), check=True)


def main_csv(N=1_000_000, whole=False):
    import os
    import tempfile

    with tempfile.TemporaryDirectory(dir=os.environ.get("TMPDIR")) as tmp:
        folder = write_csv_case(tmp, N)
        size = os.path.getsize(f"{folder}/est.csv") / 2**20
        load0 = os.getloadavg()
        el, rss, s, cpu = bench_cli(folder, whole)  # first: the readers below grow this process
        load1 = os.getloadavg()
        rows, nvalues, nbytes = bench_readers(f"{folder}/est.csv")
    print(f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())} (2 cores shared)")
    print(f"CSV reader on {N} rows x 4 columns ({size:.1f} MB of text, {nbytes / 2**20:.1f} MB "
          f"of numbers); best of 3, same process")
    print(f"{'reader':<28}{'time [s]':>9}{'values/s':>12}{'peak/numbers':>14}{'time ratio':>12}")
    t0 = rows[0][1]
    for name, t, rate, peak in rows:
        print(f"{name:<28}{t:>9.3f}{rate:>12.3g}{peak:>14.2f}{t / t0:>11.2f}x")
    print(f"\nwhole `greybox update --no-plots` at N = {N} (2-state model, spring missing"
          f"{'; search on the whole record' if whole else ''}): "
          f"{el:.2f} s wall, {cpu:.2f} s CPU, peak RSS {rss:.0f} MB (goal <= 10 s, <= 500 MB); "
          f"load average {load0[0]:.2f} before, {load1[0]:.2f} after")
    t = s["table"]
    print(f"  found {s['channel']} {s['effect']['kind']}: {s['effect']['formula']}; "
          f"validation SE {t['nominal']['se']:.3g}% -> {t['updated']['se']:.3g}%"
          + (f" (delta baseline {t['delta']['se']:.3g}%)"
             if t.get("delta", {}).get("se") is not None else ""))


def chain_data(n_masses, measured, N, seed=1):
    """``(nominal, data, i, meas)`` of one chain case: n_masses masses, the spring between
    masses i + 1 and i + 2 (the two middle ones) missing from the nominal, all states
    measured ("all") or the positions ``meas`` only ("positions")."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from plantlib import chain, draw

    i = n_masses // 2 - 1
    meas = None if measured == "all" else [f"p{j + 1}" for j in range(n_masses)]
    true = chain(n_masses, k=20.0)
    nom = chain(n_masses, k=20.0, missing=[(i, i + 1)], measured=meas)
    A, B = np.asarray(true.A), np.asarray(true.B)
    d = draw(nom, lambda x, u: A @ x + B @ u, n_true=2 * n_masses, dt=0.01,
             rng=np.random.default_rng(seed), q_std=np.array([0.0, 1e-4] * n_masses),
             r_std=1e-3, n_est=N, n_val=3000, sub=2)
    return nom, d, i, meas


def _chain_case(n_masses, measured, N, seed=1):
    """One chain case in this process; prints one table row."""
    import resource

    nom, d, i, meas = chain_data(n_masses, measured, N, seed)
    from plantlib import chain  # on the path chain_data put it on
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t, c = time.perf_counter(), time.process_time()
    # the whole update, the parallel delta baseline included (its cost is bounded by
    # the trace's: see greybox.workflow._delta_baseline); --no-baseline skips it
    rep = close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                         delta=not _NO_BASELINE)
    el, cpu = time.perf_counter() - t, time.process_time() - c
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    floor = gb.validate_model(gb.discretize(chain(n_masses, k=20.0, measured=meas), d.dt),
                              d.y_val, d.u_val, Q=d.Q, R=d.R).se.value
    eqs = {f"v{i + 1}", f"v{i + 2}"}
    law = rep.effect.law
    names = [] if law is None else [law.spec[j][0] for j in np.flatnonzero(law.coef[0])]
    rel = f"(p{i + 2}-p{i + 1})"
    found = ("right pair" if rep.updated and set(rep.effect.equations) == eqs else "wrong")
    found += (", one term in " + rel if names == [rel] else
              f", {len(names)} terms" + (f" incl. {rel}" if rel in names else ""))
    se1 = rep.table["updated"].se.value
    import os

    print(f"| {2 * n_masses} | {measured} | {N:.0e} | {el:.1f} / {cpu:.1f} | "
          f"{os.getloadavg()[0]:.1f} | {rss:.0f} ({rss - rss0:+.0f}) "
          f"| {found} | {rep.table['nominal'].se.value:.3g} -> {se1:.3g} | {floor:.3g} "
          f"| {se1 / floor:.2f} |", flush=True)


def main_chains(N=100_000, sizes=(8, 16, 32, 64)):
    """One fresh process per row; a size "32:all" or "32:positions" runs that case only."""
    import os
    import subprocess

    print(f"load average {os.getloadavg()[0]:.1f} (2 cores)")
    print("| n | measured | N | wall / CPU time [s] | load | peak RSS [MB] (+ in "
          "close_the_loop) | found | SE before -> after [%] | true model SE [%] | "
          "after / true |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for size in sizes:
        n, _, only = str(size).partition(":")
        for meas in (only,) if only else ("all", "positions"):
            subprocess.run([sys.executable, __file__, "_chain", str(int(n) // 2), meas, str(N)]
                           + (["--no-baseline"] if _NO_BASELINE else []), check=False)


if __name__ == "__main__":
    if {"-h", "--help"} & set(sys.argv[1:]):
        print(__doc__)
        sys.exit(0)
    _whole = "--whole-record" in sys.argv
    _NO_BASELINE = "--no-baseline" in sys.argv
    sys.argv = [a for a in sys.argv if a not in ("--whole-record", "--no-baseline")]
    if sys.argv[1:2] == ["_chain"]:
        _chain_case(int(sys.argv[2]), sys.argv[3], int(sys.argv[4]))
    elif sys.argv[1:2] == ["chains"]:
        args = sys.argv[2:]
        main_chains(*([int(args[0])] if args else [100_000]),
                    *([tuple(args[1:])] if args[1:] else []))
    elif sys.argv[1:2] == ["_stages"]:
        _stage_profile(sys.argv[2], _whole)
    elif sys.argv[1:2] == ["stages"]:
        main_stages(*(int(a) for a in sys.argv[2:3]), whole=_whole)
    elif sys.argv[1:2] == ["csv"]:
        main_csv(*(int(a) for a in sys.argv[2:3]), whole=_whole)
    else:
        main(tuple(int(a) for a in sys.argv[1:]) or (10_000, 100_000))
