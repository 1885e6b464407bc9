"""Tutorial 06: three more REAL measured systems, through the one call and the command line.

The heat exchanger (DaISy 97-002), the coupled electric drives (CE8) and the
cascaded tanks, each from ``../shared/data`` (read each folder's README), on
the benchmark's official estimation/test split. For each set:

1. the nominal physical model (structure from the data's README; its few
   unknown nominal parameters fitted by least squares on the ESTIMATION data
   only, on samples where the nominal model holds: stated per set);
2. Q and R from one stated rule (never from the test data): R from the
   sensor (resolution, quantization step or the stated SNR, per set) and
   Q = R * I per sample, process noise of the sensor noise's order. The model
   error is what the trace is for: a Q as large as the nominal model's
   one-step equation residual would call all of it noise (tried on the
   exchanger: the trace then reports "d^ is mostly estimation noise" and an
   empty law);
3. :func:`greybox.close_the_loop` end to end, its verdict in physical words;
4. before/after on the official test split: SE and PE (eq. 42, relative
   RMS, %) and the simulation RMS in the data's units, from sample 20 on
   (every row's simulation starts from the filter's state there);
5. ``greybox update`` on MODEL.json / MODEL.py and CSV files written here,
   so that the command line runs on real files (its verdict must equal the
   one call's); the exchanger's files hold the deviations from the
   estimation means (q - q0, T - T0, the flow advanced as below);
6. a figure per set: the measured test output beside each model's
   simulation (fig9_exchanger.png, fig10_drives_*.png, fig11_tanks.png).

Set-by-set choices (the README of each data folder is the source):

* **Heat exchanger** (Ts = 1 s, 4000 samples; no official split: the common
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
* **Coupled electric drives** (Ts = 20 ms, DATAUNIF, official split [:400]
  estimation, [400:] test, the low-amplitude record u11/z11; the
  high-amplitude record u12/z12 is run too). Nominal: the report's trusted
  reference linear part H(z) = 0.0414 / (z^3 - 2.6011 z^2 + 2.4060 z -
  0.7823) (README) in observer form with the pulley speed w as first state,
  its static gain rescaled by least squares on the estimation samples where
  the model's speed has been positive for 4 samples (where |w| = w, the
  nominal model holds): this record's gain is 0.37 of the PRBS reference's.
  R = one sensor quantization step squared (0.0049^2). Omitted effect: the rectifying |.| speed sensor (output side).
* **Cascaded tanks** (Ts = 4 s, estimation uEst/yEst, test uVal/yVal,
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
  the README ("Real data"); where the test error goes (not the initial
  state: the README's same state for both records is checked) is measured
  by ``bench/tanks_floors.py``.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SETS = ("daisy_exchanger", "coupled_electric_drives", "cascaded_tanks")
if not all((DATA / s).is_dir() for s in SETS):
    print(f"measured data not found under {DATA}; nothing to do")
    sys.exit(0)

import control as ct  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402
from scipy.signal import lfilter  # noqa: E402

import greybox as gb  # noqa: E402
from greybox.model_io import write_model  # noqa: E402
from greybox.system import named_ss  # noqa: E402
from greybox.trace import resolve_channel_spec, simulate_with_law, trace_channel  # noqa: E402

OUT = Path(os.environ.get("GREYBOX_TUTORIAL_OUT") or tempfile.mkdtemp(prefix="greybox06_"))
OUT.mkdir(parents=True, exist_ok=True)
REPO = Path(__file__).resolve().parents[1]
SKIP = 20
SUMMARY: dict = {}


def rows(rep, y_val):
    """SE, PE [%] and simulation RMS [data units] of every row of the report's table."""
    out = {}
    for name, v in rep.table.items():
        e = (y_val - v.y_sim)[:, SKIP:]
        out[name] = {"se": float(v.se.value), "pe": float(v.pe.value),
                     "rms": float(np.sqrt(np.mean(e**2))), "order": int(v.order)}
    return out


