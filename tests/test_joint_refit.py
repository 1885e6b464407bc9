"""The joint output-error refit (greybox.trace.joint) on small plants with a known truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

import greybox as gb
from greybox.system import discretize, named_ss
from greybox.trace.channels import resolve_channel_spec
from greybox.trace.joint import JointEffect, refine_jointly
from greybox.trace.laws import fit_static
from greybox.validate import simulate_output
from plantlib import draw, linear_f, msd


def _pair_plant():
    A = np.array([[-1.0, 0.5], [0.3, -2.0]])
    B = np.array([[1.0], [0.5]])
    kw = dict(states=["x1", "x2"], inputs=["F"], outputs=["x1", "x2"])
    return A, B, kw


def _pair_record(seed: int, dt: float = 0.01, N: int = 3000):
    """The pair plant's continuous model, a white input (1, N) and its nearly noise-free
    states (2, N) sampled at dt; the generator, to draw more from."""
    rng = np.random.default_rng(seed)
    A, B, kw = _pair_plant()
    sys = named_ss(A, B, np.eye(2), np.zeros((2, 1)), 0, **kw)
    u = rng.standard_normal((1, N))
    x = gb.simulate(discretize(sys, dt), u, R=np.eye(2) * 1e-8, rng=1).y
    return sys, u, x, rng


def _with_law(G, law):
    """The continuous pair model with ``law`` folded into A and B along G."""
    A, B, kw = _pair_plant()
    return named_ss(A + G @ law.Ddx, B + G @ law.Ddu, np.eye(2), np.zeros((2, 1)), 0, **kw)


def test_a_two_equation_law_along_one_direction_is_refitted_and_keeps_its_direction():
    """A law of two equations acting along one direction (a force: d = g f, g = [1, 0.5],
    f = -0.4 x1) is refitted jointly; its formula keeps the direction line. (The line's
    term scale simulates the base model: it raised a TypeError until 2026-11-27.) The
    data are the law's own model, so the refit must return the coefficients unchanged
    within their intervals."""
    sys, u, x, rng = _pair_record(0)
    dt = 0.01
    d = np.vstack([-0.4 * x[0], -0.2 * x[0]]) + 1e-4 * rng.standard_normal((2, x.shape[1]))
    ch = resolve_channel_spec(sys, [("x1", "x2")])[0]
    law = fit_static(d, x, u, sys, False, list(ch.labels), ch.units)
    assert "one direction" in law.formula, law.formula
    final = _with_law(np.asarray(ch.G, dtype=float), law)
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


def test_the_joint_refit_says_whether_it_moved_the_effects():
    """``JointRefinement.moved``: a coefficient moved by its 95 % half-width or more (or a
    term dropped). A law found 30 % off its model's truth (noisy output) is moved; the
    refit's own result refitted again is not (it moves by the optimizer's tolerance, far
    inside the intervals). The loop skips the re-trace of the last effect when the joint
    refit did not move anything (the last pass saw what it would see again)."""
    sys, u, x, rng = _pair_record(1)
    dt, N = 0.01, x.shape[1]
    ch = resolve_channel_spec(sys, [("x1",)])[0]
    G = np.asarray(ch.G, dtype=float)
    truth = fit_static(-0.4 * x[:1] + 1e-4 * rng.standard_normal((1, N)), x, u, sys, False,
                       list(ch.labels), ch.units)
    y_true = simulate_output(discretize(_with_law(G, truth), dt), u, np.zeros(2))
    y = y_true + 1e-3 * rng.standard_normal(y_true.shape)
    off = fit_static(-0.52 * x[:1] + 1e-4 * rng.standard_normal((1, N)), x, u, sys, False,
                     list(ch.labels), ch.units)
    names = [s_[0] for s_ in off.spec]
    final = _with_law(G, off)
    noise = dict(Q=np.eye(2) * 1e-8, R=np.eye(2) * 1e-6, dt=dt, x0=np.zeros(2), k0=0)
    jr = refine_jointly([JointEffect(base=sys, channel=ch, law=off)], final, y, u, **noise)
    j = np.flatnonzero(jr.laws[0].coef[0])
    assert jr.moved, (names, jr.laws[0].formula)
    np.testing.assert_allclose(jr.laws[0].coef[0, j], -0.4, rtol=0.01)  # back at the truth
    again = refine_jointly([JointEffect(base=sys, channel=ch, law=jr.laws[0])], jr.continuous,
                           y, u, **noise)
    assert not again.moved, (jr.laws[0].formula, again.laws[0].formula)


def test_two_sensor_gains_are_named_without_a_joint_refit_that_has_nothing_to_refit():
    """Both sensors of a mass-spring-damper read with a gain error (pos 0.8x, vel 1.15x).
    The loop names both sensors' gains; a sensor's gain acts on C and D, which the joint
    refit holds (each sensor law is refitted on its own on the loop's model), so with two
    such effects there is nothing to refit jointly. Until 2026-11-28 the refit ran with
    no parameter and the report's trail read "joint refinement failed: cannot reshape
    array of size 0 into shape (0,newaxis)"."""
    nom = msd()
    d = draw(nom, linear_f(nom), n_true=2, dt=0.02, rng=np.random.default_rng(0), n_est=4000,
             n_val=2000, q_std=np.array([0.0, 1e-3]), r_std=1e-3)
    g = np.array([[0.8], [1.15]])
    rep = gb.close_the_loop(nom, d.y * g, d.u, d.y_val * g, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    assert rep.updated and [st.channel for st in rep.steps] == ["output(pos)", "output(vel)"]
    for st, truth in zip(rep.steps, (-0.2, 0.15)):
        law = st.effect.law
        names = [law.spec[j][0] for j in np.flatnonzero(law.coef[0])]
        assert len(names) == 1 and names[0].endswith("_model"), law.formula  # the gain alone
        # within 2 % of the truth: the half-widths are ~1 % (over seeds 0-11, 22 of 24
        # intervals cover the truth, both misses this seed's: 1.2 and 1.4 half-widths off;
        # with the residual's HAC alone, before 2026-11-28, 21 of 24 and 2.6 half-widths)
        np.testing.assert_allclose(law.coef[0, np.flatnonzero(law.coef[0])[0]], truth,
                                   rtol=0.02)
    assert not any("failed" in x.reason for x in rep.decisions), \
        [x.reason for x in rep.decisions if "failed" in x.reason]
    # the table's updated row is near the noise floor (measurement noise 1e-3 on signals of
    # ~0.3: SE ~0.2 %); the nominal one is the gains' 19 %
    assert rep.table["updated"].se.value < 0.05 * rep.table["nominal"].se.value


def test_an_effect_whose_only_term_holds_zero_once_refitted_is_dropped_whole():
    """Two effects: the true one (-0.4 x1 in eq(x1)) and a spurious one-term law of eq(x2)
    (-0.05 x2, which the data do not contain). Refitted jointly, the spurious term's 95 %
    interval holds 0 (in ~95 % of noise draws) and it is dropped although it is its
    effect's only term: that effect is then no effect (the loop drops its step). Until
    2026-12-07 the last term of an effect always stayed (zoo two_static 270939893 #1
    handed over ``d_v4 = -(3.37e-05 +- 0.03)*v1`` as an effect). The true term stays in
    every draw, within 1 % (the noise is 1e-3 of an output of ~0.1-1)."""
    dropped = 0
    for seed in (2, 3, 4):
        sys, u, x, rng = _pair_record(seed)
        dt, N = 0.01, x.shape[1]
        ch1, ch2 = resolve_channel_spec(sys, [("x1",), ("x2",)])
        G1, G2 = np.asarray(ch1.G, dtype=float), np.asarray(ch2.G, dtype=float)
        law1 = fit_static(-0.4 * x[:1] + 1e-4 * rng.standard_normal((1, N)), x, u, sys, False,
                          list(ch1.labels), ch1.units)
        law2 = fit_static(-0.05 * x[1:] + 1e-4 * rng.standard_normal((1, N)), x, u, sys,
                          False, list(ch2.labels), ch2.units)
        assert np.count_nonzero(law2.coef) == 1, law2.formula  # one term: x2
        base2 = _with_law(G1, law1)
        A2 = np.asarray(base2.A) + G2 @ law2.Ddx
        final = named_ss(A2, np.asarray(base2.B) + G2 @ law2.Ddu, np.eye(2), np.zeros((2, 1)),
                         0, states=["x1", "x2"], inputs=["F"], outputs=["x1", "x2"])
        y = simulate_output(discretize(base2, dt), u, np.zeros(2))
        y = y + 1e-3 * rng.standard_normal(y.shape)
        jr = refine_jointly([JointEffect(base=sys, channel=ch1, law=law1),
                             JointEffect(base=base2, channel=ch2, law=law2)], final, y, u,
                            Q=np.eye(2) * 1e-8, R=np.eye(2) * 1e-6, dt=dt, x0=np.zeros(2),
                            k0=0)
        j1 = np.flatnonzero(jr.laws[0].coef[0])
        assert len(j1) == 1, jr.laws[0].formula
        np.testing.assert_allclose(jr.laws[0].coef[0, j1], -0.4, rtol=0.01)
        dropped += int(jr.laws[1].npar == 0 and not np.any(jr.laws[1].coef))
    assert dropped >= 2, dropped  # P(fewer | method right) ~ 3 * 0.05^2 < 1 %


# --------------------------------------------------------------------------- an input's gain
# Two masses on springs, a damper each, the force F acting between them (SI units).
_M = np.array([1.3, 0.8])
_A2 = np.array([[0, 0, 1, 0], [0, 0, 0, 1],
                [-(6.0 + 3.0) / _M[0], 3.0 / _M[0], -0.5 / _M[0], 0],
                [3.0 / _M[1], -(4.0 + 3.0) / _M[1], 0, -0.7 / _M[1]]])
_B2 = np.array([[0.0], [0.0], [1.0 / _M[0]], [-1.0 / _M[1]]])
_KW2 = dict(states=["p1", "p2", "v1", "v2"], inputs=["F"], outputs=["p1", "p2", "v1", "v2"])


def _gain_case(row_gains, seed=5, dt=0.02, N=3000):
    """The loop's state after two effects on the two-mass model (F reaching each mass at
    ``row_gains`` of the model's, m1's damping 1.5 N s/m larger than the model's): the
    problem, its joint refit, the passes (a law of F in eq(v1)+eq(v2), then eq(v1)'s
    damping, fitted on the true d) and their refitted steps."""
    from greybox.records import Effect, EffectStep
    from greybox.workflow import _JointRefit, _prepare, _refitted_steps

    rng = np.random.default_rng(seed)
    nom = named_ss(_A2, _B2, np.eye(4), np.zeros((4, 1)), 0, **_KW2)
    dA = np.zeros((4, 4))
    dA[2, 2] = -1.5 / _M[0]
    true = named_ss(_A2 + dA, _B2 * np.array([[1], [1], [row_gains[0]], [row_gains[1]]]),
                    np.eye(4), np.zeros((4, 1)), 0, **_KW2)
    u = np.sign(np.sin(np.cumsum(rng.uniform(0, 0.2, (1, 2 * N)), axis=1)))
    sim = [gb.simulate(discretize(true, dt), u[:, k * N:(k + 1) * N], R=np.eye(4) * 1e-6,
                       rng=seed + k).y for k in range(2)]
    P = _prepare(nom, sim[0], u[:, :N], sim[1], u[:, N:], Q=np.eye(4) * 1e-10,
                 R=np.eye(4) * 1e-6, dt=dt, channels=None, nonlinear=False, max_order=0,
                 alpha=1e-3, lags=20, delta=False, delta_max_order=None, parsimony=1.1,
                 min_se_drop=0.8, bic_factor=10.0, progress=None, max_effects=3)
    pair, v1 = resolve_channel_spec(nom, [("v1", "v2"), ("v1",)])
    x = simulate_output(discretize(true, dt), u[:, :N], np.zeros(4))
    d1 = (np.array(row_gains) - 1.0)[:, None] * _B2[2:] * u[:, :N]
    law1 = replace(fit_static(d1 + 1e-6 * rng.standard_normal(d1.shape), x, u[:, :N], nom,
                              False, list(pair.labels), pair.units), time_base="continuous")
    base2 = named_ss(_A2 + np.asarray(pair.G) @ law1.Ddx, _B2 + np.asarray(pair.G) @ law1.Ddu,
                     np.eye(4), np.zeros((4, 1)), 0, **_KW2)
    law2 = replace(fit_static(-1.5 / _M[0] * x[2:3] + 1e-6 * rng.standard_normal((1, N)), x,
                              u[:, :N], base2, False, list(v1.labels), v1.units),
                   time_base="continuous")
    final = named_ss(np.asarray(base2.A) + np.asarray(v1.G) @ law2.Ddx, base2.B, np.eye(4),
                     np.zeros((4, 1)), 0, **_KW2)
    effs = [Effect(kind="static", order=0, formula=law.formula, channel=ch.name,
                   equations=ch.equations, law=law) for law, ch in ((law1, pair), (law2, v1))]
    passes = [(nom, pair, effs[0]), (base2, v1, effs[1])]
    joint = _JointRefit(P)
    jr, row = joint(passes, final, np.eye(4) * 1e-10, always=True)
    steps = [EffectStep(effect=e, channel=ch.name, se_before=1.0, se_after=1.0, model=None,
                        message=f"model error found in {', '.join(f'eq({s})' for s in ch.equations)}"
                                ": static effect; validation SE 1% -> 1%")
             for e, ch in zip(effs, (pair, v1))]
    return joint, passes, jr, row, _refitted_steps(steps, passes, jr, row), dt


def test_an_input_gain_stated_row_by_row_is_refitted_as_the_input_s_one_gain():
    """F reaches both masses at 0.7 of the model's gain (an actuator's gain error) beside a
    damping error of m1: the law of eq(v1)+eq(v2) holds F in each row (two parameters).
    Tried as the input's channel (``workflow._input_gains``), one gain refitted jointly
    with the damping, the criterion prefers it: input(F), d_F = -0.3 F within 1 % (the
    output noise is 1e-3 of the states' scale), the damping -1.5/m1 within 1 %, the
    message naming the input. With F reaching the masses at 0.7 and 0.4 (two errors, not
    one gain) the one gain fits worse and the law of the two equations stays."""
    from greybox.workflow import _input_gains

    joint, passes, jr, row, steps, dt = _gain_case((0.7, 0.7))
    notes = []
    jr2, row2, steps2, passes2 = _input_gains(joint, passes, jr, row, steps, dt, notes)
    assert [st.channel for st in steps2] == ["input(F)", "eq(v1)"], notes
    assert steps2[0].message.startswith("model error found in input F (it enters eq(v1), "
                                        "eq(v2))")
    law = steps2[0].effect.law
    np.testing.assert_allclose(law.coef[np.nonzero(law.coef)], [-0.3], rtol=0.01)
    damp = steps2[1].effect.law
    np.testing.assert_allclose(damp.coef[np.nonzero(damp.coef)], [-1.5 / _M[0]], rtol=0.01)
    assert passes2[0][1].name == "input(F)" and "input(F) kept" in notes[-1].reason
    # two row errors are not one gain: the law of the two equations stays
    joint, passes, jr, row, steps, dt = _gain_case((0.7, 0.4))
    notes = []
    _, _, steps3, _ = _input_gains(joint, passes, jr, row, steps, dt, notes)
    assert steps3[0].channel == "eq(v1)+eq(v2)", notes
    assert "eq(v1)+eq(v2) kept" in notes[-1].reason


# ------------------------------------------------------------- an integrator of a velocity
# One mass on a damper (SI units, m = 1): the model lacks a spring to ground (k = 4) or has
# a viscoelastic element (d = b / (s + 2) v) it lacks, found as a first-order law of v.
_KW1 = dict(states=["p", "v"], inputs=["F"], outputs=["p", "v"])


def _integrator_case(true_pole, seed, dt=0.02, N=3000):
    """(JointRefinement, effects) of a first-order law of v (started near a pole of 0)
    refitted on a mass whose missing effect is ``-4 / (s - true_pole) * v`` (a spring to
    ground at ``true_pole = 0``: -4 p from rest)."""
    from greybox.trace.dynamic import _law_from, _problem

    rng = np.random.default_rng(seed)
    base = named_ss(np.array([[0.0, 1.0], [0.0, -0.8]]), np.array([[0.0], [1.0]]), np.eye(2),
                    np.zeros((2, 1)), 0, **_KW1)
    ch = resolve_channel_spec(base, [("v",)])[0]
    truth = named_ss(np.array([[0.0, 1.0, 0.0], [0.0, -0.8, 1.0], [0.0, -4.0, true_pole]]),
                     np.array([[0.0], [1.0], [0.0]]), np.eye(3)[:2], np.zeros((2, 1)), 0,
                     states=["p", "v", "z"], inputs=["F"], outputs=["p", "v"])
    u = np.repeat(rng.choice([-1.0, 1.0], N // 50), 50)[None]  # steps held 1 s
    y = simulate_output(discretize(truth, dt), u, np.zeros(3))
    y = y + 1e-3 * np.std(y, axis=1, keepdims=True) * rng.standard_normal(y.shape)
    drv = [("x", 1)]
    prob = _problem(base, ch, y, u, dt, np.zeros(2), 0, drv)
    law = _law_from(base, ch, prob, drv, np.array([-0.05, -3.5, 0.0]), np.full(3, np.nan),
                    np.eye(2) * 1e-8, np.eye(2) * 1e-6)
    effs = [JointEffect(base=base, channel=ch, law=law)]
    jr = refine_jointly(effs, law.continuous, y, u, Q=np.eye(3) * 1e-10, R=np.eye(2) * 1e-6,
                        dt=dt, x0=np.zeros(3), k0=0)
    return jr, effs, y, u, dt


def test_an_integrator_of_a_velocity_is_stated_as_the_law_of_its_position():
    """A first-order law whose gain drives a velocity and whose pole's 95 % interval holds 0
    is the static law of the position (``b / s * v = b * p`` where dp/dt = v): one parameter
    fewer, the law's state gone (zoo two_static 270939893 #1 named a missing stiffness
    ``-29.6 / (s - (2.9e-05 +- 0.0017)) * v5``). Over 3 noise draws: the refitted pole's
    interval holds 0 (a 95 % interval: all 3 in ~86 % of runs of a right method, at least
    2 in > 99 %), the position's coefficient is the spring's -4 within 1 % (the noise is
    1e-3 of each output's RMS; measured error < 0.1 %) and the model without the state
    simulates the record as the law's model did (same SE within 1 %). A lag the data
    determine (pole -2, the interval far from 0) stays dynamic."""
    from greybox.trace.joint import integrators_as_positions, without_dead_states
    from greybox.trace.laws import StaticLaw

    held = 0
    for seed in (11, 12, 13):
        jr, effs, y, u, dt = _integrator_case(0.0, seed)
        law = jr.laws[0]
        if not abs(law.pole) <= law.ci[0]:
            continue
        held += 1
        alt = without_dead_states(integrators_as_positions(jr, effs, dt), effs)
        new = alt.laws[0]
        assert isinstance(new, StaticLaw) and new.npar == 1, new.formula
        assert [s[0] for s, c in zip(new.spec, new.coef[0]) if c] == ["p"], new.formula
        np.testing.assert_allclose(new.coef[0][new.coef[0] != 0], -4.0, rtol=0.01)
        assert alt.continuous.nstates == 2 and alt.npar_after == jr.npar_after - 1
        np.testing.assert_allclose(np.asarray(alt.continuous.A)[1], [-4.0, -0.8], rtol=0.01)
        se = [100 * np.mean(np.sqrt(np.mean((y - simulate_output(m.model.sys, u,
                                                                   np.zeros(m.model.sys.nstates)))
                                            ** 2, axis=1) / np.mean(y ** 2, axis=1)))
              for m in (jr, alt)]
        assert abs(se[1] - se[0]) <= 0.01 * se[0] + 1e-3, se
    assert held >= 2, held
    jr, effs, *_ = _integrator_case(-2.0, 14)
    assert not abs(jr.laws[0].pole) <= jr.laws[0].ci[0], jr.laws[0].formula
    assert integrators_as_positions(jr, effs, 0.02) is jr
