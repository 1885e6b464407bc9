"""Silverbox: simulation RMS on the arrow test without extrapolation ([100:32100]), re-measured.

Goal (issue 12): <= 1 mV; published: good nonlinear models 0.3-1 mV, linear
10+ mV. The nominal linear model (k1/m, d/m, 1/m, input offset) is fitted
by output error, the input fed at the sample midpoint, as in
tutorials/04_measured_data.py, in two variants:

* ``arrow-start``: on the low-amplitude start of the arrow, [100:8100]
  (tutorial 04's choice; these samples are part of the test, so this
  variant is NOT a clean benchmark figure);
* ``estimation``: on the first estimation multisine [40650:48650] (clean;
  the cubic stiffness then biases the linear fit).

Then ``close_the_loop`` on the estimation multisine [40650:48650] (test of
the table: [49050:57050]), and the nominal and updated models simulated on
the arrow from sample 50 (state from y and its central difference), the RMS
taken over [100:32100].

A third row is the honest floor of this model structure: the Duffing ODE
``y'' = -(k1/m) y - (d/m) y' - (k3/m) y^3 + (1/m) (u - offset)`` with all
five parameters fitted jointly by output error on the estimation multisine
(the same input midpoint, held over the sample; RK4, 2 sub-steps), the
truth's structure with nothing else (no trace): what the arrow RMS of the
right law is with this discretization.

Run: ``python bench/silverbox_arrow.py`` (prints one table; ~1-3 min).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import lfilter, welch

import greybox as gb
from greybox.system import named_ss
from greybox.trace import simulate_with_law

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "silverbox" / "SNLS80mV.csv"


def duffing(p, uu, x0, dt, nsub=2):
    """Simulated y of y'' = -w2 y - c y' + k3 y^3 + b (u - off), u held per sample, RK4."""
    w2, c, b, off, k3 = (float(v) for v in p)
    h = dt / nsub
    yy, vv = float(x0[0]), float(x0[1])
    out = np.empty(len(uu))

    def f(a, v, uk):
        return v, -w2 * a - c * v + k3 * a * a * a + b * uk

    for j, uj in enumerate(uu):
        out[j] = yy
        uk = float(uj) - off
        for _ in range(nsub):
            a1, b1 = f(yy, vv, uk)
            a2, b2 = f(yy + h / 2 * a1, vv + h / 2 * b1, uk)
            a3, b3 = f(yy + h / 2 * a2, vv + h / 2 * b2, uk)
            a4, b4 = f(yy + h * a3, vv + h * b3, uk)
            yy += h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
            vv += h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
        if not abs(yy) < 1e3:
            out[j + 1:] = 1e3
            break
    return out


