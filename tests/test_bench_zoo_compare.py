"""``bench/zoo_compare.py``: two zoo runs side by side (the tool that judges a method change)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

_SPEC = importlib.util.spec_from_file_location(
    "zoo_compare", Path(__file__).resolve().parents[1] / "bench" / "zoo_compare.py")
zoo_compare = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(zoo_compare)


def _draw(cls, i, right, found, se, seconds, true=1.0):
    return {"cls": cls, "seed": 7, "draw": i, "right": right, "found": found,
            "error_updated": se, "error_true": true, "seconds": seconds}


def _write(path, rows):
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return str(path)


def test_repaired_broken_and_worse_draws_are_listed_with_the_totals(tmp_path, capsys):
    before = _write(tmp_path / "b.jsonl", [
        _draw("coulomb", 0, False, "dynamic", 20.0, 10.0),
        _draw("coulomb", 1, True, "sign(v1)", 1.0, 10.0),
        _draw("dead_zone", 0, False, "v1|v1| + deadzone", 0.3, 5.0),
        _draw("static_state", 0, True, "v1", 1.0, 1.0),
        _draw("static_state", 1, True, "v1", 1.0, 1.0)])   # missing after
    after = _write(tmp_path / "a.jsonl", [
        _draw("coulomb", 0, True, "sign(v1)", 7.0, 15.0),    # repaired
        _draw("coulomb", 1, False, "v1 + v2", 3.0, 20.0),    # broken, error 3x
        _draw("dead_zone", 0, False, "v1 + deadzone", 1.5, 5.0),  # same verdict, 5x error
        _draw("static_state", 0, True, "v1", 1.0, 1.0)])     # unchanged: not listed
    assert zoo_compare.main([before, after]) == 0
    out = capsys.readouterr().out
    assert "| coulomb | 2 | 1 -> 1 | 20 -> 35 |" in out
    assert "| coulomb | 0 | False -> True | dynamic -> sign(v1) | 20 -> 7 (1) |" in out
    assert "| coulomb | 1 | True -> False | sign(v1) -> v1 + v2 | 1 -> 3 (1) |" in out
    assert "| dead_zone | 0 | False -> False |" in out
    assert "| static_state | 0 |" not in out.split("| class | draw |")[1]
    # right 2 -> 2 of the 4 matched draws (one repaired, one broken); 3 changed; 2 above
    # 1.5x (3 > 1.5, 1.5 > 0.45; 7 < 30 is not); 26 -> 41 s; 1 unmatched
    assert ("right 2 -> 2 of 4; 3 draws changed; 2 with the error above 1.5x its value "
            "before; time 26 -> 41 s (x1.58); 1 draws in one file only") in out


def test_unreadable_input_is_one_line_and_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.jsonl"
    bad.write_text("{not json\n")
    assert zoo_compare.main([str(bad), str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("zoo_compare: cannot read the runs"), err
    assert zoo_compare.main([str(bad)]) == 2  # one file: the usage line
