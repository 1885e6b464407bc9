"""The randomized plant zoo (greybox.zoo, issue 27 item 1): the draws, the scorer, and a few
fixed draws through close_the_loop.

1. Every class draws reproducibly from a seed, records a consistent truth, and its data
   are what the truth says: the true plant simulated by greybox's own discretization
   equals the noise-free validation record; the nominal model plus the recorded effects
   (built from the records alone) equals the true plant; the noise has the declared
   covariance and an SNR of 40-60 dB; the effect is visible above the noise.
2. The scorer, on hand-made reports: a right explanation scores right, and each way of
   being wrong (coefficient, extra term, channel, orientation, false flag, update of a
   correct model) is caught.
3. close_the_loop on one fixed draw of each correct-model class (the model must stay
   unchanged) and of the classes where greybox is right today (channel, kind, terms,
   coefficients within 10 % and inside their 95 % intervals). Classes where greybox is
   wrong today are measured by bench/zoo.py only.
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from types import SimpleNamespace

import numpy as np
import pytest

import greybox as gb
from greybox import zoo
from greybox.nonlinear import discretize_nonlinear, simulate_nonlinear
from greybox.terms import term_kind

N_EST = 400         # short records: the checks of part 1 are per sample, not statistical
SEED = 7
CLASSES = list(zoo.CLASSES)


@lru_cache(maxsize=None)
def _draw(cls: str, seed: int = SEED) -> zoo.ZooDraw:
    return zoo.draw_class(cls, seed, 0, n_est=N_EST)


def _horizon(d: zoo.ZooDraw) -> int:
    """Samples over which two simulations of the same plant may be compared: all, or for an
    open-loop unstable truth 2 time constants of its fastest unstable pole (rounding
    differences of 1e-16 then grow by e^2 at most)."""
    N = d.u_val.shape[1]
    if hasattr(d.true, "A"):     # a StateSpace truth (the unstable ones are)
        lam = np.linalg.eigvals(np.asarray(d.true.A, float)).real.max()
        if lam > 0:
            return min(N, int(2.0 / (lam * d.dt)))
    return N


def _rel_err(a, b) -> float:
    """Largest deviation relative to each output's rms."""
    sc = np.sqrt(np.mean(b ** 2, axis=1, keepdims=True))
    return float(np.max(np.abs(a - b) / sc))


# ------------------------------------------------------------------------- 1. the draws
def test_registry_names_every_class_of_the_issue():
    """Issue 27 item 1's list, one class each (two effects of different kinds: two), and the
    quadratic drag that measures the signed-square term kind."""
    assert set(zoo.CLASSES) == {
        "static_state", "linear_force", "cubic_force", "coulomb", "quadratic_drag",
        "actuator_gain",
        "actuator_lag1", "actuator_lag2", "dead_zone", "saturation", "flexible_shaft",
        "thermal_mass", "sensor_gain_offset", "sensor_lag", "sensor_drift", "two_static",
        "state_sensor", "state_input", "unstable_closed_loop", "nonlinear_model",
        "correct_linear", "correct_nonlinear", "correct_closed_loop"}
    assert set(zoo.CORRECT_CLASSES) == {"correct_linear", "correct_nonlinear",
                                        "correct_closed_loop"}
    for name, fn in zoo.CLASSES.items():
        assert "Parameters" in fn.__doc__ and "ZooDraw" in fn.__doc__, name


