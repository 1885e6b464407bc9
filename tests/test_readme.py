"""The README's Python snippets, and those of the user guide in docs/, run as written;
the benchmark tables quoted in docs/results/benchmarks.md are the measured ones.

Each fenced ``python`` block that starts with an import is executed in a
fresh namespace; a block that uses names it does not define fails here.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted(p for p in (ROOT / "docs").rglob("*.md") if "_build" not in p.parts)
BENCHMARKS = ROOT / "docs" / "results" / "benchmarks.md"  # the tables the README once held


def _runnable(path: Path) -> list[str]:
    blocks = re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)
    return [b for b in blocks if b.lstrip().startswith(("import ", "from "))]


RUNNABLE = _runnable(README)
SNIPPETS = [(README, b) for b in RUNNABLE] + [(p, b) for p in DOCS for b in _runnable(p)]


def test_there_are_runnable_snippets():
    assert RUNNABLE, "no self-contained python snippet in README.md"


@pytest.mark.parametrize("path, code", SNIPPETS,
                         ids=[f"{p.relative_to(ROOT)}-block{i}" for i, (p, _) in enumerate(SNIPPETS)])
def test_snippet_runs(path, code):
    exec(compile(code, str(path), "exec"), {"__name__": "readme_snippet"})


RESULTS_WORKFLOW = ROOT / "bench" / "RESULTS_workflow.md"


def _table_rows(marker: str, what: str, min_rows: int) -> list[str]:
    """Data rows of the benchmarks page's table between ``<!-- marker -->`` and ``<!-- /marker -->``."""
    m = re.search(rf"<!-- {marker} -->(.*?)<!-- /{marker} -->", BENCHMARKS.read_text(), flags=re.S)
    assert m, f"docs/results/benchmarks.md lost its marked table of {what}"
    rows = [ln for ln in m.group(1).splitlines() if ln.startswith("|") and "---" not in ln][1:]
    assert len(rows) >= min_rows, f"the table of {what} needs at least {min_rows} rows"
    return rows


def test_big_file_figures_are_the_measured_ones():
    """The benchmarks page's 1e6-sample table quotes bench/RESULTS_workflow.md (the raw outputs)."""
    rows = _table_rows("workflow-1e6", "the 1e6-sample run", 2)  # a before and an after row
    raw = RESULTS_WORKFLOW.read_text()
    for row in rows:
        for number in re.findall(r"(?<![\w.])\d+(?:\.\d+)?(?![\w.])", row.split("|", 2)[2]):
            assert re.search(rf"(?<![\w.]){re.escape(number)}(?![\w.])", raw), \
                (f"docs/results/benchmarks.md quotes {number} ({row.strip()}) but "
                 f"bench/RESULTS_workflow.md has not")


RESULTS_UKF = ROOT / "bench" / "RESULTS_ukf.md"


def test_ukf_benchmark_figures_are_the_measured_ones():
    """The benchmarks page's unscented-filter table quotes bench/RESULTS_ukf.md (the raw output)."""
    rows = _table_rows("ukf-bench", "bench/ukf.py", 8)  # the rows of both models
    raw = RESULTS_UKF.read_text()
    for row in rows:  # cells after "model | method"
        for number in re.findall(r"(?<![\w.])\d+(?:\.\d+)?(?:e-\d+)?(?![\d.e])",
                                 row.split("|", 3)[3]):  # "3.7x" counts as 3.7
            assert re.search(rf"(?<![\w.]){re.escape(number)}(?![\d.e])", raw), \
                (f"docs/results/benchmarks.md quotes {number} ({row.strip()}) but "
                 f"bench/RESULTS_ukf.md has not")
