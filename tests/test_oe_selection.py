"""Pieces of the output-error term selection (issue 12): the shared forward selection,
the residual's colour and the batched simulation of the nonlinear pipeline.

The end-to-end laws (positions-only pendulum, overflow seed 7) are asserted in
tests/test_workflow_nonlinear.py and tests/test_tanks_overflow.py.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.signal import lfilter

import greybox as gb
from greybox.nonlinear import add_law
from greybox.trace.laws import StaticLaw, law_terms
from greybox.trace.oe import forward_select_oe
from greybox.nominal_refit import law_coordinates
from greybox.workflow_nonlinear import (SKIP, _LawColumns, _LawOutputError, _residual_colour,
                                       _run_columns, _takes_batch)
from test_workflow_nonlinear import DT, pendulum


class _Regression:
    """A linear least-squares problem with the output-error protocol (exact fits)."""

    def __init__(self, X, y):
        self.X, self.y = X, y

    def resid(self, theta, sel):
        cols = [j for _, j in sel]
        return self.y - (self.X[:, cols] @ theta if cols else 0.0)

    def fit(self, sel, start, max_nfev=100, trial=False):  # exact: trial changes nothing
        A = self.X[:, [j for _, j in sel]]
        th = np.linalg.lstsq(A, self.y, rcond=None)[0]
        return SimpleNamespace(x=th, fun=self.y - A @ th, jac=-A)

    def halfwidths(self, sol, sel):  # white-noise intervals: the prune keeps what BIC took
        s2 = np.mean(sol.fun ** 2)
        return 1.96 * np.sqrt(np.diag(s2 * np.linalg.inv(sol.jac.T @ sol.jac)))


def test_colour_is_one_for_white_and_large_for_coloured_residuals():
    white, ar = [], []
    for seed in range(5):
        w = np.random.default_rng(seed).standard_normal((1, 20000))
        white.append(_residual_colour(w))
        ar.append(_residual_colour(lfilter([1], [1, -0.9], w, axis=1)))
    # white: the Bartlett sum of sampling-noise autocorrelations, measured 1.00-1.007
    assert max(white) < 1.05 and min(white) >= 1.0
    # AR(1), phi = 0.9: long-run over short-run variance (1 + phi) / (1 - phi) = 19; the
    # data-driven bandwidth makes single estimates noisy (7.5-39 on these seeds), the median
    # within a factor 1.5 (16.2 measured)
    assert 19 / 1.5 < np.median(ar) < 19 * 1.5, ar


def test_selection_on_the_effective_sample_count_refuses_terms_fitting_the_colour():
    """y = 10 x0 + AR(1) noise (phi 0.95); five more regressors are random walks.

    Smooth regressors correlate with coloured noise by chance (spurious regression): a
    BIC on N residuals takes them, one on N / colour mostly does not, and with the gate's
    factor on each term's evidence (bic_factor = 10) none. Measured over seeds 0-19:
    plain BIC 19/20 laws with a spurious term, effective count 5/20, with the factor 0/20;
    x0 always first.
    """
    plain, eff, strict = 0, 0, 0
    colour = lambda r: _residual_colour(np.asarray(r)[None])  # noqa: E731
    for seed in range(20):
        rng = np.random.default_rng(seed)
        N = 2000
        X = np.cumsum(rng.standard_normal((N, 6)), axis=0)
        X /= X.std(axis=0)
        y = 10.0 * X[:, 0] + lfilter([1], [1, -0.95], rng.standard_normal(N))
        prob = _Regression(X, y)
        cands = [(0, j) for j in range(6)]
        sel_p = forward_select_oe(prob, cands, 4, N)[0]
        sel_e = forward_select_oe(prob, cands, 4, N, colour=colour)[0]
        sel_s = forward_select_oe(prob, cands, 4, N, colour=colour, factor=10.0)[0]
        assert sel_p[0] == sel_e[0] == sel_s[0] == (0, 0)  # the true term first
        plain += len(sel_p) > 1
        eff += len(sel_e) > 1
        strict += len(sel_s) > 1
    # bounds far from the measured counts (19, 5, 0 of 20): the effective count's bound
    # fails on a regression to the plain count (>= 15)
    assert plain >= 15, plain
    assert eff <= 9, eff
    assert strict <= 1, strict


def test_batched_simulation_equals_column_by_column_and_the_plain_simulation():
    """One coefficient column per state column: the same numbers as one at a time, and as
    greybox.simulate_nonlinear of the model with the law (an independent path)."""
    rng = np.random.default_rng(4)
    N = 300
    u = gb.multisine(N, dt=DT, amplitude=4.0, fmin=0.05, fmax=1.5, rng=rng)
    x = rng.uniform(-1, 1, (2, N))
    _, spec, eps = law_terms(x, u, ["theta", "omega"], ["T"])
    law = StaticLaw(spec=tuple(spec), eps=eps, coef=np.zeros((1, len(spec))),
                    Ddx=np.zeros((1, 2)), Ddu=np.zeros((1, 1)), nonlinear=True,
                    residual_var=np.ones(1), bic_gain=0.0, npar=0, formula="")
    G = np.array([[0.0], [1.0]])

    def disc(s):
        return gb.discretize_nonlinear(s, DT, substeps=2)

    y = rng.standard_normal((2, N))
    x0 = np.array([0.3, -0.2])
    prob = _LawOutputError(law, pendulum(), G, disc, y, u, x0, np.eye(2), np.zeros((2, 1)))
    names = [s[0] for s in spec]
    sel = [(0, names.index("omega^3")), (0, names.index("theta"))]
    TH = np.array([[-0.5, -0.2, 0.0], [0.3, 0.0, -1.0]])
    xs = prob.simulate(sel, TH)
    assert prob._batched
    prob._batched = False
    xs1 = prob.simulate(sel, TH)
    np.testing.assert_allclose(xs, xs1, rtol=1e-12, atol=1e-12)  # the same arithmetic
    # a model written for one state vector at a time (a user's MODEL.py: float(x[0]))
    f = pendulum().updfcn

    def scalar_only(t, xk, uk, p):
        return f(t, np.array([float(xk[0]), float(xk[1])]), np.array([float(uk[0])]), p)

    import control as ct
    one = ct.nlsys(scalar_only, lambda t, xk, uk, p: xk, states=2, inputs=1, outputs=2)
    prob1 = _LawOutputError(law, one, G, disc, y, u, x0, np.eye(2), np.zeros((2, 1)))
    xs2 = prob1.simulate(sel, TH)
    assert not prob1._batched  # detected: column by column
    np.testing.assert_allclose(xs2, xs, rtol=1e-12, atol=1e-12)
    coef = np.zeros((1, len(spec)))
    coef[0, names.index("omega^3")], coef[0, names.index("theta")] = -0.5, 0.3
    ref = gb.simulate_nonlinear(disc(add_law(pendulum(), G, replace_coef(law, coef).evaluate)),
                                u[:, SKIP:], x0=x0)
    np.testing.assert_allclose(xs[:, :, 0].T, ref.x, rtol=1e-10, atol=1e-12)


def test_laws_per_column_equal_each_law_alone_hinge_levels_included():
    """The batched forward-difference Jacobian of the law's output-error refinement runs one
    law per state column (its coefficients and hinge levels perturbed): the simulation of
    the batch equals each law's own simulation (greybox.simulate_nonlinear), columns with
    another hinge level included, and a model taking one state at a time is detected."""
    from greybox.trace.laws import hinge_name

    rng = np.random.default_rng(5)
    N = 200
    u = gb.multisine(N, dt=DT, amplitude=4.0, fmin=0.05, fmax=1.5, rng=rng)
    spec = (("omega^3", "x^3", 1), ("theta", "x", 0),
            (hinge_name("theta", "x_hi", 0.4), "x_hi", (0, 0.4)))
    coef = np.array([[-0.5, 0.3, -2.0]])
    law = StaticLaw(spec=spec, eps=np.array([0.1]), coef=coef, Ddx=np.zeros((1, 2)),
                    Ddu=np.zeros((1, 1)), nonlinear=True, residual_var=np.ones(1),
                    bic_gain=0.0, npar=3, formula="")
    theta0, law_at, sel, hinges = law_coordinates(law)
    assert hinges == [2] and theta0.size == 4  # three coefficients, one hinge level
    TH = theta0[:, None] + np.diag([0.1, -0.2, 0.5, 0.15])  # the last column moves the level
    laws = [law_at(TH[:, k]) for k in range(4)]
    G = np.array([[0.0], [1.0]])

    def disc(s):
        return gb.discretize_nonlinear(s, DT, substeps=2)

    cols = _LawColumns(laws[:1])
    model = disc(add_law(pendulum(), G, cols))
    x0 = np.array([0.3, -0.2])
    X0 = np.repeat(x0[:, None], 2, axis=1)
    assert _takes_batch(model, X0, u, lambda c: setattr(cols, "laws", [laws[i] for i in c]))
    cols.laws = laws
    xs = _run_columns(model, np.repeat(x0[:, None], 4, axis=1), u)
    for k in range(4):
        ref = gb.simulate_nonlinear(disc(add_law(pendulum(), G, laws[k].evaluate)), u, x0=x0)
        np.testing.assert_allclose(xs[:, :, k].T, ref.x, rtol=1e-12, atol=1e-12)
    assert len(cols._groups) == 2  # the moved level is its own group of terms
    f = pendulum().updfcn

    def scalar_only(t, xk, uk, p):
        return f(t, np.array([float(xk[0]), float(xk[1])]), np.array([float(uk[0])]), p)

    import control as ct
    one = ct.nlsys(scalar_only, lambda t, xk, uk, p: xk, states=2, inputs=1, outputs=2)
    model1 = disc(add_law(one, G, cols))
    assert not _takes_batch(model1, X0, u, lambda c: setattr(cols, "laws",
                                                            [laws[i] for i in c]))


def replace_coef(law, coef):
    from dataclasses import replace

    return replace(law, coef=coef)
