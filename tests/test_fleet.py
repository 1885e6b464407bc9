"""greybox fleet: a generated fleet of a dozen two-mass chains on a 2-worker LocalCluster.

Every unit's nominal model is ``plantlib.chain(2)``; its true plant has a wall spring on
mass 2 the model lacks (six units, 4 to 30 N/m: d_v2 = -k p2), a damper on mass 1 (two
units, 1 and 2.5 N s/m: d_v1 = -c v1) or nothing (four units, one of which has a corrupt
estimation CSV until the last test fixes it). Records are short (2000 + 1000 samples) and
the parallel delta baseline is off, so the whole module stays within the suite's budget
(25 to 44 s measured on the shared 2-core machine, load 2.7 to 6.5).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from greybox.cli import main
from greybox.exceptions import DataError, MissingDependencyError
from greybox.fleet import (EXIT_FAILED, UnitResult, find_units, fleet, group_units, run_unit)
from greybox.model_io import write_model
from plantlib import chain, chain_unit, write_unit

distributed = pytest.importorskip("distributed")

# unit -> (effect, size, seed); seeds drawn once, the verdicts asserted below
UNITS = {
    "pump01": ("spring", 4.0, 11), "pump02": ("spring", 8.0, 12), "pump03": ("spring", 12.0, 13),
    "pump04": ("spring", 20.0, 15), "pump05": ("spring", 25.0, 16), "pump06": ("spring", 30.0, 17),
    "pump07": ("damping", 1.0, 18), "pump08": ("damping", 2.5, 23),
    "pump09": ("right", 0.0, 20), "pump10": ("right", 0.0, 21), "pump11": ("right", 0.0, 24),
    "pump12": ("right", 0.0, 22),
}
CORRUPT = "pump12"   # its estimation CSV gets a cell "n/a"; fixed, its model is right
SPRING = [u for u, (e, _, _) in UNITS.items() if e == "spring"]
DAMPING = [u for u, (e, _, _) in UNITS.items() if e == "damping"]


def _corrupt(path: Path) -> None:
    lines = path.read_text().splitlines()
    cells = lines[50].split(",")
    cells[2] = "n/a"
    lines[50] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet")
    for name, (effect, size, seed) in UNITS.items():
        case = chain_unit(effect, size, seed)
        write_unit(root / "units" / name, case)
    write_model(root / "MODEL.json", chain(2), case.Q, case.R, Ts=case.dt)
    _corrupt(root / "units" / CORRUPT / "estimation.csv")
    return root


@pytest.fixture(scope="module")
def client():
    import logging

    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=logging.ERROR)
    c = distributed.Client(cluster)
    yield c
    c.close()
    cluster.close()


@pytest.fixture(scope="module")
def first(fleet_dir, client):
    lines = []
    rep = fleet(fleet_dir / "MODEL.json", fleet_dir / "units", out=fleet_dir / "out",
                client=client, progress=lambda p: lines.append(p))
    return rep, lines


def test_every_verdict_and_group(first, fleet_dir):
    rep, lines = first
    by = {r.unit: r for r in rep.units}
    assert sorted(by) == sorted(UNITS)
    for name, (effect, size, _) in UNITS.items():
        r = by[name]
        if name == CORRUPT:
            continue
        assert r.status == "done", (name, r.error)
        want = {"spring": "deviates", "damping": "deviates", "right": "right"}[effect]
        assert r.verdict == want, (name, r.message)
    # the groups: six springs in eq(v2) on p2, two dampers in eq(v1) on v1
    assert [(g.key, set(g.units)) for g in rep.groups] == [
        ("eq(v2) static: p2", set(SPRING)), ("eq(v1) static: v1", set(DAMPING))]
    spring = rep.groups[0].coefficients
    assert [c.name for c in spring] == ["p2"]
    for unit, k in spring[0].values:  # d_v2 = -k p2 (m2 = 1 kg); 3 %: noise, short records
        np.testing.assert_allclose(k, -UNITS[unit][1], rtol=0.03)
    np.testing.assert_allclose(spring[0].median, -16.0, rtol=0.03)   # sizes 4 ... 30
    assert rep.by_verdict("right") == ("pump09", "pump10", "pump11")
    for r in rep.units:
        if r.verdict == "deviates":
            assert len(r.effects) == 1 and r.se_after < r.se_before / 3, (r.unit, r.effects)
    assert len(lines) == len(UNITS) and lines[-1].k == lines[-1].K == len(UNITS)


def test_corrupt_unit_reported_and_others_complete(first, fleet_dir):
    rep, _ = first
    assert [r.unit for r in rep.failed] == [CORRUPT]
    err = rep.failed[0].error
    assert err.startswith("DataError") and "'n/a' is not a number" in err and "\n" not in err
    out = fleet_dir / "out"
    assert sorted(p.stem for p in (out / "units").glob("*.json")) == sorted(UNITS)
    assert rep.answer == ("12 units: 8 deviate from the model (2 explanations: 6 by eq(v2) "
                          "static: p2; 2 by eq(v1) static: v1), 3 are right, 1 failed.")
    md = (out / "fleet.md").read_text()
    assert md.startswith("# greybox fleet report\n\n**12 units: 8 deviate")
    assert "## Failed units" in md and CORRUPT in md.split("## Failed units")[1]
    assert (out / "coefficients.png").stat().st_size > 1000

    def strict(s):
        raise ValueError(f"non-strict JSON constant {s}")

    doc = json.loads((out / "fleet.json").read_text(), parse_constant=strict)
    assert doc["counts"]["failed"] == 1 and doc["failed"][CORRUPT] == err
    unit = json.loads((out / "units" / "pump03.json").read_text(), parse_constant=strict)
    assert unit["status"] == "done" and unit["report"]["effect"]["kind"] == "static"
    assert unit["explanation"] == [{"equations": ["v2"], "kind": "static", "order": 0,
                                    "terms": ["p2"]}]


def test_rerun_skips_done_units_and_cli_exit_codes(first, fleet_dir, client, capsys):
    out = fleet_dir / "out"
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "units").glob("*.json")}
    again = fleet(fleet_dir / "MODEL.json", fleet_dir / "units", out=out, client=client)
    status = {r.unit: r.status for r in again.units}
    assert status.pop(CORRUPT) == "failed"          # a failed unit is tried again
    assert set(status.values()) == {"skipped (done before)"}
    assert again.answer == first[0].answer
    for name, ns in stamps.items():
        if name != f"{CORRUPT}.json":
            assert (out / "units" / name).stat().st_mtime_ns == ns, name
    # the command line on the same cluster: exit 3 while a unit fails ...
    args = ["fleet", str(fleet_dir / "MODEL.json"), str(fleet_dir / "units"), "--out", str(out),
            "--scheduler", client.scheduler.address]
    assert main(args + ["--quiet"]) == EXIT_FAILED
    assert "1 failed." in capsys.readouterr().out
    # ... and 0 once its file is fixed; only that unit runs
    case = chain_unit(*UNITS[CORRUPT])
    write_unit(fleet_dir / "units" / CORRUPT, case)
    assert main(args + ["--json"]) == 0
    cap = capsys.readouterr()
    doc = json.loads(cap.out)
    assert doc["counts"] == {"units": 12, "deviates": 8, "right": 4, "unexplained": 0,
                             "failed": 0, "skipped (done before)": 11}
    assert f"[12/12] {CORRUPT}: done (model right)" in cap.err
    assert doc["right"] == ["pump09", "pump10", "pump11", CORRUPT]


def test_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path, fleet_dir, capsys):
    out = tmp_path / "out"
    base = ["fleet", str(fleet_dir / "MODEL.json"), str(fleet_dir / "units"), "--out", str(out)]
    bad = [["fleet", str(tmp_path / "nope.json")] + base[2:],
           ["fleet", str(fleet_dir / "MODEL.json"), str(tmp_path / "empty")] + base[3:],
           base + ["--workers", "0"]]
    (tmp_path / "empty").mkdir()
    for argv in bad:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("greybox: error: ") and err.count("\n") == 1, err
        assert not out.exists()


def test_missing_dask_names_the_extra(monkeypatch, tmp_path, fleet_dir):
    monkeypatch.setitem(sys.modules, "distributed", None)   # import distributed fails
    with pytest.raises(MissingDependencyError, match=r'pip install "greybox\[fleet\]"'):
        fleet(fleet_dir / "MODEL.json", fleet_dir / "units", out=tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_import_greybox_does_not_import_dask():
    code = ("import sys, greybox; "
            "print(sorted(m for m in ('dask', 'distributed') if m in sys.modules))")
    got = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert got.stdout.strip() == "[]"


def test_timeout_fails_the_unit_with_one_line(fleet_dir):
    d = run_unit(str(fleet_dir / "MODEL.json"), "pump01",
                 str(fleet_dir / "units" / "pump01" / "estimation.csv"),
                 str(fleet_dir / "units" / "pump01" / "validation.csv"), timeout=1e-9)
    assert d["status"] == "failed" and d["error"].startswith("timeout: still running after")


def test_manifest_and_unit_names(tmp_path, fleet_dir):
    m = tmp_path / "manifest.csv"
    m.write_text(f"unit,estimation,validation\na,{fleet_dir}/units/pump01/estimation.csv,"
                 f"x/validation.csv\n")
    (u,) = find_units(m)
    assert u.name == "a" and u.validation == tmp_path / "x" / "validation.csv"
    m.write_text("unit,estimation,validation\n../up,e.csv,v.csv\n")
    with pytest.raises(DataError, match="cannot name a file"):
        find_units(m)
    m.write_text("unit,estimation\na,e.csv\n")
    with pytest.raises(DataError, match="expected"):
        find_units(m)


def test_mad_rule_outliers_and_groups():
    expl = ((("v2",), "static", 0, ("p2",)),)
    units = [UnitResult(f"u{i}", "done", "deviates", explanation=expl,
                        coefficients=(("p2", v),))
             for i, v in enumerate([-10.0, -10.5, -9.5, -10.2, -9.8, -30.0])]
    units.append(UnitResult("r", "done", "right"))
    (g,) = group_units(units)
    assert g.key == "eq(v2) static: p2" and len(g.units) == 6
    (c,) = g.coefficients
    assert c.median == pytest.approx(-10.1) and c.mad == pytest.approx(0.35)
    assert c.outliers == ("u5",)
