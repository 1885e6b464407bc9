"""The joint output-error refit (greybox.trace.joint) on small plants with a known truth."""

from __future__ import annotations

import numpy as np

import greybox as gb
from greybox.system import discretize, named_ss
from greybox.trace.channels import resolve_channel_spec
from greybox.trace.joint import JointEffect, refine_jointly
from greybox.trace.laws import fit_static
from greybox.validate import simulate_output


def _pair_plant():
    A = np.array([[-1.0, 0.5], [0.3, -2.0]])
    B = np.array([[1.0], [0.5]])
    kw = dict(states=["x1", "x2"], inputs=["F"], outputs=["x1", "x2"])
    return A, B, kw


def test_a_two_equation_law_along_one_direction_is_refitted_and_keeps_its_direction():
    """A law of two equations acting along one direction (a force: d = g f, g = [1, 0.5],
    f = -0.4 x1) is refitted jointly; its formula keeps the direction line. (The line's
    term scale simulates the base model: it raised a TypeError until 2026-11-27.) The
    data are the law's own model, so the refit must return the coefficients unchanged
    within their intervals."""
    rng = np.random.default_rng(0)
    A, B, kw = _pair_plant()
    sys = named_ss(A, B, np.eye(2), np.zeros((2, 1)), 0, **kw)
    dt, N = 0.01, 3000
    u = rng.standard_normal((1, N))
    x = gb.simulate(discretize(sys, dt), u, R=np.eye(2) * 1e-8, rng=1).y
    d = np.vstack([-0.4 * x[0], -0.2 * x[0]]) + 1e-4 * rng.standard_normal((2, N))
    ch = resolve_channel_spec(sys, [("x1", "x2")])[0]
    law = fit_static(d, x, u, sys, False, list(ch.labels), ch.units)
    assert "one direction" in law.formula, law.formula
    G = np.asarray(ch.G, dtype=float)
    final = named_ss(A + G @ law.Ddx, B + G @ law.Ddu, np.eye(2), np.zeros((2, 1)), 0, **kw)
    y = simulate_output(discretize(final, dt), u, np.zeros(2))
    jr = refine_jointly([JointEffect(base=sys, channel=ch, law=law)], final, y, u,
                        Q=np.eye(2) * 1e-8, R=np.eye(2) * 1e-8, dt=dt, x0=np.zeros(2), k0=0)
    new = jr.laws[0]
    assert "one direction" in new.formula, new.formula
    j = [s[0] for s in new.spec].index("x1")
    # noise-free output of the law's own model: the refit stays at the fitted values
    # (to the optimizer's tolerance, far inside the printed intervals)
    np.testing.assert_allclose(new.coef[:, j], law.coef[:, j], rtol=1e-6)
    assert np.all(np.abs(new.coef[:, j] - np.array([-0.4, -0.2])) <= 1e-3)