@pytest.mark.parametrize("cls", CLASSES)
def test_draw_is_reproducible_from_its_seed(cls):
    a, b = _draw(cls), zoo.draw_class(cls, SEED, 0, n_est=N_EST)
    for f in ("y", "u", "y_val", "u_val", "y_val_clean", "Q", "R", "true_x0", "snr_db"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    assert a.truth == b.truth and a.description == b.description and a.dt == b.dt
    c = zoo.draw_class(cls, SEED + 1, 0, n_est=N_EST)
    assert c.description != a.description or not np.array_equal(c.y, a.y)
    # time is the last axis; the validation record is half as long (at least 300)
    assert a.y.shape[1] == a.u.shape[1] == N_EST
    assert a.y_val.shape[1] == a.u_val.shape[1] == 300


@pytest.mark.parametrize("cls", CLASSES)
def test_truth_is_structurally_consistent(cls):
    d = _draw(cls)
    assert d.truth.correct == (cls in zoo.CORRECT_CLASSES)
    st, ins, outs = (list(d.nominal.state_labels), list(d.nominal.input_labels),
                     list(d.nominal.output_labels))
    assert list(d.true.state_labels[:len(st)]) == st
    assert list(d.true.output_labels) == outs and list(d.true.input_labels) == ins
    if any(e.channel in ("input", "sensor") for e in d.truth.effects) and \
            cls not in ("dead_zone", "saturation"):
        # one output of a one-input plant: a gain or lag at the input is one at the sensor
        assert len(outs) >= 2
    for e in d.truth.effects:
        assert e.channel in ("state", "input", "sensor") and e.law in ("static", "dynamic")
        pool = {"state": st, "input": ins, "sensor": outs}[e.channel]
        assert e.targets and set(e.targets) <= set(pool), e
        if e.law == "static":
            assert e.order == 0 and e.terms and e.dynamics is None
            assert {t.target for t in e.terms} <= set(e.targets)
            assert {v for t in e.terms for v in t.variables} == set(e.drivers)
        else:
            h = e.dynamics
            assert e.order == h.order >= 1 and not e.terms
            assert set(h.drivers) == set(e.drivers) and tuple(h.targets) == e.targets
            assert np.all(h.poles.real < 0)          # a hidden part that settles


@pytest.mark.parametrize("cls", CLASSES)
def test_true_plant_simulation_equals_the_noise_free_record(cls):
    """The generator's fast path (exact ZOH, its own RK4) against greybox's discretization of
    ``draw.true``: 1e-8 when both are exact (linear), 1e-4 when one is RK4 with 4+ sub-steps
    per sample (the RK4 error at |lambda| h <= 0.3 is ~1e-6 over 300 samples)."""
    d = _draw(cls)
    k = _horizon(d)
    y = zoo.simulate_true(d, d.u_val)
    tol = 1e-8 if hasattr(d.true, "A") else 1e-4     # a StateSpace truth: both exact
    assert _rel_err(y[:, :k], d.y_val_clean[:, :k]) < tol


@pytest.mark.parametrize("cls", CLASSES)
def test_nominal_plus_recorded_effects_is_the_true_plant(cls):
    """The truth is exactly what the nominal lacks: the nominal with the recorded effects
    added (zoo.model_with_truth, built from the records alone) reproduces the true plant.
    1e-4: RK4 of the composed model (8 sub-steps) against the exact simulation of a
    linear truth; a nonlinear truth is integrated with its own sub-steps (the same RK4 on
    the same equations, rounding apart); a coefficient or a pole 1 % off gives 4e-4 to 5e-2
    (measured on six classes)."""
    d = _draw(cls)
    k = _horizon(d)
    m, x0 = zoo.model_with_truth(d)
    sub = 8 if hasattr(d.true, "A") else d.substeps
    y = simulate_nonlinear(discretize_nonlinear(m, d.dt, substeps=sub),
                           d.u_val[:, :k], x0=x0).y_clean
    assert _rel_err(y, d.y_val_clean[:, :k]) < 1e-4


@pytest.mark.parametrize("cls", CLASSES)
def test_noise_and_snr(cls):
    """Measurement noise as declared by R (std within 20 %: 300 samples give a 4 % standard
    error, so 20 % is 5 of them) and an SNR of 40-60 dB; the estimation record's SNR is the
    drawn one within 0.5 dB (process noise is 3 % of the measurement noise level)."""
    d = _draw(cls)
    assert np.all((d.snr_db >= 40) & (d.snr_db <= 60))
    r = np.sqrt(np.diag(d.R))
    ratio = np.std(d.y_val - d.y_val_clean, axis=1) / r
    assert np.all(np.abs(ratio - 1) < 0.2), ratio
    snr = 20 * np.log10(np.sqrt(np.mean(d.y ** 2, axis=1)) / r)
    assert np.all(np.abs(snr - d.snr_db) < 0.5), (snr, d.snr_db)
    assert d.Q.shape == (len(d.nominal.state_labels),) * 2 and np.all(np.diag(d.Q) > 0)


@pytest.mark.parametrize("cls", [c for c in CLASSES if c not in zoo.CORRECT_CLASSES and
                                 not _draw(c).closed_loop])
def test_each_effect_is_visible_above_the_noise(cls):
    """Leaving any one recorded effect out of the truth misses the validation record by more
    than 5x the noise on some output (zoo.VISIBLE; the generator draws again below it, as
    it did for 1 of 24 two_static draws): each effect is there to be found. The ratio is
    computed here independently of zoo.effect_visibility, over the whole record."""
    d = _draw(cls)
    for q in range(len(d.truth.effects)):
        rest = zoo.Truth(d.truth.effects[:q] + d.truth.effects[q + 1:])
        m, x0 = zoo.model_with_truth(dataclasses.replace(d, truth=rest))
        y = simulate_nonlinear(discretize_nonlinear(m, d.dt, substeps=4), d.u_val,
                               x0=x0).y_clean
        gap = np.sqrt(np.mean((y - d.y_val_clean) ** 2, axis=1)) / np.sqrt(np.diag(d.R))
        assert gap.max() > zoo.VISIBLE, (q, gap)
    assert min(zoo.effect_visibility(d)) > zoo.VISIBLE


# ----------------------------------------------------------------------- 2. the scorer
def _law(spec, coef, ci):
    return SimpleNamespace(spec=list(spec), coef=np.atleast_2d(coef).astype(float),
                           ci=np.atleast_2d(ci).astype(float))


def _report(d, channel, equations, spec, coef, ci, *, notes=(), kind="static", updated=True,
            G=None):
    """A hand-made LoopReport with one static effect (the fields found_effects reads)."""
    law = _law(spec, coef, ci)
    ef = SimpleNamespace(kind=kind, order=0, formula="", channel=channel,
                         equations=tuple(equations), parameter_notes=tuple(notes), law=law,
                         dynamic_law=None, subsystem=None)
    row = SimpleNamespace(se=SimpleNamespace(value=1.0), pe=SimpleNamespace(value=1.0),
                          se_defined=True)
    ch = SimpleNamespace(name=channel, G=G)
    return SimpleNamespace(updated=updated, steps=(SimpleNamespace(effect=ef, channel=channel,
                                                                   message=""),),
                           effect=ef, channel=ch, message="", nominal=d.nominal,
                           table={"nominal": row, "updated": row})


@lru_cache(maxsize=None)
def _static_draw():
    """A static_state draw of a chain (a damper or a spring to the ground on one mass)."""
    for seed in range(50):
        d = zoo.draw_class("static_state", seed, 0, n_est=N_EST)
        if d.description.startswith("chain"):
            return d
    raise AssertionError("no chain in 50 static_state draws")


def _true_term(d):
    (e,) = d.truth.effects
    (t,) = e.terms
    return e, t


def test_score_right_explanation():
    d = _static_draw()
    e, t = _true_term(d)
    v = t.variables[0]
    rep = _report(d, f"eq({t.target})", e.equations, [(v, "x", 0)], t.coefficient,
                  0.02 * abs(t.coefficient))
    s = zoo.score(d, rep, 1.5)
    assert s.right and s.right_channel and s.right_terms and s.coefficients_within
    assert (s.covered, s.n_coefficients, s.false_flags, s.seconds) == (1, 1, 0, 1.5)
    assert s.false_update is None and s.why == ""


def test_score_catches_each_way_of_being_wrong():
    d = _static_draw()
    e, t = _true_term(d)
    v, c, eq = t.variables[0], t.coefficient, t.target
    # 20 % off, its interval too narrow to cover the truth
    s = zoo.score(d, _report(d, f"eq({eq})", (eq,), [(v, "x", 0)], 1.2 * c, 0.01 * abs(c)))
    assert s.right_terms and not s.coefficients_within and not s.right and s.covered == 0
    # an extra term beside the right one
    other = next(x for x in d.nominal.state_labels if x != v)
    s = zoo.score(d, _report(d, f"eq({eq})", (eq,), [(v, "x", 0), (other, "x", 1)],
                             [c, 0.1], [0.01, 0.01]))
    assert not s.right_terms and not s.right and s.coefficients_within
    # the right law in another equation
    wrong_eq = next(x for x in d.nominal.state_labels if x.startswith("v") and x != eq) \
        if len(d.nominal.state_labels) > 2 else "p1"
    s = zoo.score(d, _report(d, f"eq({wrong_eq})", (wrong_eq,), [(v, "x", 0)], c, 0.01))
    assert not s.right_channel and not s.right
    # a note flagging a parameter the truth has right, and one on the true entry
    notes = (f"A[{eq}; {other}] = 1 in the model; the data want 1.1 (+10 %)",
             f"A[{eq}; {v}] = 2 in the model; the data want 3 (+50 %)")
    s = zoo.score(d, _report(d, f"eq({eq})", (eq,), [(v, "x", 0)], c, 0.01, notes=notes))
    assert s.false_flags == 1
    # nothing found
    s = zoo.score(d, _report(d, f"eq({eq})", (eq,), [(v, "x", 0)], c, 0.01, updated=False))
    assert not s.right and "not found" in s.why


def test_score_false_update_of_a_correct_model():
    d = _draw("correct_linear")
    st = d.nominal.state_labels[0]
    s = zoo.score(d, _report(d, f"eq({st})", (st,), [(st, "x", 0)], 0.1, 0.01))
    assert s.correct_model and s.false_update and not s.right
    s = zoo.score(d, _report(d, f"eq({st})", (st,), [(st, "x", 0)], 0.1, 0.01, updated=False))
    assert s.right and s.false_update is False


def test_score_reads_a_force_and_a_relative_cube_either_way_round():
    """One force along g in two equations (md = 1) is per-equation coefficients g_e * c; a
    cube of (p1-p2) is minus the cube of (p2-p1)."""
    d = _draw("cubic_force")
    (e,) = d.truth.effects
    t1, t2 = e.terms
    a, b = t1.variables
    g = np.array([1.0, t2.coefficient / t1.coefficient])
    st = list(d.nominal.state_labels)
    G = np.zeros((len(st), 1))
    G[[st.index(t1.target), st.index(t2.target)], 0] = g
    rep = _report(d, f"force({t1.target},{t2.target})", e.equations,
                  [(f"({a}-{b})^3", "rel^3", 0)], -t1.coefficient, 1e-6 * abs(t1.coefficient),
                  G=G)
    s = zoo.score(d, rep)
    assert s.right, s.why
    assert s.covered == 2    # the interval is tight, but the coefficient is exact


def test_score_accepts_an_input_effect_stated_in_its_only_equation():
    """An input that enters one equation: d_F = (g - 1) F equals d_v = b (g - 1) F there."""
    for seed in range(50):
        d = zoo.draw_class("actuator_gain", seed, 0, n_est=N_EST)
        (e,) = d.truth.effects
        if len(e.equations) == 1:
            break
    (t,) = e.terms
    eq = e.equations[0]
    b = float(np.asarray(d.nominal.B)[list(d.nominal.state_labels).index(eq), 0])
    s = zoo.score(d, _report(d, f"eq({eq})", (eq,), [("F", "u", 0)], b * t.coefficient, 0.01))
    assert s.right, s.why
    s = zoo.score(d, _report(d, "input(F)", (eq,), [("F", "u", 0)], t.coefficient, 0.01))
    assert s.right, s.why


# -------------------------------------------------------- 3. close_the_loop on fixed draws
N_RUN = 2000        # long enough for today's greybox on these draws, short enough for CI


@lru_cache(maxsize=None)
def _run(cls: str):
    d = zoo.draw_class(cls, 0, 0, n_est=N_RUN)
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    return d, rep, zoo.score(d, rep)


@pytest.mark.parametrize("cls", zoo.CORRECT_CLASSES)
def test_correct_model_stays_unchanged(cls):
    d, rep, s = _run(cls)
    assert not rep.updated and s.false_update is False, rep.message
    # the table's error is the true model's: the noise floor (SE, or PE in closed loop),
    # within 10 % (the estimated initial state and the predictor's own error)
    assert s.error_updated < 1.1 * s.error_true


@pytest.mark.parametrize("cls", ["static_state", "actuator_gain", "sensor_drift",
                                 "sensor_gain_offset"])
def test_explanation_is_right_on_a_fixed_draw(cls):
    """Channel, kind, exactly the true terms, every coefficient within 10 % and inside its
    reported 95 % interval; the updated model's validation SE within 1.5x the true
    model's (the issue's goal)."""
    d, rep, s = _run(cls)
    assert rep.updated, rep.message
    assert s.right_channel and s.right_kind and s.right_order, (s.why, s.found)
    assert s.right_terms and s.coefficients_within, (s.why, s.found)
    assert s.covered == s.n_coefficients, s.found
    assert s.false_flags == 0
    assert s.error_updated <= 1.5 * s.error_true


def test_score_reads_two_laws_traced_together_as_two_effects():
    """Two static effects in two equations, found in one channel of both equations with one
    law per component, are the same model as two effects; a third equation in that
    channel, or one law missing, is not."""
    for seed in range(50):
        d = zoo.draw_class("two_static", seed, 0, n_est=N_EST)
        if d.description.startswith("chain"):
            break
    (e1, e2) = d.truth.effects
    (t1,), (t2,) = e1.terms, e2.terms
    spec = [(t1.variables[0], "x", 0), (t2.variables[0], "x", 1)]
    chan = f"eq({t1.target})+eq({t2.target})"
    s = zoo.score(d, _report(d, chan, (t1.target, t2.target), spec,
                             [[t1.coefficient, 0.0], [0.0, t2.coefficient]],
                             [[0.01, np.nan], [np.nan, 0.01]]))
    assert s.right, s.why
    s = zoo.score(d, _report(d, chan, (t1.target, t2.target), spec[:1],
                             [[t1.coefficient], [0.0]], [[0.01], [np.nan]]))
    assert not s.right


def test_score_reads_a_damper_and_a_gain_in_one_equation_as_two_effects():
    """A damper and an actuator gain in the only equation the input enters: one law with
    both terms is the same model as the two effects; a spurious third term is caught."""
    for seed in range(200):
        d = zoo.draw_class("state_input", seed, 0, n_est=N_EST)
        e1, e2 = d.truth.effects
        if e2.equations == e1.targets:
            break
    else:
        raise AssertionError("no state_input draw with the damper on the forced mass")
    (t1,), (t2,) = e1.terms, e2.terms
    eq = t1.target
    b = float(np.asarray(d.nominal.B)[list(d.nominal.state_labels).index(eq), 0])
    spec = [(t1.variables[0], "x", 0), ("F", "u", 0)]
    s = zoo.score(d, _report(d, f"eq({eq})", (eq,), spec, [t1.coefficient,
                                                             b * t2.coefficient], [0.01, 0.01]))
    assert s.right, s.why
    other = next(x for x in d.nominal.state_labels if x.startswith("p"))
    s = zoo.score(d, _report(d, f"eq({eq})", (eq,), spec + [(other, "x", 2)],
                             [t1.coefficient, b * t2.coefficient, 0.5], [0.01, 0.01, 0.01]))
    assert not s.right and not s.right_terms


@lru_cache(maxsize=None)
def _run_draw(cls: str, seed: int, i: int, max_order: int = 1, n_est: int = N_RUN):
    d = zoo.draw_class(cls, seed, i, n_est=n_est)
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False, max_order=max_order)
    return d, rep, zoo.score(d, rep)


