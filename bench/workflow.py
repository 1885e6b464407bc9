"""Time close_the_loop on 1e5 samples of a 6-state model (issue 5 goal: < 10 s).

Three-mass chain (states p1 v1 p2 v2 p3 v3, force on mass 1, dt = 0.01 s),
the nominal model misses a 15 N/m spring from mass 3 to the wall. Run:
``python bench/workflow.py [nsteps]``.
"""

import sys
import time

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


def main(N=100_000):
    dt = 0.01
    rng = np.random.default_rng(0)
    truth = gb.discretize(chain3(k3=15.0), dt)
    Q = np.diag([0, 1e-8] * 3)
    R = 1e-6 * np.eye(6)
    u = gb.lowpass_noise(N, dt=dt, bandwidth=1.0, amplitude=2.0, rng=rng)
    uv = gb.lowpass_noise(N // 4, dt=dt, bandwidth=1.0, amplitude=2.0, rng=rng)
    y = gb.simulate(truth, u, Q=Q, R=R, rng=rng).y
    yv = gb.simulate(truth, uv, R=R, rng=rng).y
    t = time.perf_counter()
    rep = close_the_loop(chain3(), y, u, yv, uv, Q=Q + 1e-12 * np.eye(6), R=R, dt=dt)
    el = time.perf_counter() - t
    print(f"close_the_loop, 6 states, {N} estimation samples: {el:.2f} s (goal < 10 s)")
    print(rep.message)
    print(rep.effect.formula)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 100_000)