def show(rep, y_val, units):
    """Print the verdict, the candidates, the gate and the before/after table."""
    print("  ", rep.message)
    if rep.effect.formula:
        print("   law:", rep.effect.formula)
    for c in rep.candidates:
        why = f"  ({c.reason[:70]})" if c.reason else ""
        print(f"   candidate {c.channel:9s} {c.kind:17s} order {c.order}  estimation SE "
              f"{c.se_estimation:7.3g} %{why}")
    g = rep.gate
    print("   gate passed:", g.get("passed"))
    table = rows(rep, y_val)
    for name, r in table.items():
        print(f"   {name:<22} SE {r['se']:7.3g} %   PE {r['pe']:9.3g} %   simulation RMS "
              f"{r['rms']:.3g} {units}")
    return table


def figure(rep, y_val, dt, units, title, name):
    """Measured test output beside every row of the report's table; saved under OUT."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.2))
    t = np.arange(y_val.shape[1]) * dt
    ax.plot(t, y_val[0], "k", lw=1.2, label="measured (test)")
    for row, v in rep.table.items():
        if row == "updated" and not rep.updated:
            continue
        ax.plot(t[SKIP:], v.y_sim[0, SKIP:], lw=0.9, label=f"{row} (SE {v.se.value:.3g} %)")
    ax.set_xlabel("t [s]")
    ax.set_ylabel(units)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT / name, dpi=100)
    plt.close(fig)
    print("   saved", OUT / name)


def write_csv(path, names, signals):
    """A measurement CSV: a header naming the signals, one row per sample."""
    np.savetxt(path, np.asarray(signals).T, delimiter=",", header=",".join(names), comments="",
               fmt="%.10g")


def cli(model, est_csv, val_csv, name):
    """``greybox update MODEL EST --validate VAL --json`` as a user runs it; its summary."""
    env = dict(os.environ, MPLBACKEND="Agg",
               PYTHONPATH=os.pathsep.join([str(REPO)] + [p for p in
                                                         [os.environ.get("PYTHONPATH")] if p]))
    cmd = [sys.executable, "-m", "greybox", "update", str(model), str(est_csv), "--validate",
           str(val_csv), "--out", str(OUT / f"{name}_report"), "--json", "--no-plots", "--force"]
    t0 = time.time()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    print(f"   $ greybox update {Path(model).name} {Path(est_csv).name} --validate "
          f"{Path(val_csv).name} --json   (exit code {proc.returncode}, "
          f"{time.time() - t0:.1f} s)")
    if proc.returncode != 0:
        print(proc.stderr[-2000:])
        return {"exit_code": proc.returncode}
    s = json.loads(proc.stdout)
    print("   CLI verdict:", s["message"])
    return {"exit_code": 0, "message": s["message"], "channel": s["channel"],
            "updated": s["updated"], "formula": s["effect"]["formula"],
            "se": {k: v["se"]["value"] if isinstance(v["se"], dict) else v["se"]
                   for k, v in s["table"].items()}}


def terms_of(law):
    """{term name: (coefficient, 95 % half-width)} of a static law's selected terms."""
    names = [sp[0] for sp in law.spec]
    return {names[j]: (float(law.coef[0, j]), float(law.ci[0, j]))
            for j in np.flatnonzero(law.coef[0])}


# %% 1. Heat exchanger ------------------------------------------------------------------------
print("=== 1. Heat exchanger (DaISy 97-002, steam-heated liquid, Ts = 1 s) ===")
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
       "fig9_exchanger.png")
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
paths = [OUT / f"exchanger_{s}" for s in ("MODEL.json", "estimation.csv", "test.csv")]
write_model(paths[0], hx, Q_hx, R_hx, Ts=dt)
write_csv(paths[1], ["q", "T"], [dq[est], dT[est]])
write_csv(paths[2], ["q", "T"], [dq[val], dT[val]])
SUMMARY["exchanger"] = {"message": rep.message, "updated": rep.updated,
                        "detected": rep.model_error_detected,
                        "channel": rep.channel.name if rep.channel is not None else None,
                        "passed": rep.gate.get("passed"), "table": table,
                        "eq_law": tr.static.formula, "eq_terms": law_terms_hx,
                        "forced_static": {"se": se_forced, "rms": rms_forced},
                        "candidates": [c.__dict__.copy() for c in rep.candidates],
                        "cli": cli(*paths, "exchanger"), "units": "degC",
                        "nominal": {"a": float(a_T), "b": float(b_q)}}