@pytest.mark.parametrize("cls,i", [("dead_zone", 0), ("dead_zone", 1), ("saturation", 0),
                                   ("saturation", 1)])
def test_input_dead_zone_and_saturation_are_named_with_their_breakpoint(cls, i):
    """An input dead zone or saturation (random chains, sizes, measured sets and levels):
    the input's channel (or the one equation it enters), a static law of one breakpoint
    term, the breakpoint within 10 % of the truth (the issue's tolerance). Two draws per
    class, seed 3 (not chosen: the first seed tried)."""
    d, rep, s = _run_draw(cls, 3, i)
    assert rep.updated, rep.message
    assert s.right_channel and s.right_kind, (s.why, s.found)
    law = rep.effect.law
    brk = [sp for j, sp in enumerate(law.spec) if sp[1] in ("u_dz", "u_sat") and
           np.any(law.coef[:, j])]
    assert len(brk) == 1, law.formula
    assert brk[0][1] == ("u_dz" if cls == "dead_zone" else "u_sat"), law.formula
    true_level = d.truth.effects[0].terms[0].coefficient
    assert abs(brk[0][2][1] - true_level) <= 0.1 * true_level, (law.formula, true_level)
    assert s.error_updated < 0.5 * s.error_nominal  # and the model is better than before


@pytest.mark.parametrize("i", [1, 3, 5])
def test_actuator_lag_is_named_as_the_input_reaching_the_plant_through_a_lag(i):
    """A first-order actuator lag (random chains, sizes, measured sets, time constants):
    the input's channel (or the one equation it enters), a dynamic law of order 1 driven
    by the input alone, its pole within 10 % of 1/tau and its interval covering it, and a
    validation SE within 1.5x the true model's (the issue's goal). Seed 3 (the first
    tried): its first six draws are all right (at N = 2000, and at this test's 1000: each
    pole within 0.2 % of 1/tau and inside its interval); these are one measured
    in full (1) and the two measured in part (3: 4 of 12 states, 5: positions only), where
    d^ is delayed and the lag was missed before the input's own lag candidate (stage 2d)
    and the gate's output-error evidence for a delayed channel (measured at N = 2000)."""
    d, rep, s = _run_draw("actuator_lag1", 3, i, n_est=1000)
    assert rep.updated, rep.message
    assert s.right, (s.why, s.found)
    assert s.coefficients_within and s.covered == s.n_coefficients, (s.found, rep.effect.formula)
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


@pytest.mark.parametrize("i", [0, 1, 2])
def test_second_order_actuator_lag_is_named_with_its_mode(i):
    """A second-order actuator lag w^2/(s^2 + 2 zeta w s + w^2) (random chains, measured
    sets, w and zeta): the input's channel (or the one equation it enters), a dynamic law
    of order 2 driven by the input alone, its poles within 10 % and covered (the zoo's
    scorer), validation SE within 1.5x the true model's. Seed 3 (the first tried): its
    first five draws are all right (at N = 2000, and at this test's 1000: each pole within
    0.7 % of the truth, the SE within 1.04x the true model's); these are two measured in
    full and one in part (1: positions of a 3-mass chain). Before the input's second-order
    lag candidate every draw of the class was wrong (seed 1946288768: 0 of 3)."""
    d, rep, s = _run_draw("actuator_lag2", 3, i, max_order=2, n_est=1000)
    assert rep.updated, rep.message
    assert s.right, (s.why, s.found)
    assert rep.effect.order == 2 and "reaches the plant through" in rep.effect.formula
    assert s.coefficients_within, (s.found, rep.effect.formula)
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)
    # not asserted: the poles' 95 % intervals cover the truth in 2 of 2, 1 of 2 and 0 of 2
    # coordinates of these draws (measured at N = 1000; at N = 2000 1, 0 and 0 of 2; the
    # zoo at N = 4000, seed 1946288768: 5 of 6;
    # found within 0.2-1 % of the truth, the intervals narrower still): too narrow, the
    # issue's item 7 (intervals that mean something), open


