"""What the trace names over seeds on the issue-8 plants whose tests run one or two seeds.

``python bench/trace_seeds.py [lag_spring|maxwell|thermal|thermal_three|thermal_row|
thermal_row_ok|thermal_chain|thermal_chain3|
thermal_three_half] [seed ...]`` (default: all, seeds 0-4). Prints, per seed, the effects
found with their laws, the validation SE after and the true model's SE. The plants are
the tests' own (``tests/test_trace_scale.py::_lag_and_spring``,
``tests/test_trace_shared.py::_maxwell``);
``thermal`` (``tests/plantlib.py::thermal_pair``: a hidden thermal mass shared by two
bodies, along no fixed direction; issue 8 item 2, the shared-state law, tested on
seeds 1-3 in ``tests/test_trace_shared_state.py``); ``thermal_three``
(``plantlib.thermal_three``: that shared mass and an independent missing conductance of a
third body, two effects over the several-effects loop, refitted jointly; issue 8 item 5,
``tests/test_trace_shared_joint.py``); ``thermal_row`` (``plantlib.thermal_row``: six
bodies in a row, a hidden mass touching three of them, a 6-state model above
SCREEN_ABOVE; ``tests/test_trace_shared_group.py``) and ``thermal_row_ok`` (the same row
without the hidden mass: the model is right and must stay unchanged); ``thermal_chain``
(``plantlib.thermal_chain_pair``: a hidden chain of two masses behind the pair, one
second-order subsystem shared by eq(T1) and eq(T2); ``tests/test_trace_shared_order2.py``);
``thermal_chain3`` (``plantlib.thermal_chain3_pair``: a chain of three, one third-order
subsystem; ``tests/test_trace_shared_order3.py``);
``thermal_three_half`` (``thermal_three`` at N = 1e4).
Each row also
prints the time and the load average.
"""

from __future__ import annotations

import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))


import greybox as gb  # noqa: E402
from test_trace_scale import _lag_and_spring  # noqa: E402
from test_trace_shared import _maxwell  # noqa: E402
from plantlib import thermal_chain3_pair, thermal_chain_pair, thermal_pair, thermal_row, \
    thermal_three, true_floor  # noqa: E402


def _with_floor(plant, **kw):
    """The case with the true model's validation SE (its hidden states noise-free)."""
    def case(seed):
        nom, d, true = plant(seed, **kw)
        return nom, d, true_floor(true, d)
    return case


CASES = {"lag_spring": _lag_and_spring, "maxwell": _maxwell, "thermal": _with_floor(thermal_pair),
         "thermal_three": _with_floor(thermal_three), "thermal_row": _with_floor(thermal_row),
         "thermal_row_ok": _with_floor(thermal_row, hidden=()),
         "thermal_chain": _with_floor(thermal_chain_pair),
         "thermal_chain3": _with_floor(thermal_chain3_pair),
         "thermal_three_half": _with_floor(thermal_three, n_est=10000)}


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
            print(f"{name} seed {seed}: {el:.1f} s (load {os.getloadavg()[0]:.1f}), SE "
                  f"{rep.table['nominal'].se.value:.3g} -> {se:.3g} % (true model {floor:.3g} %, "
                  f"ratio {se / floor:.2f})")
            for st in rep.steps or ():
                print(f"   {st.channel}: {st.effect.formula}")
            if not rep.steps:
                print(f"   {rep.message}")


if __name__ == "__main__":
    args = sys.argv[1:]
    names = [a for a in args if a in CASES] or list(CASES)
    seeds = [int(a) for a in args if a not in CASES] or list(range(5))
    main(names, seeds)
