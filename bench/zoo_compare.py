"""Two runs of the plant zoo side by side: what a method change did to the explanations.

``python bench/zoo_compare.py BEFORE.jsonl AFTER.jsonl`` reads two ``--jsonl`` files of
``bench/zoo.py`` run with the same ``--seed`` and ``--draws`` (the same plants: one
before a change, one after) and prints

- per class: right before -> after, and the summed run time before -> after;
- every draw whose verdict (right or wrong) or found law changed: the class, the
  draw, right before -> after, the law found before -> after, the validation error
  before -> after against the true model's;
- the totals: right, draws whose error rose above 1.5x its value before, time ratio.

A change to the method is judged on these draws, not on the plant it was written for:
a draw it repairs, a draw it breaks and a draw whose error it raises are all listed.
Draws are matched by (class, seed, draw); a draw present in one file only is counted as
missing. Exit status 0; 2 on unreadable input.
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict


def load(path: str) -> dict[tuple, dict]:
    """The draws of one ``--jsonl`` file keyed by (class, seed, draw); the last record wins."""
    out = {}
    with open(path) as fh:
        for line in fh:
            if not line.strip():
                continue
            r = json.loads(line)
            cls = r.get("cls", r.get("class"))
            out[(cls, r["seed"], r["draw"])] = r
    return out


def _err(r: dict) -> float:
    v = r.get("error_updated")
    return float("nan") if v is None else float(v)


def compare(before: dict, after: dict) -> list[str]:
    """The report's lines (markdown)."""
    keys = [k for k in before if k in after]
    missing = len(set(before) ^ set(after))
    per = defaultdict(lambda: [0, 0, 0, 0.0, 0.0])  # n, right before, after, time b, a
    changed, worse = [], 0
    for k in keys:
        b, a = before[k], after[k]
        row = per[k[0]]
        row[0] += 1
        row[1] += bool(b.get("right"))
        row[2] += bool(a.get("right"))
        row[3] += b.get("seconds") or 0.0
        row[4] += a.get("seconds") or 0.0
        if _err(a) > 1.5 * _err(b):
            worse += 1
        if b.get("right") != a.get("right") or b.get("found") != a.get("found"):
            changed.append((k, b, a))
    lines = ["| class | draws | right before -> after | time before -> after [s] |",
             "|---|---|---|---|"]
    for cls, (n, rb, ra, tb, ta) in per.items():
        lines.append(f"| {cls} | {n} | {rb} -> {ra} | {tb:.0f} -> {ta:.0f} |")
    lines += ["", "| class | draw | right | found before -> after | SE before -> after "
                  "(true) [%] |", "|---|---|---|---|---|"]
    for (cls, _, i), b, a in changed:
        lines.append(f"| {cls} | {i} | {bool(b.get('right'))} -> {bool(a.get('right'))} | "
                     f"{b.get('found', b.get('error'))} -> {a.get('found', a.get('error'))} | "
                     f"{_err(b):.3g} -> {_err(a):.3g} ({b.get('error_true', float('nan')):.3g}) |")
    tb = sum(r[3] for r in per.values())
    ta = sum(r[4] for r in per.values())
    lines += ["", f"right {sum(r[1] for r in per.values())} -> "
                  f"{sum(r[2] for r in per.values())} of {len(keys)}; "
                  f"{len(changed)} draws changed; {worse} with the error above 1.5x its "
                  f"value before; time {tb:.0f} -> {ta:.0f} s "
                  f"(x{ta / tb if tb else float('nan'):.2f}); {missing} draws in one file only"]
    return lines


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print("usage: python bench/zoo_compare.py BEFORE.jsonl AFTER.jsonl", file=sys.stderr)
        return 2
    try:
        before, after = load(argv[0]), load(argv[1])
    except (OSError, ValueError, KeyError) as e:
        print(f"zoo_compare: cannot read the runs: {type(e).__name__}: {e}", file=sys.stderr)
        return 2
    print("\n".join(compare(before, after)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