def test_second_order_actuator_lag_far_from_its_first_order_fit_is_found():
    """zoo actuator_lag2, seed 71207 (fresh), draw 0: a chain of 2, positions measured, the
    force through 10.7 rad/s at damping 0.36. The first-order lag's fit put its corner at
    95 rad/s, the second-order fit started only from 1, 1.6 and 2.5 times it and ended at
    a lightly damped 86 rad/s (SE 2.63 % against the true model's 0.75 %). Started also
    from frequencies across the band up to Nyquist, it finds the mode: poles within 10 %,
    the SE within 1.5x the true model's."""
    d, rep, s = _run_full_draw("actuator_lag2", 71207, 0)
    assert rep.updated and s.right, (s.why, s.found)
    assert s.coefficients_within, s.found
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


@pytest.mark.parametrize("seed,i", [(3, 0), (3, 1), (5150, 1)])
def test_flexible_shaft_is_a_hidden_part_driven_by_the_speed_alone(seed, i):
    """A DC motor whose model lacks the load behind a flexible shaft (random torsional
    mode, inertia ratio, damping, measured sets): the speed's equation, a dynamic law of
    order 2 driven by the speed alone (not by the voltage and current beside it, as the
    unstructured subsystem named it in 6 of 6 zoo draws before the hidden-part candidate),
    its poles within the zoo scorer's 10 %, validation SE within 1.5x the true model's.
    Seed 3 (the first tried): its first six draws are all right at N = 2000. Seed 5150
    draw 1 (a fresh seed's one wrong draw): the unstructured law, driven by V, i and om,
    put the mode at 26.5 rad/s for a true 14.6, and output error from there diverged; the
    hidden part is now also started from the best of a grid of lightly damped modes."""
    d, rep, s = _run_draw("flexible_shaft", seed, i, max_order=2)
    assert rep.updated, rep.message
    assert s.right, (s.why, s.found)
    assert rep.effect.order == 2 and rep.effect.channel == "eq(om)", rep.effect.formula
    assert s.coefficients_within, (s.found, rep.effect.formula)
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


def test_a_hidden_mass_between_two_far_bodies_is_one_shared_state_not_two_laws():
    """A hidden thermal mass touching bodies 4 and 8 of a row of 8, 5 of 8 temperatures
    measured: the equation screen is unavailable (rank C < n) and no pair channel is
    formed, so the passes name a static law in eq(T8), then one in eq(T4) (validation SE
    3.8 %, the true model's 0.25 %). Traced again as one channel, the pair is one hidden
    state of order 1 driven by T4 and T8 (6 parameters against 7) at the true model's
    error: the report says that, and the trail says why. The zoo's fresh seed of the
    session (20261127, draw 0; N = 4000: at 2000 samples no pass finds an error); two
    passes (max_effects=2) are enough for the two equations, and the effect is linear and
    of order 1 (nonlinear=False, max_order=1: 10 s instead of 12 s)."""
    d = zoo.draw_class("thermal_mass", 20261127, 0, n_est=4000)
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False, max_effects=2, nonlinear=False, max_order=1)
    s = zoo.score(d, rep)
    assert rep.updated and s.right, (s.why, s.found)
    assert rep.effect.kind == "dynamic" and rep.effect.order == 1
    assert set(rep.effect.equations) == {"T4", "T8"}
    assert s.error_updated <= 1.1 * s.error_true, (s.error_updated, s.error_true)
    assert any(dd.stage == "loop" and "one hidden state of the pair" in dd.reason
               for dd in rep.decisions)


@pytest.mark.parametrize("i", [22, 23])
def test_a_hidden_mass_with_no_equation_screen_is_traced_on_the_two_best_equations(i):
    """zoo thermal_mass, seed 4242 (fresh), draws 22 and 23: rows of 5 and 7 bodies, some
    temperatures measured, a hidden mass between T1 and T4 (draw 22) or T2 and T7 (draw
    23), bodies the model does not link. With fewer outputs than equations there is no
    equation screen: every equation was traced alone, and the only pairs offered were the
    links of the model, so no channel held both equations (draw 22: a static law of
    eq(T4), eq(T5) driven by T3; draw 23: one of eq(T1), eq(T2) driven by T7). Now the two
    equations whose single static laws fit best are traced together and one state shared
    by them is fitted: the right channel, kind, order and drivers, the coefficients within
    10 % and inside their 95 % intervals, the true model's error. Over that seed's small
    partial-measurement draws (5-8 states, N = 2000) 0 -> 4 of 6 right; on the fresh seed
    20261130 (``python bench/zoo.py --draws 6 --classes thermal_mass``) 3 -> 4 of 6."""
    d, rep, s = _run_draw("thermal_mass", 4242, i, max_order=2, n_est=2000)
    assert d.nominal.noutputs < d.nominal.nstates and "hidden thermal mass" in d.description
    assert rep.updated and s.right, (s.why, s.found)
    assert rep.effect.kind == "dynamic" and rep.effect.order == 1
    assert s.false_flags == 0 and s.error_updated <= 1.1 * s.error_true, \
        (s.error_updated, s.error_true)


def test_law_figure_shows_the_dead_zone_in_the_data():
    """plot_law draws d^ against the dead zone's input: the binned partial residual follows
    the true law -B clip(F, c) within each bin's 2 standard errors plus 5 % of the law's
    range (a bin's mean of a nonlinear law is not the law at the bin's centre)."""
    import matplotlib

    matplotlib.use("Agg")
    from greybox.plotting import plot_law

    d, rep, s = _run_draw("dead_zone", 3, 0)
    arts = plot_law(rep, d.u)
    c_true = d.truth.effects[0].terms[0].coefficient
    law = rep.effect.law
    (mid, mean, err), = [b for b in arts["bins"] if b is not None]
    assert arts["variables"] == ["F"]
    j = next(j for j, sp in enumerate(law.spec) if sp[1] == "u_dz" and law.coef[0, j])
    scale = -law.coef[0, j] / 1.0                      # the law's amplitude (B or 1)
    truth = -scale * np.clip(mid, -c_true, c_true)
    assert np.all(np.abs(mean - truth) <= err + 0.05 * 2 * scale * c_true), (mean, truth, err)


@pytest.mark.slow
def test_a_law_whose_updated_model_diverges_on_validation_is_not_handed_over(monkeypatch):
    """A pendulum missing a strong cubic damping (-1.27e3 om^3, seed 1946288768 draw 0): the
    law passes the gate on the estimation record, but the updated model's UKF diverges on
    the validation record from its prior P0 = I (x ~ 1e68). That used to end
    close_the_loop with a ModelError; a model whose validation diverges must stay
    unchanged, say why in its first line, and mark the validation as failed in the gate.

    The validation now restarts from a settled prior, where this draw's law is right
    (validation SE 13.3 -> 0.721 %, the true model's 0.721 %); here the settled prior is
    withheld, so that the divergence stands and the refusal is what is tested."""
    import greybox.workflow_nonlinear as wfn

    monkeypatch.setattr(wfn, "_settled_prior", lambda *a, **k: None)
    d = zoo.draw_class("nonlinear_model", 1946288768, 0)
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    assert rep.model_error_detected and not rep.updated
    assert "diverges on the validation record" in rep.message, rep.message
    assert rep.gate["passed"]["validation"] is False
    assert rep.table["updated"] is rep.table["nominal"]


