"""``greybox update`` through greybox.cli.main(argv): reports, JSON summary, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from greybox.cli import main
from greybox.model_io import model_to_dict, read_model
from test_workflow import DT, QD, run_case


def _write_case(tmp_path, case, *, time_column=True):
    _, (y, u, yv, uv, nom, R) = run_case(case)
    model = tmp_path / "model.json"
    model.write_text(json.dumps(model_to_dict(nom, QD + 1e-12 * np.eye(4), R, Ts=DT)))

    def csv(path, y, u):
        cols = (["time"] if time_column else []) + list(nom.input_labels) + \
            list(nom.output_labels)
        data = np.vstack(([np.arange(y.shape[1]) * DT] if time_column else []) + [u, y])
        lines = [",".join(cols)] + [",".join(f"{v:.10g}" for v in row) for row in data.T]
        path.write_text("\n".join(lines) + "\n")
        return path

    return model, csv(tmp_path / "est.csv", y, u), csv(tmp_path / "val.csv", yv, uv)


def test_update_spring_json_and_report(tmp_path, capsys):
    model, est, val = _write_case(tmp_path, "spring")
    out = tmp_path / "report"
    code = main(["update", str(model), str(est), "--validate", str(val), "--out", str(out),
                 "--json"])
    assert code == 0
    s = json.loads(capsys.readouterr().out)
    assert s["model_error_detected"] is True
    assert s["channels"] == ["v2"]
    assert s["effect"]["kind"] == "static" and s["effect"]["order"] == 0
    assert "p2" in s["effect"]["formula"]
    se0, se1 = s["table"]["nominal"]["se"], s["table"]["updated"]["se"]
    assert se0 / se1 >= 3
    for f in ("report.md", "updated_model.json", "summary.json", "autocorrelation.png",
              "outputs.png", "d_estimate.png"):
        assert (out / f).exists(), f
    upd = read_model(out / "updated_model.json")  # same schema, readable back
    assert upd.sys.nstates == 4 and list(upd.sys.state_labels) == ["p1", "v1", "p2", "v2"]


def test_correct_model_and_no_overwrite_without_force(tmp_path, capsys):
    model, est, val = _write_case(tmp_path, "right", time_column=False)
    out = tmp_path / "report"
    argv = ["update", str(model), str(est), "--validate", str(val), "--out", str(out),
            "--json", "--no-plots"]
    assert main(argv) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["model_error_detected"] is False and s["effect"]["kind"] == "none"
    before = (out / "summary.json").read_text()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--force" in err and len(err.strip().splitlines()) == 1
    assert (out / "summary.json").read_text() == before
    assert main(argv + ["--force"]) == 0


def _bad(tmp_path, what):
    model, est, val = _write_case(tmp_path, "right")
    text = est.read_text().splitlines()
    if what == "missing column":
        text = [",".join(r.split(",")[:-1]) for r in text]
    elif what == "extra column":
        text = [r + (",extra" if i == 0 else ",1") for i, r in enumerate(text)]
    elif what == "non-numeric":
        text[5] = text[5].replace(text[5].split(",")[2], "abc", 1)
    elif what == "nan row":
        text[7] = ",".join(["nan"] * len(text[7].split(",")))
    elif what == "time disagrees":
        text = [text[0]] + [",".join([f"{2 * i * DT:.10g}"] + r.split(",")[1:])
                            for i, r in enumerate(text[1:])]
    elif what == "too short":
        text = text[:50]
    est.write_text("\n".join(text) + "\n")
    if what == "malformed json":
        model.write_text("{not json")
    elif what == "bad shapes":
        d = json.loads(model.read_text())
        d["A"] = d["A"][:3]
        model.write_text(json.dumps(d))
    return model, est, val


@pytest.mark.parametrize("what, match", [
    ("missing column", "missing"), ("extra column", "unexpected"),
    ("non-numeric", "not a number"), ("nan row", "NaN"), ("time disagrees", "Ts"),
    ("too short", "samples"), ("malformed json", "not valid JSON"), ("bad shapes", "shape"),
])
def test_bad_input_exit_2_one_line_no_output(tmp_path, capsys, what, match):
    model, est, val = _bad(tmp_path, what)
    out = tmp_path / "report"
    code = main(["update", str(model), str(est), "--validate", str(val), "--out", str(out)])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0], err
    assert not out.exists()


def test_force_rewrite_leaves_no_stale_figures(tmp_path, capsys):
    model, est, val = _write_case(tmp_path, "spring")
    out = tmp_path / "report"
    base = ["update", str(model), str(est), "--validate", str(val), "--out", str(out)]
    assert main(base) == 0
    assert (out / "outputs.png").exists()
    (out / "my_notes.txt").write_text("mine")  # a user's file in the report folder
    assert main(base + ["--force", "--no-plots"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["figures"] == {}
    assert not any(p.suffix == ".png" for p in out.iterdir())  # the old figures are gone
    assert (out / "my_notes.txt").read_text() == "mine"  # the user's file is kept
    capsys.readouterr()


def test_excel_bom_csv_and_name_clash(tmp_path, capsys):
    model, est, val = _write_case(tmp_path, "right")
    est.write_bytes(b"\xef\xbb\xbf" + est.read_bytes())  # UTF-8 BOM as Excel writes it
    out = tmp_path / "report"
    assert main(["update", str(model), str(est), "--validate", str(val), "--out", str(out),
                 "--no-plots"]) == 0
    d = json.loads(model.read_text())
    d["outputs"][0] = d["inputs"][0]
    model.write_text(json.dumps(d))
    capsys.readouterr()
    assert main(["update", str(model), str(est), "--validate", str(val), "--out",
                 str(tmp_path / "r2")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "both as input and as output" in err
    assert not (tmp_path / "r2").exists()
