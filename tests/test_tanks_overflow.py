"""A simulated two-tank plant whose upper tank overflows, traced end to end.

Only the lower tank is measured, so the overflow's equation eq(x1) has
relative degree 2 (rank(C G) = 0): the nonlinear pipeline traces it with the
delayed unscented filter (``greybox.delayed_ui_ukf``) and fits a saturation
hinge. Truth: Torricelli tanks (the cascaded-tanks benchmark's orders of
magnitude, Ts = 4 s) with x1 clipped at XMAX, integrated by RK4 with 20
sub-steps per sample; the nominal model is the same ODE without the clip,
4 RK4 sub-steps (1 s) per sample. Measurement noise 0.02 (about 2 % of y's
range, like the benchmark's 40 dB), no process noise in the truth.
"""

from __future__ import annotations

import control as ct
import numpy as np
import pytest

from greybox.metrics import relative_error
from greybox.workflow_nonlinear import SKIP, close_the_loop_nonlinear

K1, K2, K3, K4, TS = 0.045, 0.058, 0.082, 0.053, 4.0
XMAX = 8.0
R_STD = 0.02


def f_nom(x, u):
    s1 = np.sqrt(np.maximum(x[0], 0.0))
    # filled in place rather than np.stack (the same numbers): the pipeline calls the
    # nominal ~1.8e6 times per run (RK4 stages x samples x trial fits), np.stack's
    # dispatch was a third of the run
    out = np.empty((2,) + np.shape(s1))
    out[0] = -K1 * s1 + K4 * u[0]
    out[1] = K2 * s1 - K3 * np.sqrt(np.maximum(x[1], 0.0))
    return out


def truth(u, xmax, rng, soft=None):
    """States and noisy output of the true tanks (x1 clipped at xmax), RK4, 20 sub-steps.

    ``soft = (ko, xo)`` adds a soft overflow ``-ko max(x1 - xo, 0)`` to dx1/dt (a law
    the trace can express exactly: bench/nonlinear_coverage.py).
    """
    N, h = u.shape[1], TS / 20

    def f(x, uk):
        out = f_nom(x, uk)
        if soft is not None:
            out[0] -= soft[0] * max(x[0] - soft[1], 0.0)
        return out

    x, xk = np.empty((2, N)), np.array([5.0, 5.0])
    for k in range(N):
        x[:, k] = xk
        for _ in range(20):
            a = f(xk, u[:, k])
            b = f(xk + h / 2 * a, u[:, k])
            c = f(xk + h / 2 * b, u[:, k])
            d = f(xk + h * c, u[:, k])
            xk = xk + h / 6 * (a + 2 * b + 2 * c + d)
            xk[0] = min(xk[0], xmax)
    return x, x[1:] + R_STD * rng.standard_normal((1, N))


def multisine(rng, N):
    """Pump voltage: 12 sines over the benchmark's band (0-0.0144 Hz) around 2.5 V."""
    t = np.arange(N) * TS
    u = 2.5 + sum(rng.uniform(0.2, 0.6) * np.sin(2 * np.pi * f * t + rng.uniform(0, 6.3))
                  for f in np.linspace(0.0005, 0.0144, 12))
    return np.clip(u, 0, None)[None]


NOMINAL = ct.nlsys(lambda t, x, u, p: f_nom(np.asarray(x, float), np.asarray(u, float)),
                   lambda t, x, u, p: x[1:2], states=["x1", "x2"], inputs=["u"],
                   outputs=["y"], dt=0, name="tanks")
Q = R_STD ** 2 * np.eye(2)
R = np.array([[R_STD ** 2]])


def run(xmax, seed, n=1024):
    rng = np.random.default_rng(seed)
    u, uv = multisine(rng, n), multisine(rng, n)
    (_, y), (xv, yv) = truth(u, xmax, rng), truth(uv, xmax, rng)
    # 4 RK4 sub-steps of 1 s (the default count is taken at the least-squares prior, where
    # the unmeasured x1 = 0 makes sqrt stiff)
    rep = close_the_loop_nonlinear(NOMINAL, y, u, yv, uv, Q=Q, R=R, dt=TS, substeps=4)
    return rep, (xv, yv, uv)


# Seeds 0-9 (python bench/nonlinear_coverage.py overflow --seeds 10): 10 of 10 name eq(x1)
# with one hinge at 7.99-8.00 and reach the true model's validation SE within 1.1x. Seed 7
# was the failure of the d^-chosen terms: its d^ law holds no hinge (x1, x2^3, x1*u) and the
# output-error gate took it (SE 9.7x the true model's); the terms are now also chosen by
# output error (workflow_nonlinear._select_law_oe) and the hinge wins. Three seeds are
# tested (~30 s each): 5, 7 (the former failure) and 9; seed 2 was dropped for seed 7 to
# keep the file's run time.
SEEDS = (5, 7, 9)


@pytest.fixture(scope="module", params=[SEEDS[0]] + [pytest.param(s, marks=pytest.mark.slow)
                                                     for s in SEEDS[1:]],
                ids=lambda s: f"seed{s}")
def overflow(request):
    return run(XMAX, request.param)