@lru_cache(maxsize=None)
def _run_full_draw(cls: str, seed: int, i: int):
    """A zoo draw at the benchmark's own record length (``bench/zoo.py``), as measured."""
    d = zoo.draw_class(cls, seed, i)
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    return d, rep, zoo.score(d, rep)


def test_two_static_effects_each_named_in_its_own_equation_not_through_a_proxy():
    """Two wrong loss coefficients in a thermal row of 10, all measured (seed 1554573307,
    draw 1, the benchmark's fresh seed): the greedy first term was T4 for the loss of T3
    (four terms, then two more passes and a 7-driver dynamic law); with the forward
    selection's swaps (trace.oe._exchange), exactly -a*T2 in eq(T2) and -b*T3 in eq(T3),
    each within 10 % and inside its 95 % interval, at the true model's validation SE."""
    d, rep, s = _run_full_draw("two_static", 1554573307, 1)
    assert rep.updated and s.right, (s.why, s.found)
    assert s.coefficients_within and s.covered == s.n_coefficients == 2, s.found
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)
    assert len(rep.steps) == 1, rep.message  # one effect, not three passes


@pytest.mark.parametrize("seed,i", [(1554573307, 2), (1946288768, 0)])
def test_coulomb_friction_on_an_unmeasured_speed_is_named_as_friction(seed, i):
    """Coulomb friction in an equation measured only through others (a 5-mass chain at 2
    of 10 states; a 2-mass chain by positions): the delayed d^ chose the viscous -c*v
    (SE 13.9 % and 11.2 %), which the gate's output-error evidence let through; the
    siblings' exchange by output error (trace.oe.exchange_siblings) names -F*sign(v),
    the one term, its coefficient within 10 % (the two draws where the benchmark saw the
    wrong law; the interval covers the truth in the first only, not asserted: item 7)."""
    d, rep, s = _run_full_draw("coulomb", seed, i)
    assert rep.updated and s.right and s.coefficients_within, (s.why, s.found)
    assert "sign(" in rep.effect.formula, rep.effect.formula
    assert any("term form chosen by output error" in n for n in rep.notes), rep.notes
    assert s.error_updated < 0.2 * s.error_nominal  # and the model is far better than before


@pytest.mark.parametrize("seed,i", [(20261208, 0), (777, 3)])
def test_a_friction_s_own_width_is_fitted_and_its_law_is_the_sign_alone(seed, i):
    """Coulomb friction on one mass, speed measured (the two draws of two fresh seeds with
    a smooth input, where the friction reverses slowly enough for its width to show). The
    truth's sign is tanh(v / eps) with eps 8.3 % and 3.2 % of the record's RMS of v; the
    law's was 5 %: a spurious linear term beside the sign made up for the shape
    (-0.032*v, SE 1.44 % against the true model's 0.28 %; +0.022*p1, 0.86 % against
    0.16 %). The width is now fitted by output error where the one criterion pays for it
    (trace.oe.fit_smoothing) and the law stepped as finely as its slope needs
    (hold.LawHold.substeps): the sign alone, its coefficient within 10 % and inside its
    interval, the width within 10 % of the truth's (the search's tolerance is 5 % on its
    factor), the error within 1.5x the true model's."""
    d, rep, s = _run_full_draw("coulomb", seed, i)
    assert rep.updated and s.right and s.coefficients_within, (s.why, s.found)
    assert s.covered == s.n_coefficients == 1, s.found
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)
    law, term = rep.effect.law, d.truth.effects[0].terms[0]
    j = int(np.flatnonzero(law.coef[0])[0])
    eps = law.eps[term_kind(law.spec[j][1]).eps_slot(law.spec[j][2])]
    assert abs(eps / term.smoothing - 1) < 0.1, (eps, term.smoothing)
    assert any("smoothing width" in n for n in rep.notes), rep.notes


@pytest.mark.parametrize("cls,seed,i", [("quadratic_drag", 20261208, 1), ("coulomb", 777, 2)])
def test_a_diverging_d_hat_law_is_refitted_not_dropped(cls, seed, i):
    """An effect on one mass of a chain measured by positions only (drag on the last of 5;
    friction on the second of 2): the delayed d^'s law of the right equation (6 and 4
    terms) diverged in simulation, its candidate scored an infinite error, and a force
    between the mass and its neighbour was named instead (SE 3.73 % against the true
    model's 0.30 %; 18.4 % against 0.52 %). The output-error refit now starts from the d^
    law shrunk until it simulates (trace.oe._refine_nonlinear_oe), and the criterion
    prunes it: the one true term in the one equation, its coefficient within 10 %, the
    error within 1.5x the true model's."""
    d, rep, s = _run_full_draw(cls, seed, i)
    assert rep.updated and s.right and s.coefficients_within, (s.why, s.found)
    assert rep.channel.kind == "equation", rep.message
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)
    assert any("the d^ law diverges" in n for n in rep.notes), rep.notes


# The two-mass draws of cubic_force among the first 30 of two fresh seeds (20261204 #0;
# 20261205 #14 and #15), chosen by size alone: up to 4 states no equation screen runs and
# the pairs of equations are traced in the bodies' own states.
@pytest.mark.parametrize("seed,i", [(20261204, 0), (20261205, 14), (20261205, 15)])
def test_a_cubic_spring_in_a_small_chain_is_a_force_in_the_relative_coordinate(seed, i):
    """A hardening spring between the two masses of a 2-mass chain, positions measured: the
    pair's law in p1, p2, F cannot hold (p2-p1)^3, and where it gives no force of its own
    (20261204 #0: a proxy in F in both equations, SE 5.07 % against the true model's
    0.32 %) nothing else offered the relative coordinate. The force between the bodies the
    model links, along the link's direction, is traced too (workflow._linked_forces): one
    force, the one term (p2-p1)^3, coefficients within 10 % (the zoo's "right"), the error
    within 1.5x the true model's. 20261205 #14 (2 of 4 states measured): the force's d^
    law is not sparse and the law is chosen among linear terms by output error, (p2-p1)
    alone (SE 7.4 % against 0.36 %); its odd forms are now weighed by output error
    (trace.oe.exchange_siblings), the cube's size searched up to 1024x the linear term's
    of the same RMS (it was 32x). Not asserted: the interval's coverage (#0's is 2.2
    half-widths off, #14's ~6)."""
    d, rep, s = _run_draw("cubic_force", seed, i)
    assert d.nominal.nstates == 4
    assert rep.updated and s.right and s.coefficients_within, (s.why, s.found)
    assert rep.channel.kind == "force", rep.message
    law = rep.effect.law
    assert [law.spec[j][0] for j in np.flatnonzero(np.any(law.coef, axis=0))] == \
        ["(p2-p1)^3"], law.formula
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


def test_a_cubic_spring_s_shape_is_weighed_in_both_bodies_equations_at_once():
    """zoo cubic_force, seed 53736598 (fresh, drawn for the last session's zoo table), draw
    0: a chain of 8, positions of a subset measured, a cubic spring between m4 and m5. The
    pair's law was the linear force ``25.7*(p5-p4)`` in eq(v4) and ``-12.4*(p5-p4)`` in
    eq(v5) at 11x the true model's validation error: each term's odd forms were weighed in
    one equation at a time (trace.oe.exchange_siblings), where the two bodies' forces then
    disagree and neither trial simulates better. A term that several components hold is
    now also swapped in all of them at once: ``(p5-p4)^3`` in both equations, coefficients
    within 10 % (the zoo's "right"), the error within 1.5x the true model's."""
    d, rep, s = _run_full_draw("cubic_force", 53736598, 0)
    assert rep.updated and s.right and s.coefficients_within, (s.why, s.found)
    assert set(rep.channel.equations) == {"v4", "v5"}, rep.message
    law = rep.effect.law
    assert [law.spec[j][0] for j in np.flatnonzero(np.any(law.coef, axis=0))] == \
        ["(p5-p4)^3"], law.formula
    assert np.all(law.coef[:, law.spec.index(next(sp for sp in law.spec
                                                   if sp[0] == "(p5-p4)^3"))] != 0)
    assert any("(p5-p4)^3 in 2 components" in n for n in rep.notes), rep.notes
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


