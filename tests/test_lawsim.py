"""The compiled loops (numba, the ``fast`` extra) against the NumPy/SciPy code they replace.

The simulation of a model with a static law (greybox.lawsim): every compiled kind, each
hold, independent and shared columns, divergence at the same sample, and the numpy path
where numba or a kind's code is absent. The modal recursions of an LTI simulation
(greybox._lti): as ``lfilter`` computes them.

Tolerance: the two paths sum the same products in another order (a matrix product by
BLAS, a loop compiled), so they differ by roundings that a 400-sample recursion of a
stable model carries but does not grow past ~1e-12 relative (measured 2e-14 to 3e-12);
1e-9 leaves room for another CPU's BLAS and still fails on any wrong term (a sign, an
index, a level or an eps misread moves the states by 1e-3 or more).
"""

import control as ct
import numpy as np
import pytest
import scipy.linalg as sl

from greybox import lawsim
from greybox.hold import LawHold
from greybox.terms import KINDS
from greybox.trace.oe import _OutputErrorNonlinearLaw

pytestmark = pytest.mark.skipif(not lawsim.HAVE_NUMBA,
                                reason="numba not installed or GREYBOX_NO_NUMBA=1")

#: One term of every compiled kind on a 4-state, 2-input model (eps by index, levels).
SPEC = [("x1^3", "x^3", 1), ("sign(x2)", "sign", 2), ("x0", "x", 0), ("u1", "u", 1),
        ("(x3-x0)", "rel", (0, 3, 5)), ("(x2-x1)^3", "rel^3", (1, 2, 6)),
        ("max(x2 - 0.3, 0)", "x_hi", (2, 0.3)), ("min(x1 + 0.2, 0)", "x_lo", (1, -0.2)),
        ("x3*|x3|", "x|x|", 3), ("x2*u0", "x*u", (2, 0)), ("1", "const", 0),
        ("|x0|", "abs", 0), ("sign(x1-x0)", "rel_sign", (0, 1, 5)),
        ("dz(u0)", "u_dz", (0, 0.5, np.nan, "u0")), ("sat(u1)", "u_sat", (1, 0.7, np.nan, "u1")),
        ("|x2-x0|", "rel_abs", (0, 2, 6))]


class _Law:
    def __init__(self, spec, eps, hold):
        self.spec, self.eps, self.hold = spec, eps, hold


def _problem(hold_kind, spec=SPEC, N=400, seed=3):
    rng = np.random.default_rng(seed)
    n, m, dt = 4, 2, 0.05
    Ac = rng.standard_normal((n, n))
    Ac -= 3 * np.eye(n) * np.abs(np.linalg.eigvals(Ac)).max()
    A, Gc = sl.expm(Ac * dt), rng.standard_normal((n, 2))
    hold = {"none": None, "heun": (LawHold.of(Ac, Gc, dt).G0, LawHold.of(Ac, Gc, dt).G1),
            "etdrk4": LawHold.of(Ac, Gc, dt),
            "etdrk4x3": LawHold.of(Ac, Gc, dt, substeps=3)}[hold_kind]
    model = ct.ss(A, np.c_[0.1 * rng.standard_normal((n, m)), Gc * dt],
                  rng.standard_normal((1, n)), np.zeros((1, m + 2)), dt)
    u, y = rng.standard_normal((m, N)), rng.standard_normal((1, N))
    sel = [(q % 2, q) for q in range(len(spec))]
    th0 = 0.1 * rng.standard_normal(len(sel))
    law = _Law(spec, rng.uniform(0.1, 1, 8), hold)
    return _OutputErrorNonlinearLaw(law, model, 2, y, u, np.full(n, 0.1), 10, sel, th0,
                                    window=N), th0


def _both(p, TH, isolate):
    fast = p.simulate(TH, isolate)
    saved, p._compiled = p._compiled, None
    try:
        slow = p.simulate(TH, isolate)
    finally:
        p._compiled = saved
    return fast, slow


