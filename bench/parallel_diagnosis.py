"""Why the parallel delta baseline stays above the paper's 6.7 % on the tape
drive (issue 9): the estimation data, not the method, set the limit.

For each seed (default 2006-2010; Table III's setting: 20 000 samples, 5 V
inputs below 20 Hz, validation on seed + 1 without process noise) it prints
the validation SE (eq. 42, relative RMS, mean over 6 outputs) [%] of

* ``initial``: the nominal model;
* ``delta clean``, ``delta meas``, ``delta full``: ``delta_update`` defaults on
  estimation data without noise, with measurement noise only, and with the
  paper's process and measurement noise (Table III's setting);
* ``oracle``: the delta model with the *exact* poles of ``G_true - G_nominal``
  (minimal order 6, one of them the nominal's differential integrator, held
  at 1), full residue matrices fitted by the same prediction-error least
  squares as ``delta_update`` (noise model: the nominal's Kalman predictor)
  on the full-noise data: no pole or order error, only the residues' noise;
* ``oracle (true noise)``: the same with the *true* model's Kalman predictor
  as the noise model (the efficient weighting);
* ``true model``: the floor.

Also: RMS of the output error ``dy = y - y_nominal`` without noise, and of
the noise in ``dy`` (process + measurement), per output group, to show the
signal-to-noise ratio of the delta model's estimation data.

Run: ``python bench/parallel_diagnosis.py [seed ...]`` (load average printed;
about 1-3 min per seed on the shared 2-core machine).
"""

import os
import sys
import time
import warnings

import control as ct
import numpy as np

from greybox.exceptions import GreyboxWarning
from greybox.metrics import relative_error
from greybox.plants.tape_drive import (
    TAPE_DRIVE_Q,
    TAPE_DRIVE_R,
    tape_drive_nominal,
    tape_drive_true,
)
from greybox.reproduce import TapeDriveSetting
from greybox.signals import lowpass_noise, simulate
from greybox.system import split_inputs
from greybox.update import _fit_delta, _held_integrators, _Whitener, delta_update
from greybox.validate import simulate_output

S = TapeDriveSetting()
true = tape_drive_true(dt=S.dt)
base = split_inputs(tape_drive_nominal(dt=S.dt), "T").sys


def record(seed, process_noise, meas_noise):
    rng = np.random.default_rng(seed)
    u = lowpass_noise(S.nsteps, dt=S.dt, bandwidth=S.bandwidth, nsignals=2,
                      amplitude=S.amplitude, rng=rng)
    sim = simulate(true, u, Q=TAPE_DRIVE_Q if process_noise else None,
                   R=TAPE_DRIVE_R if meas_noise else None, rng=rng)
    return sim.y, u


def exact_delta_poles():
    At, Bt, Ct = (np.asarray(a) for a in (true.A, true.B, true.C))
    An, Bn, Cn = (np.asarray(a) for a in (base.A, base.B, base.C))
    d = ct.ss(np.block([[At, np.zeros((6, 6))], [np.zeros((6, 6)), An]]), np.vstack([Bt, Bn]),
              np.hstack([Ct, -Cn]), 0, S.dt)
    lam = np.linalg.eigvals(ct.minreal(d, tol=1e-9, verbose=False).A).astype(complex)
    return lam[(lam.imag >= 0) & (np.abs(lam - 1) > 1e-9)]


def main(seeds):
    print(f"load average at start: {os.getloadavg()[0]:.1f}")
    poles = exact_delta_poles()
    print(f"exact delta: minimal order 6, stable poles {np.round(poles, 4)} and 1")
    A, C = np.asarray(base.A), np.asarray(base.C)
    held = _held_integrators(A, C)
    wh_nom = _Whitener(base, TAPE_DRIVE_Q, TAPE_DRIVE_R)
    wh_true = _Whitener(true, TAPE_DRIVE_Q, TAPE_DRIVE_R)
    cols = ("initial", "delta clean", "delta meas", "delta full", "oracle",
            "oracle (true noise)", "true model")
    print("| seed | " + " | ".join(cols) + " | dy RMS I/p/w | noise RMS I/p/w | time [s] |")
    print("|" + "---|" * (len(cols) + 4))
    table = {c: [] for c in cols}
    for seed in seeds:
        t0 = time.perf_counter()
        rng = np.random.default_rng(seed + 1)
        uv = lowpass_noise(S.nsteps, dt=S.dt, bandwidth=S.bandwidth, nsignals=2,
                           amplitude=S.amplitude, rng=rng)
        yv = simulate(true, uv, R=TAPE_DRIVE_R, rng=rng).y
        yv0 = simulate_output(base, uv)
        row = {"initial": relative_error(yv, yv0).value,
               "true model": relative_error(yv, simulate_output(true, uv)).value}
        for col, pn, mn in (("delta clean", False, False), ("delta meas", False, True),
                            ("delta full", True, True)):
            y, u = record(seed, pn, mn)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", GreyboxWarning)
                dm = delta_update(base, y, u, Q=TAPE_DRIVE_Q, R=TAPE_DRIVE_R)
            row[col] = relative_error(yv, simulate_output(dm.updated.sys, uv)).value
        y, u = record(seed, True, True)
        yc, _ = record(seed, False, False)
        dy = y - simulate_output(base, u)
        for col, wh in (("oracle", wh_nom), ("oracle (true noise)", wh_true)):
            fit = _fit_delta(wh, poles, held, u, wh.apply(dy))
            row[col] = relative_error(yv, yv0 + fit.predict(uv)).value
        sig = np.sqrt(np.mean((yc - simulate_output(base, u)) ** 2, axis=1))
        noise = np.sqrt(np.mean((y - yc) ** 2, axis=1))
        grp = lambda v: "/".join(f"{v[i]:.3g}" for i in (0, 2, 4))  # noqa: E731
        for c in cols:
            table[c].append(row[c])
        print(f"| {seed} | " + " | ".join(f"{row[c]:.2f}" for c in cols)
              + f" | {grp(sig)} | {grp(noise)} | {time.perf_counter() - t0:.0f} "
              f"(load {os.getloadavg()[0]:.1f}) |", flush=True)
    print("| median | " + " | ".join(f"{np.median(table[c]):.2f}" for c in cols) + " | | | |")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or list(range(2006, 2011)))
