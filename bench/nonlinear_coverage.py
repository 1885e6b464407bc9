"""Coverage of the 95 % intervals of the nonlinear pipeline's output-error laws, over seeds.

``python bench/nonlinear_coverage.py [case ...] [--seeds N]`` (default: every case, 20
seeds). Each case runs ``greybox.close_the_loop`` on a fresh record per seed and checks
whether the reported 95 % interval of the law's coefficient contains the truth:

``pendulum``
    the torque-driven pendulum of ``tests/test_workflow_nonlinear.py``, both angles
    measured, the cubic drag ``-0.5 omega^3`` omitted (r = 1 channel; the law refined by
    output error when that lowers the estimation SE).
``pendulum_pos``
    the same, theta alone measured: eq(omega) has relative degree 2 (the delayed filter);
    the chosen candidate's law (``rep.trace.static``), whether or not the gate took it.
    Each seed also gets a verdict (issue 12): ``right`` (updated with ``-c omega^3`` alone in
    eq(omega), c within its 95 % interval of 0.5), ``refused`` (no update) or ``WRONG``
    (another law accepted), and the true model (with its drag, theta alone) is run on the
    same records: ``unchanged`` or ``CHANGED``.
``overflow_soft``
    the two tanks of ``tests/test_tanks_overflow.py`` (lower tank measured) whose upper
    tank loses ``KO * max(x1 - XO, 0)`` above XO: a hinge the law can express, so its
    coefficient (and level) have a truth.
``overflow``
    the tests' hard clip at 8 (no true coefficient: the stiff hinge only stands in for
    it). Reported: the spread of the estimates over seeds against the stated half-widths
    (coverage of the seeds' median).

For the tank cases each seed also prints the law, the validation SE before/after and
the true model's, and a verdict: ``right`` (eq(x1), one upper hinge on x1 at the level
within 2 %), ``refused`` or ``WRONG`` (``overflow --seeds 10``; issue 12), and whether
the hinge level's 95 % interval (in the formula) covers 8. The verdicts and the level
coverage are counted per case at the end.

A case that names another law (or none) counts as a miss of the right law, not of the
interval; the coverage is over the seeds that named it. Printed per seed: estimate,
half-width, covered; then per case: covered/named with the 95 % binomial band of the
count for a calibrated 95 % interval, the ratio of the estimates' spread to the mean
stated standard error (1 when calibrated), time and the load average.
"""

from __future__ import annotations

import os
import re
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

import control as ct  # noqa: E402
import numpy as np  # noqa: E402
from scipy.stats import binom  # noqa: E402

import greybox as gb  # noqa: E402
from greybox.metrics import relative_error  # noqa: E402
from greybox.workflow_nonlinear import SKIP, close_the_loop_nonlinear  # noqa: E402
import test_tanks_overflow as tk  # noqa: E402
from test_workflow_nonlinear import C3, DT, QD, RM, pendulum, record  # noqa: E402

KO, XO = 0.1, 8.0
"""Soft overflow of the upper tank: coefficient [1/s] and level of the hinge."""


LEVELS = {}
"""Per tank case, whether each seed's hinge-level interval covers the truth (8)."""
VERDICTS = {}
"""Per case, the verdict of each seed: 'right' law, 'refused' (no update) or 'WRONG'."""


def _verdict(case, seed, rep, right: bool, line: str, se_true: float):
    v = "right" if rep.updated and right else "refused" if not rep.updated else "WRONG"
    VERDICTS.setdefault(case, []).append(v)
    print(f"{'':14s} seed {seed:2d}: {v:7s} {line}; validation SE "
          f"{rep.table['nominal'].se.value:.3g} % -> {rep.table['updated'].se.value:.3g} % "
          f"(true model {se_true:.3g} %)", flush=True)


def _theta_only(c3):
    return ct.nlsys(pendulum(c3).updfcn, lambda t, x, u, p: x[:1], states=["theta", "omega"],
                    inputs=["T"], outputs=["theta"], name="pendulum_theta_only")


def _pendulum(seed, positions_only):
    est = record(3000, seed, process_noise=True)
    val = record(2000, seed + 100, process_noise=False)
    if positions_only:
        rep = gb.close_the_loop(_theta_only(0.0), est.y[:1], est.u, val.y[:1], val.u, Q=QD,
                                R=RM[:1, :1], dt=DT)
        law = rep.trace.static if rep.trace is not None else None
        true = gb.close_the_loop(_theta_only(C3), est.y[:1], est.u, val.y[:1], val.u, Q=QD,
                                 R=RM[:1, :1], dt=DT)
        got = _term(rep.effect.law if rep.updated else None, "omega^3", -C3)
        right = (got is not None and rep.effect.equations == ("omega",)
                 and abs(got[0] - got[2]) <= got[1])
        _verdict("pendulum_pos", seed, rep, right,
                 f"{rep.effect.equations} {rep.effect.formula or '-'}",
                 true.table["nominal"].se.value)
        VERDICTS.setdefault("pendulum_pos_true", []).append(
            "unchanged" if not true.updated else "CHANGED")
        print(f"{'':14s} seed {seed:2d}: true model "
              f"{'unchanged' if not true.updated else 'CHANGED: ' + true.effect.formula}",
              flush=True)
    else:
        rep = gb.close_the_loop(pendulum(), est.y, est.u, val.y, val.u, Q=QD, R=RM, dt=DT)
        law = rep.effect.law if rep.updated else None
    return rep, _term(law, "omega^3", -C3)