@pytest.mark.parametrize("i,pair", [(1, ("v9", "v10")), (2, ("v6", "v7"))])
def test_a_force_the_screen_sees_in_one_body_only_is_traced_between_both(i, pair):
    """zoo cubic_force, seed 20261207 (fresh, drawn for the thirty-second session's
    side-by-side run), draws 1 and 2: chains of 10 and 12 masses, a cubic spring between
    m9 and m10 (the chain's end) and between m6 and m7. The equation screen ranked one
    body of the pair (eq(v10), eq(v7)) and no pair was formed: a 3-term law of eq(v10) at
    26x, and -0.723*p8 + 0.611*p9 in eq(v7) at 7x, the true model's validation error. An
    equation ranked without the bodies the model links it to now brings its force with
    each (workflow._lone_forces); the criterion chooses the force: the one cubic term of
    the relative coordinate in both equations, coefficients within 10 %."""
    d, rep, s = _run_full_draw("cubic_force", 20261207, i)
    assert rep.updated and s.right and s.coefficients_within, (s.why, s.found)
    assert set(rep.channel.equations) == set(pair), rep.message
    law = rep.effect.law
    rel = f"(p{pair[1][1:]}-p{pair[0][1:]})^3"
    assert [law.spec[j][0] for j in np.flatnonzero(np.any(law.coef, axis=0))] == [rel], \
        law.formula
    assert any("an equation ranked without the bodies it is linked to" in n
               for n in rep.notes), rep.notes
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


# The first three seeds >= 1 whose sensor_lag draw has more than 6 outputs (chosen by size
# alone, by scanning seeds 1, 2, ...; asserted below): above 6 outputs no sensor channel is
# offered by default, so the sensor must come from the screen of sensor laws.
@pytest.mark.parametrize("seed", [3, 9, 24])
def test_a_lagging_sensor_among_many_outputs_is_named_as_the_sensor(seed):
    d = zoo.draw_class("sensor_lag", seed, 0)
    assert d.nominal.noutputs > 6
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    s = zoo.score(d, rep)
    assert rep.updated and s.right, (s.why, s.found)
    assert s.covered == s.n_coefficients, s.found  # tau inside its 95 % interval
    assert any("sensors offered by the share" in x.reason for x in rep.decisions)


def test_a_sensor_lag_and_a_state_error_fused_in_one_law_are_split_into_two():
    """Two effects of different kinds (a heat loss 0.31x of the truth on T1 and a 2.66 s
    lag on the T2 sensor; zoo state_sensor, seed 8675309) that one first-order law of both
    equations reproduces as well as the truth (8 parameters): tried as the sensor's lag
    first and then a static law of each equation, refitted jointly, the two effects
    (2 parameters) win by the criterion, each with its true value inside its interval."""
    d = zoo.draw_class("state_sensor", 8675309, 0)
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    s = zoo.score(d, rep)
    assert rep.updated and s.right, (s.why, s.found)
    assert s.covered == s.n_coefficients, s.found
    assert any("tried as two of different kinds" in x.reason and "the two effects" in x.reason
               for x in rep.decisions)


@pytest.mark.parametrize("seed", [4, 10])
def test_a_sensor_lag_found_first_is_refitted_with_the_state_law_found_after_it(seed):
    """A sensor lag found in pass 1 absorbs part of a damping error (its time constant is
    biased); the next pass runs on the continuous model read through the lag, and the
    joint refit corrects the lag with the damping law (zoo state_sensor, the first two
    seeds >= 1 whose draw is a chain with a lagging sensor). Before 2026-11-27 the next
    pass ran on the discrete model and nothing refitted the lag: 0 of 2 right (seed 4: the
    damping beside a biased lag, validation SE 3.14 % against the true model's 0.72 %;
    seed 10: a second, spurious sensor law instead of the damping, 11.3 %)."""
    d = zoo.draw_class("state_sensor", seed, 0)
    assert "lags by" in d.description and d.description.startswith("chain")
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    s = zoo.score(d, rep)
    assert rep.updated and s.right, (s.why, s.found)


def test_a_proxy_term_beside_an_input_gain_error_is_pruned_at_the_choices_price():
    """zoo actuator_gain, seed 1386191387, draw 1 (a 30 % gain error on F, 10 states,
    positions only, binary input): the chosen input law held ``-0.00371*p4`` beside
    ``+0.308*F`` when its terms were pruned at the BIC's own price while candidates were
    chosen at ``bic_factor`` (10) times it. Pruned at the choice's price, the law is the
    gain error alone, within 10 % of the truth, at the true model's error."""
    d, rep, s = _run_full_draw("actuator_gain", 1386191387, 1)
    assert rep.updated and s.right, (s.why, s.found)
    assert s.coefficients_within and s.false_flags == 0, s.found
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


@pytest.mark.parametrize("seed,i", [(1176755609, 0), (7, 3)])
def test_a_wrong_link_between_two_bodies_is_named_where_no_screen_ranks_the_equations(seed, i):
    """A damper between two masses the model has wrong (zoo linear_force: chains of 5,
    3 or 5 of 10 states measured), where the equation screen is not available (the
    outputs do not determine every equation's error). Before, only single equations were
    traced there (no pair: pairs came from the screen), and a proxy law in another body's
    equation was named (``-5.21*v1 + 4.28*v2``; a first-order filter in eq(v3)). Now one
    force between each two bodies the model links is traced along the link's own
    direction: the right pair, the relative velocity alone, its coefficient within 10 %
    and its interval covering it in both equations, at the true model's error. Both
    draws with the screen unavailable among the first eight of seeds 1176755609 (a fresh
    seed of the zoo) and 7 (the next tried)."""
    d, rep, s = _run_draw("linear_force", seed, i)
    assert any(dc.stage == "screen" and dc.reason.startswith("equation screen unavailable")
               for dc in rep.decisions)  # the premise
    assert rep.updated and s.right, (s.why, s.found)
    assert s.coefficients_within and s.covered == s.n_coefficients, s.found
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


@pytest.mark.parametrize("seed,i", [(20261128, 2), (1536943047, 1)])
def test_a_state_error_found_before_a_sensor_lag_is_traced_again_after_it(seed, i):
    """zoo state_sensor, thermal rows (a loss coefficient wrong in one body, a thermocouple
    lag on another), the two draws of this session's two seeds whose loop found the state
    effect first and the sensor after. A sensor lag colours d^ in the equations of the
    states it reads: pass 1 named a first-order filter of T3 where eq(T3) lacks -0.264*T3
    (seed 20261128), or a force between T2 and T4 whose pair law had no term in eq(T2)
    (seed 1536943047), and the sensor's lag found in pass 2 never changed that. Now a pair
    law acting in one equation gives no force, and effects found state first and sensor
    after are tried the other way round, the one criterion deciding: the lag and the
    static loss, the loss within 10 %, at the true model's error."""
    d, rep, s = _run_full_draw("state_sensor", seed, i)
    assert "lags by" in d.description and d.description.startswith("row")  # the premise
    assert rep.updated and s.right, (s.why, s.found)
    assert s.coefficients_within, s.found
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


