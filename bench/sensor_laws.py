"""Sensor laws of an output channel over seeds: drift rate, clipping level, lag; and their cost.

``python bench/sensor_laws.py [nseeds]`` (default 40). The plants are the
tests' own (``tests/test_sensor_drift.py::_case``: a mass-spring-damper whose
position sensor drifts by 0.05 m + 0.004 m/s t, or clips at 1.5 m;
``tests/test_sensor_dynamics.py::_lag_case``: read through 1/(0.1 s + 1)),
seeds 100 .. 100 + nseeds - 1, 4000 estimation samples. Per case:

* the law chosen on ``output(pos)`` (how many seeds chose the right kind);
* the 95 % interval's coverage of the truth, the mean error, and the spread
  of the estimates over the mean stated sigma (1: calibrated);
* the CPU time of ``trace_channel`` on that channel (median over seeds) and,
  side by side in the same calls (cProfile, wall clock), the mean time of each
  sensor-law fit (static refit, lag, drift, saturation): the filter and the
  smoother take the rest.
"""

from __future__ import annotations

import cProfile
import os
import pstats
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

from greybox.trace import output_channel, trace_channel  # noqa: E402
from test_sensor_drift import DT, LEVEL, RATE, _case  # noqa: E402
from test_sensor_dynamics import TAU, _lag_case  # noqa: E402

FITS = ("_refit_sensor_law", "_fit_sensor_lag", "_fit_sensor_drift", "_fit_sensor_saturation")


def _data(case, seed):
    """(nominal, y, u, Q, R, dt) of a case."""
    if case == "lag":
        nom, y, u, _, _, Q, R, dt = _lag_case(TAU, seed)
        return nom, y, u, Q, R, dt
    rate, level = {"right": (0.0, np.inf), "drift": (RATE, np.inf), "clip": (0.0, LEVEL)}[case]
    nom, y, u, _, _, Q, R, _ = _case(rate, level, seed)
    return nom, y, u, Q, R, DT


TRUTH = {"drift": ("drift", RATE), "clip": ("yhat_sat", LEVEL), "lag": ("yhat_lag", TAU),
         "right": (None, None)}


def main(nseeds: int) -> None:
    print(f"# load average {' '.join(f'{v:.2f}' for v in os.getloadavg())} (2 shared cores); "
          f"seeds 100..{99 + nseeds}, 4000 samples, dt 0.01 s")
    print("\n| case | right kind | coverage | mean error | spread / sigma | trace CPU [s] | "
          "static refit [ms] | lag fit [ms] | drift fit [ms] | clip fit [ms] |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for case in ("right", "drift", "clip", "lag"):
        kind, truth = TRUTH[case]
        ok, err, sig, cpu = 0, [], [], []
        share = np.zeros(len(FITS))  # summed seconds per fit
        for seed in range(100, 100 + nseeds):
            nom, y, u, Q, R, dt = _data(case, seed)
            prof = cProfile.Profile()
            t = time.process_time()
            prof.enable()
            law = trace_channel(nom, output_channel(nom, "pos"), y, u, Q=Q, R=R, dt=dt,
                                max_order=0).static
            prof.disable()
            cpu.append(time.process_time() - t)
            st = pstats.Stats(prof).stats
            for q, fn in enumerate(FITS):
                share[q] += sum(v[3] for k, v in st.items() if k[2] == fn)
            kinds = [sp[1] for j, sp in enumerate(law.spec) if law.coef[0, j]]
            if kind is None:
                ok += not any(k in ("drift", "yhat_sat", "yhat_lag") for k in kinds)
                continue
            if kind not in kinds:
                continue
            ok += 1
            j = [sp[1] for sp in law.spec].index(kind)
            err.append(law.coef[0, j] - truth)
            sig.append(law.ci[0, j] / 1.96)
        err, sig = np.array(err), np.array(sig)
        cov = f"{np.sum(np.abs(err) <= 1.96 * sig)}/{err.size}" if err.size else "-"
        me = f"{err.mean():.2g}" if err.size else "-"
        sp = f"{err.std() / sig.mean():.2f}" if err.size else "-"
        shares = " | ".join(f"{1e3 * s / nseeds:.1f}" for s in share)
        print(f"| {case} | {ok}/{nseeds} | {cov} | {me} | {sp} | {np.median(cpu):.2f} | "
              f"{shares} |")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 40)
