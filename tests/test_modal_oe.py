"""Output-error refinement in modal form (greybox.ident.modal_oe)."""

from __future__ import annotations

import numpy as np
import pytest

from greybox import IdentificationError
from greybox._lti import lti_states
from greybox.ident import refine_output_error


def _truth():
    # a lightly damped pair (|lambda| = 0.95) and a real pole 0.6; 2 inputs, 2 outputs
    r, th = 0.95, 0.3
    A = np.array([[r * np.cos(th), -r * np.sin(th), 0], [r * np.sin(th), r * np.cos(th), 0],
                  [0, 0, 0.6]])
    B = np.array([[1.0, 0.0], [0.0, 0.5], [1.0, -1.0]])
    C = np.array([[1.0, 0.0, 1.0], [0.0, 1.0, -0.5]])
    return A, B, C


def test_refinement_recovers_the_poles_from_a_perturbed_start():
    A, B, C = _truth()
    rng = np.random.default_rng(5)
    u = rng.standard_normal((2, 4000))
    y = C @ lti_states(A, B @ u, np.zeros(3)) + 0.05 * rng.standard_normal((2, 4000))
    # start: poles moved by ~0.03-0.05, B perturbed by 20 %
    A0 = A.copy()
    A0[:2, :2] *= 0.97
    A0[2, 2] = 0.65
    B0 = B * (1 + 0.2 * rng.standard_normal(B.shape))
    res = refine_output_error(A0, B0, C, u, y)
    assert res.cost < 0.5 * res.cost_start
    lam = np.sort_complex(np.linalg.eigvals(res.A))
    true = np.sort_complex(np.linalg.eigvals(A))
    # 4000 samples at SNR ~20: pole standard errors ~1e-3; 5e-3 is 5 sigma and
    # 10x below the starting error
    np.testing.assert_allclose(lam, true, atol=5e-3)
    # the refined model reproduces the noise-free output to the noise level
    yhat = res.C @ lti_states(res.A, res.B @ u, np.zeros(3))
    y0 = C @ lti_states(A, B @ u, np.zeros(3))
    assert np.sqrt(np.mean((yhat - y0) ** 2)) < 0.01
    # the similarity maps the start's states to the refined ones' (x_start = T x)
    np.testing.assert_allclose(np.linalg.solve(res.T, A0 @ res.T)[2, 2], 0.65, atol=1e-12)


def test_refinement_rejects_unstable_start():
    A, B, C = _truth()
    u = np.ones((2, 100))
    with pytest.raises(IdentificationError, match="stable starting model"):
        refine_output_error(1.2 * A, B, C, u, np.zeros((2, 100)))


def test_the_bracketed_condition_check_decides_as_the_singular_values_do():
    """``_lti._cond_at_most`` (the modal path's gate, in each coordinates it tries) brackets
    cond_2 by the 1-norm condition number and takes the singular values only between the
    brackets: its decision must be ``np.linalg.cond(V) <= _MAX_COND`` for every V, well and
    badly conditioned alike (the draws below span cond_2 from ~1 to ~1e6, a third of them
    near the threshold)."""
    from greybox._lti import _MAX_COND
    from greybox._lti import _cond_at_most as _conditioned

    rng = np.random.default_rng(7)
    near = 0
    for trial in range(600):
        n = int(rng.integers(1, 17))
        U, _ = np.linalg.qr(rng.standard_normal((n, n)))
        W, _ = np.linalg.qr(rng.standard_normal((n, n)))
        top = 10 ** rng.uniform(0, 6) if trial % 3 else _MAX_COND * rng.uniform(0.5, 2)
        V = U @ np.diag(np.geomspace(1.0, top, n)) @ W.T  # cond_2(V) = top (n > 1)
        c2 = np.linalg.cond(V)
        near += 0.5 * _MAX_COND < c2 < 2 * _MAX_COND
        assert _conditioned(V, np.linalg.inv(V)) == (c2 <= _MAX_COND), (n, c2)
    assert near > 100  # the threshold's neighbourhood was exercised


def test_a_chain_s_modes_take_the_modal_path_once_its_states_are_rescaled():
    """The bench's 32-state chain by positions (16 masses, the middle spring missing, dt =
    0.01 s) with a candidate law's terms in eq(v9) (a linear law the output-error selection
    tried, from ``bench/workflow.py chains 20000 32:positions``): its eigenvector matrix
    reads cond 2.2e3 in the state's own units and 17 once the states are rescaled
    (``_lti._scaled``), so the modal path (O(n N)) is taken, not the Schur one (O(n^2 N):
    69 % of that run's time went there). Its states agree with the Schur path's within
    1e-9 of each state's RMS over 4000 samples (measured 9e-12); a nearly defective matrix
    still takes Schur."""
    import scipy.linalg as sla
    from plantlib import chain

    from greybox import _lti

    Ac = np.array(chain(16, k=20.0, missing=[(7, 8)]).A, dtype=float)
    Ac[17, [12, 15, 18, 20]] += [0.762, 1.837, 1.324, -2.076]
    Phi = sla.expm(Ac * 0.01)
    lam, V = np.linalg.eig(Phi)
    assert np.linalg.cond(V) > _lti._MAX_COND  # the raw gate alone would refuse it
    rec = _lti.LTIRecursion(Phi)
    assert rec.kind == "modal"
    rng = np.random.default_rng(0)
    v, x0 = 1e-3 * rng.standard_normal((32, 4000)), rng.standard_normal(32)
    xm = _lti.lti_states(Phi, v, x0)
    saved = _lti._MAX_COND
    try:
        _lti._MAX_COND = 0.5  # every matrix takes the Schur path
        assert _lti.LTIRecursion(Phi).kind == "schur"
        xs = _lti.lti_states(Phi, v, x0)
    finally:
        _lti._MAX_COND = saved
    rms = np.sqrt(np.mean(xs**2, axis=1))
    assert np.max(np.abs(xm - xs).max(axis=1) / rms) < 1e-9
    # a Jordan block, exact or barely split (eigenvalues 1 +- 1e-7): only scales 1e7-1e16
    # apart would condition it, past _SCALE_RANGE (its modal simulation was off by 1.7 of
    # the state's RMS before the scales were clipped): Schur
    for J in ([[1.0, 1.0], [0.0, 1.0]], [[1.0, 1.0], [1e-14, 1.0]],
              [[0.99, 1.0, 0.0], [0.0, 0.99, 1.0], [0.0, 0.0, 0.99]]):
        assert _lti.LTIRecursion(np.array(J)).kind == "schur", J
