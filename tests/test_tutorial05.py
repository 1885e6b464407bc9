"""Tutorial 05 (nonlinear motor-pump) runs end to end and saves its figure."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "tutorials" / "05_nonlinear_motor_pump.py"


@pytest.mark.slow
def test_tutorial05_runs_and_saves_figure(tmp_path):
    env = dict(os.environ, GREYBOX_TUTORIAL_OUT=str(tmp_path), MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, str(SCRIPT)], env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for heading in ("Table V", "unknown-input UKF", "recovered load h_r",
                    "ModelError: the state update of tank returned NaN or inf for state "
                    "'level' at step",
                    "close_the_loop on a nonlinear model", "law: d_omega = -(0.5",
                    "the right model: no significant model error"):
        assert heading in proc.stdout
    fig = tmp_path / "fig8_pump_load.png"
    assert fig.is_file() and fig.stat().st_size > 1000