def test_a_hidden_mass_no_dense_fit_reveals_is_one_shared_state():
    """zoo thermal_mass, seed 244465831 (fresh), draw 0: a row of 3 bodies, all measured,
    a hidden mass of 6.54 J/K between T1 and T2. On small models one shared state was
    tried only for a pair whose dense dynamic law (24 parameters) fitted better than its
    static law; here it fitted worse (SE 2.52 % against 0.383 %) and a 7-term static law
    of the pair was named (wrong kind). Now the pair whose static law fits best is also
    tried where the best static law leaves coloured innovations: one state shared by T1
    and T2, driven by both, at the true model's error. Its pole was -0.54 against the
    true -0.358 1/s while the shared state's fit stopped at 80 residual evaluations; fitted
    to convergence (trace.dynamic._DynProblem.fit) it is -0.360: the coefficients are
    asserted too (within 10 %)."""
    d, rep, s = _run_full_draw("thermal_mass", 244465831, 0)
    assert d.description.startswith("row of 3") and "hidden thermal mass" in d.description
    assert rep.updated and s.right_channel and s.right_kind and s.right_order, (s.why, s.found)
    assert s.right_terms and s.coefficients_within and s.right, (s.why, s.found)
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


def test_a_shared_state_is_fitted_to_convergence_not_to_a_fixed_budget():
    """zoo thermal_mass, seed 270939893 (fresh, drawn for the thirty-third session's zoo
    run), draw 0: a row of 7 bodies, all measured, a hidden mass on T3 and T4. The
    shared state's template start (driven by the pair's own states) stopped at 80
    residual evaluations, 11 iterations in, its pole at -0.836 against the -0.706 1/s the
    same start reaches in 93; the 6-parameter truth then lost to an 8-parameter and a
    9-parameter second-order law (named: order 2, driven by T3, T4, T5, T7). Fitted to
    convergence: order 1, driven by T3 and T4, the pole within 1 % of the truth."""
    d, rep, s = _run_full_draw("thermal_mass", 270939893, 0)
    assert rep.updated and s.right and s.coefficients_within, (s.why, s.found)
    assert rep.effect.order == 1 and set(rep.channel.equations) == {"T3", "T4"}, rep.message
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


@pytest.mark.parametrize("seed,i", [(31337, 5), (711567674, 2)])
def test_a_stiff_cubic_law_is_validated_from_a_settled_prior_not_refused(seed, i):
    """A pendulum whose speed is measured through its angle only, a cubic drag omitted
    (-181 and -324 om^3): the law is found right, but the updated model's UKF diverged at
    the validation's second sample from the prior P0 = I (sigma points at om = +-1.7 rad/s,
    where -324 om^3 is stiff for one RK4 step) and the model was refused as "diverges on
    the validation record" (SE 47.5 % and 34.8 % kept; the true model's 0.20 % and 0.13 %).
    The validation now starts from the steady-state covariance of the updated model's
    linearization: the law handed over, the error within 1.5x the true model's (the
    issue's 2x for a nonlinear law is not needed). Both draws from two seeds not chosen
    (the fresh seed of a benchmark run and one of the session's), 2 of 2 refused before,
    4 of 4 such draws right after at this length."""
    d, rep, s = _run_draw("nonlinear_model", seed, i)
    assert rep.updated and s.right, (s.why, s.found, rep.message)
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)
    assert any("settled" in n or "steady-state covariance" in n for n in rep.notes), rep.notes


def test_a_first_order_law_whose_lag_the_joint_refit_drops_is_named_static():
    """zoo state_sensor, seed 20261207, draw 1 (wrong on that fresh seed; at the test's
    2000 samples the same): an 11-mass chain, all 22 states measured, m6's damping 1.91x in
    the model and an offset of -0.0878 on the v8 sensor. Pass 1, before the offset is
    known, chose a first-order law of v6 (3 parameters); the joint refit of both effects
    drops its lag (the driver's gain, whose interval contains 0) and leaves the feedthrough
    ``1.48*v6``. The report still named "a dynamic effect of order 1" with a time constant
    "not determined by the data", and the model carried the state nothing drives any more.
    Now that effect is the static law it is (trace.joint._feedthrough_law), its state out of
    the model (trace.joint.without_dead_states): the zoo's right explanation, the damping
    error within 10 %."""
    d = zoo.draw_class("state_sensor", 20261207, 1, n_est=N_RUN)
    rep = gb.close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    s = zoo.score(d, rep)
    assert rep.updated and s.right and s.coefficients_within, (s.why, s.found)
    assert [st.effect.kind for st in rep.steps] == ["static", "static"], rep.message
    assert rep.steps[0].effect.dynamic_law is None and "dynamic" not in rep.message
    assert any("dropped eq(v6): lag v6" in x.reason for x in rep.decisions)
    # the sensor's offset is the one state the model gains (the law's state is gone)
    assert rep.model.sys.nstates == d.nominal.nstates + 1, rep.model.sys.state_labels


def test_a_sensor_offset_beside_a_state_error_is_traced_with_the_sensor_first():
    """Two effects of different kinds (issue 27 item 5): a sensor's offset and a state
    equation's error. Zoo state_sensor, seed 2112803, draw 0 (the first draw of that class
    on a seed drawn for this session): a row of 3 bodies, all measured, T3's loss 1.49x too
    large in the model and an offset of 0.105 on T2. Before, T3's error was named a
    first-order filter of T3 and the offset second, as a nonlinear law (the loop could not
    try it the other way round). Now the offset is a state of a linear model: the effects
    are tried with the sensor first (its law refitted after the state law, its gain
    dropped), and the one criterion prefers the offset and a static law of eq(T3)."""
    d, rep, s = _run_draw("state_sensor", 2112803, 0, max_order=2, n_est=4000)
    assert rep.updated, rep.message
    assert s.right_channel and s.right_kind and s.right_order, (s.why, s.found)
    assert s.right_terms and s.coefficients_within, (s.why, s.found)
    assert s.false_flags == 0
    assert s.error_updated <= 1.5 * s.error_true
    assert any("the sensor first, a lower criterion" in x.reason for x in rep.decisions)
    assert "T2_offset" in rep.model.sys.state_labels
    sensor = next(st.effect for st in rep.steps if st.channel == "output(T2)")
    assert not sensor.nonlinear


def test_an_actuator_lag_seen_on_two_outputs_is_not_taken_for_two_sensor_lags():
    """A first-order actuator lag on a chain of 3 with 2 outputs (zoo actuator_lag1, seed
    2112802, draw 1): identical lags on both outputs are the same input-output map with
    fewer parameters counted, and a version of the sensor-first alternative that also
    tried a sensor's lag first named it so (two sensor lags). Only a sensor's offset is
    tried first: the input's lag stays the explanation, and the decision trail says why
    the sensor was not tried first."""
    d, rep, s = _run_draw("actuator_lag1", 2112802, 1, max_order=2, n_est=4000)
    assert rep.updated, rep.message
    assert s.right, (s.why, s.found)
    assert not any(st.channel.startswith("output(") for st in rep.steps), s.found
    assert any("is not an offset" in x.reason for x in rep.decisions)


def test_a_lag_the_data_cannot_see_is_dropped_when_the_criterion_compares_refits():
    """zoo state_sensor, seed 71207 (fresh), draw 1: a row of 10 bodies, 8 measured, the
    loss of T2 missing from the model and a 0.643 s lag on the T6 thermocouple. Pass 1
    chose a first-order law of T2 (SE 2.18 % against the static law's 2.19 %, the sensor's
    lag still unexplained); after the sensor's lag, the re-traced set's joint refit
    dropped the lag (5.4e-6 +- 3.9e-5) at the same SE, and was thrown away because its SE
    was not lower. The two refits are compared by the one criterion (every effect's
    parameters counted): the static loss within 10 %, the lag, at the true model's
    error."""
    d, rep, s = _run_full_draw("state_sensor", 71207, 1)
    assert "lags by" in d.description  # the premise
    assert rep.updated and s.right, (s.why, s.found)
    assert s.coefficients_within and s.false_flags == 0, s.found
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)
    assert any(x.reason.startswith("the re-traced set by the criterion") for x in rep.decisions)


