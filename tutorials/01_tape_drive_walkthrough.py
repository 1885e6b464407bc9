"""Tutorial 1: the tape-drive example of Gillijns & De Moor, end to end.

What this script does, with greybox's public functions only:

1. simulate the true tape drive (two DC motors, two wheels, one elastic tape);
2. run the Kalman filter that ignores the tape tension and the unknown-input
   filter that estimates it (the paper's Table II and Fig. 1);
3. identify the missing subsystem from the filter's record, static (order 0)
   and dynamic (order >= 1);
4. augment the nominal model with it (eqs. 30-31 with feedthrough);
5. build the paper's baseline, the parallel delta model (eqs. 21-24);
6. validate every model on fresh data (Table III) and print a table;
7. save the figures into ``$GREYBOX_TUTORIAL_OUT`` (default: a new temp dir).

Run it with ``python tutorials/01_tape_drive_walkthrough.py`` (20-40 s).
All errors are eq. (42) with the square root (relative RMS), averaged over the
six outputs, in percent. The setting (5 V inputs low-passed at 20 Hz, 2 s of
data, seed 2006) is greybox's documented choice: the paper gives none, so
compare orderings and distances to the true-model floor, not the paper's digits.
"""

# %% Imports and output folder
import os
import tempfile
import time
import warnings
from pathlib import Path

import matplotlib

matplotlib.use(os.environ.get("MPLBACKEND", "Agg"))
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import greybox as gb  # noqa: E402
from greybox.metrics import relative_error  # noqa: E402
from greybox.plotting import (  # noqa: E402
    plot_outputs,
    plot_residual_autocorrelation,
    plot_unknown_input,
)
from greybox.reproduce import PAPER_TABLE2, PAPER_TABLE3, TapeDriveSetting  # noqa: E402
from greybox.update import augment_model, delta_update, identify_subsystem  # noqa: E402
from greybox.validate import validate_model  # noqa: E402

OUT = Path(os.environ.get("GREYBOX_TUTORIAL_OUT") or tempfile.mkdtemp(prefix="greybox_tut1_"))
OUT.mkdir(parents=True, exist_ok=True)
t_start = time.perf_counter()

# %% 1. The plant and the nominal model
# The true drive has the tape tension T = K/2 (p2 - p1) + D r/2 (w2 - w1) acting
# on both wheels (restoring sign, PAPER_NOTES 8.1). The nominal model leaves the
# tension out but keeps it as a third input "T" entering through G: that is the
# channel the unknown-input filter estimates. Both are ZOH-discretized at 1e-4 s.
setting = TapeDriveSetting()          # nsteps=20000, 5 V, 20 Hz, seed 2006
dt = setting.dt
true = gb.tape_drive_true(dt=dt)
nominal = gb.tape_drive_nominal(dt=dt)            # inputs V1, V2, T
base = gb.split_inputs(nominal, "T").sys          # inputs V1, V2 only (initial model)
Q, R = gb.TAPE_DRIVE_Q, gb.TAPE_DRIVE_R           # the paper's noise covariances
print("states :", list(true.state_labels))
print("inputs :", list(nominal.input_labels), "(T = unknown tape tension [N])")
# Continuous-time poles: the tension couples the wheels. With Table I's
# friction (beta/J = 1000 1/s) the differential "tape" mode is overdamped.
print("poles true    [1/s]:", np.round(np.sort_complex(np.linalg.eigvals(
    np.asarray(gb.tape_drive_true().A))), 1))
print("poles nominal [1/s]:", np.round(np.sort_complex(np.linalg.eigvals(
    np.asarray(gb.tape_drive_nominal().A))), 1))

# %% 2. Estimation data: simulate the true drive
# Band-limited Gaussian voltages; the truth has process and measurement noise
# with the paper's Q and R, so the filters' noise model is exact.
rng = np.random.default_rng(setting.seed)
u = gb.lowpass_noise(setting.nsteps, dt=dt, bandwidth=setting.bandwidth, nsignals=2,
                     amplitude=setting.amplitude, rng=rng)
est = gb.simulate(true, u, Q=Q, R=R, rng=rng)
tension = gb.tape_drive_tension() @ est.x          # the true tension [N], shape (1, N)

# %% 3. Kalman filter vs unknown-input filter (Table II, Fig. 1)
kf = gb.kalman_filter(nominal, est.y, est.u, unknown="T", Q=Q, R=R)  # ignores T
uif = gb.uikf(nominal, est.y, est.u, unknown="T", Q=Q, R=R)          # estimates T
ee_kf = relative_error(est.y, kf.y_filt).value
ee_uif = relative_error(est.y, uif.y_filt).value
# d_est[:, j] estimates d[j] from y[j+1]; the last column is NaN.
err = uif.d_est[0, :-1] - tension[0, :-1]
cover = np.mean(np.abs(err) <= uif.d_halfwidth[0, :-1])
print("\nTable II - estimation error EE [%]      ours    paper")
print(f"  Kalman filter (ignores tension)   {ee_kf:8.2f} {PAPER_TABLE2['kalman_filter_ee']:8.1f}")
print(f"  unknown-input filter              {ee_uif:8.2f} "
      f"{PAPER_TABLE2['unknown_input_filter_ee']:8.1f}")
