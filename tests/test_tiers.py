"""The extended tier's table (``tests/conftest.py``, ``EXTENDED``) names tests that exist.

A renamed test would leave the table without a word and return to CI's run, whose budget
has ~50 s of margin on the slower machines (2026-12-08); a stale entry would hide nothing
but mislead the reader."""

from __future__ import annotations

import re
from pathlib import Path

from conftest import EXTENDED, _extended

HERE = Path(__file__).resolve().parent


def test_every_extended_entry_names_a_test_function_that_exists():
    for key in EXTENDED:
        file, name = key.split("::")
        src = (HERE / file).read_text(encoding="utf-8")
        func = name.split("[")[0]
        pattern = rf"^def {re.escape(func)}" + ("" if key.endswith("_") else r"\(")
        assert re.search(pattern, src, re.M), key


def test_the_tier_matches_ids_functions_and_prefixes_only():
    """A node id with its parameters, a function with all of them, a file's prefix."""
    key = next(k for k in EXTENDED if "[" in k)
    assert _extended(f"tests/{key}@group")
    fn = "test_nominal_refit.py::test_overflow_law_spill_and_the_wrong_parameter_are_named"
    assert _extended(f"tests/{fn}[x]") and _extended(f"tests/{fn}")
    assert _extended("tests/test_real_sets.py::test_tanks_goal_test_rms")
    assert not _extended("tests/test_real_sets.py::test_exchanger_before_after")
    assert not _extended("tests/test_zoo.py::test_a_sensor_lag_found_first_is_refitted_"
                         "with_the_state_law_found_after_it[10]")
