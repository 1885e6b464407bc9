"""Shared helpers of the real-data tutorials (04, 06, 07, 08, 09): not a tutorial itself.

Each real-data tutorial runs one set of ``../shared/data`` through
:func:`greybox.close_the_loop` and through ``greybox update`` on files it
writes, prints the verdict and the before/after table, saves a figure and a
JSON summary (asserted by ``tests/test_real_sets.py``). What they share is
here: where the data and the outputs are, the table's rows (SE and PE, eq.
42, and the simulation RMS in the data's units, from sample ``SKIP`` on), the
figure, the CSV writer and the command-line run; for the two position-only
sets (EMPS, Silverbox) a look inside the velocity equation's channel.

The steps every set goes through:

1. the nominal physical model (structure from the data's README; its few
   unknown nominal parameters fitted by least squares on the ESTIMATION data
   only, on samples where the nominal model holds: stated in each tutorial).
   Two exceptions: EMPS uses the published M, Fv, gtau; the Silverbox's
   linear part is fitted on the low-amplitude start of the arrow, which lies
   inside its test range (its test figure is not clean; the clean variant,
   fitted on an estimation multisine: ``bench/silverbox_arrow.py``);
2. Q and R from one stated rule (never from the test data): R from the
   sensor (resolution, quantization step or the stated SNR, per set) and
   Q = R * I per sample, process noise of the sensor noise's order (EMPS
   and the Silverbox state their own Q: the nominal force residual, 1e-3). The model
   error is what the trace is for: a Q as large as the nominal model's
   one-step equation residual would call all of it noise (tried on the
   exchanger: the trace then reports "d^ is mostly estimation noise" and an
   empty law);
3. :func:`greybox.close_the_loop` end to end, its verdict in physical words;
4. before/after on the official test split: SE and PE (eq. 42, relative
   RMS, %) and the simulation RMS in the data's units, from sample 20 on
   (every row's simulation starts from the filter's state there);
5. ``greybox update`` on the MODEL.json / MODEL.py and CSV files the
   tutorial writes, so that the command line runs on real files (its
   verdict must equal the one call's);
6. a figure (the measured test output beside each model's simulation) and
   a JSON summary (``tests/test_real_sets.py`` asserts on it).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import greybox as gb
from greybox.trace import aligned, law_terms, resolve_channel_spec, simulate_with_law, trace_channel
from greybox.model_io import write_model
from greybox.trace.intervals import hac_covariance

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
REPO = Path(__file__).resolve().parents[1]
SKIP = 20


def data_or_exit(*folders):
    """Exit 0 with a message when a data folder is absent (the tutorial has nothing to do)."""
    if not all((DATA / f).is_dir() for f in folders):
        print(f"measured data not found under {DATA}; nothing to do")
        sys.exit(0)


def out_dir(prefix):
    """Where figures, files and the summary go: $GREYBOX_TUTORIAL_OUT or a new temporary folder."""
    out = Path(os.environ.get("GREYBOX_TUTORIAL_OUT") or tempfile.mkdtemp(prefix=prefix))
    out.mkdir(parents=True, exist_ok=True)
    return out


def save_summary(out, name, summary):
    """Write ``<name>_summary.json`` under out (what the tests assert on)."""
    path = out / f"{name}_summary.json"
    path.write_text(json.dumps(summary, indent=1, default=float))
    print("\nsaved", path)


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


def figure(rep, y_val, dt, units, title, path):
    """Measured test output beside every row of the report's table, saved to ``path``."""
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
    fig.savefig(path, dpi=100)
    plt.close(fig)
    print("   saved", path)


def write_csv(path, names, signals):
    """A measurement CSV: a header naming the signals, one row per sample."""
    np.savetxt(path, np.asarray(signals).T, delimiter=",", header=",".join(names), comments="",
               fmt="%.10g")


def cli(model, est_csv, val_csv, report):
    """``greybox update MODEL EST --validate VAL --json`` as a user runs it; its summary."""
    env = dict(os.environ, MPLBACKEND="Agg",
               PYTHONPATH=os.pathsep.join([str(REPO)] + [p for p in
                                                         [os.environ.get("PYTHONPATH")] if p]))
    cmd = [sys.executable, "-m", "greybox", "update", str(model), str(est_csv), "--validate",
           str(val_csv), "--out", str(report), "--json", "--no-plots", "--force"]
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