@pytest.mark.parametrize("hold", ["none", "heun", "etdrk4", "etdrk4x3"])
@pytest.mark.parametrize("isolate", [False, True])
def test_every_compiled_kind_simulates_as_the_numpy_recursion(hold, isolate):
    p, th0 = _problem(hold)
    assert p._compiled is not None  # every kind of SPEC has a code
    TH = np.c_[th0, 2 * th0, -th0, 0.5 * th0]
    fast, slow = _both(p, TH, isolate)
    assert np.all(np.isfinite(slow))
    np.testing.assert_allclose(fast, slow, rtol=1e-9, atol=1e-12)
    # the test can fail: one coefficient changed by 1e-3 of itself moves the outputs
    TH2 = TH.copy()
    TH2[0] *= 1.001
    assert np.max(np.abs(p.simulate(TH2, isolate) - slow)) > 1e-9


@pytest.mark.parametrize("hold", ["none", "etdrk4"])
def test_a_diverging_column_is_nan_from_the_same_sample_on_both_paths(hold):
    p, th0 = _problem(hold)
    TH = np.c_[th0, 4e3 * th0, th0]  # the middle column diverges (a cube at 4e3)
    fast, slow = _both(p, TH, isolate=True)
    assert np.array_equal(np.isfinite(fast), np.isfinite(slow))
    assert not np.all(np.isfinite(slow[1])) and np.all(np.isfinite(slow[[0, 2]]))
    np.testing.assert_allclose(fast[[0, 2]], slow[[0, 2]], rtol=1e-9, atol=1e-12)
    # shared fate (a Jacobian's columns): every column stops where the first diverges
    fast, slow = _both(p, TH, isolate=False)
    assert np.array_equal(np.isfinite(fast), np.isfinite(slow))
    assert not np.all(np.isfinite(slow[0]))


def test_every_code_is_a_registered_kind_and_an_uncompiled_kind_falls_back():
    assert set(lawsim.CODES) <= set(KINDS)
    uncompiled = [k for k in KINDS if k not in lawsim.CODES]
    assert uncompiled  # the sensor kinds (yhat, lag, drift) stay in numpy
    spec = SPEC[:3] + [("yhat", uncompiled[0], ((1.0, 0.0, 0.0, 0.0), ()))]
    assert lawsim.compiled_terms(spec, np.ones(8)) is None


def test_without_numba_the_numpy_recursion_runs(monkeypatch):
    p, th0 = _problem("etdrk4")
    TH = np.c_[th0, 2 * th0]
    fast = p.simulate(TH)
    monkeypatch.setattr(lawsim, "HAVE_NUMBA", False)
    assert lawsim.compiled_terms(SPEC, np.ones(8)) is None
    assert lawsim.simulate_columns(p.A, p.G, None, p.Bu, p.u, p.x0, TH, p._compiled,
                                   p.comp, False) is None
    p._compiled = lawsim.compiled_terms(p.spec, p.law.eps)
    np.testing.assert_allclose(p.simulate(TH), fast, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("n", [2, 3, 7])
def test_the_modal_recursions_compiled_are_lfilter_s(monkeypatch, n):
    """Real modes and complex pairs, over several chunks, outputs and states: the same
    numbers as ``lfilter`` per mode (bit for bit on the machine it was written on: the
    same products and sums in the same order; 1e-13 allows a SciPy built with fused
    multiply-adds; a wrong pole or a swapped real and imaginary part moves them by 1e-2)."""
    import greybox._lti as lti

    rng = np.random.default_rng(n)
    A = rng.standard_normal((n, n))
    A /= 1.02 * np.abs(np.linalg.eigvals(A)).max()
    B, C = rng.standard_normal((n, 2)), rng.standard_normal((3, n))
    u, x0 = rng.standard_normal((2, 2 * lti.CHUNK + 17)), rng.standard_normal(n)
    assert lti.LTIRecursion(A).kind == "modal"
    y, x = lti.lti_output(A, B, C, np.zeros((3, 2)), u, x0), lti.lti_states(A, B @ u, x0)
    monkeypatch.setattr(lti, "HAVE_NUMBA", False)
    np.testing.assert_allclose(y, lti.lti_output(A, B, C, np.zeros((3, 2)), u, x0),
                               rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(x, lti.lti_states(A, B @ u, x0), rtol=1e-13, atol=1e-13)
