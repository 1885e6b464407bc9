"""Coverage of the refitted nominal parameters' 95 % intervals, over seeds (issue 12).

``python bench/nominal_refit_coverage.py [--seeds N] [--first S]`` (default 10 seeds from 1).

The plant of ``tests/test_nominal_refit.py`` (``plantlib.tanks_spill``): Torricelli
tanks, only the lower tank measured, noise 0.01, the upper tank overflowing at 8.0 with
60 % of the overflow falling into the lower tank. The nominal declares k2 (right,
0.058) and k3 (15 % high: 0.0943 against 0.082) as ``params``; ``close_the_loop`` refits
them jointly with the law it adds. Per seed: the verdict (``right``: updated, eq(x1)
with one upper hinge on x1, a spill into eq(x2), k3 named; ``refused``; ``WRONG``), k3
and k2 with their 95 % half-widths and whether the truth is inside, the spill ratio
(truth -0.6 for the per-sub-step clip; the per-sample hinge cannot express it exactly,
so its "truth" is approximate) and the hinge level. Then per quantity: covered / named
with the 95 % binomial band of the count for a calibrated interval, and the ratio of
the estimates' spread to the mean stated standard error (1 when calibrated).

The suite asserts seed 1 only (tests/test_nominal_refit.py, ~35 s a seed).
"""

from __future__ import annotations

import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

import numpy as np  # noqa: E402
from scipy.stats import binom  # noqa: E402

from greybox.workflow_nonlinear import close_the_loop_nonlinear  # noqa: E402
from plantlib import TANKS_K, tanks_declared, tanks_spill  # noqa: E402

K3_DECLARED = 1.15 * TANKS_K["k3"]
Q, R = 1e-4 * np.eye(2), np.array([[1e-4]])
TRUTH = {"k3": TANKS_K["k3"], "k2": TANKS_K["k2"], "spill": -0.6}


def one(seed):
    u, y, uv, yv = tanks_spill(seed, xmax=8.0, gamma=0.6, r_std=0.01)
    nom = tanks_declared({"k2": TANKS_K["k2"], "k3": K3_DECLARED})
    t0 = time.time()
    rep = close_the_loop_nonlinear(nom, y, u, yv, uv, Q=Q, R=R)
    dt = time.time() - t0
    out = {"time": dt, "verdict": "refused", "est": {}}
    if not rep.updated:
        return out, rep
    law = rep.effect.law
    sel = [law.spec[j] for j in np.flatnonzero(law.coef[0])] if law is not None else []
    hinge = [s for s in sel if s[1] == "x_hi" and s[2][0] == 0]
    spill = rep.nonlinear.spill if rep.nonlinear is not None else ()
    right = (rep.channel is not None and rep.channel.name == "eq(x1)" and len(hinge) == 1
             and any(s[0] == "x2" for s in spill))
    out["verdict"] = "right" if right else "WRONG"
    out["level"] = hinge[0][2][1] if hinge else np.nan
    out["nterms"] = len(sel)
    for p in rep.nonlinear.parameters:
        out["est"][p.name] = (p.refitted, p.halfwidth)
    for s in spill:
        if s[0] == "x2":
            out["est"]["spill"] = (s[1], s[2])
    return out, rep


def main(argv):
    seeds, first = 10, 1
    if "--seeds" in argv:
        seeds = int(argv[argv.index("--seeds") + 1])
    if "--first" in argv:
        first = int(argv[argv.index("--first") + 1])
    rows = []
    t_all = time.time()
    print("| seed | verdict | terms | hinge level | k3 (truth 0.082) | k2 (truth 0.058) | "
          "spill (truth ~-0.6) | time [s] |")
    print("|---|---|---|---|---|---|---|---|")
    for seed in range(first, first + seeds):
        out, _ = one(seed)
        rows.append(out)

        def cell(k):
            if k not in out["est"]:
                return "-"
            v, h = out["est"][k]
            inside = abs(v - TRUTH[k]) <= h if np.isfinite(h) else False
            return f"{v:.4g} ± {h:.2g} {'in' if inside else 'OUT'}"
        print(f"| {seed} | {out['verdict']} | {out.get('nterms', '-')} | "
              f"{out.get('level', np.nan):.4g} | {cell('k3')} | {cell('k2')} | "
              f"{cell('spill')} | {out['time']:.1f} |", flush=True)
    print()
    verdicts = [r["verdict"] for r in rows]
    print(f"verdicts: right {verdicts.count('right')}, refused {verdicts.count('refused')}, "
          f"WRONG {verdicts.count('WRONG')} of {len(rows)}")
    print("| quantity | covered / named | 95 % band for a calibrated interval | "
          "spread / mean stated SE | mean estimate |")
    print("|---|---|---|---|---|")
    for k in ("k3", "k2", "spill"):
        est = [r["est"][k] for r in rows if r["verdict"] == "right" and k in r["est"]
               and np.isfinite(r["est"][k][1])]
        if not est:
            continue
        v = np.array([e[0] for e in est])
        h = np.array([e[1] for e in est])
        cov = int(np.sum(np.abs(v - TRUTH[k]) <= h))
        n = len(est)
        lo, hi = binom.ppf(0.025, n, 0.95), binom.ppf(0.975, n, 0.95)
        ratio = float(np.std(v, ddof=1) / np.mean(h / 1.96)) if n > 1 else np.nan
        print(f"| {k} | {cov} / {n} | {lo:.0f}-{hi:.0f} | {ratio:.2f} | {np.mean(v):.4g} |")
    print(f"\ntotal {time.time() - t_all:.0f} s, load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main(sys.argv[1:])
