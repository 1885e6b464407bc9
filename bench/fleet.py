"""``greybox fleet`` on 64 generated units of a 4-state plant, with 1 and 2 workers (issue 29).

Every unit's nominal model is the two-mass chain of ``tests/plantlib.chain(2)``
(states p1 v1 p2 v2, force F on mass 1, dt = 0.01 s). Its true plant lacks a
wall spring on mass 2 (most units, stiffness 4 to 30 N/m, two units far out
at 60 N/m: the robust outliers of their group), a damper on mass 1 (a few
units, 0.5 to 3 N s/m), or nothing (a few units). Each runs the same fleet,
folder and files with a fresh ``LocalCluster`` of 1, then 2, single-threaded
worker processes, ``--force`` so that every unit is computed, and prints:

- per worker count: wall time, units/s, speed-up, the CPU share each worker
  got (the units' CPU time over wall time x workers: below 100 % when other
  processes share the cores), peak RSS of each worker (``ru_maxrss`` of the
  worker process at the end), the load average;
- per unit: the mean CPU time of a task (a worker has one thread: the unit's
  cost on an idle core), the task's pickled size, the bytes it reads and the
  size of its result;
- the scheduler's own cost per task (1000 no-op tasks);
- whether every unit's verdict and group is the generated truth.

Run: ``python bench/fleet.py [--units 64] [--samples 2000] [--workers 1,2] [--dir DIR]``
(``--samples``: estimation samples per unit; validation gets half). The
machine is shared: wall times depend on the load printed beside them; CPU
times much less.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import pickle
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def plan(n_units: int, seed: int = 2029) -> dict:
    """unit -> (effect, size, seed): ~80 % springs, ~10 % dampers, ~10 % right."""
    rng = np.random.default_rng(seed)
    n_damp = max(1, round(0.1 * n_units))
    n_right = max(1, round(0.1 * n_units))
    n_spring = n_units - n_damp - n_right
    sizes = list(rng.uniform(4.0, 30.0, n_spring - 2)) + [60.0, 60.0]
    kinds = ([("spring", float(s)) for s in sizes]
             + [("damping", float(c)) for c in rng.uniform(0.5, 3.0, n_damp)]
             + [("right", 0.0)] * n_right)
    order = rng.permutation(len(kinds))
    return {f"unit{i + 1:03d}": (*kinds[j], 1000 + i) for i, j in enumerate(order)}


def generate(folder: Path, units: dict, n_est: int) -> None:
    from greybox.model_io import write_model
    from plantlib import chain, chain_unit, write_unit

    for name, (effect, size, seed) in units.items():
        if not (folder / "units" / name / "validation.csv").exists():
            case = chain_unit(effect, size, seed, n_est=n_est, n_val=n_est // 2)
            write_unit(folder / "units" / name, case)
    case = chain_unit("right", 0.0, 0, n_est=200, n_val=100)
    write_model(folder / "MODEL.json", chain(2), case.Q, case.R, Ts=case.dt)


def scheduler_cost(client, n: int = 1000) -> float:
    """Seconds of scheduler and transport per task (n no-op tasks submitted at once)."""
    t = time.perf_counter()
    client.gather(client.map(lambda i: i, range(n), pure=False))
    return (time.perf_counter() - t) / n


def run(folder: Path, workers: int) -> dict:
    from distributed import Client, LocalCluster

    from greybox.fleet import fleet

    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address=None, silence_logs=logging.ERROR,
                           env={"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                                "MKL_NUM_THREADS": "1"})
    client = Client(cluster)
    try:
        client.run(lambda: __import__("greybox.workflow"))  # imports before the clock
        load0 = os.getloadavg()[0]
        t = time.perf_counter()
        rep = fleet(folder / "MODEL.json", folder / "units", out=folder / "out", client=client,
                    force=True)
        wall = time.perf_counter() - t
        load1 = os.getloadavg()[0]
        rss = client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
        per_task = scheduler_cost(client) if workers == max(ARGS.workers) else float("nan")
    finally:
        client.close()
        cluster.close()
    return {"workers": workers, "wall": wall, "rss": sorted(rss.values()), "report": rep,
            "load": (load0, load1), "per_task": per_task}


def check(rep, units) -> tuple[int, str]:
    """(units whose verdict and group are the truth, groups found)."""
    want = {"spring": "eq(v2) static: p2", "damping": "eq(v1) static: v1", "right": ""}
    ok = 0
    for r in rep.units:
        effect = units[r.unit][0]
        verdict = "right" if effect == "right" else "deviates"
        ok += r.status != "failed" and r.verdict == verdict and r.key == want[effect]
    groups = "; ".join(f"{len(g.units)} x {g.key}" for g in rep.groups)
    return ok, groups


def task_sizes(folder: Path, units: dict) -> tuple[float, float, float]:
    """(pickled task bytes, CSV bytes read, result JSON bytes), means over units."""
    task = np.mean([len(pickle.dumps(("greybox.fleet.run_unit", str(folder / "MODEL.json"), n,
                                      str(folder / "units" / n / "estimation.csv"),
                                      str(folder / "units" / n / "validation.csv"),
                                      {"delta": False, "timeout": None}))) for n in units])
    read = np.mean([sum((folder / "units" / n / f).stat().st_size
                        for f in ("estimation.csv", "validation.csv")) for n in units])
    read += (folder / "MODEL.json").stat().st_size
    res = np.mean([(folder / "out" / "units" / f"{n}.json").stat().st_size for n in units])
    return task, read, res


def main() -> None:
    folder = Path(ARGS.dir or tempfile.mkdtemp(prefix="greybox-fleet-bench-"))
    units = plan(ARGS.units)
    t = time.perf_counter()
    generate(folder, units, ARGS.samples)
    print(f"{len(units)} units of {ARGS.samples} + {ARGS.samples // 2} samples in {folder} "
          f"(generated in {time.perf_counter() - t:.0f} s)", flush=True)
    rows = [run(folder, w) for w in ARGS.workers]
    base = rows[0]["wall"]
    print("\n| workers | wall [s] | units/s | speed-up | CPU share of each worker | "
          "peak RSS per worker [MB] | load avg (start, end) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        n = len(r["report"].units)
        busy = sum(u.cpu_seconds for u in r["report"].units) / (r["wall"] * r["workers"])
        print(f"| {r['workers']} | {r['wall']:.1f} | {n / r['wall']:.2f} | "
              f"{base / r['wall']:.2f} | {100 * busy:.0f} % | "
              f"{', '.join(f'{m:.0f}' for m in r['rss'])} | "
              f"{r['load'][0]:.1f}, {r['load'][1]:.1f} |")
    rep = rows[-1]["report"]
    cpu = np.array([u.cpu_seconds for u in rep.units if u.status != "failed"])
    wall = np.array([u.seconds for u in rep.units if u.status != "failed"])
    task, read, res = task_sizes(folder, units)
    ok, groups = check(rep, units)
    print(f"\nper unit (last run): CPU {cpu.mean():.2f} s mean, {np.median(cpu):.2f} s median, "
          f"{cpu.max():.2f} s max; task wall {wall.mean():.2f} s mean")
    print(f"task {task:.0f} B pickled; reads {read / 1024:.0f} kB of CSV and model; result "
          f"{res / 1024:.1f} kB of JSON; scheduler {1e3 * rows[-1]['per_task']:.2f} ms per "
          f"no-op task ({max(ARGS.workers)} workers)")
    print(f"verdict and group right: {ok}/{len(units)}; groups: {groups}")
    print(f"answer: {rep.answer}")
    outl = [(c.name, c.outliers) for g in rep.groups for c in g.coefficients if c.outliers]
    print(f"robust outliers: {outl}")
    print(json.dumps({"cpu_mean": cpu.mean(), "rows": [
        {k: v for k, v in r.items() if k != "report"} for r in rows]}, default=float))


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--units", type=int, default=64)
    p.add_argument("--samples", type=int, default=2000)
    p.add_argument("--workers", type=lambda s: [int(v) for v in s.split(",")], default=[1, 2])
    p.add_argument("--dir", help="folder for the generated units (kept; default a new "
                                 "temporary folder)")
    ARGS = p.parse_args()
    main()
