"""The golden guard itself (tests/golden_guard.py): it can fail, and its keys repeat."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import golden_guard as g

HERE = Path(__file__).resolve().parent


def test_a_moved_verdict_is_a_difference_a_new_key_is_not():
    old = {"updated": True, "effect": {"formula": "d_v2 = -(15 ± 0.0026)*p2"},
           "table": {"updated": {"se": 0.351}}}
    assert g._diff(old, old) == []
    assert g._diff(old, {**old, "recommended": True}) == []          # a key gained
    assert g._diff(old, {k: v for k, v in old.items() if k != "updated"})  # a key lost
    assert g._diff(old, {**old, "updated": False})
    assert g._diff(old, {**old, "table": {"updated": {"se": 0.351 * (1 + 1e-5)}}})
    assert not g._diff(old, {**old, "table": {"updated": {"se": 0.351 * (1 + 1e-8)}}})
    # a printed number to one unit of its last digit; another term is a change
    assert not g._diff(old, {**old, "effect": {"formula": "d_v2 = -(15 ± 0.0027)*p2"}})
    assert g._diff(old, {**old, "effect": {"formula": "d_v2 = -(15 ± 0.0029)*p2"}})
    assert g._diff(old, {**old, "effect": {"formula": "d_v2 = -(15 ± 0.0026)*p1"}})


def _key(c3: str) -> str:
    code = ("import sys; sys.path.insert(0, %r); import golden_guard as g; "
            "from test_workflow_nonlinear import pendulum; "
            "print(g.fingerprint((pendulum(%s),), {'Q': [[1.0]]}))" % (str(HERE), c3))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True).stdout.strip()


def test_keys_repeat_across_processes_and_see_the_closure():
    """A NonlinearIOSystem's key comes from its equations' code and the values they close
    over, never from an address (a key that changed between runs would leave its
    snapshot unchecked, silently)."""
    a, b = _key("0.1"), _key("0.1")
    assert a == b and len(a) == 24
    assert _key("0.0") != a


def test_why_a_row_has_no_se_is_compared_by_its_words_not_its_numbers():
    """The reason's numbers measure a simulation that amplifies rounding; its words do
    not move. Any other text's numbers still count to their last printed digit."""
    why = "sensitive to where it starts: it still moves by {} % of y; PE used"
    a = {"table": {"nominal": {"se_reason": why.format("2.81e+03")}}}
    b = {"table": {"nominal": {"se_reason": why.format("2.94e+03")}}}
    assert g._diff(a, b) == []
    c = {"table": {"nominal": {"se_reason": "a pole on the unit circle; PE used"}}}
    assert g._diff(a, c)
    f1, f2 = {"formula": "-(0.502 ± 0.0074)*sign(v)"}, {"formula": "-(0.512 ± 0.0074)*sign(v)"}
    assert g._diff(f1, f2)