print(f"  tension RMS {np.sqrt(np.mean(tension**2)):.3f} N, estimate RMS error "
      f"{np.sqrt(np.mean(err**2)):.3f} N, 95% band covers the truth in {100 * cover:.1f}%")

# %% 4. Identify the missing subsystem from the filter's record
# Inputs of the subsystem: (u[j], x^[j|j]); output: d^[j]. These data are
# closed-loop (PAPER_NOTES 8.4): greybox uses least squares for order 0 and
# an output-error fit (the default) for order >= 1.
with warnings.catch_warnings():
    warnings.simplefilter("ignore", gb.GreyboxWarning)
    sub_auto = identify_subsystem(uif, max_order=1)            # BIC over orders 0, 1 (2, 3: slow)
    sub_static = identify_subsystem(uif, order=0)               # T = Ddx x + Ddu u
    sub_dynamic = identify_subsystem(uif, order=1)  # output-error, 1 state
print(f"\nBIC selects subsystem order {sub_auto.order} "
      f"(criterion per order: { {k: round(v) for k, v in sub_auto.criterion.items()} })")
cT = gb.tape_drive_tension()
print("static law  T = Ddx x + Ddu u")
print("  identified Ddx:", np.array2string(sub_static.Ddx[0], precision=4))
print("  physics c_T   :", np.array2string(cT[0], precision=4),
      "(continuous-time law, for comparison)")
print("  identified Ddu:", np.array2string(sub_static.Ddu[0], precision=4), "(physics: 0)")
print(f"dynamic candidate: order {sub_dynamic.order}, method {sub_dynamic.method}")

# %% 5. Augment the nominal model (eqs. 30-31 with feedthrough)
static = augment_model(nominal, sub_static, unknown="T", Q=Q, R=R)
dynamic = augment_model(nominal, sub_dynamic, unknown="T", Q=Q, R=R)
print(f"\nstatic update : order {static.order}, states {list(static.sys.state_labels)}")
print(f"dynamic update: order {dynamic.order}, states {list(dynamic.sys.state_labels)}")

# %% 6. The paper's baseline: a parallel delta model on the output error
with warnings.catch_warnings():
    warnings.simplefilter("ignore", gb.GreyboxWarning)
    delta = delta_update(base, est.y, est.u, Q=Q, R=R)
print(f"delta model   : order {delta.order} (combined {delta.updated.order}); "
      f"{delta.message}")

# %% 7. Validate on fresh data (Table III)
# New seed, same input statistics, no process noise in the truth (with it even
# the true model drifts along the wheel-position integrator, PAPER_NOTES 8.6).
rng_v = np.random.default_rng(setting.seed + 1)
u_v = gb.lowpass_noise(setting.nsteps, dt=dt, bandwidth=setting.bandwidth, nsignals=2,
                       amplitude=setting.amplitude, rng=rng_v)
val = gb.simulate(true, u_v, R=R, rng=rng_v)
rows = {
    "initial": validate_model(base, val.y, val.u, Q=Q, R=R, name="initial"),
    "static update": validate_model(static.sys, val.y, val.u, Q=static.Q, R=static.R,
                                    name="static update"),
    "dynamic update": validate_model(dynamic.sys, val.y, val.u, Q=dynamic.Q, R=dynamic.R,
                                     name="dynamic update"),
    "parallel (delta)": validate_model(delta.updated.sys, val.y, val.u, Q=delta.updated.Q,
                                       R=delta.updated.R, name="parallel (delta)"),
    "true model": validate_model(true, val.y, val.u, Q=Q, R=R, name="true model"),
}
paper = {"initial": PAPER_TABLE3["initial"], "dynamic update": PAPER_TABLE3["dynamic"],
         "parallel (delta)": PAPER_TABLE3["parallel"]}
print("\nTable III - validation on fresh data [%]")
print(f"  {'model':<18}{'order':>6}{'SE':>8}{'PE':>8}   paper order/SE/PE")
for name, v in rows.items():
    ref = paper.get(name)
    ref_s = f"{ref['order']} / {ref['se']} / {ref['pe']}" if ref else "-"
    print(f"  {name:<18}{v.order:>6}{v.se.value:>8.2f}{v.pe.value:>8.2f}   {ref_s}")
print("  (PE uses each model's own Q, R; the truth has no process noise here, so the\n"
      "   predictors' Q is overstated and no residual is white, PAPER_NOTES 8.8)")

# %% 8. Figures
figures = {}
arts = plot_unknown_input(uif, "T", d_true=tension, window=(1750, 2250))
arts["ax"].set_title("Fig. 1: true and estimated tape tension")
arts["ax"].set_ylabel("tape tension T [N]")
figures["fig1_tension"] = arts["figure"]

arts = plot_residual_autocorrelation([rows["initial"], rows["static update"]])
figures["fig2_autocorrelation"] = arts["figure"]

arts = plot_outputs(val.y, [rows["initial"], rows["static update"], rows["parallel (delta)"]],
                    outputs=[2, 3, 4, 5], dt=dt, window=(0, 5000))
arts["axes"][0].set_title("validation data: measured vs simulated outputs")
figures["fig3_outputs"] = arts["figure"]

for name, fig in figures.items():
    path = OUT / f"{name}.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    print(f"saved {path}")
print(f"done in {time.perf_counter() - t_start:.1f} s")
