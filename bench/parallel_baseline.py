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


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or list(range(2006, 2011)))
