"""``greybox update`` through greybox.cli.main(argv): reports, JSON summary, bad input."""

from __future__ import annotations

import contextlib
import io
import json
import shutil

import numpy as np
import pytest

from greybox.cli import main
from greybox.model_io import model_to_dict, read_model
from test_workflow import DT, QD, case_data


# the first 2000 estimation and 1000 validation samples of test_workflow's draw (6000 +
# 3000): the same verdict (measured: eq(v2), -(15 +- 0.004)*p2, SE 128 % -> 0.59 %, 218x;
# at 6000 + 3000: +- 0.0023, 157 % -> 0.35 %, 453x), one update run 15.8 s -> 7.2 s
N_EST, N_VAL = 2000, 1000


def _write_case(tmp_path, case, *, time_column=True):
    y, u, yv, uv, nom, R = case_data(case)
    y, u, yv, uv = y[:, :N_EST], u[:, :N_EST], yv[:, :N_VAL], uv[:, :N_VAL]
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


@pytest.fixture(scope="module")
def spring(tmp_path_factory):
    """The spring case's files and one full ``update --json`` run on them (plots, delta
    baseline): (model, est, val, report folder, exit code, stdout). Three tests ask this
    very run; each copies the report folder before changing it."""
    tmp = tmp_path_factory.mktemp("spring")
    model, est, val = _write_case(tmp, "spring")
    out = tmp / "report"
    with contextlib.redirect_stdout(io.StringIO()) as buf:
        code = main(["update", str(model), str(est), "--validate", str(val), "--out",
                     str(out), "--json"])
    return model, est, val, out, code, buf.getvalue()


def test_update_spring_json_and_report(spring):
    model, est, val, out, code, stdout = spring
    assert code == 0
    s = json.loads(stdout)
    assert s["model_error_detected"] is True
    assert s["channels"] == ["v2"]
    assert s["effect"]["kind"] == "static" and s["effect"]["order"] == 0
    assert "p2" in s["effect"]["formula"]
    se0, se1 = s["table"]["nominal"]["se"], s["table"]["updated"]["se"]
    assert se0 / se1 >= 3
    for f in ("report.md", "updated_model.json", "summary.json", "autocorrelation.png",
              "outputs.png", "d_estimate.png", "law.png"):
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


def test_force_rewrite_leaves_no_stale_figures(tmp_path, capsys, spring):
    model, est, val, report, code, _ = spring
    out = tmp_path / "report"
    shutil.copytree(report, out)  # the shared run's report: with figures
    base = ["update", str(model), str(est), "--validate", str(val), "--out", str(out)]
    assert code == 0
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


# --- issue 13: strict JSON, clean stdout, atomic reports, Ctrl-C, permissions --------------

def _strict_loads(text):
    """json.loads that refuses NaN and Infinity, as JavaScript's JSON.parse does."""
    def bad(c):
        raise ValueError(f"non-standard JSON constant {c}")
    return json.loads(text, parse_constant=bad)


def test_json_stdout_holds_the_document_alone(tmp_path, capfd, monkeypatch):
    """Text a numerical library prints on file descriptor 1 goes to stderr under --json."""
    import os

    import greybox.workflow as wf
    from test_bad_inputs import Case, _unstable

    real = wf.close_the_loop

    def noisy(*a, **k):
        os.write(1, b" ** On entry to DLASCL parameter number  4 had an illegal value\n")
        return real(*a, **k)

    monkeypatch.setattr(wf, "close_the_loop", noisy)
    c = Case(tmp_path)
    _unstable(c)
    assert main(c.argv() + ["--json"]) == 0
    out, err = capfd.readouterr()
    s = _strict_loads(out)  # stdout is one strict JSON document
    assert s["table"]["nominal"]["se"] is None and s["table"]["nominal"]["se_reason"]
    assert "DLASCL" in err and "DLASCL" not in out
    _strict_loads((c.out / "summary.json").read_text())
    _strict_loads((c.out / "updated_model.json").read_text())


def test_json_safe_nonfinite_become_null_with_reason():
    from greybox.io import dumps_json, json_safe

    d = json_safe({"se": float("inf"), "pe": 1.5, "per": np.array([1.0, np.nan]),
                   "n": np.int64(3), "ok": np.bool_(True), "nest": [{"x": -np.inf}]})
    assert d["se"] is None and "infinite" in d["se_reason"]
    assert d["per"] == [1.0, None] and "1 non-finite" in d["per_reason"]
    assert d["nest"][0]["x"] is None and d["nest"][0]["x_reason"]
    assert d["pe"] == 1.5 and d["n"] == 3 and d["ok"] is True
    assert "reason" not in json.dumps({k: v for k, v in d.items()
                                       if k in ("pe", "n", "ok")})
    with pytest.raises(ValueError, match="non-standard"):
        _strict_loads(json.dumps({"a": float("nan")}))  # the checker itself can fail
    _strict_loads(dumps_json({"a": float("nan"), "b": [float("inf")]}))


def test_ctrl_c_while_plotting_keeps_the_old_report(tmp_path, capsys, monkeypatch):
    import greybox.plotting as gp
    from test_bad_inputs import Case

    c = Case(tmp_path)
    assert main(c.argv()[:-1]) == 0  # with plots
    before = {p.name: p.read_bytes() for p in c.out.iterdir()}
    capsys.readouterr()

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(gp, "plot_outputs", interrupted)
    assert main(c.argv()[:-1] + ["--force"]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["greybox: interrupted"]
    assert {p.name: p.read_bytes() for p in c.out.iterdir()} == before  # old report, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["est.csv", "model.json", "report",
                                                          "val.csv"]  # no temporary folder


def test_interrupt_during_commit_is_held_back(tmp_path):
    import os
    import signal

    from greybox.io import commit_output_dir, deferred_interrupt, stage_output_dir

    with pytest.raises(KeyboardInterrupt):
        with deferred_interrupt():
            os.kill(os.getpid(), signal.SIGINT)
            done = True  # reached: the interrupt waits for the end of the block
    assert done
    out = tmp_path / "rep"
    st = stage_output_dir(out)
    (st / "a.txt").write_text("new")
    commit_output_dir(st, out, kind="report", names=["a.txt"])
    assert (out / "a.txt").read_text() == "new" and not st.exists()


def test_report_files_respect_the_umask(tmp_path, capsys):
    import os
    import stat

    from test_bad_inputs import Case

    old = os.umask(0o022)
    try:
        c = Case(tmp_path)
        assert main(c.argv()) == 0
    finally:
        os.umask(old)
    assert stat.S_IMODE(c.out.stat().st_mode) == 0o755
    for f in c.out.iterdir():
        assert stat.S_IMODE(f.stat().st_mode) == 0o644, f
    capsys.readouterr()


def test_no_baseline_skips_the_delta_row_only(tmp_path, capsys, spring):
    """``--no-baseline``: no parallel delta row, the same verdict and updated row."""
    model, est, val, _, code, stdout = spring
    argv = ["update", str(model), str(est), "--validate", str(val), "--json", "--no-plots"]
    assert code == 0
    full = json.loads(stdout)  # the shared full run (its plots change no number)
    assert main(argv + ["--out", str(tmp_path / "b"), "--no-baseline"]) == 0
    lean = json.loads(capsys.readouterr().out)
    assert "delta" in full["table"] and "delta" not in lean["table"]
    assert lean["message"] == full["message"]
    assert lean["table"]["updated"] == full["table"]["updated"]
