"""Tutorial 08: the coupled electric drives (CE8), REAL data, through the one call and the CLI.

One REAL measured system from ``../shared/data`` (read its folder's README), on
the benchmark's official estimation/test split, through the steps every
real-data tutorial takes (the nominal model fitted on estimation data only,
Q and R from one rule, ``close_the_loop``, before/after on the test split,
``greybox update`` on written files, a figure and a JSON summary: listed in
``_real_data.py``). ``greybox update`` runs on the low-amplitude
record's files.

**Coupled electric drives** (Ts = 20 ms, DATAUNIF, official split [:400]
estimation, [400:] test, the low-amplitude record u11/z11; the
high-amplitude record u12/z12 is run too). Nominal: the report's trusted
reference linear part H(z) = 0.0414 / (z^3 - 2.6011 z^2 + 2.4060 z -
0.7823) (README) in observer form with the pulley speed w as first state,
its static gain rescaled by least squares on the estimation samples where
the model's speed has been positive for 4 samples (where |w| = w, the
nominal model holds): this record's gain is 0.37 of the PRBS reference's.
R = one sensor quantization step squared (0.0049^2). Omitted effect: the rectifying |.| speed sensor (output side).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _real_data, beside this file
from _real_data import (  # noqa: E402
    DATA, cli_on_files, data_or_exit, figure, out_dir, save_summary, show, terms_of, verdict)

data_or_exit("coupled_electric_drives")

from scipy.signal import lfilter  # noqa: E402

import greybox as gb  # noqa: E402
from greybox.system import named_ss  # noqa: E402

OUT = out_dir("greybox08_")

# %% Coupled electric drives ---------------------------------------------------------------
print("=== Coupled electric drives (CE8, DATAUNIF, Ts = 20 ms) ===")
d = np.genfromtxt(DATA / "coupled_electric_drives" / "DATAUNIF.csv", delimiter=",",
                  skip_header=1)[:, :4]
den = np.array([1, -2.6011, 2.4060, -0.7823])       # the report's reference H(z), eq. 9
b_ref, dt = 0.0414, 0.02
est, val = slice(0, 400), slice(400, 500)
A_obs = np.array([[-den[1], 1, 0], [-den[2], 0, 1], [-den[3], 0, 0]])   # y = w = x[0]
summary = {}
for rec, (u, z) in {"low (u11)": (d[:, 0], d[:, 2]), "high (u12)": (d[:, 1], d[:, 3])}.items():
    y_ref = lfilter([0, 0, 0, b_ref], den, u[est])
    held = np.ones(est.stop, bool)                  # model speed > 0 for 4 samples: |w| = w
    for k in range(4):
        held &= np.r_[np.zeros(k, bool), y_ref[:est.stop - k] > 0.1]
    gain = float(y_ref[held] @ z[est][held] / (y_ref[held] @ y_ref[held]))
    b = b_ref * gain
    R_ced = np.array([[0.0049**2]])
    Q_ced = R_ced[0, 0] * np.eye(3)
    ced = named_ss(A_obs, [[0], [0], [b]], [[1, 0, 0]], [[0]], dt, states=["w", "x2", "x3"],
                   inputs=["u"], outputs=["z"], name="drives")
    print(f"record {rec}: reference gain x {gain:.3f} (least squares on {held.sum()} estimation "
          f"samples with w > 0); Q = R I, R = {R_ced[0, 0]:.3g}")
    t0 = time.time()
    rep = gb.close_the_loop(ced, z[None, est], u[None, est], z[None, val], u[None, val],
                            Q=Q_ced, R=R_ced)
    print(f"close_the_loop ({time.time() - t0:.1f} s):")
    table = show(rep, z[None, val], "(sensor units)")
    figure(rep, z[None, val], dt, "pulley speed z (sensor units)",
           f"coupled electric drives, record {rec}, test [400:500]",
           OUT / f"fig10_drives_{rec.split()[0]}.png")
    out = {**verdict(rep),
           "kind": rep.channel.kind if rep.channel is not None else None,
           "passed": rep.gate.get("passed"), "table": table, "gain": gain,
           "terms": terms_of(rep.effect.law) if rep.effect.law is not None else {},
           "formula": rep.effect.formula,
           "candidates": [c.__dict__.copy() for c in rep.candidates]}
    if rec.startswith("low"):
        if rep.channel is not None and rep.channel.kind == "output":
            print("   -> the error is on the SENSOR side (output(z)), not in a state equation: "
                  "z = (1 + c_z) z_model + c_abs |z_model| + c_1, a rectifying speed sensor")
        out["cli"] = cli_on_files(OUT, "drives", ced, Q_ced, R_ced, ["u", "z"],
                                  [u[est], z[est]], [u[val], z[val]])
    summary[rec.split()[0]] = out
save_summary(OUT, "drives", summary)
