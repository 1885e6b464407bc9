"""Tutorial 09: the cascaded tanks, REAL data, a nonlinear Torricelli model, through the one call and the CLI.

One REAL measured system from ``../shared/data`` (read its folder's README), on
the benchmark's official estimation/test split, through the steps every
real-data tutorial takes (the nominal model fitted on estimation data only,
Q and R from one rule, ``close_the_loop``, before/after on the test split,
``greybox update`` on written files, a figure and a JSON summary: listed in
``_real_data.py``).

**Cascaded tanks** (Ts = 4 s, estimation uEst/yEst, test uVal/yVal,
1024 samples each). Nominal: Torricelli, ``dx1/dt = -k1 sqrt(x1) + k4 u``,
``dx2/dt = k2 sqrt(x1) - k3 sqrt(x2 - off)``, ``y = x2`` as a ``control.nlsys``,
discrete with dt = Ts (RK4, 4 sub-steps of 1 s inside the update: the
continuous form would get 260 sub-steps per sample from the library's
operating point, which puts the unmeasured x1 at 0 where sqrt is stiff).
k1..k4, the level sensor's offset (``y = x2``, the sensor's reading, the
level ``x2 - off``: the README calls the reading raw and uncalibrated; a
gain is absorbed by k1..k4, an offset is not, through the square roots)
and the initial state by output error on the estimation samples
with y < 9.9 V (the lower tank's sensor clips at 10 V: there the model
does not hold). R = (1 % of std(yEst))^2 (SNR 40 dB, README). Omitted effect: overflow of
the upper tank and the clip at 10 V. Only the lower tank is measured, so the
upper tank's equation eq(x1) reaches y two samples later (relative degree
2): the trace estimates it with the delayed unscented filter
(``greybox.delayed_ui_ukf``) and offers saturation hinges ``max(x1 - c, 0)``
to its law. MODEL.py declares k1, k2, k3 and the offset as ``params``
(k4 is kept: x1 is not measured, so only k4 pins its scale), and greybox
refits them jointly with the law, its hinge level and its spill into
eq(x2) (the data README: the overflow falls partly into the lower tank).
What it finds and why the gate still refuses it is printed below and in
``docs/results/real-data.md``; where the test error goes (not the initial
state: the README's same state for both records is checked) is measured
by ``bench/tanks_floors.py``.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _real_data, beside this file
from _real_data import (  # noqa: E402
    DATA, SKIP, cli, data_or_exit, figure, out_dir, save_summary, show, verdict, write_csv)

data_or_exit("cascaded_tanks")

from scipy.optimize import least_squares  # noqa: E402

import greybox as gb  # noqa: E402

OUT = out_dir("greybox09_")

# %% Cascaded tanks ------------------------------------------------------------------------
print("=== Cascaded tanks (Ts = 4 s, Torricelli nominal as control.nlsys) ===")
d = np.genfromtxt(DATA / "cascaded_tanks" / "dataBenchmark.csv", delimiter=",",
                  skip_header=1)[:, :4]
uE, uV, yE, yV = d.T
dt, NSUB = 4.0, 4


def tanks_sim(p, u):
    """Output-error simulation of the Torricelli model, RK4, NSUB sub-steps, u held.

    x2 is the lower tank's sensor reading [V], its level x2 - off (the sensor's offset).
    """
    k1, k2, k3, k4, x1, x2, off = p
    h = dt / NSUB
    out = np.empty(len(u))

    def f(a, b, uk):
        s1 = math.sqrt(max(a, 0.0))
        return -k1 * s1 + k4 * uk, k2 * s1 - k3 * math.sqrt(max(b - off, 0.0))

    for k, uk in enumerate(u):
        out[k] = x2
        for _ in range(NSUB):
            a1, b1 = f(x1, x2, uk)
            a2, b2 = f(x1 + h / 2 * a1, x2 + h / 2 * b1, uk)
            a3, b3 = f(x1 + h / 2 * a2, x2 + h / 2 * b2, uk)
            a4, b4 = f(x1 + h * a3, x2 + h * b3, uk)
            x1 += h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
            x2 += h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
    return out


holds = yE < 9.9
t0 = time.time()
fit = least_squares(lambda p: (tanks_sim(p, uE) - yE)[holds], [0.05, 0.05, 0.05, 0.05, 5, 5, 0],
                    x_scale="jac", bounds=([1e-4] * 4 + [0, 0, -10], [1] * 4 + [20, 20, 10]))
kk = fit.x
rms_nom_all = float(np.sqrt(np.mean((tanks_sim(kk, uV) - yV) ** 2)))
print(f"Torricelli fit on {holds.sum()} estimation samples with y < 9.9 V ({time.time() - t0:.1f}"
      f" s): k1..k4 = {np.round(kk[:4], 5)}, sensor offset {kk[6]:.3f} V; test simulation RMS "
      f"from the fitted initial state "
      f"(all 1024 samples): {rms_nom_all:.3f} V")
# where the test error is NOT: the initial state. The data README says both records start
# from the same unknown state, so the estimation fit's x(0) is reused above; a floor for any
# treatment of the initial state is x(0) fitted on the whole TEST output (not a test figure)
x0_floor = least_squares(lambda x: tanks_sim(np.r_[kk[:4], x, kk[6]], uV) - yV, kk[4:6],
                         x_scale="jac", bounds=([0, 0], [20, 20])).x
rms_nom_x0_floor = float(np.sqrt(np.mean(
    (tanks_sim(np.r_[kk[:4], x0_floor, kk[6]], uV) - yV) ** 2)))
print(f"   the same with x(0) fitted on the whole test output (a floor for the initial state, "
      f"not a test figure): {rms_nom_x0_floor:.3f} V: the initial state is not where the error "
      f"is (bench/tanks_floors.py)")
MODEL_PY = f'''"""Cascaded tanks, Torricelli nominal (written by tutorials/09_cascaded_tanks.py)."""
import math
import control
import numpy as np

# fitted on the estimation record (tutorial 09); declared as params so that greybox refits
# them with a law it adds. K4 is not declared: the upper level x1 is not measured, so its
# scale is free (k1, k2, k4 would only be determined as a combination); K4 pins it.
PARAMS = {{"k1": {float(kk[0])!r}, "k2": {float(kk[1])!r}, "k3": {float(kk[2])!r},
          "off": {float(kk[6])!r}}}  # off: the level sensor's offset [V]: the level is x2 - off
K4 = {float(kk[3])!r}
Ts, NSUB = {dt!r}, {NSUB}


def _update(t, x, u, params):
    k1, k2, k3, off = params["k1"], params["k2"], params["k3"], params["off"]
    x1, x2, uk, h = float(x[0]), float(x[1]), float(u[0]), Ts / NSUB

    def _f(a, b):
        s1 = math.sqrt(max(a, 0.0))
        return -k1 * s1 + K4 * uk, k2 * s1 - k3 * math.sqrt(max(b - off, 0.0))

    for _ in range(NSUB):
        a1, b1 = _f(x1, x2)
        a2, b2 = _f(x1 + h / 2 * a1, x2 + h / 2 * b1)
        a3, b3 = _f(x1 + h / 2 * a2, x2 + h / 2 * b2)
        a4, b4 = _f(x1 + h * a3, x2 + h * b3)
        x1 += h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
        x2 += h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
    return np.array([x1, x2])


model = control.nlsys(_update, lambda t, x, u, params: np.array([x[1]]), dt=Ts,
                      states=["x1", "x2"], inputs=["u"], outputs=["y"], name="tanks",
                      params=PARAMS)
R = np.array([[{float(0.01 * yE.std()) ** 2!r}]])
Q = R[0, 0] * np.eye(2)
'''
paths = [OUT / s for s in ("tanks_MODEL.py", "tanks_estimation.csv", "tanks_test.csv")]
paths[0].write_text(MODEL_PY, encoding="utf-8")
ns: dict = {}
exec(compile(MODEL_PY, str(paths[0]), "exec"), ns)     # the same model the CLI will read
tanks, Q_t, R_t = ns["model"], ns["Q"], ns["R"]
t0 = time.time()
rep = gb.close_the_loop(tanks, yE[None], uE[None], yV[None], uV[None], Q=Q_t, R=R_t, dt=dt)
print(f"close_the_loop ({time.time() - t0:.1f} s):")
table = show(rep, yV[None], "V")
figure(rep, yV[None], dt, "lower tank level y [V]", "cascaded tanks, test (uVal, yVal)",
       OUT / "fig11_tanks.png")
write_csv(paths[1], ["u", "y"], [uE, yE])
write_csv(paths[2], ["u", "y"], [uV, yV])
tr = rep.trace  # the best candidate, whether or not the gate let it through
best = None
if tr is not None and tr.static is not None:
    law = tr.static
    best = {"channel": tr.channel.name, "relative_degree": int(tr.relative_degree),
            "formula": law.formula,
            "terms": [[law.spec[j][0], law.spec[j][1], float(law.coef[0, j])]
                      for j in np.flatnonzero(law.coef[0])]}
    print(f"   best candidate: {tr.channel.name} (relative degree {tr.relative_degree}): "
          f"{law.formula}")
    # what the update would do on the test split if it were made anyway (forced): the
    # refused joint refit (the nominal's declared parameters refitted with the law and its
    # spill into eq(x2)) when there is one, else the Torricelli model plus the law; simulated
    # from the UKF's state at sample SKIP as the table's rows are
    refused = rep.nonlinear.refused if rep.nonlinear is not None else None
    forced = refused.model if refused is not None else gb.add_law(tanks, tr.channel.G,
                                                                  law.evaluate)
    kf_v = gb.ukf(forced, yV[None], uV[None], Q=Q_t, R=R_t, x0=[0.0, yV[0]])
    sim_v = gb.simulate_nonlinear(forced, uV[None, SKIP:], x0=kf_v.x_filt[:, SKIP])
    best["rms_forced"] = float(np.sqrt(np.mean((yV[SKIP:] - sim_v.x[1]) ** 2)))
    if refused is not None:
        best["parameters"] = [p.as_dict() for p in refused.parameters]
        best["spill"] = [list(s) for s in refused.spill]
        best["se_joint"] = refused.se
        print(f"   joint refit (refused by the gate): {refused.parameter_text()}; "
              f"{refused.spill_text()}")
    print(f"   the update made anyway (not what greybox does): test simulation RMS "
          f"{best['rms_forced']:.3g} V")
    g = rep.gate
    print(f"   gate: evidence {g['bic_gain']:.3g} (needs > {g['bic_factor']:g} x "
          f"{g['bic_penalty']:.3g}; {g['evidence']}); estimation SE "
          f"{g['se_estimation_nominal']:.3g} % -> {g['se_estimation_updated']:.3g} % "
          f"(needs < {g['min_se_drop']:g} x)")
summary = {**verdict(rep), "passed": rep.gate.get("passed"), "table": table, "k": kk.tolist(),
           "rms_nominal_all_samples": rms_nom_all,
           "rms_nominal_x0_floor": rms_nom_x0_floor,
           "candidates": [c.__dict__.copy() for c in rep.candidates],
           "best": best,
           "gate": {k: float(np.min(v)) for k, v in rep.gate.items()
                    if k not in ("passed", "measure", "evidence")},
           "evidence": rep.gate.get("evidence"),
           "cli": cli(*paths, OUT / "tanks_report")}
if best is not None and best["channel"] == "eq(x1)":
    print("   -> the trace names the upper tank's equation eq(x1), a saturation of its level "
          "spilling into the lower tank, and the sensor offset as the parameter that moves; "
          "against the parameters refitted alone its evidence stays below the gate's "
          "(docs/results/real-data.md)")

save_summary(OUT, "tanks", summary)
