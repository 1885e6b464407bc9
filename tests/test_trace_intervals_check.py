"""Output-error intervals of a nonlinear law checked against the law's own simulation.

``greybox.trace.oe.checked_intervals``: the half-widths come from a forward-difference
Jacobian of the simulation; where the simulation is not smooth at that scale (a friction
law too fast for one step per sample chatters around zero speed) the Jacobian is noise
and the intervals were printed orders of magnitude too narrow (zoo coulomb, seed
361028620: ``± 7.9e-07`` on 0.379). Truth here: a mass on a spring with one law term,
data simulated with that very law (so the coefficient is exactly right).
"""

from __future__ import annotations

import numpy as np
import pytest

import greybox as gb
from greybox.trace.laws import StaticLaw, simulate_with_law
from greybox.trace.oe import checked_intervals
from greybox.terms import law_terms

DT = 0.05


def _case(term: str, coef: float, eps_scale: float, seed: int = 0):
    """(law, augmented discrete model, y, u) for d_v = coef * term on a mass-spring."""
    rng = np.random.default_rng(seed)
    sysc = gb.named_ss([[0.0, 1.0], [-4.0, -0.4]], [[0.0], [1.0]], np.eye(2), np.zeros((2, 1)),
                       0, states=["p", "v"], inputs=["F"], outputs=["p", "v"])
    # the model with d as a second input entering eq(v) (what the trace fits)
    aug = gb.named_ss(sysc.A, np.array([[0.0, 0.0], [1.0, 1.0]]), np.eye(2),
                      np.zeros((2, 2)), 0, states=["p", "v"], inputs=["F", "d_v"],
                      outputs=["p", "v"])
    model = gb.discretize(aug, DT)
    u = np.repeat(rng.standard_normal((1, 300)), 5, axis=1)  # held 5 samples
    x = np.vstack([np.sin(np.arange(1500) * 0.05), np.cos(np.arange(1500) * 0.05)])
    _, spec, eps = law_terms(x, u, ["p", "v"], ["F"])
    eps = eps * eps_scale
    j = [sp[0] for sp in spec].index(term)
    c = np.zeros((1, len(spec)))
    c[0, j] = coef
    ci = np.full_like(c, np.nan)
    ci[0, j] = 1e-2 * abs(coef)  # an interval at a scale the simulation should resolve
    law = StaticLaw(spec=tuple(spec), eps=eps, coef=c, Ddx=np.zeros((1, 2)),
                    Ddu=np.zeros((1, 1)), nonlinear=True, residual_var=np.zeros(1),
                    bic_gain=0.0, npar=1, formula=f"d_v = {coef}*{term}", ci=ci)
    G = np.asarray(model.B, dtype=float)[:, 1:]
    plain = gb.discretize(sysc, DT)
    y = simulate_with_law(plain, G, law, u, np.zeros(2))
    y = y + 1e-3 * rng.standard_normal(y.shape)
    return law, model, y, u, j


def test_a_smooth_laws_interval_is_kept():
    # a cubic spring: the simulation is smooth in its coefficient; the cost at the
    # interval's ends rises as the Jacobian predicts (ratio ~1, far above 0.1)
    law, model, y, u, j = _case("v^3", -0.5, 1.0)
    out, notes = checked_intervals(law, model, 1, y, u, np.zeros(2), 20, ["d_v"], ["[v]/s"])
    assert out is law and notes == []


def test_a_chattering_laws_interval_is_not_determined():
    # sign(v) over 0.1 % of v's RMS with coefficient 3: the law's rate times dt is
    # ~3 / 7e-4 * 0.05 = 200 (a step is stable up to 2): the simulation chatters
    law, model, y, u, j = _case("sign(v)", -3.0, 0.02)
    rate = 3.0 / law.eps[1] * DT
    assert rate > 2
    out, notes = checked_intervals(law, model, 1, y, u, np.zeros(2), 20, ["d_v"], ["[v]/s"])
    assert np.isinf(out.ci[0, j]) and out.coef[0, j] == law.coef[0, j]
    assert "interval not determined" in out.formula and len(notes) == 1
    assert "sign(v)" in notes[0]


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_a_smoothed_sign_slow_enough_for_one_step_keeps_its_interval(scale):
    # the same sign law at the library's width (5 % of the RMS, ~0.035) and a coefficient
    # whose rate times dt is below 2: stable, smooth; the interval is kept
    law, model, y, u, j = _case("sign(v)", -0.5 * scale, 1.0)
    assert 0.5 * scale / law.eps[1] * DT < 2
    out, notes = checked_intervals(law, model, 1, y, u, np.zeros(2), 20, ["d_v"], ["[v]/s"])
    assert out is law and notes == []