def test_overflow_is_traced_to_the_upper_tank_as_a_saturation(overflow):
    rep, _ = overflow
    assert rep.updated and rep.effect.equations == ("x1",), rep.message
    assert rep.trace.relative_degree == 2  # eq(x1) does not reach the next lower-tank sample
    law = rep.effect.law
    on = np.flatnonzero(law.coef[0])
    assert len(on) == 1, law.formula  # one term: the hinge
    name, kind, (i, level) = law.spec[on[0]]
    assert kind == "x_hi" and i == 0, law.formula
    # the level where the upper tank stops rising: 7.99-8.01 measured on seeds 0-9; 2 % =
    # 0.16, about a quarter of the filtered level's error std in these records
    np.testing.assert_allclose(level, XMAX, rtol=0.02)
    assert law.coef[0, on[0]] < 0  # a loss above the level (stiff: x1 held near it)
    # the delayed channel's gate weighs the law on the output error, not on d^
    g = rep.gate
    assert g["evidence"].startswith("output error") and g["passed"]["bic"], g


def test_overflow_update_reaches_the_true_models_validation_error(overflow):
    rep, (xv, yv, uv) = overflow
    # the true model's floor: the noise-free true output against the measured one
    floor = relative_error(yv[:, SKIP:], xv[1:, SKIP:]).value
    se = rep.table["updated"].se.value
    assert se <= 2 * floor, (se, floor)  # measured 0.570-0.635 % vs 0.56-0.59 % (seeds 0-9)
    assert rep.table["nominal"].se.value > 20 * floor  # the nominal misses it (27-42 %)


@pytest.mark.slow
def test_tanks_without_overflow_are_left_unchanged():
    """The same pipeline on tanks that never overflow: no saturation is invented.

    512 samples per record (half the overflow's): the same path as at 1024, innovations
    not white (Ljung-Box p 1.9e-8; 1.3e-17 at 1024), the terms of eq(x1) and eq(x2)
    searched by output error (on all 492 samples after SKIP: none chosen, as at 1024),
    eq(x2)'s d^ law refused by the gate, far from passing (BIC gain 26.6 against
    10 x 12.4; estimation SE 0.559 -> 0.548 %, a 2 % drop where 20 % is asked; at 1024:
    16.1 against 10 x 13.8, 0.491 -> 0.488 %).
    """
    rep, _ = run(np.inf, 6, n=512)
    assert not rep.updated, rep.message


def test_a_short_record_chooses_the_terms_by_output_error_on_all_of_it():
    """400 samples (fewer than the line search's window of 1000 after SKIP): the overflow
    is still found, its hinge chosen by output error on y.

    The output-error term choice's line search simulated ``_LS_WINDOW`` samples whatever
    the record held: on a record shorter than SKIP + 1000 it raised (an IndexError for a
    model that takes one state at a time, a ValueError for a batch one, which the stage
    caught and skipped without a word). Now it searches the whole record after SKIP, and
    says so. Seed 5: the hinge at 7.991 +- 0.016 (truth 8.0), from the output-error
    choice (the d^ path alone also ends at the hinge here, so the note is the check that
    the stage ran and won); ~7 s.
    """
    rep, _ = run(XMAX, 5, n=400)
    assert rep.updated and rep.effect.equations == ("x1",), rep.message
    law = rep.effect.law
    on = np.flatnonzero(law.coef[0])
    assert len(on) == 1, law.formula
    name, kind, (i, level) = law.spec[on[0]]
    assert kind == "x_hi" and i == 0 and law.coef[0, on[0]] < 0, law.formula
    np.testing.assert_allclose(level, XMAX, rtol=0.02)
    notes = [d.reason for d in rep.decisions if d.subject == "eq(x1)"]
    # the stage ran on the 380 samples after SKIP, chose one term, and that choice won
    assert any("line search simulated the whole record" in r and "(380 samples" in r
               and "1 term(s) chosen" in r for r in notes), notes
    assert any("the law's terms were chosen by output error on y" in r for r in notes), notes
    assert not any("could not be chosen by output error" in r for r in notes), notes


def test_saturation_hinges_are_offered_at_the_record_quantiles_and_evaluate_alike():
    from greybox.trace.laws import SAT_QUANTILES, _eval_terms, law_terms
    from greybox.terms import term_kind

    rng = np.random.default_rng(1)
    x, u = rng.uniform(-2, 10, (2, 400)), rng.standard_normal((1, 400))
    T0, spec0, _ = law_terms(x, u, ["x1", "x2"], ["u"])
    T, spec, eps = law_terms(x, u, ["x1", "x2"], ["u"], saturation=True)
    hinges = [(r, s) for r, s in enumerate(spec) if s[1] in ("x_hi", "x_lo")]
    # 3 upper and 2 lower hinges per state, before the offset (which stays last)
    assert len(hinges) == 2 * 5 and spec[-1][1] == "const" and len(spec) == len(spec0) + 10
    for i in range(2):
        lv = [s[2][1] for _, s in hinges if s[2][0] == i]
        np.testing.assert_allclose(lv, np.quantile(x[i], SAT_QUANTILES[0] + SAT_QUANTILES[1]),
                                   rtol=1e-12)  # the same numbers, computed twice
    r, (name, kind, (i, c)) = hinges[0]
    assert name == f"max(x1 - {c:.4g}, 0)" and kind == "x_hi"
    np.testing.assert_array_equal(T[r], np.maximum(x[0] - c, 0))
    np.testing.assert_array_equal(_eval_terms(spec, eps, x, u), T)  # evaluated alike
    # a refined level renames the term, the state's name kept (spaces and signs too)
    lo = ("min(x 1 + 0.43, 0)", "x_lo", (0, -0.43))
    assert term_kind("x_lo").at_level(lo, 2.5) == ("min(x 1 - 2.5, 0)", "x_lo", (0, 2.5))
    assert term_kind("x_hi").at_level(spec[r], -1e-5)[0] == "max(x1 + 1e-05, 0)"
