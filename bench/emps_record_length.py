"""EMPS: the trace's law and the test error against the length of the estimation record.

The official split trains on all of DATA_EMPS (24841 samples) and tests on
DATA_EMPS_PULSES; tutorials/04_emps.py estimates on its first 8000 samples.
This prints, for estimation records DATA_EMPS[0:N], the law close_the_loop
names, Fc = -M x its sign(v) coefficient, the test simulation error (SE %,
RMS mm, the whole test record simulated from vir) and the time, with the
published M, Fv, gtau and the tutorial's Q and R.

    python bench/emps_record_length.py [N ...]      (default 8000 16000 24841; ~50 s)

Before FilterResult.settled, N = 22000 read ``(16.2 ± 0.95)*q^3`` (fitted on
the 28 samples after the r = 1 filter's covariance met its convergence test
at sample 21969) and N = 24841 left the model unchanged. Now N = 8000 and
16000 give the two friction terms; N = 24841 names the kinematic equation
eq(q) (an open defect of the law selection on long records: ``docs/results/real-data.md``).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from greybox.system import named_ss
from greybox.workflow import close_the_loop

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "emps"


def main(lengths):
    z, zt = np.load(DATA / "DATA_EMPS.npz"), np.load(DATA / "DATA_EMPS_PULSES.npz")
    dt, M, Fv, gtau = 1e-3, 95.1089, 203.5034, float(z["gtau"])
    q, vir, qt, virt = z["qm"], z["vir"], zt["qm"], zt["vir"]
    steps = np.diff(np.unique(q))
    R = np.array([[steps[steps > 1e-12].min() ** 2 / 12]])
    v = np.gradient(q, dt)
    Q = np.diag([0.0, np.var((M * np.gradient(v, dt) + Fv * v - gtau * vir) / M * dt)])
    emps = named_ss([[0, 1], [0, -Fv / M]], [[0], [gtau / M]], [[1, 0]], [[0]], 0,
                    states=["q", "v"], inputs=["vir"], outputs=["q"], name="emps")
    print(f"{'N':>6} {'time s':>7} {'updated':>8} {'Fc N':>7} {'test SE %':>10} "
          f"{'test RMS mm':>12}  law")
    for N in lengths:
        t0 = time.time()
        rep = close_the_loop(emps, q[None, :N], vir[None, :N], qt[None], virt[None], Q=Q, R=R,
                             dt=dt)
        el = time.time() - t0
        law = rep.effect.law
        names = [s[0] for s in law.spec] if law is not None else []
        Fc = -M * law.coef[0, names.index("sign(v)")] if "sign(v)" in names else float("nan")
        row = rep.table["updated"]
        rms = 1e3 * np.sqrt(np.mean((qt[None] - row.y_sim)[:, 20:] ** 2))
        print(f"{N:>6} {el:7.1f} {str(rep.updated):>8} {Fc:7.2f} {row.se.value:10.3g} "
              f"{rms:12.3g}  {rep.effect.formula or rep.message}")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [8000, 16000, 24841])
