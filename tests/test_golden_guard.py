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


def test_another_machine_compares_the_verdict_not_the_numbers():
    """On a machine other than the recording one, numbers (BLAS kernels, optimizer paths)
    are not compared; the verdict still is: a term, a channel, a pass or a fail."""
    old = {"updated": True, "effect": {"formula": "d_x1 = -(2.03 ± 0.017)*max(x1 - (8.045 ± "
                                                  "0.0093), 0)", "order": 0},
           "gate": {"passed": {"bic": True}, "bic_gain": 72810.0},
           "candidates": [{"npar": 4, "se_estimation": 70.47}]}
    moved = {"updated": True, "effect": {"formula": "d_x1 = -(1.82 ± 0.054)*max(x1 - (7.943 ± "
                                                    "0.029), 0)", "order": 0},
             "gate": {"passed": {"bic": True}, "bic_gain": 19211.0},
             "candidates": [{"npar": 3, "se_estimation": 68.2}]}
    assert g._diff(old, moved)                      # the recording machine: numbers count
    assert g._diff(old, moved, portable=True) == []
    for wrong in ({**moved, "updated": False},
                  {**moved, "gate": {"passed": {"bic": False}, "bic_gain": 1.0}},
                  {**moved, "effect": {**moved["effect"], "order": 1}},
                  {**moved, "explanation": [{"law": {"terms": [{"name": "x1"}]}}]}):
        assert g._diff({**old, "explanation": [{"law": {"terms": [{"name": "x2"}]}}]},
                       {"explanation": [{"law": {"terms": [{"name": "x2"}]}}], **wrong},
                       portable=True)


def test_the_machine_signature_names_the_blas_kernels_and_versions():
    sig = g.machine()
    assert sig["blas"]
    assert {"cpu", "numpy", "scipy", "control", "slycot", "probe"} <= set(sig)
    assert sig["probe"] == g._probe()  # the same bits on a second run


def test_a_key_survives_the_last_bits_of_another_machine():
    """Data simulated on another machine differ in their last bits; the key does not (to
    ~4.5 digits), so that machine still finds the snapshot. A real change of the data
    (here 1e-3 relative) is another key."""
    import numpy as np

    y = np.random.default_rng(0).standard_normal((2, 500))
    a = g.fingerprint((y,), {"Q": [[1.0]]})
    assert g.fingerprint((y * (1 + 1e-13),), {"Q": [[1.0]]}) == a
    assert g.fingerprint((y * (1 + 1e-3),), {"Q": [[1.0]]}) != a
    assert g.fingerprint((y,), {"Q": [[2.0]]}) != a


def test_the_probe_is_compared_once_a_recording_carries_it(tmp_path, monkeypatch):
    """Every number is compared only with ``GREYBOX_GOLDEN=strict``, and then only where
    the signature is the recording's: a recording made before the probe existed still
    matches its machine; one that carries a probe matches only an equal probe."""
    import json

    monkeypatch.setattr(g, "GOLDEN", tmp_path)
    sig = g.machine()
    cases = [({k: v for k, v in sig.items() if k != "probe"}, "strict", True),
             (sig, "strict", True), ({**sig, "probe": "0" * 16}, "strict", False),
             (sig, "", False), ({**sig, "cpu": "other"}, "strict", False)]
    for rec, mode, same in cases:
        (tmp_path / "MACHINE.json").write_text(json.dumps(rec))
        monkeypatch.setenv("GREYBOX_GOLDEN", mode)
        monkeypatch.setattr(g, "_SAME", [])
        assert g.same_machine() is same, (rec, mode)
