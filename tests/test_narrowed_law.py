"""A law of several state equations that holds terms in some of them only is stated as the
law of those equations (``workflow._narrowed``: the joint refit can drop every term of one
row of a pair channel's law, zoo two_static 1984922569 #1: ``d_v2 = 29.2*p2; d_v4 = 0`` and
``d_v2 = 0; d_v4 = -0.66*v4``, each scored as an extra empty effect). The narrowed law must
be the same law: the same model, the same simulation, the terms, intervals and units of
the rows kept."""

from __future__ import annotations

import numpy as np
import pytest
from dataclasses import replace

from greybox.hold import LawHold
from greybox.records import Effect, EffectStep
from greybox.system import discretize, named_ss
from greybox.trace.channels import equation_subset, resolve_channel_spec
from greybox.trace.laws import StaticLaw, law_rows, law_terms, simulate_with_law
from greybox.workflow import _narrowed

# two masses on springs, a damper between them (SI units); the law of eq(v1) and eq(v2)
A = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [-5.0, 2.0, -0.4, 0.4], [2.0, -3.0, 0.4, -0.4]])
B = np.array([[0.0], [0.0], [1.0], [0.0]])
KW = dict(states=["p1", "p2", "v1", "v2"], inputs=["F"], outputs=["p1", "p2"])
DT = 0.02


def _law_of_one_row(sys, ch, rng):
    """A cubic law in row 0 (d_v1 = -3 p1^3 - 0.7 v1, intervals set) and nothing in row 1,
    integrated over each sample (a continuous-time law's hold)."""
    x, u = rng.standard_normal((4, 200)), rng.standard_normal((1, 200))
    _, spec, eps = law_terms(x, u, list(sys.state_labels), list(sys.input_labels))
    spec = tuple(spec)
    j_cube = next(j for j, s in enumerate(spec) if s[1] == "x^3" and s[2] == 0)
    j_v1 = next(j for j, s in enumerate(spec) if s[1] == "x" and s[2] == 2)
    coef = np.zeros((2, len(spec)))
    coef[0, j_cube], coef[0, j_v1] = -3.0, -0.7
    ci = np.full(coef.shape, np.nan)
    ci[0, j_cube], ci[0, j_v1] = 0.05, 0.01
    Ddx = np.zeros((2, 4))
    Ddx[0, 2] = -0.7
    return StaticLaw(spec=spec, eps=eps, coef=coef, Ddx=Ddx, Ddu=np.zeros((2, 1)),
                     nonlinear=True, residual_var=np.array([0.1, 0.2]), bic_gain=50.0,
                     npar=2, formula="d_v1 = ...; d_v2 = 0", ci=ci, time_base="continuous",
                     hold=LawHold.of(A, ch.G, DT))


def test_the_law_of_the_rows_kept_is_the_same_law():
    sys = named_ss(A, B, np.eye(2, 4), np.zeros((2, 1)), 0, **KW)
    (ch,) = resolve_channel_spec(sys, [("v1", "v2")])
    rng = np.random.default_rng(3)
    law = _law_of_one_row(sys, ch, rng)
    sub = equation_subset(ch, [0])
    assert (sub.name, sub.equations, sub.labels) == ("eq(v1)", ("v1",), ("d_v1",))
    (one,) = resolve_channel_spec(sys, ["v1"])
    assert sub == one  # the channel greybox forms for that equation
    new = law_rows(law, [0], sub.labels, sub.units)
    assert new.npar == 2 and new.coef.shape == (1, law.coef.shape[1])
    assert np.array_equal(new.coef[0], law.coef[0]) and np.array_equal(new.ci[0], law.ci[0],
                                                                         equal_nan=True)
    assert "d_v2" not in new.formula and new.formula.startswith("d_v1 = ")
    assert "p1^3" in new.formula and "[v1]/s" in new.formula
    # the same simulation through the narrowed channel (the row dropped adds exactly 0)
    sd = discretize(sys, DT)
    u = rng.standard_normal((1, 1500))
    x0 = np.array([0.3, -0.2, 0.0, 0.1])
    y_full = simulate_with_law(sd, np.asarray(ch.G), law, u, x0)
    y_sub = simulate_with_law(sd, np.asarray(sub.G), new, u, x0)
    assert np.all(np.isfinite(y_full)) and np.ptp(y_full) > 0.1
    np.testing.assert_allclose(y_sub, y_full, rtol=1e-12, atol=1e-12)


def test_a_step_whose_law_kept_terms_in_one_equation_names_that_equation():
    sys = named_ss(A, B, np.eye(2, 4), np.zeros((2, 1)), 0, **KW)
    (ch,) = resolve_channel_spec(sys, [("v1", "v2")])
    law = _law_of_one_row(sys, ch, np.random.default_rng(4))
    eff = Effect(kind="static", order=0, formula=law.formula, channel=ch.name,
                 equations=ch.equations, nonlinear=True, law=law)
    st = EffectStep(effect=eff, channel=ch.name, se_before=5.0, se_after=1.0, model=None,
                    message="model error found in eq(v1), eq(v2): static effect; "
                            "validation SE 5% -> 1% (5x)")
    st2, ch2 = _narrowed(st, ch)
    assert ch2.name == "eq(v1)" and st2.channel == "eq(v1)"
    assert st2.effect.channel == "eq(v1)" and st2.effect.equations == ("v1",)
    assert st2.message.startswith("model error found in eq(v1): static effect")
    assert st2.effect.formula == st2.effect.law.formula and "d_v2" not in st2.effect.formula
    # a law with terms in every row, a force, a channel of one equation: as they are
    full = replace(law, coef=law.coef + np.eye(*law.coef.shape))
    st3 = replace(st, effect=replace(eff, law=full))
    assert _narrowed(st3, ch) == (st3, ch)
    assert _narrowed(st, None) == (st, None)
    with pytest.raises(ValueError, match="not a channel of state equations"):
        equation_subset(replace(ch, kind="force"), [0])
