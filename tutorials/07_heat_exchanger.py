"""Tutorial 07: the heat exchanger (DaISy 97-002), REAL data, through the one call and the CLI.

One REAL measured system from ``../shared/data`` (read its folder's README), on
the benchmark's official estimation/test split, through the steps every
real-data tutorial takes (the nominal model fitted on estimation data only,
Q and R from one rule, ``close_the_loop``, before/after on the test split,
``greybox update`` on written files, a figure and a JSON summary: listed in
``_real_data.py``). The files ``greybox update`` reads hold the
deviations from the estimation means (q - q0, T - T0, the flow advanced as
below).

**Heat exchanger** (Ts = 1 s, 4000 samples; no official split: the common
one, estimation [0:2800], test [2800:4000]). Nominal: the linearized
energy balance, a first-order lag ``dT/dt = -a T + b q`` in deviations from
the estimation means; a, b by output error on the whole estimation record.
Timing: the increments T[k+1] - T[k] correlate with q[k+1] (-0.67) and not
with q[k] (-0.06) on the estimation data, so the flow sample q[k+1] is the
flow that acts during (k, k+1]: the input is advanced by one sample.
R = (0.01 degC)^2 (the record has 1e-4 degC resolution and is constant to
it over its first 40 samples at rest: 0.01 degC bounds the sensor noise).
Omitted effect (README): flow-dependent gain and time constant, the
bilinear q*T term of the energy balance.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _real_data, beside this file
from _real_data import (  # noqa: E402
    DATA, SKIP, cli_on_files, data_or_exit, figure, out_dir, save_summary, show, terms_of,
    verdict)

data_or_exit("daisy_exchanger")

from scipy.optimize import least_squares  # noqa: E402
from scipy.signal import lfilter  # noqa: E402

import greybox as gb  # noqa: E402
from greybox.system import named_ss  # noqa: E402
from greybox.trace import resolve_channel_spec, simulate_with_law, trace_channel  # noqa: E402

OUT = out_dir("greybox07_")

# %% Heat exchanger ------------------------------------------------------------------------
print("=== Heat exchanger (DaISy 97-002, steam-heated liquid, Ts = 1 s) ===")
d = np.loadtxt(DATA / "daisy_exchanger" / "exchanger.csv", delimiter=",", skiprows=1)
q, T = d[:, 1], d[:, 2]
est, val = slice(0, 2800), slice(2800, 4000)
dT_inc = np.diff(T[est])
corr = {lag: float(np.corrcoef(dT_inc[10:-2], (q - q.mean())[10 + lag:est.stop - 1 + lag - 2])
                   [0, 1]) for lag in (0, 1)}
print(f"timing: corr(T[k+1]-T[k], q[k]) = {corr[0]:.2f}, with q[k+1] = {corr[1]:.2f} "
      f"-> input q[k+1] acts during (k, k+1]")
q_adv = np.r_[q[1:], q[-1]]
q0, T0 = q_adv[est].mean(), T[est].mean()
dq, dT = q_adv - q0, T - T0
dt = 1.0


def lag_model(p):
    return named_ss([[-p[0]]], [[p[1]]], [[1]], [[0]], 0, states=["T"], inputs=["q"],
                    outputs=["T"], name="exchanger")


def lag_sim(p, uu):
    sd = gb.discretize(lag_model(p), dt)
    return lfilter([0, float(sd.B[0, 0])], [1, -float(sd.A[0, 0])], uu)


fit = least_squares(lambda p: (lag_sim(p, dq[est]) - dT[est])[10:], [0.2, -3.5], x_scale="jac")
a_T, b_q = fit.x
hx = lag_model(fit.x)
sd = gb.discretize(hx, dt)
R_hx = np.array([[0.01**2]])
Q_hx = R_hx.copy()
print(f"nominal lag: dT/dt = -{a_T:.4g} T + ({b_q:.4g}) q  (time constant {1 / a_T:.3g} s, "
      f"gain {b_q / a_T:.3g} degC per flow unit; about q0 = {q0:.3f}, T0 = {T0:.2f} degC); "
      f"Q = {Q_hx[0, 0]:.3g} degC^2, R = {R_hx[0, 0]:g} degC^2")
t0 = time.time()
rep = gb.close_the_loop(hx, dT[None, est], dq[None, est], dT[None, val], dq[None, val],
                        Q=Q_hx, R=R_hx, dt=dt)
print(f"close_the_loop ({time.time() - t0:.1f} s):")
table = show(rep, dT[None, val], "degC")
figure(rep, dT[None, val], dt, "T - T0 [degC]", "heat exchanger, test [2800:4000]",
       OUT / "fig9_exchanger.png")
ch = [c for c in resolve_channel_spec(hx, None) if c.name == "eq(T)"][0]
tr = trace_channel(hx, ch, dT[None, est], dq[None, est], Q=Q_hx, R=R_hx, dt=dt, max_order=0)
law_terms_hx = terms_of(tr.static)
print("   inside eq(T): static law (on d^; refitted by output error where the simulation "
      "contradicts it):", tr.static.formula)
if "T*q" in law_terms_hx:
    c_, h_ = law_terms_hx["T*q"]
    print(f"   -> the bilinear energy-balance term T*q: {c_:.3g} +- {h_:.2g} 1/(s flow unit) "
          f"(the physics says negative: more flow, faster and smaller response)")
# what the static law would do on the test split if it were added anyway (forced, for the table)
y_forced = simulate_with_law(tr.filter_result.sys, tr.filter_result.G, tr.static,
                                dq[None, val], np.array([dT[val.start]]))
se_forced = float(gb.relative_error(dT[None, val], y_forced, skip=SKIP).value)
rms_forced = float(np.sqrt(np.mean((dT[None, val] - y_forced)[:, SKIP:] ** 2)))
print(f"   the static law added anyway (not what greybox does): test SE {se_forced:.3g} %, "
      f"RMS {rms_forced:.3g} degC")
summary = {**verdict(rep), "passed": rep.gate.get("passed"), "table": table,
           "eq_law": tr.static.formula, "eq_terms": law_terms_hx,
           "forced_static": {"se": se_forced, "rms": rms_forced},
           "candidates": [c.__dict__.copy() for c in rep.candidates],
           "cli": cli_on_files(OUT, "exchanger", hx, Q_hx, R_hx, ["q", "T"], [dq[est], dT[est]],
                               [dq[val], dT[val]], Ts=dt),
           "units": "degC",
           "nominal": {"a": float(a_T), "b": float(b_q)}}
save_summary(OUT, "exchanger", summary)
