"""Silverbox: simulation RMS on the arrow test without extrapolation ([100:32100]), re-measured.

Goal (issue 12): <= 1 mV; published: good nonlinear models 0.3-1 mV, linear
10+ mV. The nominal linear model (k1/m, d/m, 1/m, input offset) is fitted
by output error, as in tutorials/06_silverbox.py, on two segments:

* ``arrow-start``: on the low-amplitude start of the arrow, [100:8100]
  (tutorial 06's choice; these samples are part of the test, so this
  variant is NOT a clean benchmark figure);
* ``estimation``: on the first estimation multisine [40650:48650] (clean;
  the cubic stiffness then biases the linear fit, which the law corrects);

and with two treatments of the input between samples:

* ``midpoint held``: (u[k] + u[k+1]) / 2 held over the sample (the old choice);
* ``ZOH equivalent``: :func:`greybox.zoh_equivalent_input` of the nominal
  (fitted with the midpoint first, then refitted once with its equivalent:
  a fixed point to 1e-6): the data README describes the input as
  band-limited (filtered noise, multisines), not held.

Then ``close_the_loop`` on the estimation multisine [40650:48650] (test of
the table: [49050:57050]), and the nominal and updated models simulated on
the arrow from sample 50 (state from y and its central difference), the RMS
taken over [100:32100].

Two more rows are this model structure's floor: the Duffing ODE
``y'' = -(k1/m) y - (d/m) y' + (k3/m) y^3 + (1/m) (u - offset)`` with all
five parameters fitted jointly by output error on the estimation multisine
(RK4, 2 sub-steps), the input midpoint held or band-limited (DFT
interpolation), the truth's structure with nothing else (no trace).
bench/silverbox_structures.py has the other candidate structures' floors.

Measured (load 3.2, 2 cores, 40 s in all): midpoint held 1.47 mV (arrow-start)
and 1.48 mV (estimation), the Duffing floor 1.48 mV; ZOH equivalent
**0.304 mV** (arrow-start; law y^3, |y|, v^3 + linear corrections) and
**0.445 mV** (estimation, the clean figure); the Duffing floor with the
band-limited input 0.357 mV.

Run: ``python bench/silverbox_arrow.py`` (prints one table; ~1 min).
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
from silverbox_structures import fit, held, quarter_grid  # noqa: E402  (bench/ is on sys.path)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "silverbox" / "SNLS80mV.csv"


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

    def nominal(p):
        return named_ss([[0, 1], [-p[0], -p[1]]], [[0], [p[2]]], [[1, 0]], [[0]], 0,
                        states=["y", "v"], inputs=["u"], outputs=["y"], name="silverbox")

    w0 = 2 * np.pi * 69.0
    f, Py = welch(y[40650:127400], 1 / dt, nperseg=4096)
    R = np.array([[Py[(f > 210) & (f < 260)].mean() * f[-1]]])
    Q = np.diag([0.0, 1e-3])
    est, val, arrow = slice(40650, 48650), slice(49050, 57050), slice(100, 32100)
    rows, innov = [], []
    cases = [(v, seg, how) for how in ("midpoint held", "ZOH equivalent")
             for v, seg in (("arrow-start", slice(100, 8100)), ("estimation", est))]
    for variant, seg, how in cases:
        p0 = [w0**2, 2 * 0.044 * w0, w0**2, float(np.mean(u_raw))]
        p = least_squares(lambda p: (oe_linear(p, u_mid[seg]) - y[seg])[200:], p0,
                          x_scale="jac").x
        u_in = u_mid
        if how == "ZOH equivalent":   # band-limited input: its ZOH equivalent, nominal refitted
            u_in = gb.zoh_equivalent_input(nominal(p), u_raw, dt)[0]
            p = least_squares(lambda q: (oe_linear(q, u_in[seg]) - y[seg])[200:], p,
                              x_scale="jac").x
        w2, c_d, b_in, off = p
        uc = u_in - off
        sys = nominal(p)
        t0 = time.time()
        rep = gb.close_the_loop(sys, y[None, est], uc[None, est], y[None, val], uc[None, val],
                                Q=Q, R=R, dt=dt, max_order=1, delta=False)
        took = time.time() - t0
        k = 50
        x0 = np.array([y[k], (y[k + 1] - y[k - 1]) / (2 * dt)])
        uu = uc[None, k:arrow.stop]
        yy = y[arrow]
        nom_d = gb.discretize(sys, dt)
        x = np.empty((2, uu.shape[1]))
        xk = x0.copy()
        A, B = np.asarray(nom_d.A), np.asarray(nom_d.B)
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
        rows.append((f"{variant}, {how}", rep.effect.formula or "-", rep.table["nominal"].se.value,
                     rep.table["updated"].se.value, rms[0], rms[1], took))
        if rep.updated and rep.effect.law is not None and rep.trace is not None:
            innov.append((f"{variant}, {how}",) + innovations(rep, y, uc, est, dt, R))
    # the floor: the Duffing ODE fitted jointly by output error on the estimation data, the
    # input midpoint held and band-limited (bench/silverbox_structures.py: every structure)
    for how in ("midpoint held", "band-limited"):
        t0 = time.time()
        src = (lambda x: held(np.r_[0.5 * (x[:-1] + x[1:]), x[-1]])) if how == "midpoint held" \
            else (lambda x: quarter_grid(x, "band-limited"))
        p_duf = np.array([1.844e5, 41.6, 2.015e5, 5.4e-3, -7.38e5])
        px, rms3, se_duf, _ = fit("Duffing", (src, u_raw, src(u_raw)), y, p_duf)
        rows.append((f"estimation, Duffing ODE by output error, input {how} (floor, no trace)",
                     f"k3/m = {px[4]:.4g} 1/(V^2 s^2), k1/m = {px[0]:.5g}, d/m = {px[1]:.4g}",
                     float("nan"), se_duf, float("nan"), rms3[2], time.time() - t0))
    load = os.getloadavg()[0]
    print(f"Silverbox arrow test [100:32100], simulation RMS; load average {load:.1f}")
    print("| nominal fitted on | law (eq(v)) | validation SE nominal -> updated [%] | "
          "arrow RMS nominal [mV] | arrow RMS updated [mV] | close_the_loop [s] |")
    print("|---|---|---|---|---|---|")
    for v, law, s0, s1, r0, r1, tk in rows:
        print(f"| {v} | `{law}` | {s0:.3g} -> {s1:.3g} | {r0:.3g} | {r1:.3g} | {tk:.1f} |")
    print("(the last rows' time is their output-error fit; their 'nominal' entries are n/a)")
    print("published: good nonlinear models 0.3-1 mV, linear 10+ mV; goal <= 1 mV")
    print("\nThe updated model's innovations on the estimation data (extended Kalman filter on "
          "the law, greybox.trace.ekf_predict_with_law, Q of the report, from sample 50):")
    print("| nominal fitted on | innovations RMS [mV] | Ljung-Box statistic, 20 lags (white "
          "below 45.3) | max \\|corr(u[k-l], e[k])\\|, \\|l\\| <= 20 | its 99 % band |")
    print("|---|---|---|---|---|")
    for v, rms_e, lb, xc, band in innov:
        print(f"| {v} | {rms_e:.3g} | {lb:.0f} | {xc:.3f} | {band:.3f} |")


def innovations(rep, y, uc, est, dt, R):
    """The updated model's innovations on ``est``: RMS [mV], Ljung-Box, input correlation, band."""
    from greybox.metrics import correlation_band, cross_correlation
    from greybox.trace import ekf_predict_with_law
    res = rep.trace.filter_result
    x0 = np.array([y[est.start], (y[est.start + 1] - y[est.start - 1]) / (2 * dt)])
    yp = ekf_predict_with_law(res.sys, res.G, rep.effect.law, y[None, est], uc[None, est], x0,
                              Q=np.asarray(rep.model.Q), R=R)
    e = (y[None, est] - yp)[:, 50:]
    wt = gb.whiteness_test(e, 20)
    xc = np.abs(cross_correlation(uc[None, est][:, 50:], e, 20)).max()
    return (1e3 * float(np.sqrt(np.mean(e**2))), float(wt.statistic[0]), float(xc),
            correlation_band(e.shape[1], 0.99))


if __name__ == "__main__":
    main()
