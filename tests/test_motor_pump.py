"""The motor-pump reproduction: `greybox demo motor-pump` (Table V, Fig. 3)."""

from __future__ import annotations

import contextlib
import io
import json

import matplotlib
import numpy as np
import pytest

import greybox as gb
from greybox.cli import main

matplotlib.use("Agg")


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("mp") / "out"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["demo", "motor-pump", "--json", "--out", str(out)])
    return code, json.loads(buf.getvalue()), out


@pytest.mark.slow
def test_demo_motor_pump_json_table5(demo):
    code, js, out = demo
    assert code == 0
    t5 = js["table5"]
    assert {"ukf_ee", "ui_ukf_ee", "ensemble_ee", "hr_rms_error", "hr_bias_pct",
            "setting"} <= set(t5)
    # the ordering: the unknown-input UKF at least 10x below the UKF
    assert t5["ui_ukf_ee"] * 10 <= t5["ukf_ee"]
    # recovered load: bias within 6 % (issue); ours, with G from the discretized
    # model and sigma points propagated at the previous d^, is far inside it
    assert abs(t5["hr_bias_pct"]) < 6.0
    # the paper's literal form (G = [0 0 Ts], d = 0) leaks more (PAPER_NOTES §8.9)
    assert abs(t5["hr_bias_pct_paper_form"]) > 5 * abs(t5["hr_bias_pct"])
    # the 95 % band of h_r^ covers the truth near 95 % (2900 correlated samples)
    assert 0.92 <= t5["hr_ci95_coverage"] <= 0.98
    # the ensemble filter is as good as the UI-UKF on this smooth plant (within 10 %)
    assert t5["ensemble_ee"] < 1.1 * t5["ui_ukf_ee"]
    assert (out / "fig3_pump_load.png").stat().st_size > 1000


def test_demo_motor_pump_text_refuses_foreign_folder(tmp_path, capsys):
    target = tmp_path / "mine"
    target.mkdir()
    (target / "notes.txt").write_text("my file")
    assert main(["demo", "motor-pump", "--out", str(target), "--no-plots"]) == 2
    assert "--force" in capsys.readouterr().err


def test_fig3_plot_artists():
    from greybox.reproduce import MotorPumpSetting, reproduce_table5
    from greybox.plotting import plot_pump_load

    t5 = reproduce_table5(MotorPumpSetting(nsteps=400, nmembers=10, burn_in=50))
    arts = plot_pump_load(t5, window=(100, 300))
    est, half = t5.load_estimate()
    np.testing.assert_array_equal(arts["estimate"].get_ydata(), est[100:300])
    np.testing.assert_array_equal(arts["truth"].get_ydata(), t5.load[100:300])
    assert np.all(half[:-1] > 0)
    import matplotlib.pyplot as plt

    plt.close(arts["figure"])


def test_motor_pump_models_share_the_dynamics():
    true, nom = gb.motor_pump_true(), gb.motor_pump_nominal()
    x = np.array([[6.0, 5.0], [4.0, 3.0], [1.2, 1.0]])
    hr = 150.0
    ft = true.updfcn(0, x, np.array([[10.0, 10.0], [hr, hr]]), {})
    fn = nom.updfcn(0, x, np.array([[10.0, 10.0], -hr * x[2] ** 2]), {})
    # d = -h_r Mdot^2 makes the nominal model the true one: identical arithmetic
    np.testing.assert_allclose(fn, ft, rtol=1e-14, atol=0)
    assert gb.linear_output_map(nom)[0].tolist() == np.eye(3).tolist()
