"""What the trace names over seeds on the issue-8 plants whose tests run one or two seeds.

``python bench/trace_seeds.py [lag_spring|maxwell|thermal] [seed ...]`` (default: all,
seeds 0-4). Prints, per seed, the effects found with their laws, the validation SE after
and the true model's SE. The plants are the tests' own
(``tests/test_trace_scale.py::_lag_and_spring``, ``tests/test_trace_shared.py::_maxwell``);
``thermal`` (``tests/plantlib.py::thermal_pair``: a hidden thermal mass shared by two
bodies, along no fixed direction; issue 8 item 2, the shared-state law, tested on
seeds 1-3 in ``tests/test_trace_shared_state.py``).
"""

from __future__ import annotations

import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

import numpy as np  # noqa: E402

import greybox as gb  # noqa: E402
from test_trace_scale import _lag_and_spring  # noqa: E402
from test_trace_shared import _maxwell  # noqa: E402
from plantlib import thermal_pair  # noqa: E402


def _thermal(seed):
    nom, d, true = thermal_pair(seed)
    Qt = np.zeros((3, 3))
    Qt[:2, :2] = d.Q
    return nom, d, gb.validate_model(true, d.y_val, d.u_val, Q=Qt + 1e-12 * np.eye(3),
                                     R=d.R).se.value


CASES = {"lag_spring": _lag_and_spring, "maxwell": _maxwell, "thermal": _thermal}


def main(names, seeds):
    print(f"load average {os.getloadavg()[0]:.1f} (2 cores)")
    for name in names:
        for seed in seeds:
            nom, d, floor = CASES[name](seed)
            t = time.perf_counter()
            rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                                    delta=False)
            el = time.perf_counter() - t
            se = rep.table["updated"].se.value
            print(f"{name} seed {seed}: {el:.1f} s, SE {rep.table['nominal'].se.value:.3g} -> "
                  f"{se:.3g} % (true model {floor:.3g} %, ratio {se / floor:.2f})")
            for st in rep.steps or ():
                print(f"   {st.channel}: {st.effect.formula}")
            if not rep.steps:
                print(f"   {rep.message}")


if __name__ == "__main__":
    args = sys.argv[1:]
    names = [a for a in args if a in CASES] or list(CASES)
    seeds = [int(a) for a in args if a not in CASES] or list(range(5))
    main(names, seeds)