# %% 2. Coupled electric drives ---------------------------------------------------------------
print("\n=== 2. Coupled electric drives (CE8, DATAUNIF, Ts = 20 ms) ===")
d = np.genfromtxt(DATA / "coupled_electric_drives" / "DATAUNIF.csv", delimiter=",",
                  skip_header=1)[:, :4]
den = np.array([1, -2.6011, 2.4060, -0.7823])       # the report's reference H(z), eq. 9
b_ref, dt = 0.0414, 0.02
est, val = slice(0, 400), slice(400, 500)
A_obs = np.array([[-den[1], 1, 0], [-den[2], 0, 1], [-den[3], 0, 0]])   # y = w = x[0]
SUMMARY["drives"] = {}
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
           f"fig10_drives_{rec.split()[0]}.png")
    out = {"message": rep.message, "updated": rep.updated, "detected": rep.model_error_detected,
           "channel": rep.channel.name if rep.channel is not None else None,
           "kind": rep.channel.kind if rep.channel is not None else None,
           "passed": rep.gate.get("passed"), "table": table, "gain": gain,
           "terms": terms_of(rep.effect.law) if rep.effect.law is not None else {},
           "formula": rep.effect.formula,
           "candidates": [c.__dict__.copy() for c in rep.candidates]}
    if rec.startswith("low"):
        if rep.channel is not None and rep.channel.kind == "output":
            print("   -> the error is on the SENSOR side (output(z)), not in a state equation: "
                  "z = (1 + c_z) z_model + c_abs |z_model| + c_1, a rectifying speed sensor")
        paths = [OUT / f"drives_{s}" for s in ("MODEL.json", "estimation.csv", "test.csv")]
        write_model(paths[0], ced, Q_ced, R_ced)
        write_csv(paths[1], ["u", "z"], [u[est], z[est]])
        write_csv(paths[2], ["u", "z"], [u[val], z[val]])
        out["cli"] = cli(*paths, "drives")
    SUMMARY["drives"][rec.split()[0]] = out

# %% 3. Cascaded tanks ------------------------------------------------------------------------
print("\n=== 3. Cascaded tanks (Ts = 4 s, Torricelli nominal as control.nlsys) ===")
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
MODEL_PY = f'''"""Cascaded tanks, Torricelli nominal (written by tutorials/06_real_data_sets.py)."""
import math
import control
import numpy as np

# fitted on the estimation record (tutorial 06); declared as params so that greybox refits
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
       "fig11_tanks.png")
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
SUMMARY["tanks"] = {"message": rep.message, "updated": rep.updated,
                    "detected": rep.model_error_detected,
                    "channel": rep.channel.name if rep.channel is not None else None,
                    "passed": rep.gate.get("passed"), "table": table, "k": kk.tolist(),
                    "rms_nominal_all_samples": rms_nom_all,
                    "rms_nominal_x0_floor": rms_nom_x0_floor,
                    "candidates": [c.__dict__.copy() for c in rep.candidates],
                    "best": best,
                    "gate": {k: float(np.min(v)) for k, v in rep.gate.items()
                             if k not in ("passed", "measure", "evidence")},
                    "evidence": rep.gate.get("evidence"),
                    "cli": cli(*paths, "tanks")}
if best is not None and best["channel"] == "eq(x1)":
    print("   -> the trace names the upper tank's equation eq(x1), a saturation of its level "
          "spilling into the lower tank, and the sensor offset as the parameter that moves; "
          "against the parameters refitted alone its evidence stays below the gate's "
          "(README, Real data)")

(OUT / "real_sets_summary.json").write_text(json.dumps(SUMMARY, indent=1, default=float))
print("\nsaved", OUT / "real_sets_summary.json")
