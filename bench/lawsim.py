"""The compiled simulation of a model with a static law against the numpy recursion.

Output-error fits of a nonlinear law (``greybox.trace.oe._OutputErrorNonlinearLaw``)
simulate the model with the law for K coefficient columns at once (a Jacobian's
forward differences, a screen's trials), hundreds of times per fit. This prints, per
model size n, column count K and hold, the time of one simulation of N samples by the
numpy loop and by the compiled kernel (``greybox.lawsim``, numba), their ratio, the
peak memory each allocates (tracemalloc) and their largest relative difference.

    python bench/lawsim.py [N]          # N samples (default 2000)

The law: per state a cube, a smoothed sign and a linear term, a relative cube between
neighbours and an input term (3n + n - 1 + 1 terms), feeding two components of d.
The first compiled call (compiling, ~4 s, or loading the disk cache) is not timed.
"""

from __future__ import annotations

import sys
import time
import tracemalloc

import control as ct
import numpy as np
import scipy.linalg as sl

from greybox import lawsim
from greybox.hold import LawHold
from greybox.trace.oe import _OutputErrorNonlinearLaw


class _Law:
    def __init__(self, spec, eps, hold):
        self.spec, self.eps, self.hold = spec, eps, hold


def problem(n: int, N: int, hold: str, seed: int = 0):
    rng = np.random.default_rng(seed)
    dt = 0.01
    Ac = rng.standard_normal((n, n)) / np.sqrt(n)
    Ac -= (np.abs(np.linalg.eigvals(Ac)).max() + 1.0) * np.eye(n)
    Gc = rng.standard_normal((n, 2))
    spec = [(f"x{i}^3", "x^3", i) for i in range(n)] + \
        [(f"sign(x{i})", "sign", i) for i in range(n)] + [(f"x{i}", "x", i) for i in range(n)] + \
        [(f"(x{i + 1}-x{i})^3", "rel^3", (i, i + 1, n + i)) for i in range(n - 1)] + \
        [("u0", "u", 0)]
    eps = rng.uniform(0.05, 0.2, 2 * n)
    hl = LawHold.of(Ac, Gc, dt) if hold == "etdrk4" else None
    model = ct.ss(sl.expm(Ac * dt), np.c_[0.1 * rng.standard_normal((n, 1)), Gc * dt],
                  np.eye(n)[:2], np.zeros((2, 3)), dt)
    u = rng.standard_normal((1, N))
    y = rng.standard_normal((2, N))
    sel = [(q % 2, q) for q in range(len(spec))]
    th0 = 0.05 * rng.standard_normal(len(sel))
    p = _OutputErrorNonlinearLaw(_Law(spec, eps, hl), model, 2, y, u, np.zeros(n), 10, sel,
                                 th0, window=N)
    return p, th0


def timed(f, repeat: int):
    tracemalloc.start()
    t = time.perf_counter()
    for _ in range(repeat):
        out = f()
    dt = (time.perf_counter() - t) / repeat
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return out, dt, peak


def main(N: int = 2000) -> None:
    if not lawsim.HAVE_NUMBA:
        sys.exit("numba is not installed: pip install -e '.[fast]'")
    print(f"N = {N} samples per simulation; time per simulation [ms]; peak memory [MB]")
    print("| n | K | hold | numpy [ms] | compiled [ms] | ratio | numpy peak [MB] | "
          "compiled peak [MB] | max rel. difference |")
    print("|---|---|---|---|---|---|---|---|---|")
    for hold in ("none", "etdrk4"):
        for n in (2, 8, 32):
            for K in (1, 16, 128):
                p, th0 = problem(n, N, hold)
                TH = th0[:, None] * np.linspace(0.5, 1.5, K)[None]
                p.simulate(TH)  # compile or load the cache
                fast, tf, mf = timed(lambda: p.simulate(TH), 3)
                saved, p._compiled = p._compiled, None
                slow, ts, ms = timed(lambda: p.simulate(TH), 1)
                p._compiled = saved
                ok = np.isfinite(slow)  # a diverged column: NaN on both paths (tested)
                rel = float(np.max(np.abs(fast - slow)[ok]) / np.max(np.abs(slow[ok])))
                print(f"| {n} | {K} | {hold} | {1e3 * ts:.1f} | {1e3 * tf:.2f} | "
                      f"{ts / tf:.0f}x | {ms / 2**20:.1f} | {mf / 2**20:.1f} | {rel:.1e} |")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 2000)