def verdict(rep):
    """The one call's verdict as every summary records it (channel None when unchanged)."""
    return {"message": rep.message, "updated": rep.updated,
            "detected": rep.model_error_detected,
            "channel": rep.channel.name if rep.channel is not None else None}


def cli_on_files(out, name, model, Q, R, names, est, test, Ts=None):
    """Write ``<name>_MODEL.json`` and the estimation/test CSVs, then run :func:`cli` on them.

    ``names``: the CSV's columns (inputs, then outputs); ``est``, ``test``:
    the signals in that order. Returns :func:`cli`'s summary.
    """
    paths = [out / f"{name}_{s}" for s in ("MODEL.json", "estimation.csv", "test.csv")]
    write_model(paths[0], model, Q, R, Ts=Ts)
    write_csv(paths[1], names, est)
    write_csv(paths[2], names, test)
    return cli(*paths, out / f"{name}_report")


def terms_of(law):
    """{term name: (coefficient, 95 % half-width)} of a static law's selected terms."""
    names = [sp[0] for sp in law.spec]
    return {names[j]: (float(law.coef[0, j]), float(law.ci[0, j]))
            for j in np.flatnonzero(law.coef[0])}


# ------------------------------------------------- inside eq(v) (EMPS, Silverbox)
def inside(sys_c, y, u, Q, R, dt, channel="eq(v)", skip=50):
    """trace_channel on one channel: the r = 1 filter's d^ and the delayed, smoothed d^."""
    ch = [c for c in resolve_channel_spec(sys_c, None) if c.name == channel][0]
    tr = trace_channel(sys_c, ch, y, u, Q=Q, R=R, dt=dt, max_order=0)
    d1 = tr.filter_result.d_est[0, skip:-1]
    est = tr.law_estimate
    w, _ = gb.input_weights(tr.model, unknown=list(ch.labels), r=tr.relative_degree,
                            continuous=(np.asarray(sys_c.A), ch.G))
    # the law's terms as d^ sees them: weighted over the samples d^[j] averages
    last_d = np.flatnonzero(np.isfinite(est.d_est[0]))[-1]
    last_x = np.flatnonzero(np.all(np.isfinite(est.x_filt), axis=0))[-1]
    K = min(last_d + 1, last_x - len(w) + 2) - skip
    d2 = est.d_est[0, skip:skip + K]
    xs = est.x_filt[:, skip:skip + K + len(w) - 1]
    us = u[:, skip:skip + K + len(w) - 1]
    terms, spec, eps = law_terms(xs, us, sys_c.state_labels, sys_c.input_labels)
    return dict(trace=tr, d1=d1, d2=d2, r=tr.relative_degree, w=w[:, 0, 0],
                lag1=float(np.corrcoef(d1[1:], d1[:-1])[0, 1]),
                lag1_2=float(np.corrcoef(d2[1:], d2[:-1])[0, 1]), var1=d1.var(),
                var2=d2.var(), pd2=float(np.mean(est.d_var[0, skip:skip + K])),
                terms=aligned(terms, w[:, 0, 0]), names=[sp[0] for sp in spec], eps=eps,
                x=aligned(xs, w[:, 0, 0]))


def fit_terms(info, names):
    """Least squares of d^ on the named aligned terms, with 95 % HAC half-widths."""
    X = np.array([info["terms"][info["names"].index(nm)] for nm in names])
    d = info["d2"]
    th = np.linalg.lstsq(X.T, d, rcond=None)[0]
    sx = np.sqrt(np.mean(X**2, axis=1))
    cov = hac_covariance((X / sx[:, None]).T, d - th @ X, 1) / np.outer(sx, sx)
    return th, 1.96 * np.sqrt(np.diag(cov))


def simulate_law(info, law, u, x0):
    """Simulate the nominal model plus ``law`` as the trace does (first-order hold of the law)."""
    res = info["trace"].filter_result
    return simulate_with_law(res.sys, res.G, law, u, x0)


def with_terms(law, names, values):
    """``law`` with only the named terms, at the given coefficients."""
    spec = [sp[0] for sp in law.spec]
    coef = np.zeros_like(law.coef)
    for nm, v in zip(names, values):
        coef[0, spec.index(nm)] = v
    return replace(law, coef=coef)


def se(y, ysim, skip=20):
    return float(gb.relative_error(y, ysim, skip=skip).value)
