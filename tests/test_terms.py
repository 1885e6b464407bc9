"""Law terms as one class per kind (greybox.terms), and the kind added through it alone.

The registry is the one place that knows a kind: every kind evaluates as its library
row, the linear kinds are the law's linear part exactly, an unknown kind is a clear
error. The signed square ``v|v|`` (quadratic drag) was added as one class in
greybox/terms.py; the zoo's quadratic_drag draws check that close the loop names it,
alone and with its coefficient, on plants nobody tuned to.
"""

import functools
import warnings

import numpy as np
import pytest

import greybox as gb
from greybox import zoo
from greybox.exceptions import ModelError
from greybox.terms import (KINDS, LIBRARY, evaluate_terms, law_terms, linear_part,
                           output_terms, siblings, term_kind)


def _library(seed=0, N=300):
    rng = np.random.default_rng(seed)
    x, u = rng.standard_normal((3, N)), rng.standard_normal((2, N))
    T, spec, eps = law_terms(x, u, ["p1", "v1", "p2"], ["F", "G"], relative=[(0, 2)],
                             saturation=True, breaks=[1])
    return x, u, T, spec, eps


def test_every_kind_of_the_library_evaluates_as_its_library_row():
    x, u, T, spec, eps = _library()
    kinds = {sp[1] for sp in spec}
    # the library offers every state-equation kind of LIBRARY (sensor kinds: output_terms)
    assert kinds == {k for _, ks, _ in LIBRARY for k in ks}
    np.testing.assert_array_equal(evaluate_terms(spec, eps, x, u), T)  # bit for bit
    To, so, eo = output_terms(x, u, [1.0, 0.0, -0.5], [0.0, 2.0], "y")
    np.testing.assert_array_equal(evaluate_terms(so, eo, x, u), To)
    # the names carry the variables (the report's formula reads them)
    names = [sp[0] for sp in spec]
    for expect in ("v1^3", "sign(v1)", "|v1|", "v1*|v1|", "(p2-p1)", "v1*G", "1"):
        assert expect in names, expect


@pytest.mark.parametrize("shape", [(), (7,), (3, 4)])
def test_a_law_evaluates_its_terms_by_kind_as_each_term_alone(shape):
    """The evaluator gathers the terms of one kind into one call (a simulation evaluates
    the law at every sample, for K coefficient columns at once): bit for bit each
    term's own value, in the spec's order, on a shuffled spec, at one sample (x (n,)),
    on K columns and on a stack of them."""
    from greybox.terms import evaluator
    _, _, _, spec, eps = _library()
    rng = np.random.default_rng(1)
    x, u = rng.standard_normal((3,) + shape), rng.standard_normal((2,) + shape)
    for order in (np.arange(len(spec)), rng.permutation(len(spec))):
        sp = [spec[i] for i in order]
        out = evaluator(sp, eps)(x, u)
        each = np.array([term_kind(k).value(i, x, u, eps) * np.ones(shape) for _, k, i in sp])
        assert out.shape == (len(sp),) + shape
        np.testing.assert_array_equal(out, each)


def test_the_linear_part_is_exactly_the_linear_terms():
    x, u, T, spec, eps = _library(1)
    rng = np.random.default_rng(2)
    lin = [j for j, sp in enumerate(spec) if term_kind(sp[1]).linear]
    coef = np.zeros((2, len(spec)))
    coef[:, lin] = rng.standard_normal((2, len(lin)))
    Ddx, Ddu = linear_part(spec, coef, x.shape[0], u.shape[0])
    # the same sums in another order: equal to rounding (1e-12 of terms of size ~1)
    np.testing.assert_allclose(Ddx @ x + Ddu @ u, coef @ T, atol=1e-12)
    assert all(not term_kind(sp[1]).linear for sp in spec if sp[1] in ("x^3", "x|x|"))


def test_the_odd_forms_of_one_variable_are_siblings_and_the_even_form_is_not():
    _, _, _, spec, _ = _library()
    names = [sp[0] for sp in spec]
    j = names.index("v1")
    assert sorted(names[q] for q in siblings(spec, j)) == sorted(
        ["v1^3", "sign(v1)", "v1*|v1|"])
    assert siblings(spec, names.index("|v1|")) == []


def test_an_unknown_kind_is_a_clear_model_error():
    with pytest.raises(ModelError, match=r"unknown law term kind 'x\^5'.*greybox.terms"):
        evaluate_terms([("v^5", "x^5", 0)], np.ones(1), np.ones((1, 3)), np.ones((0, 3)))
    assert all(KINDS[k].kind == k for k in KINDS)  # each registered under its own name


# the two tests of a draw share its run (the cache below) only in one process: both run in
# one worker (--dist loadgroup), or each of two workers ran the three draws (~18 s)
DRAG_GROUP = pytest.mark.xdist_group("test_terms_drag")


@functools.lru_cache(maxsize=None)
def _drag(i):
    """Zoo quadratic_drag draw i (seed 90210) and its close-the-loop report, run once."""
    d = zoo.draw_class("quadratic_drag", 90210, i, n_est=4000)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R,
                                dt=d.dt, delta=False)
    return d, rep, zoo.score(d, rep)


@DRAG_GROUP
@pytest.mark.parametrize("i", [0, 1, 2])
def test_close_the_loop_names_a_quadratic_drag_alone_with_its_coefficient(i):
    """Zoo quadratic_drag draws (seed 90210): a chain of 1-6 masses with -cq v|v| on one
    mass (10-40 % of the force at v's rms), all states, the positions or a random subset
    measured. The right equation, the one term v|v| (not v^3, sign(v) or a sum of them,
    nor the p and F terms a law fitted at the sample's start took beside it), its
    coefficient within the zoo's 10 % and the truth inside its 95 % interval. The
    measurement noise dominates these records (the process noise makes up 0.1-26 % of the
    noise floor), so the law is refitted by output error: draw 0's d^ fit, kept before
    because it simulated within the floor rule, was -2.4334 +- 0.0043 against the truth's
    -2.4156 (4.2 half-widths off); output error gives -2.41561 +- 0.0014. Measured: the
    truth 0.03, 0.52, 0.66 half-widths from the estimate on draws 0, 1, 2."""
    d, rep, s = _drag(i)
    assert rep.updated and s.right_channel and s.right_kind and s.right_terms, (
        d.description, s.why, s.found)
    assert s.coefficients_within, s.found
    assert s.covered == s.n_coefficients == 1, s.found


@DRAG_GROUP
@pytest.mark.parametrize("i", [0, 1, 2])
def test_a_quadratic_drag_update_simulates_as_well_as_the_true_model(i):
    """The zoo's bar: validation SE within 1.5x the true model's. Draw 2 (only v1
    measured) was a known limit while a non-affine law started from the linear part's
    initial state (SE 0.78 % vs the true model's 0.10 %, right term and coefficient);
    it starts where its own simulation fits the first samples best now."""
    _, _, s = _drag(i)
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)