def test_an_actuator_gain_fused_with_a_damping_error_is_split_by_the_criterion():
    """zoo state_input, seed 71207 (fresh), draw 0: a chain of 10, all measured, the damping
    of m5 wrong and the force F's gain 0.614 of the model's, F entering two masses. One
    static law of eq(v5), eq(v6), eq(v8) explained both (``-1.04*v5``, F in each of the two
    rows at its own coefficient: 3 parameters, SE 0.422 %). Tried as two passes, the
    input's channel then each equation, the criterion prefers the two effects: F's gain
    error and v5's damping, each within 10 %, 2 parameters at the same SE."""
    d, rep, s = _run_full_draw("state_input", 71207, 0)
    assert rep.updated and s.right, (s.why, s.found)
    assert s.coefficients_within and s.false_flags == 0, s.found
    assert [st.channel for st in rep.steps] == ["input(F)", "eq(v5)"], s.found
    assert any("the two effects, a lower criterion" in x.reason for x in rep.decisions)


def test_an_equations_own_state_replaces_a_law_of_its_neighbours():
    """zoo static_state, seed 71207 (fresh), draw 1: a row of 6 bodies, 3 measured (T2 is
    not), the loss of T2 2.28x too large in the model. On T2's delayed d^ the law took
    six neighbours' states and inputs (T1, T3, T4, T5, Q1, Q4: SE 0.534 %), and a force
    between T2 and T3 refitted to act almost on T2 alone (its direction 424:1) won with 2
    parameters. Offered its own state by output error, eq(T2)'s law becomes +T2 alone
    (criterion -500), pruned before the choice: the loss within 10 %, 1 parameter."""
    d, rep, s = _run_full_draw("static_state", 71207, 1)
    assert rep.updated and s.right, (s.why, s.found)
    assert s.coefficients_within and s.covered == s.n_coefficients, s.found
    assert any("term offered by output error: T2" in x.reason for x in rep.decisions)


def test_an_actuator_gain_no_equation_screen_ranks_is_traced_on_the_inputs_channel():
    """zoo actuator_gain, seed 354441888 (fresh), draw 0: a chain of 9, positions only, F's
    gain 0.794 of the model's (validation SE 25.5 %, the true model's 0.49 %). The joint
    equation screen ranked no equation above its threshold (its d^ is a second difference
    of the positions) and F enters one equation, so F had no channel of its own: only the
    sensors were traced and the model stayed unchanged. The inputs' channels are traced
    where the screen ranks nothing; the channel's d^ law had ten terms (p, v, sign(v),
    v*F), left as fitted on d^ and diverging, and a law that dense is now chosen by output
    error among the terms d^ correlates with most, whatever its kind: F's gain alone,
    within 10 %, at the true model's error (the first-order lag of F scored beside it:
    +205 by the criterion, its lag not determined)."""
    d, rep, s = _run_full_draw("actuator_gain", 354441888, 0)
    assert any("the inputs' channels traced" in x.reason for x in rep.decisions)  # premise
    assert rep.updated and s.right, (s.why, s.found)
    assert s.coefficients_within and s.false_flags == 0, s.found
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


def test_a_nonlinear_law_left_linear_is_refitted_in_continuous_time_and_refitted_jointly():
    """zoo state_sensor, seed 1984922569, draw 1 (at 2000 samples; the benchmark's 4000
    alike): one mass, both states measured, its damping 2.31x the truth's and sensor v1
    lagging by 0.133 s. The damping was found by a nonlinear law the criterion pruned to
    ``+1.1*v1``, still held over each sample (a discrete-time law): pass 2 then ran on a
    discrete model, the sensor lag came out at 0.095 s and no joint refit could run (40x
    the true model's error). A law left linear is refitted in continuous time: the damping
    and the lag within 10 % of the truth, at the true model's error within 1.5x."""
    d, rep, s = _run_draw("state_sensor", 1984922569, 1, max_order=2, n_est=2000)
    assert any("refitted in continuous time" in x.reason for x in rep.decisions)  # premise
    assert rep.updated and s.right, (s.why, s.found)
    assert s.coefficients_within, s.found
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


def test_a_law_the_prune_empties_in_one_equation_is_stated_in_the_others():
    """zoo two_static, seed 164466021, draw 1 (at 2000 samples; the benchmark's 4000
    alike): a chain of 3, 5 of 6 states measured, the damping of m3 missing and the
    stiffness of m2 1.74x the truth's. Both were found in one pass by the law of the three
    equations, with ``+0.004*p1`` in eq(v1) (and at 4000 samples ``-0.0009*v1`` in eq(v3))
    beside them. The criterion's prune dropped those terms, which left eq(v1) without a
    term, and such a law was discarded as a smaller channel's: the 4-term law stood. It is
    now scored, and the step stated as the law of eq(v2) and eq(v3): the two true terms
    alone, within 10 %, at the true model's error within 1.5x."""
    d, rep, s = _run_draw("two_static", 164466021, 1, max_order=2, n_est=2000)
    assert rep.updated and s.right, (s.why, s.found)
    assert rep.channel.name == "eq(v2)+eq(v3)", rep.channel.name
    assert s.coefficients_within and s.false_flags == 0, s.found
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)


def test_a_delayed_law_refined_by_output_error_drops_the_terms_its_intervals_do_not_hold():
    """zoo nonlinear_model, seed 270939893 (fresh in the 34th session), draw 1: a pendulum whose
    speed is measured through its angle only, Coulomb friction -0.0785 sign(om) omitted.
    The delayed d^'s law, refined by output error before the channels are compared, kept
    ``+0.000427*th`` and ``+0.000421*T`` beside the right ``-0.0786*sign(om)``, both with
    95 % intervals holding 0 (the trail said so) and the explanation scored wrong. That
    refinement now prunes as the output-error choice of terms does
    (``workflow_nonlinear._refine_pruned``): ``sign(om)`` alone, within 1 %, at the true
    model's error within 1.5x. (At 2000 and 3000 samples this draw takes other paths.)"""
    d, rep, s = _run_full_draw("nonlinear_model", 270939893, 1)
    assert rep.updated and s.right, (s.why, s.found)
    assert s.coefficients_within and s.error_updated <= 1.5 * s.error_true, s.found


def test_a_hidden_mass_the_screen_cannot_rank_is_tried_as_a_state_shared_with_a_neighbour():
    """zoo thermal_mass, seed 270939893, draw 1 (the benchmark's 4000 samples; at 2000 this
    draw takes other paths): a row of 9 bodies, 4 measured, a hidden mass on T3 and T4.
    The equation screen is unavailable (4 outputs for 9 equations), so single equations
    and linked forces were traced and no pair of equations: eq(T4)'s first-order law fitted
    9.25 % against its static law's 42 %, yet no shared state was tried, and the model
    kept 38 % (the true model's 0.39 %) with ``T3*|T3|`` named. The best one-equation law
    with evidence of dynamics is now tried as one state shared with each neighbour a force
    links it to, driven by the two bodies' own states: T3 and T4's shared state, its pole
    and gains within 10 %, at the true model's error within 1.5x. (Drivers chosen anywhere
    let such a state absorb two effects: zoo two_static 270939893 #1, see
    bench/RESULTS_zoo.md.)"""
    d, rep, s = _run_full_draw("thermal_mass", 270939893, 1)
    assert rep.updated and s.right, (s.why, s.found)
    assert s.coefficients_within, s.found
    assert s.error_updated <= 1.5 * s.error_true, (s.error_updated, s.error_true)
