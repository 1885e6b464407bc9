"""The randomized plant zoo (issue 27 item 1): is greybox's explanation right on fresh plants?

``python bench/zoo.py --draws 20`` draws 20 plants of every class of
:mod:`greybox.zoo` (a fresh seed, printed; ``--seed S`` replays a run, ``--classes a,b``
picks classes, ``--n-est N`` shortens the estimation record), runs
``greybox.close_the_loop`` on each (``delta=False``; a NonlinearIOSystem nominal goes
through the nonlinear workflow), scores the report against the draw's recorded truth
(:func:`greybox.zoo.score`) and prints one line per draw, then per class:

- right: draws with the right explanation (true channel, kind and order, exactly the
  true terms and drivers, coefficients within 10 %; for a correct model: no update);
- cover: true coefficients inside the reported 95 % intervals (static terms' coefficients,
  dynamic poles), over all draws of the class;
- flags: parameter notes flagging a parameter the truth has right (total);
- SE/true: median validation error of the updated model over the true model's (SE; PE
  for an unstable model); ``<=1.5x``: draws within 1.5x of the true model's;
- false upd: for a correct-model class, the draws whose model was changed;
- time: median run time of close_the_loop [s].

``--out FILE`` also writes the table as markdown (with the command line and the seed);
``--jsonl FILE`` appends one JSON record per draw. Run it single-process: the draws run
one after the other, BLAS on one thread.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))

import greybox as gb  # noqa: E402
from greybox import zoo  # noqa: E402
from greybox._blas import single_thread_blas  # noqa: E402


def run_one(cls: str, seed: int, i: int, n_est: int | None) -> zoo.ZooScore | str:
    """The score of draw i of class cls (or the error's text)."""
    d = zoo.draw_class(cls, seed, i, n_est=n_est)
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R,
                                    dt=d.dt, delta=False)
    except Exception as e:  # noqa: BLE001 - a failure is a result of the benchmark
        return f"{type(e).__name__}: {e}"[:200]
    seconds = time.perf_counter() - t0
    try:
        return zoo.score(d, rep, seconds)
    except Exception as e:  # noqa: BLE001 - the scorer's own failure, named as such
        return f"scorer failed: {type(e).__name__}: {e}"[:200]


def _median(v) -> float:
    v = [x for x in v if np.isfinite(x)]
    return float(np.median(v)) if v else float("nan")


def summarize(cls: str, rows: list) -> dict:
    """The class's table row from its scores (errors count as wrong)."""
    sc = [r for r in rows if isinstance(r, zoo.ZooScore)]
    n = len(rows)
    ratios = [s.error_ratio for s in sc if s.updated or s.correct_model]
    ratio_all = [s.error_ratio for s in sc]
    cov = sum(s.covered for s in sc), sum(s.n_coefficients for s in sc)
    correct = cls in zoo.CORRECT_CLASSES
    return {
        "class": cls, "n": n, "right": sum(s.right for s in sc),
        "channel": sum(s.right_channel for s in sc), "kind": sum(s.right_kind for s in sc),
        "terms": sum(s.right_terms for s in sc),
        "coef": sum(s.coefficients_within for s in sc),
        "covered": cov[0], "ncoef": cov[1], "flags": sum(s.false_flags for s in sc),
        "ratio": _median(ratio_all), "within15": sum(r <= 1.5 for r in ratio_all),
        "updated": sum(s.updated for s in sc),
        "false_updates": sum(bool(s.false_update) for s in sc) if correct else None,
        "errors": n - len(sc), "time": _median([s.seconds for s in sc]),
        "ratio_updated": _median(ratios),
    }


HEADER = ("| class | right | channel | kind | terms | coef 10 % | cover 95 % | flags | "
          "SE/true (median) | <=1.5x | false upd | errors | time [s] |")


def table_row(r: dict) -> str:
    """One markdown row of a class summary."""
    n = r["n"]
    cov = f"{r['covered']}/{r['ncoef']}" if r["ncoef"] else "-"
    fu = f"{r['false_updates']}/{n}" if r["false_updates"] is not None else "-"
    return (f"| {r['class']} | {r['right']}/{n} | {r['channel']}/{n} | {r['kind']}/{n} | "
            f"{r['terms']}/{n} | {r['coef']}/{n} | {cov} | {r['flags']} | "
            f"{r['ratio']:.3g} | {r['within15']}/{n} | {fu} | {r['errors']} | "
            f"{r['time']:.3g} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--classes", default=",".join(zoo.CLASSES))
    ap.add_argument("--n-est", type=int, default=None,
                    help="estimation samples (default: each class's own, 4000)")
    ap.add_argument("--out", default=None, help="write the table as markdown to this file")
    ap.add_argument("--jsonl", default=None, help="append one JSON record per draw")
    a = ap.parse_args(argv)
    seed = a.seed if a.seed is not None else int(np.random.SeedSequence().entropy % 2**31)
    classes = [c.strip() for c in a.classes.split(",") if c.strip()]
    cmd = "python bench/zoo.py " + " ".join(argv if argv is not None else sys.argv[1:])
    if a.seed is None:
        cmd += f"  (seed drawn: {seed}; replay with --seed {seed})"
    print(f"# {cmd}\n# seed {seed}", flush=True)
    summary = []
    t_all = time.perf_counter()
    with single_thread_blas():
        for cls in classes:
            rows = []
            for i in range(a.draws):
                r = run_one(cls, seed, i, a.n_est)
                rows.append(r)
                _print_draw(cls, i, r)
                if a.jsonl:
                    with open(a.jsonl, "a") as fh:
                        fh.write(json.dumps(_record(cls, seed, i, r)) + "\n")
            summary.append(summarize(cls, rows))
    lines = [HEADER, "|" + "---|" * 13] + [table_row(r) for r in summary]
    print("\n" + "\n".join(lines))
    print(f"\n# {time.perf_counter() - t_all:.0f} s in all")
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(_markdown(cmd, seed, a, lines, time.perf_counter() - t_all))
    return 0


def _print_draw(cls: str, i: int, r) -> None:
    if isinstance(r, str):
        print(f"{cls:21s} {i:3d}  ERROR {r}", flush=True)
        return
    mark = "RIGHT" if r.right else "wrong"
    print(f"{cls:21s} {i:3d}  {mark}  {r.error_kind} {r.error_nominal:.3g}% -> "
          f"{r.error_updated:.3g}% (true {r.error_true:.3g}%), cover {r.covered}/"
          f"{r.n_coefficients}, flags {r.false_flags}, {r.seconds:.1f} s | {r.description}"
          f" | found: {r.found}" + (f" | {r.why}" if r.why else ""), flush=True)


def _record(cls, seed, i, r) -> dict:
    if isinstance(r, str):
        return {"class": cls, "seed": seed, "draw": i, "error": r}
    out = {k: getattr(r, k) for k in r.__dataclass_fields__}
    return {"seed": seed, "draw": i, **out}


def _markdown(cmd, seed, a, lines, seconds) -> str:
    return (f"# The randomized plant zoo (issue 27 item 1)\n\n"
            f"Command: `{cmd.split('  (')[0]}`, seed {seed} (replay: `--seed {seed}`), "
            f"{a.draws} draw(s) per class, {seconds:.0f} s in all.\n\n"
            + "\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
