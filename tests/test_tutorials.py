"""The tutorials run end to end and save their figures (executed in CI)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

TUTORIALS = Path(__file__).resolve().parents[1] / "tutorials"

CASES = [
    ("01_tape_drive_walkthrough.py",
     ["fig1_tension.png", "fig2_autocorrelation.png", "fig3_outputs.png"],
     ["Table II", "Table III"]),
    ("02_controller_design.py", ["fig4_closed_loop.png", "fig5_costs.png"],
     ["closed loop on the TRUE plant"]),
    ("03_close_the_loop.py",
     ["tutorial03_report/report.md", "tutorial03_report/outputs.png",
      "tutorial03_report/autocorrelation.png", "tutorial03_report/d_estimate.png",
      "tutorial03_report/updated_model.json"],
     ["model error found in eq(v2)", "exit code 0"]),
]
# the real-data tutorials (04, 06-09) run in tests/test_real_sets.py


@pytest.mark.slow
@pytest.mark.parametrize("script, figures, headings", CASES, ids=[c[0] for c in CASES])
def test_tutorial_runs_and_saves_figures(tmp_path, script, figures, headings):
    env = dict(os.environ, GREYBOX_TUTORIAL_OUT=str(tmp_path), MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, str(TUTORIALS / script)], env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for h in headings:
        assert h in proc.stdout
    for name in figures:
        path = tmp_path / name
        assert path.is_file() and path.stat().st_size > 100, name
