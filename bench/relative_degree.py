"""Time the relative-degree search of the delayed unknown-input filter on chains (issue 29).

``python bench/relative_degree.py [n ...]``: for chains of n/2 masses (springs between
neighbours, dt = 0.01 s), all states measured and positions only, the time of
``greybox.filters.delayed._choose`` (the search over r = 1..n that
``detect_relative_degree`` runs for every delayed channel) on the middle velocity
equation, one BLAS thread, best of 3, and the r it chose. Before 3649cc8 the search
went on to r = n once G~ had lost rank (22.5 s all measured, 13.6 s positions only at
n = 128); it now stops there.
"""

import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import greybox as gb  # noqa: E402
from greybox.filters.delayed import _choose  # noqa: E402
from plantlib import chain  # noqa: E402


def one(n_states: int, measured: str) -> tuple[int, float]:
    m = n_states // 2
    meas = None if measured == "all" else [f"p{j + 1}" for j in range(m)]
    sysd = gb.discretize(chain(m, k=20.0, measured=meas), 0.01)
    A, C = np.asarray(sysd.A), np.asarray(sysd.C)
    G = np.zeros((A.shape[0], 1))
    G[2 * (m // 2 - 1) + 1, 0] = 1.0  # the middle velocity equation
    Q, R = 1e-8 * np.eye(A.shape[0]), 1e-6 * np.eye(C.shape[0])
    best = np.inf
    for _ in range(3):
        t = time.perf_counter()
        r = _choose(A, C, G, Q, R, ["d"], None, 100.0, 5000).r
        best = min(best, time.perf_counter() - t)
    return r, best


def main(sizes=(16, 32, 64, 128)):
    print("| n | measured | r chosen | search time [s] |")
    print("|---|---|---|---|")
    for n in sizes:
        for meas in ("all", "positions"):
            r, t = one(n, meas)
            print(f"| {n} | {meas} | {r} | {t:.3f} |", flush=True)


if __name__ == "__main__":
    if {"-h", "--help"} & set(sys.argv[1:]):
        print(__doc__)
        sys.exit(0)
    main(tuple(int(a) for a in sys.argv[1:]) or (16, 32, 64, 128))
