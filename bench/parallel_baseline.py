"""Table III over seeds: the parallel delta baseline against the initial model,
the dynamic update and the true-model floor (issue 9).

For every seed, ``greybox demo tape-drive``'s computation
(:func:`greybox.reproduce.reproduce_table2` and
:func:`greybox.reproduce.reproduce_table3` with ``TapeDriveSetting(seed=s)``;
validation on seed + 1, truth without process noise) is run and the
validation SE (eq. 42, relative RMS, mean over 6 outputs) of each row printed,
with the median and range over the seeds. Run:
``python bench/parallel_baseline.py [seed ...]`` (default 2006..2010).
The load average is printed beside the timings (shared machine).

A second table compares the subsystem step's methods
(``identify_subsystem(method=...)``, orders 0..2) on a plant whose missing
effect is dynamic: a mass-damper with a lagged viscous force
(``z' = -2 z - 4 v``, ``d = z``), 10 000 samples at dt = 0.01 s, seeds 20, 30, 40.
"""

import os
import sys
import time

import numpy as np

from greybox.reproduce import PAPER_TABLE3, TapeDriveSetting, reproduce_table2, reproduce_table3

ROWS = ("initial", "dynamic", "dynamic_n4sid", "parallel", "true_model")


def main(seeds):
    print(f"load average at start: {os.getloadavg()[0]:.1f}")
    head = f"| seed | {' | '.join(ROWS)} | parallel order | parallel / initial | time [s] |"
    print(head)
    print("|" + "---|" * (len(ROWS) + 4))
    table = {r: [] for r in ROWS}
    for seed in seeds:
        t0 = time.perf_counter()
        t3 = reproduce_table3(reproduce_table2(TapeDriveSetting(seed=seed)))
        el = time.perf_counter() - t0
        se = {r: t3.rows[r].se.value for r in ROWS}
        for r in ROWS:
            table[r].append(se[r])
        print(f"| {seed} | " + " | ".join(f"{se[r]:.2f}" for r in ROWS)
              + f" | {t3.rows['parallel'].order} | {se['parallel'] / se['initial']:.3f}"
              + f" | {el:.1f} (load {os.getloadavg()[0]:.1f}) |", flush=True)
        print(f"|   | {t3.notes[0]} |", flush=True)
    print("| median | " + " | ".join(f"{np.median(table[r]):.2f}" for r in ROWS) + " | | | |")
    print("| range | " + " | ".join(f"{min(table[r]):.2f}-{max(table[r]):.2f}" for r in ROWS)
          + " | | | |")
    print(f"paper (Table III, SE %): initial {PAPER_TABLE3['initial']['se']}, dynamic "
          f"{PAPER_TABLE3['dynamic']['se']}, parallel {PAPER_TABLE3['parallel']['se']}")
    worse = [s for s, p, i in zip(seeds, table["parallel"], table["initial"]) if not p < i]
    print(f"parallel below initial in every seed: {not worse}"
          + (f" (not in {worse})" if worse else ""))
    print(f"dynamic below parallel in every seed: "
          f"{all(d < p for d, p in zip(table['dynamic'], table['parallel']))}")


def subsystem_methods(seeds=(20, 30, 40)):
    import greybox as gb
    from greybox.update import augment_model, identify_subsystem
    from greybox.validate import validate_model

    dt, Q, R = 0.01, np.diag([1e-8, 1e-6]), np.diag([1e-6, 1e-6])
    A = np.array([[0, 1, 0], [0, -0.4, 1], [0, -4.0, -2.0]])
    true = gb.discretize(gb.named_ss(A, [[0], [1], [0]], np.eye(3)[:2], np.zeros((2, 1)), 0,
                                     states=["x", "v", "z"], inputs=["F"],
                                     outputs=["x", "v"]), dt)
    nominal = gb.discretize(gb.named_ss([[0, 1], [0, -0.4]], [[0, 0], [1, 1]], np.eye(2),
                                        np.zeros((2, 2)), 0, states=["x", "v"],
                                        inputs=["F", "d"], outputs=["x", "v"]), dt)
    base = gb.split_inputs(nominal, "d").sys
    methods = ("output-error", "n4sid", "pbsid")
    print("\nsubsystem step on a lagged force (validation SE %, chosen order in brackets)")
    print("| seed | nominal | true | " + " | ".join(methods) + " |")
    print("|---|---|---|" + "---|" * len(methods))
    for seed in seeds:
        rng = np.random.default_rng(seed)
        u = gb.random_binary(10000, amplitude=1.0, hold=50, rng=rng)
        est = gb.simulate(true, u, Q=np.diag([1e-8, 1e-6, 1e-8]), R=R, rng=rng)
        uv = gb.random_binary(10000, amplitude=1.0, hold=50, rng=rng)
        val = gb.simulate(true, uv, R=R, rng=rng)
        res = gb.uikf(nominal, est.y, est.u, unknown="d", Q=Q, R=R)
        row = [validate_model(base, val.y, val.u, Q=Q, R=R).se.value,
               validate_model(true, val.y, val.u, Q=np.diag([1e-8, 1e-6, 1e-8]), R=R).se.value]
        cells = []
        for meth in methods:
            sub = identify_subsystem(res, max_order=2, method=meth)
            upd = augment_model(nominal, sub, unknown="d", Q=Q, R=R)
            v = validate_model(upd.sys, val.y, val.u, Q=upd.Q, R=upd.R)
            cells.append(f"{v.se.value:.2f} ({sub.order})")
        print(f"| {seed} | {row[0]:.1f} | {row[1]:.2f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or list(range(2006, 2011)))
    subsystem_methods()
