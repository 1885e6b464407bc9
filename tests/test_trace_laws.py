"""The right law, not just a good fit: named terms, coefficients and intervals over seeds.

A 2-state mass-spring-damper (k = 4 N/m, c = 0.6 N s/m, m = 1 kg, dt =
0.01 s) whose nominal model has one parameter wrong. The law must name the
wrong parameter's term with the right coefficient, its 95 % interval must
cover the truth, and the correct parameter must never be flagged.
"""

from __future__ import annotations

import numpy as np
import pytest

import greybox as gb
from plantlib import draw, linear_f, msd

SEEDS = range(10)
CASES = {
    # case: (nominal, truth, term the law must name, its true coefficient, correct term)
    "damping": (dict(c=0.1), dict(c=0.6), "vel", -0.5, "pos"),
    "spring": (dict(k=2.0), dict(k=4.0), "pos", -2.0, "vel"),
}


def _run(case, seed):
    nom_kw, true_kw, *_ = CASES[case]
    nom = msd(**nom_kw)
    d = draw(nom, linear_f(msd(**true_kw)), n_true=2, dt=0.01,
             rng=np.random.default_rng(100 + seed), q_std=np.array([0.0, 1e-4]), r_std=1e-3)
    return gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                             delta=False)


@pytest.mark.slow
@pytest.mark.parametrize("case", list(CASES))
def test_law_named_over_seeds(case):
    _, _, term, coef, correct = CASES[case]
    named = covered = 0
    for seed in SEEDS:
        rep = _run(case, seed)
        assert rep.updated and rep.effect.equations == ("vel",), (seed, rep.message)
        law = rep.effect.law
        assert law is not None and law.time_base == "continuous", (seed, rep.message)
        names = [law.spec[j][0] for j in np.flatnonzero(law.coef[0])]
        j = [s[0] for s in law.spec].index(term)
        if names == [term] and abs(law.coef[0, j] - coef) <= 0.1 * abs(coef):
            named += 1
        covered += abs(law.coef[0, j] - coef) <= law.ci[0, j]
        # the correct parameter is never flagged
        assert not any(n.startswith(f"A[vel; {correct}]") for n in rep.effect.parameter_notes), \
            (seed, rep.effect.parameter_notes)
        assert any(n.startswith(f"A[vel; {term}]") for n in rep.effect.parameter_notes)
    # goal of the issue: >= 9 of 10 seeds name the one-term law within 10 %
    assert named >= 9, named
    # 95 % intervals: P(<= 7 of 10 covered) ~ 1.2 % if calibrated
    assert covered >= 8, covered


def test_joint_refit_merges_a_term_two_effects_hold():
    """A static law's p and a dynamic law's feedthrough of p add to the same entry of A: the
    joint refit keeps one coefficient (the earlier effect's) holding their sum, so the model
    is the same and the parameters stay identifiable."""
    from greybox.trace.joint import _Param, _independent

    dA = np.zeros((3, 3))
    dA[1, 0] = 1.0
    dB = np.zeros((3, 1))
    other = np.zeros((3, 3))
    other[2, 2] = 1.0
    ps = [_Param(0, ("s", 0, 0), dA, dB, 2.0, "a: p", True),
          _Param(1, ("a",), other, dB, -5.0, "b: pole", False),
          _Param(1, ("e", 0), 0.5 * dA, dB, 4.0, "b: p", True)]
    active, theta, merged = _independent(ps, np.array([2.0, -5.0, 4.0]))
    assert active == [0, 1] and merged == ["b: p (the same term as an earlier effect's)"]
    np.testing.assert_allclose(theta, [2.0 + 0.5 * 4.0, -5.0])  # exact: the model unchanged


def test_filtered_products_equal_the_products_of_the_filtered_terms():
    """The whitened regression's X X^T and X d accumulate over blocks of time without
    the whitened copy of the terms: they must equal the products of lfilter's output
    (start-up dropped) across block edges (K not a multiple of the block)."""
    from scipy.signal import lfilter

    from greybox.trace import laws

    rng = np.random.default_rng(3)
    K = 2 * laws._BLOCK + 777
    T = rng.standard_normal((6, K)).cumsum(axis=1)  # coloured, large: a stringent check
    d = rng.standard_normal(K)
    a = np.array([1.0, -0.9, 0.3, 0.05, -0.02])
    p = len(a) - 1
    W = lfilter(a, [1.0], T, axis=1)[:, p:]
    dw = lfilter(a, [1.0], d)[p:]
    gram, cross = laws._filtered_products(T, a, dw)
    # the same sums in another order: rounding only (1e-12 relative)
    np.testing.assert_allclose(gram, W @ W.T, rtol=1e-12)
    np.testing.assert_allclose(cross, W @ dw, rtol=1e-12, atol=1e-12 * np.abs(W @ dw).max())