def _term(law, name, truth):
    """(estimate, half-width, truth) of the law's only term if it is ``name``, else None."""
    if law is None:
        return None
    on = np.flatnonzero(law.coef[0])
    if len(on) != 1 or law.spec[on[0]][0] != name:
        return None
    half = np.nan if law.ci is None else float(law.ci[0, on[0]])
    return float(law.coef[0, on[0]]), half, truth


def _overflow(seed, soft):
    rng = np.random.default_rng(seed)
    u, uv = tk.multisine(rng, 1024), tk.multisine(rng, 1024)
    if soft:
        (_, y), (xv, yv) = (tk.truth(u, np.inf, rng, soft=(KO, XO)),
                            tk.truth(uv, np.inf, rng, soft=(KO, XO)))
    else:
        (_, y), (xv, yv) = tk.truth(u, tk.XMAX, rng), tk.truth(uv, tk.XMAX, rng)
    rep = close_the_loop_nonlinear(tk.NOMINAL, y, u, yv, uv, Q=tk.Q, R=tk.R, dt=tk.TS,
                                   substeps=4)
    floor = relative_error(yv[:, SKIP:], xv[1:, SKIP:]).value  # the true model's SE
    law = rep.effect.law if rep.updated else None
    on = np.flatnonzero(law.coef[0]) if law is not None else []
    one = (law is not None and rep.effect.equations == ("x1",) and len(on) == 1
           and law.spec[on[0]][1] == "x_hi" and law.spec[on[0]][2][0] == 0)
    # the right law: eq(x1), one upper hinge on x1 at the clip (hard: 8 within 2 %) or at
    # the soft overflow's level within its 2 % too
    right = one and abs(law.spec[on[0]][2][1] - XO) <= 0.02 * XO
    _verdict("overflow_soft" if soft else "overflow", seed, rep, right,
             f"{rep.effect.equations} {rep.effect.formula or '-'}", floor)
    if not one:
        return rep, None
    # the hinge level's 95 % interval (shown in the formula) against the truth XO = XMAX = 8
    m = re.search(r"\(([-+0-9.e]+) ± ([0-9.e+-]+)\), 0\)", law.formula)
    if m:
        lv, hl = float(m.group(1)), float(m.group(2))
        LEVELS.setdefault("overflow_soft" if soft else "overflow", []).append(
            abs(lv - XO) <= hl)
        print(f"{'':14s} seed {seed:2d}: level {lv:.5g} +- {hl:.2g} (truth {XO:g}) "
              f"{'covered' if abs(lv - XO) <= hl else 'MISSED'}", flush=True)
    half = np.nan if law.ci is None else float(law.ci[0, on[0]])
    return rep, (float(law.coef[0, on[0]]), half, -KO if soft else np.nan)


CASES = {
    "pendulum": lambda s: _pendulum(s, False),
    "pendulum_pos": lambda s: _pendulum(s, True),
    "overflow_soft": lambda s: _overflow(s, True),
    "overflow": lambda s: _overflow(s, False),
}


def main(argv):
    nseeds = 20
    if "--seeds" in argv:
        i = argv.index("--seeds")
        nseeds = int(argv[i + 1])
        argv = argv[:i] + argv[i + 2:]
    cases = argv or list(CASES)
    summary = []
    for case in cases:
        rows, t0 = [], time.time()
        for seed in range(nseeds):
            t = time.time()
            rep, got = CASES[case](seed)
            if got is None:
                print(f"{case:14s} seed {seed:2d}: law not named ({rep.message[:90]})",
                      flush=True)
                continue
            rows.append(got)
            est, half, truth = got
            cov = abs(est - truth) <= half if np.isfinite(truth) else None
            print(f"{case:14s} seed {seed:2d}: {est:+.5g} +- {half:.3g} (truth {truth:+.4g})"
                  f" {'' if cov is None else ('covered' if cov else 'MISSED')}"
                  f"  {time.time() - t:.1f} s", flush=True)
        if not rows:
            summary.append((case, 0, 0, "", np.nan, time.time() - t0))
            continue
        est, half, truth = (np.array(v) for v in zip(*rows))
        if not np.all(np.isfinite(truth)):  # no truth: the seeds' median stands in
            truth = np.full_like(est, np.median(est))
        n = len(rows)
        hit = int(np.sum(np.abs(est - truth) <= half))
        lo, hi = binom.ppf(0.025, n, 0.95), binom.ppf(0.975, n, 0.95)
        spread = float(np.std(est - truth) / np.mean(half / 1.96))
        summary.append((case, hit, n, f"[{lo:.0f}, {hi:.0f}]", spread, time.time() - t0))
    print(f"\nload average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}")
    for case, vs in LEVELS.items():
        print(f"{case:18s} hinge level's 95 % interval covers 8 on {sum(vs)} of {len(vs)}")
    for case, vs in VERDICTS.items():  # the law named (issue 12): right, refused, wrong
        counts = ", ".join(f"{v} {vs.count(v)}" for v in sorted(set(vs)))
        print(f"{case:18s} over {len(vs)} seeds: {counts}")
    print(f"{'case':14s} {'covered':>8s} {'named':>6s} {'band(95%)':>10s} "
          f"{'rms err/se':>11s} {'time [s]':>9s}")
    for case, hit, n, band, spread, tt in summary:
        print(f"{case:14s} {hit:8d} {n:6d} {band:>10s} {spread:11.2f} {tt:9.0f}")


if __name__ == "__main__":
    main(sys.argv[1:])
