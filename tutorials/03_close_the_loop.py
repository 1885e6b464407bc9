"""Tutorial 03: close the loop on your own data.

A two-mass chain whose nominal model misses a spring (15 N/m from mass 2 to
the wall). We (1) simulate "measured" data, (2) run the one call
:func:`greybox.workflow.close_the_loop`, (3) read the report, and (4) do the
same from the command line with ``greybox update``.
"""

import json
import os
import tempfile
from pathlib import Path

import numpy as np

import greybox as gb
from greybox.cli import main as greybox_cli
from greybox.model_io import model_to_dict
from greybox.system import named_ss
from greybox.workflow import close_the_loop

dt = 0.01
states = ["p1", "v1", "p2", "v2"]


def chain(k2):
    A = np.array([[0, 1, 0, 0], [-30, -0.5, 20, 0], [0, 0, 0, 1], [20, 0, -20 - k2, -0.5]])
    return named_ss(A, [[0], [1], [0], [0]], np.eye(4), np.zeros((4, 1)), 0, states=states,
                    inputs=["F"], outputs=states, name="chain")


# 1. "measured" data from the true machine (process + measurement noise)
rng = np.random.default_rng(3)
Q, R = np.diag([0, 1e-8, 0, 1e-8]), 1e-6 * np.eye(4)
truth = gb.discretize(chain(15.0), dt)
u = gb.lowpass_noise(6000, dt=dt, bandwidth=1.0, amplitude=2.0, rng=rng)
uv = gb.lowpass_noise(3000, dt=dt, bandwidth=1.0, amplitude=2.0, rng=rng)
y = gb.simulate(truth, u, Q=Q, R=R, rng=rng).y
yv = gb.simulate(truth, uv, R=R, rng=rng).y

# 2. one call: residual -> trace -> add -> before/after
nominal = chain(0.0)
rep = close_the_loop(nominal, y, u, yv, uv, Q=Q + 1e-12 * np.eye(4), R=R, dt=dt)

# 3. the report
print(rep.message)
print("effect:", rep.effect.kind, "|", rep.effect.formula)
for note in rep.effect.parameter_notes:
    print("  ", note)
for name, v in rep.table.items():
    print(f"  {name:<10} order {v.order}  SE {v.se.value:7.3g} %  PE {v.pe.value:7.3g} %")

# 4. the same from the command line: the report folder gets report.md, the
#    figures (residual autocorrelation before/after, measured vs simulated
#    outputs, d^ with its band) and the updated model in the MODEL.json schema
import matplotlib  # noqa: E402

matplotlib.use("Agg")
out_root = os.environ.get("GREYBOX_TUTORIAL_OUT", ".")
with tempfile.TemporaryDirectory() as tmp:  # the input files; the report outlives it
    tmp = Path(tmp)
    report = Path(out_root) / "tutorial03_report"
    (tmp / "model.json").write_text(json.dumps(model_to_dict(nominal, Q + 1e-12 * np.eye(4),
                                                             R, Ts=dt)))
    for name, yy, uu in (("est.csv", y, u), ("val.csv", yv, uv)):
        rows = ["time,F," + ",".join(states)] + [
            ",".join(f"{v:.10g}" for v in (k * dt, *uu[:, k], *yy[:, k]))
            for k in range(yy.shape[1])]
        (tmp / name).write_text("\n".join(rows) + "\n")
    code = greybox_cli(["update", str(tmp / "model.json"), str(tmp / "est.csv"),
                        "--validate", str(tmp / "val.csv"), "--out", str(report), "--force"])
    print("exit code", code, "; report files:", sorted(p.name for p in report.iterdir()))