class _LinearProblem:
    """A linear output error r = X theta - y; ``collapse``: a refit without that column
    ends in a worse minimum (its residual tripled), as a nonlinear refit can."""

    def __init__(self, X, y, collapse=None):
        self.X, self.y, self.collapse = X, y, collapse

    def fit(self, theta0, active):
        from types import SimpleNamespace

        Xa = self.X[:, active]
        th = np.linalg.lstsq(Xa, self.y, rcond=None)[0]
        fun = Xa @ th - self.y
        if self.collapse is not None and self.collapse not in active:
            fun = 3.0 * fun
        return SimpleNamespace(x=th, fun=fun, jac=Xa)

    def halfwidths(self, sol, active, Q, R):
        s2 = float(np.mean(sol.fun ** 2))
        return 1.96 * np.sqrt(s2 * np.diag(np.linalg.inv(self.X[:, active].T @ self.X[:, active])))


@pytest.mark.parametrize("collapse", [None, 1])
def test_joint_pruning_keeps_a_term_whose_drop_collapses_the_fit(collapse):
    """The joint refit's drop loop: terms inside their interval are dropped one at a time,
    but a drop whose refit ends far above the local prediction (another minimum) is undone
    and its term kept; the loop used to accept it."""
    from greybox.trace.joint import _Param, _prune

    rng = np.random.default_rng(0)
    X = np.linalg.qr(rng.standard_normal((500, 3)))[0]  # orthonormal columns
    e = rng.standard_normal(500)
    e -= X @ (X.T @ e)  # noise orthogonal to every term: coefficients exactly (2, 0, 0)
    prob = _LinearProblem(X, 2.0 * X[:, 0] + 0.1 * e, collapse)
    z = np.zeros((1, 1))
    ps = [_Param(0, ("s", 0, j), z, z, 0.0, f"t{j}", True, group=None) for j in range(3)]
    sol = prob.fit(np.zeros(3), [0, 1, 2])
    hw = prob.halfwidths(sol, [0, 1, 2], None, None)
    # the two zero coefficients go, unless dropping t1 collapses the fit: then t1 stays
    rss_full = float(np.sum(sol.fun ** 2))
    active, sol, hw, dropped = _prune(prob, ps, [0, 1, 2], sol, hw, None, None)
    assert sorted(dropped) == (["t1", "t2"] if collapse is None else ["t2"])
    assert active == ([0] if collapse is None else [0, 1])
    np.testing.assert_allclose(sol.x[0], 2.0, rtol=1e-12)  # a linear fit: exact
    # never the collapsed fit: the same residual as the full fit (rounding only)
    np.testing.assert_allclose(float(np.sum(sol.fun ** 2)), rss_full, rtol=1e-9)


def test_terms_that_overflow_are_a_failed_channel_not_a_traceback():
    """A diverged estimator's states (finite, ~1e200) make the law's Gram matrix overflow:
    an IdentificationError (a failed candidate in close_the_loop), not scipy's ValueError
    (a zoo draw, state_sensor seed 649577221 draw 1, ended in a traceback)."""
    from greybox.exceptions import IdentificationError
    from greybox.trace.laws import _ls_fit
    rng = np.random.default_rng(0)
    with pytest.raises(IdentificationError, match="overflow"):
        _ls_fit(1e200 * rng.normal(size=(2, 100)), rng.normal(size=100))


def test_a_term_identically_zero_on_the_record_has_no_interval():
    """A regressor row of zeros (a dead zone's breakpoint refitted past the input's range)
    gets the half-width inf ("not determined"); it was 0/0 (1e-300 squared underflows),
    a RuntimeWarning out of close_the_loop. The other rows keep the half-widths of the
    regression without it (the zero column adds nothing to J'J)."""
    from greybox.trace.laws import _regression_halfwidths
    rng = np.random.default_rng(5)
    J = rng.standard_normal((2, 500))
    e = 0.1 * rng.standard_normal(500)
    with np.errstate(all="raise"):
        hw = _regression_halfwidths(np.vstack([J, np.zeros(500)]), e)
    alone = _regression_halfwidths(J, e)
    assert hw[2] == np.inf
    np.testing.assert_allclose(hw[:2], alone, rtol=1e-9)
    assert np.all(np.isfinite(alone)) and np.all(alone > 0)
