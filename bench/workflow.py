"""Time close_the_loop on 1e5 samples of a 6-state model (issue 5 goal: < 10 s).

Three-mass chain (states p1 v1 p2 v2 p3 v3, force on mass 1, dt = 0.01 s),
the nominal model misses a 15 N/m spring from mass 3 to the wall. Run:
``python bench/workflow.py [nsteps ...]`` (default 1e4 and 1e5).
"""

import sys
import time
import tracemalloc

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


if __name__ == "__main__":
    main(tuple(int(a) for a in sys.argv[1:]) or (10_000, 100_000))
