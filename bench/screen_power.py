"""How strongly the equation screen sees the missing spring of a chain, per size (issue 29).

``python bench/screen_power.py [nsteps] [n_masses ...]`` (default 20000 and 16 32 64):
the chain of ``bench/workflow.py chains`` (n_masses masses, the spring between the two
middle ones missing from the model, all positions and velocities measured, and positions
only), screened by :func:`greybox.trace.screen.screen_equations`. One row per case: the
z-scores of the two equations the spring enters, the best other equation's, and the
threshold the pass uses (``EquationScreen.ranked``'s 5). Where the targets fall below
the threshold the pass traces nothing (the 64-mass, positions-only row of
``bench/workflow.py chains``: "nothing traced").
"""

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from workflow import chain_data  # noqa: E402  (bench/workflow.py: the same chain cases)

from greybox.trace.screen import screen_equations  # noqa: E402


def row(n_masses: int, measured: str, N: int) -> str:
    nom, d, i, _ = chain_data(n_masses, measured, N)
    t = time.perf_counter()
    s = screen_equations(nom, d.y, d.u, Q=d.Q, R=d.R, dt=d.dt)
    el = time.perf_counter() - t
    if not s.available:
        return f"| {2 * n_masses} | {measured} | {N:.0e} | unavailable: {s.reason} | | | {el:.1f} |"
    tg = [s.states.index(f"v{i + 1}"), s.states.index(f"v{i + 2}")]
    other = max(float(s.score[j]) for j in range(len(s.states)) if j not in tg)
    z = ", ".join(f"{s.states[j]} {s.score[j]:.3g}" for j in tg)
    return f"| {2 * n_masses} | {measured} | {N:.0e} | {z} | {other:.3g} | 5 | {el:.1f} |"


def main(argv):
    N = int(argv[0]) if argv else 20000
    sizes = [int(a) for a in argv[1:]] or [16, 32, 64]
    print("| states | measured | N | target equations' z | best other z | threshold | "
          "time [s] |")
    print("|---|---|---|---|---|---|---|")
    for nm in sizes:
        for meas in ("all", "positions"):
            print(row(nm, meas, N), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
