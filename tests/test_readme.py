"""The README's Python snippets run as written (issue 13, item 8).

Each fenced ``python`` block that starts with an import is executed in a
fresh namespace; a block that uses names it does not define fails here.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
RUNNABLE = [b for b in BLOCKS if b.lstrip().startswith(("import ", "from "))]


def test_there_are_runnable_snippets():
    assert RUNNABLE, "no self-contained python snippet in README.md"


@pytest.mark.parametrize("code", RUNNABLE, ids=[f"block{i}" for i in range(len(RUNNABLE))])
def test_snippet_runs(code):
    exec(compile(code, str(README), "exec"), {"__name__": "readme_snippet"})


RESULTS_WORKFLOW = README.parent / "bench" / "RESULTS_workflow.md"


def _table_rows(marker: str, what: str, min_rows: int) -> list[str]:
    """Data rows of the README table between ``<!-- marker -->`` and ``<!-- /marker -->``."""
    m = re.search(rf"<!-- {marker} -->(.*?)<!-- /{marker} -->", README.read_text(), flags=re.S)
    assert m, f"README.md lost its marked table of {what}"
    rows = [ln for ln in m.group(1).splitlines() if ln.startswith("|") and "---" not in ln][1:]
    assert len(rows) >= min_rows, f"the table of {what} needs at least {min_rows} rows"
    return rows


def test_big_file_figures_are_the_measured_ones():
    """The README's 1e6-sample table quotes bench/RESULTS_workflow.md (the raw outputs)."""
    rows = _table_rows("workflow-1e6", "the 1e6-sample run", 2)  # a before and an after row
    raw = RESULTS_WORKFLOW.read_text()
    for row in rows:
        for number in re.findall(r"(?<![\w.])\d+(?:\.\d+)?(?![\w.])", row.split("|", 2)[2]):
            assert re.search(rf"(?<![\w.]){re.escape(number)}(?![\w.])", raw), \
                f"README quotes {number} ({row.strip()}) but bench/RESULTS_workflow.md has not"


RESULTS_UKF = README.parent / "bench" / "RESULTS_ukf.md"


def test_ukf_benchmark_figures_are_the_measured_ones():
    """The README's unscented-filter table quotes bench/RESULTS_ukf.md (the raw output)."""
    rows = _table_rows("ukf-bench", "bench/ukf.py", 8)  # the rows of both models
    raw = RESULTS_UKF.read_text()
    for row in rows:  # cells after "model | method"
        for number in re.findall(r"(?<![\w.])\d+(?:\.\d+)?(?:e-\d+)?(?![\d.e])",
                                 row.split("|", 3)[3]):  # "3.7x" counts as 3.7
            assert re.search(rf"(?<![\w.]){re.escape(number)}(?![\d.e])", raw), \
                f"README quotes {number} ({row.strip()}) but bench/RESULTS_ukf.md has not"