def main():
    if not DATA.is_file():
        print(f"{DATA} not present; nothing to do")
        return
    u_raw, y = np.loadtxt(DATA, delimiter=",", skiprows=1, usecols=(0, 1)).T
    dt = 2**14 / 1e7
    u_mid = np.r_[0.5 * (u_raw[:-1] + u_raw[1:]), u_raw[-1]]

    def oe_linear(p, uu):
        w2, c, b, off = p
        sd = gb.discretize(named_ss([[0, 1], [-w2, -c]], [[0], [b]], [[1, 0]], [[0]], 0,
                                    states=["y", "v"], inputs=["u"], outputs=["y"]), dt)
        A, B = np.asarray(sd.A), np.asarray(sd.B)[:, 0]
        num = np.r_[0, B[0], A[0, 1] * B[1] - A[1, 1] * B[0]]
        return lfilter(num, np.poly(A), uu - off)

    w0 = 2 * np.pi * 69.0
    f, Py = welch(y[40650:127400], 1 / dt, nperseg=4096)
    R = np.array([[Py[(f > 210) & (f < 260)].mean() * f[-1]]])
    Q = np.diag([0.0, 1e-3])
    est, val, arrow = slice(40650, 48650), slice(49050, 57050), slice(100, 32100)
    rows = []
    for variant, seg in (("arrow-start", slice(100, 8100)), ("estimation", est)):
        p0 = [w0**2, 2 * 0.044 * w0, w0**2, float(np.mean(u_raw))]
        w2, c_d, b_in, off = least_squares(
            lambda p: (oe_linear(p, u_mid[seg]) - y[seg])[200:], p0, x_scale="jac").x
        uc = u_mid - off
        sys = named_ss([[0, 1], [-w2, -c_d]], [[0], [b_in]], [[1, 0]], [[0]], 0,
                       states=["y", "v"], inputs=["u"], outputs=["y"], name="silverbox")
        t0 = time.time()
        rep = gb.close_the_loop(sys, y[None, est], uc[None, est], y[None, val], uc[None, val],
                                Q=Q, R=R, dt=dt, max_order=1, delta=False)
        took = time.time() - t0
        k = 50
        x0 = np.array([y[k], (y[k + 1] - y[k - 1]) / (2 * dt)])
        uu = uc[None, k:arrow.stop]
        yy = y[arrow]
        nominal = gb.discretize(sys, dt)
        x = np.empty((2, uu.shape[1]))
        xk = x0.copy()
        A, B = np.asarray(nominal.A), np.asarray(nominal.B)
        for j in range(uu.shape[1]):
            x[:, j] = xk
            xk = A @ xk + B[:, 0] * uu[0, j]
        y_nom = x[0, arrow.start - k:]
        if rep.updated and rep.effect.law is not None and rep.trace is not None:
            res = rep.trace.filter_result
            y_upd = simulate_with_law(res.sys, res.G, rep.effect.law, uu, x0)[0, arrow.start - k:]
        else:
            y_upd = y_nom
        rms = [1e3 * float(np.sqrt(np.mean((yy - s) ** 2))) for s in (y_nom, y_upd)]
        rows.append((variant, rep.effect.formula or "-", rep.table["nominal"].se.value,
                     rep.table["updated"].se.value, rms[0], rms[1], took))
    # the floor: the Duffing ODE fitted jointly by output error on the estimation data
    t0 = time.time()
    w2, c_d, b_in, off = least_squares(
        lambda p: (oe_linear(p, u_mid[est]) - y[est])[200:], p0, x_scale="jac").x
    p_lin = np.array([w2, c_d, b_in, off, -1e5])
    k = 50
    xa0 = np.array([y[k], (y[k + 1] - y[k - 1]) / (2 * dt)])
    xe0 = np.array([y[est.start], (y[est.start + 1] - y[est.start - 1]) / (2 * dt)])
    fit = least_squares(lambda p: (duffing(p, u_mid[est], xe0, dt) - y[est])[200:], p_lin,
                        x_scale="jac", max_nfev=60)
    y_duf = duffing(fit.x, u_mid[k:arrow.stop], xa0, dt)[arrow.start - k:]
    y_duf_val = duffing(fit.x, u_mid[val], np.array(
        [y[val.start], (y[val.start + 1] - y[val.start - 1]) / (2 * dt)]), dt)
    se_duf = float(gb.relative_error(y[None, val], y_duf_val[None], skip=20).value)
    rms_duf = 1e3 * float(np.sqrt(np.mean((y[arrow] - y_duf) ** 2)))
    rows.append(("estimation, Duffing ODE by output error (floor, no trace)",
                 f"k3/m = {fit.x[4]:.4g} 1/(V^2 s^2), k1/m = {fit.x[0]:.5g}, d/m = {fit.x[1]:.4g}",
                 float("nan"), se_duf, float("nan"), rms_duf, time.time() - t0))
    load = os.getloadavg()[0]
    print(f"Silverbox arrow test [100:32100], simulation RMS; load average {load:.1f}")
    print("| nominal fitted on | law (eq(v)) | validation SE nominal -> updated [%] | "
          "arrow RMS nominal [mV] | arrow RMS updated [mV] | close_the_loop [s] |")
    print("|---|---|---|---|---|---|")
    for v, law, s0, s1, r0, r1, tk in rows:
        print(f"| {v} | `{law}` | {s0:.3g} -> {s1:.3g} | {r0:.3g} | {r1:.3g} | {tk:.1f} |")
    print("(the last row's time is its output-error fit; its 'nominal' entries are n/a)")
    print("published: good nonlinear models 0.3-1 mV, linear 10+ mV; goal <= 1 mV")


if __name__ == "__main__":
    main()
