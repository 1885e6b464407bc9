"""The main job: `greybox demo tape-drive` (Tables II and III, Figs. 1 and 2)."""

from __future__ import annotations

import json

import matplotlib
import pytest

from greybox.cli import main

matplotlib.use("Agg")


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "out"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["demo", "tape-drive", "--json", "--out", str(out)])
    return code, json.loads(buf.getvalue()), out


def test_demo_json_table2(demo):
    code, js, out = demo
    assert code == 0
    t2 = js["table2"]
    for key in ("kalman_filter_ee", "unknown_input_filter_ee", "tension_ci95_coverage",
                "setting"):
        assert key in t2
    # the paper's ordering: the unknown-input filter far below the Kalman filter
    assert t2["unknown_input_filter_ee"] < t2["kalman_filter_ee"] / 3
    # simulated noise matches Q and R: 95 % interval coverage near 0.95 (20 000
    # correlated samples: +-0.03 covers the run-to-run spread seen over seeds)
    assert 0.92 <= t2["tension_ci95_coverage"] <= 0.98
    assert (out / "fig1_tension.png").stat().st_size > 1000
    assert (out / "fig2_autocorrelation.png").stat().st_size > 1000


def test_demo_json_table3(demo):
    _, js, _ = demo
    t3 = js["table3"]
    for key in ("initial", "dynamic", "parallel", "static", "true_model"):
        assert {"order", "se", "pe"} <= set(t3[key])
    floor = t3["true_model"]["se"]
    best = min(t3["static"]["se"], t3["dynamic"]["se"])
    assert best < 2 * floor  # the expectation: within 2x of the floor
    assert t3["dynamic"]["se"] < t3["parallel"]["se"]
    # PE sits at the noise floor for both (measured: dynamic 1.60, parallel 1.56,
    # true model 1.64 %; PE depends on each model's Q and R, PAPER_NOTES §8.8),
    # so their order is noise since issue 9's prediction-error delta fit: pin
    # both to the floor instead
    for key in ("dynamic", "parallel"):
        assert abs(t3[key]["pe"] - t3["true_model"]["pe"]) < 0.1 * t3["true_model"]["pe"]
    assert t3["initial"]["se"] > 10 * floor  # the initial model is far worse
    assert t3["initial"]["order"] == 6 and t3["static"]["order"] == 6
    assert t3["dynamic"]["order"] >= 7


def test_demo_refuses_foreign_folder(tmp_path, capsys):
    target = tmp_path / "mine"
    target.mkdir()
    (target / "notes.txt").write_text("my file")
    code = main(["demo", "tape-drive", "--out", str(target), "--no-plots"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "--force" in err
    assert sorted(p.name for p in target.iterdir()) == ["notes.txt"]  # nothing written


def test_demo_refuses_a_file_as_folder(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["demo", "tape-drive", "--out", str(f)]) == 2
    assert "not a folder" in capsys.readouterr().err


def test_demo_json_is_strict(demo):
    """summary.json passes a strict parser (no NaN or Infinity; issue 13)."""
    _, _, out = demo

    def refuse(c):
        raise ValueError(f"non-standard JSON constant {c}")

    json.loads((out / "summary.json").read_text(), parse_constant=refuse)


README_ROWS = {  # row label of docs/results/paper.md's Table III -> key of the demo's table3 JSON
    "initial": "initial",
    "dynamic (order chosen from data, feedthrough, output-error)": "dynamic",
    "dynamic, paper structure (no feedthrough)": "dynamic_paper_structure",
    "dynamic, paper's N4SID subsystem step (`method=\"n4sid\"`)": "dynamic_n4sid",
    "parallel delta baseline (`delta_update` defaults)": "parallel",
    "static update (order 0)": "static",
    "true model (the floor)": "true_model",
}


def test_readme_quotes_what_the_demo_prints(demo):
    """The quoted Tables II and III (docs/results/paper.md, moved there from the README)
    are the numbers the demo computes today."""
    from pathlib import Path

    _, js, _ = demo
    text = (Path(__file__).resolve().parents[1] / "docs" / "results" / "paper.md").read_text()
    t2 = js["table2"]
    for label, key in (("Kalman filter (ignores tension)", "kalman_filter_ee"),
                       ("unknown-input filter", "unknown_input_filter_ee")):
        assert f"| {label} | {t2[key]:.2f} |" in text, (label, t2[key])
    assert f"covers the truth in {100 * t2['tension_ci95_coverage']:.1f} %" in text
    t3 = js["table3"]
    for label, key in README_ROWS.items():
        row = t3[key]
        assert f"| {label} | {row['order']} | {row['se']:.2f} | {row['pe']:.2f} |" in text, \
            (label, row["order"], row["se"], row["pe"])


def test_demo_json_table3_parallel_and_n4sid_rows(demo):
    """Issue 9: the parallel baseline improves on the initial model (seed 2006:
    SE 9.2 % vs 65.5 %; a baseline that breaks even fails), says so in a note,
    and the paper's N4SID subsystem step reaches the floor on the tape drive."""
    _, js, _ = demo
    t3 = js["table3"]
    assert t3["parallel"]["se"] < 0.5 * t3["initial"]["se"]
    assert t3["parallel"]["order"] > t3["initial"]["order"]
    assert any(n.startswith("parallel model: order") for n in t3["notes"])
    # measured 1.11 % vs floor 1.08 %: within 10 % of the true model
    assert t3["dynamic_n4sid"]["se"] < 1.1 * t3["true_model"]["se"]
    assert t3["n4sid_subsystem_order"] in (0, 1, 2)
