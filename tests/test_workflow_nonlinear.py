"""close_the_loop on a nonlinear nominal model (issue 10 item 5), and the model helpers.

Plant: a torque-driven pendulum, states theta [rad], omega [rad/s], both
measured, dt = 0.01 s. The truth has a cubic air drag ``-0.5 omega^3`` that
the nominal model omits; the truth is simulated with RK4 at 10 sub-steps per
sample (the nominal's own discretization takes fewer: the law must survive
that mismatch). Estimation data carry process and measurement noise,
validation data only measurement noise (PAPER_NOTES §8.6).
"""

from __future__ import annotations

import json
from functools import lru_cache

import control as ct
import numpy as np
import pytest

import greybox as gb
from greybox.validate import before_after
from greybox.exceptions import DataError, DimensionError, ModelError

DT = 0.01
C3 = 0.5                       # true cubic drag coefficient [1/(rad s)]
QD = np.diag([1e-8, 1e-6])     # discrete process noise (theta, omega)
RM = np.diag([1e-4, 1e-4])     # 0.01 rad, 0.01 rad/s measurement noise


def pendulum(c3: float = 0.0, *, name: str = "pendulum") -> ct.NonlinearIOSystem:
    """d theta/dt = omega, d omega/dt = -9.81 sin(theta) - 0.2 omega + T - c3 omega^3."""
    def f(t, x, u, p):
        return np.array([x[1], -9.81 * np.sin(x[0]) - 0.2 * x[1] + u[0] - c3 * x[1] ** 3])

    return ct.nlsys(f, lambda t, x, u, p: x, states=["theta", "omega"], inputs=["T"],
                    outputs=["theta", "omega"], name=name)


def record(N: int, seed: int, *, process_noise: bool):
    rng = np.random.default_rng(seed)
    u = gb.multisine(N, dt=DT, amplitude=4.0, fmin=0.05, fmax=1.5, rng=rng)
    truth = gb.discretize_nonlinear(pendulum(C3), DT, substeps=10)
    return gb.simulate_nonlinear(truth, u, Q=QD if process_noise else None, R=RM, rng=rng)


@lru_cache(maxsize=None)
def data():
    return record(3000, 1, process_noise=True), record(2000, 2, process_noise=False)


# The tests that read one cached run share it only in one process: they run in one worker
# (--dist loadgroup), or two workers each ran it (run(0.0): ~5 s; the true positions-only
# model of seeds 1 and 2, read by both positions-only tests: ~2-4 s each)
RUN_GROUP = pytest.mark.xdist_group("test_workflow_nonlinear_run")
THETA_GROUP = pytest.mark.xdist_group("test_workflow_nonlinear_theta_only")


@lru_cache(maxsize=None)
def run(nominal_c3: float, discrete: bool = False):
    est, val = data()
    nom = pendulum(nominal_c3)
    if discrete:
        nom = gb.discretize_nonlinear(nom, DT, substeps=2)
    return gb.close_the_loop(nom, est.y, est.u, val.y, val.u, Q=QD, R=RM,
                             dt=None if discrete else DT), nom


# --------------------------------------------------------------------------- the workflow
@RUN_GROUP
def test_missing_cubic_drag_is_found_with_its_coefficient():
    rep, nom = run(0.0)
    assert rep.model_error_detected and rep.updated, rep.message
    assert rep.effect.equations == ("omega",), rep.message
    assert rep.effect.kind == "static" and rep.effect.nonlinear and not rep.effect.linearized
    law = rep.effect.law
    names = [s[0] for s, c in zip(law.spec, law.coef[0]) if c != 0]
    assert names == ["omega^3"], rep.effect.formula
    j = [s[0] for s in law.spec].index("omega^3")
    # 2 %: the fit's own 95 % interval is ~0.3 %; d is held over each sample
    # while the truth's drag varies within it (PAPER_NOTES §9.5), and the nominal's
    # RK4 uses 1 sub-step against the truth's 10: each biases by well under 1 %
    np.testing.assert_allclose(law.coef[0, j], -C3, rtol=0.02)
    se0, se1 = rep.table["nominal"].se.value, rep.table["updated"].se.value
    assert se0 / se1 > 100, f"SE {se0:.3g}% -> {se1:.3g}%"  # measured ~2400x
    assert se1 < 3.0  # the measurement noise alone is ~0.8 % of theta's RMS
    assert not rep.table["nominal"].whiteness.all_white


@pytest.mark.slow
@pytest.mark.parametrize("seed", [12, 16], ids=lambda s: f"seed{s}")
def test_over_seeds_right_model_kept_and_drag_found(seed):
    """Fresh draws: the right model is never changed, the drag always found (8/8 seeds
    10-17 when this was written, on 3000 + 2000 samples: coefficients -0.4992 .. -0.5017).

    1500 estimation and 1000 validation samples (3000 and 2000 before; 4.5 -> 3 s a seed):
    coefficients -0.4997 and -0.4998 (-0.5008 and -0.4994 before), the right model's
    innovations white with p >= 0.28 (0.022 before)."""
    est = record(1500, seed, process_noise=True)
    val = record(1000, seed + 100, process_noise=False)
    right = gb.close_the_loop(pendulum(C3), est.y, est.u, val.y, val.u, Q=QD, R=RM, dt=DT)
    assert not right.updated, right.message
    rep = gb.close_the_loop(pendulum(0.0), est.y, est.u, val.y, val.u, Q=QD, R=RM, dt=DT)
    assert rep.updated and rep.effect.equations == ("omega",), rep.message
    law = rep.effect.law
    j = [s[0] for s in law.spec].index("omega^3")
    np.testing.assert_allclose(law.coef[0, j], -C3, rtol=0.02)  # as the first test
    # the updated model simulates the validation record as the right model does (measured
    # 1.452 vs 1.452 %, 1.340 vs 1.340 %); the nominal without its drag is far worse by
    # the report's measure (SE 198 % at seed 12, 1072 % at seed 16; on the former 2000
    # validation samples seed 16's nominal simulation depended on where it started, its SE
    # was undefined, and PE 9.99 -> 1.32 %)
    assert rep.table["updated"].se.value <= 1.02 * right.table["updated"].se.value
    _, before, after = before_after(rep.table)
    assert after < before / 5


@RUN_GROUP
def test_updated_model_is_nonlinear_and_simulates_the_law_exactly():
    rep, nom = run(0.0)
    nl = rep.nonlinear
    assert isinstance(nl, gb.NonlinearUpdate)
    assert isinstance(nl.model, ct.NonlinearIOSystem) and nl.model.isctime(strict=True)
    assert list(nl.model.state_labels) == ["theta", "omega"]
    # its f is the nominal f plus the found law: compare with the true plant's f
    rng = np.random.default_rng(5)
    X = rng.uniform(-2, 2, size=(2, 50))
    U = rng.uniform(-4, 4, size=(1, 50))
    truth = pendulum(C3)
    for k in range(50):
        got = nl.model.updfcn(0.0, X[:, k], U[:, k], {})
        want = truth.updfcn(0.0, X[:, k], U[:, k], {})
        # 2 % of the drag term |0.5 omega^3| <= 4 at |omega| <= 2 (the coefficient's tolerance)
        np.testing.assert_allclose(got, want, atol=0.02 * C3 * 8)
    # the table's "updated" row simulates nl.discrete from its UKF's state at sample 20
    val = data()[1]
    kf = gb.ukf(nl.discrete, val.y, val.u, Q=QD, R=RM, x0=val.y[:, 0], P0=np.eye(2))
    sim = gb.simulate_nonlinear(nl.discrete, val.u[:, 20:], x0=kf.x_filt[:, 20])
    # 1e-9: the same arithmetic in the same order, up to rounding
    np.testing.assert_allclose(rep.table["updated"].y_sim[:, 20:], sim.y, rtol=1e-9,
                               atol=1e-12)
    assert nl.substeps >= 1 and "RK4" in " ".join(rep.notes)


@RUN_GROUP
def test_linearization_is_a_statespace_for_control_design():
    rep, _ = run(0.0)
    nl = rep.nonlinear
    lin = nl.linearization
    assert isinstance(lin, ct.StateSpace) and lin.dt == DT
    assert rep.model.sys is lin and rep.model.kind == "static"
    # oracle: central differences of the discrete map against the analytic Jacobian of
    # one RK4 step is circular; instead compare with python-control's own linearize
    ref = nl.discrete.linearize(nl.x_op, nl.u_op)
    # 1e-5: python-control uses forward differences with eps = 1e-6
    np.testing.assert_allclose(lin.A, ref.A, atol=1e-5)
    np.testing.assert_allclose(lin.B, ref.B, atol=1e-5)
    K, _, _ = ct.dlqr(lin, np.eye(2), np.eye(1))
    assert K.shape == (1, 2) and np.all(np.isfinite(K))
    assert "mean" in nl.operating_point
    doc = rep.as_dict()
    json.dumps(doc)
    assert doc["nonlinear"]["x_op"] == nl.x_op.tolist()


def test_right_nonlinear_model_is_left_unchanged():
    rep, nom = run(C3)
    assert not rep.model_error_detected and not rep.updated, rep.message
    assert "no significant model error" in rep.message
    assert rep.nonlinear.model is nom
    assert rep.effect.kind == "none"
    # the nominal's validation SE is already at the noise level
    assert rep.table["nominal"].se.value < 3.0


def test_discrete_nonlinear_nominal_goes_through_the_same_pipeline():
    rep, nom = run(0.0, discrete=True)
    # a discrete model's input column is [dt^2/2, dt]-like: the drag, a torque held over
    # the sample like T, is best described in T's own channel (it enters both equations)
    assert rep.updated and rep.channel.name == "input(T)", rep.message
    assert rep.effect.equations == ("theta", "omega")
    law = rep.effect.law
    names = [s[0] for s, c in zip(law.spec, law.coef[0]) if c != 0]
    assert names == ["omega^3"], rep.effect.formula
    j = names and [s[0] for s in law.spec].index("omega^3")
    # 2 %: d is in T's units [N m], so the coefficient is the continuous one (same
    # reasons as the continuous case; the nominal's RK4 has 2 sub-steps)
    np.testing.assert_allclose(law.coef[0, j], -C3, rtol=0.02)
    eq = {c.channel: c for c in rep.candidates}
    assert eq["input(T)"].se_estimation < eq["eq(omega)"].se_estimation
    assert not rep.nonlinear.model.isctime(strict=True)
    assert rep.nonlinear.substeps == 0  # already discrete: no RK4 of greybox's


def test_coulomb_friction_non_smooth_is_found_as_a_sign_law():
    """A non-smooth omitted effect: Coulomb friction -Fc sign(omega), Fc = 1 N m."""
    fc = 1.0

    def f(t, x, u, p):
        return np.array([x[1], -9.81 * np.sin(x[0]) - 0.2 * x[1] + u[0] - fc * np.sign(x[1])])

    truth = gb.discretize_nonlinear(ct.nlsys(f, lambda t, x, u, p: x, states=2, inputs=1,
                                             outputs=2), DT, substeps=10)

    def rec(N, seed, q):
        rng = np.random.default_rng(seed)
        # amplitude 3: the pendulum swings without going over the top (an overturning,
        # chaotic record makes every long simulation diverge in phase: SE is then no guide)
        u = gb.multisine(N, dt=DT, amplitude=3.0, fmin=0.05, fmax=1.5, rng=rng)
        return gb.simulate_nonlinear(truth, u, Q=QD if q else None, R=RM, rng=rng)

    est, val = rec(3000, 11, True), rec(2000, 12, False)
    rep = gb.close_the_loop(pendulum(), est.y, est.u, val.y, val.u, Q=QD, R=RM, dt=DT)
    assert rep.updated and rep.effect.equations == ("omega",), rep.message
    law = rep.effect.law
    names = [s[0] for s, c in zip(law.spec, law.coef[0]) if c != 0]
    assert names == ["sign(omega)"], rep.effect.formula
    # on d^, least squares of sign on the smoothed tanh(omega/eps) inflates the level
    # (-1.04 here, PAPER_NOTES §9.4); the output-error refinement on y removes it: 3 %,
    # for tanh against sign near the zero crossings and the switching inside a held sample
    assert "refined by output error" in " ".join(rep.notes)
    j = [s[0] for s in law.spec].index("sign(omega)")
    np.testing.assert_allclose(law.coef[0, j], -fc, rtol=0.03)
    se0, se1 = rep.table["nominal"].se.value, rep.table["updated"].se.value
    assert se0 / se1 > 10, f"SE {se0:.3g}% -> {se1:.3g}%"  # measured ~54x


def theta_only(c3: float = 0.0) -> ct.NonlinearIOSystem:
    """The pendulum with theta alone measured."""
    return ct.nlsys(pendulum(c3).updfcn, lambda t, x, u, p: x[:1], states=["theta", "omega"],
                    inputs=["T"], outputs=["theta"], name="pendulum_theta_only")


@lru_cache(maxsize=None)
def run_theta_only(c3: float, seed: int = 1, alpha: float = 1e-3, n_est: int = 3000):
    # the validation record depends on the seed only (n_est changes the estimation record)
    val = data()[1] if seed == 1 else record(2000, seed + 100, process_noise=False)
    if (seed, n_est) == (1, 3000):
        est = data()[0]
    else:
        est = record(n_est, seed, process_noise=True)
    return gb.close_the_loop(theta_only(c3), est.y[:1], est.u, val.y[:1], val.u, Q=QD,
                             R=RM[:1, :1], dt=DT, alpha=alpha)


@pytest.mark.slow
@THETA_GROUP
@pytest.mark.parametrize("seed", [1, 2], ids=lambda s: f"seed{s}")
def test_positions_only_drag_is_found_through_the_delayed_channel(seed):
    """theta alone: the omega equation reaches y through C G ~ dt^2/2 (relative degree 2).

    The delayed unscented filter estimates d^ in eq(omega); d^ is mostly estimation
    noise, so the law's terms are also chosen by output error (forward selection on the
    simulation error, BIC on the effective sample count) and the gate weighs the law on
    the output error, where its coefficient was estimated: the likelihood ratio against
    the nominal, over the residual's colour. Seed 2 is where d^'s regression chose a
    linear damping ``-1.65*omega`` (SE 18.9 % against the true model's 2.1 %) and the gate
    took it before the terms were chosen by output error (3000 estimation samples); over
    seeds 0-9 the law is now ``omega^3`` alone with the truth inside its interval on all
    ten (``python bench/nonlinear_coverage.py pendulum_pos --seeds 10``, 3000 samples).

    The test estimates on 1500 samples (3000 before; 13-14 -> 8-9 s a seed alone), the
    validation record kept (2000 samples, shared with the true model's run of the next
    test). With the output-error choice of terms switched off, the terms chosen on d^
    give no update on either seed at 1500 samples (at 3000 seed 2 took ``-1.64*omega``):
    the test fails without it at either length.
    """
    rep = run_theta_only(0.0, seed, n_est=1500)
    notes = " ".join(rep.notes)
    assert "eq(omega): relative degree 2" in notes
    assert rep.updated and rep.effect.equations == ("omega",), rep.message
    assert rep.trace.relative_degree == 2
    law = rep.effect.law
    names = [law.spec[j][0] for j in np.flatnonzero(law.coef[0])]
    assert names == ["omega^3"], law.formula
    j = [s[0] for s in law.spec].index("omega^3")
    # the truth inside the law's own 95 % interval (seed 1: -0.4989 +- 0.0059, seed 2:
    # -0.4988 +- 0.0048; at 3000 samples -0.494 +- 0.011, -0.500 +- 0.0035), and
    # determined by the data
    assert abs(law.coef[0, j] + C3) <= law.ci[0, j], law.formula
    assert law.ci[0, j] < 0.05 * C3
    g = rep.gate
    assert g["evidence"].startswith("output error"), g
    assert g["passed"] == {"whiteness": True, "bic": True, "se_drop": True}
    # the quasi likelihood ratio (seed 1: 8.9e3 measured, colour 2.3; seed 2: 1.2e4,
    # colour 1.8; at 3000 samples 1143, colour 35, and 1.0e4, colour 5) far above 10x its
    # penalty (1 x log(Ny / colour) = 6.5 and 6.7)
    assert g["bic_gain"] > 10 * g["bic_factor"] * g["bic_penalty"]
    # validation SE of the updated model against the true model's (simulated the same way,
    # the true model as nominal, estimated on 3000 samples: its validation row does not
    # depend on them): measured 2.034 % vs 2.034 % (seed 1), 1.877 % vs 1.879 % (2)
    true_se = run_theta_only(C3, seed).table["nominal"].se.value
    se = rep.table["updated"].se.value
    assert se <= 1.5 * true_se, (se, true_se)
    assert rep.table["nominal"].se.value > 100 * se  # the drag-free model is far off


@THETA_GROUP
@pytest.mark.parametrize("seed", [1, 2, 3], ids=lambda s: f"seed{s}")
def test_positions_only_true_model_is_left_unchanged(seed):
    """The false-alarm side: the true pendulum (with its drag), theta alone, stays unchanged.

    Its UKF innovations are white (Ljung-Box p >= 1e-3 on the three seeds), so nothing
    is traced. Forced to trace anyway (alpha ~ 1), no candidate explains d^: eq(theta)'s
    regression selects no term and eq(omega)'s delayed filter fails on the cubic drag's
    stiffness (sigma points at large omega; see the issue-12 report).
    """
    rep = run_theta_only(C3, seed)
    assert not rep.model_error_detected and not rep.updated, rep.message
    forced = run_theta_only(C3, seed, alpha=1 - 1e-9)
    assert forced.model_error_detected and not forced.updated, forced.message


def test_named_channel_is_the_only_candidate():
    est, val = data()
    rep = gb.close_the_loop(pendulum(), est.y, est.u, val.y, val.u, Q=QD, R=RM, dt=DT,
                            channels={"drag": [0.0, 1.0]})
    assert [c.channel for c in rep.candidates] == ["drag"]
    assert rep.updated and rep.channel.name == "drag", rep.message
    assert rep.effect.formula.startswith("drag = -(0.")  # d named after the channel
    assert "*omega^3" in rep.effect.formula


def test_unobservable_channels_are_skipped_by_the_rank_condition():
    """A third state z that no output sees: its channels fail (17) and are skipped."""
    est, val = data()

    def f(t, x, u, p):
        return np.array([x[1], -9.81 * np.sin(x[0]) - 0.2 * x[1] + u[0], -x[2]])

    nom = ct.nlsys(f, lambda t, x, u, p: x[:2], states=["theta", "omega", "z"],
                   inputs=["T"], outputs=["theta", "omega"], name="pendulum_z")
    rep = gb.close_the_loop(nom, est.y, est.u, val.y, val.u, Q=np.diag([1e-8, 1e-6, 1e-8]),
                            R=RM, dt=DT)
    status = {c.channel: c.status for c in rep.candidates}
    assert status["eq(z)"] == "skipped" and status["eq(omega)+eq(z)"] == "skipped"
    assert "rank(C @ G) = 0" in {c.channel: c.reason for c in rep.candidates}["eq(z)"]
    assert rep.updated and rep.effect.equations == ("omega",), rep.message


# --------------------------------------------------------------------------- bad input
def test_nonlinear_output_map_is_refused():
    est, val = data()
    bad = ct.nlsys(pendulum().updfcn, lambda t, x, u, p: np.array([np.sin(x[0]), x[1]]),
                   states=2, inputs=["T"], outputs=["theta", "omega"], name="sin_out")
    with pytest.raises(ModelError, match="output map .* is not linear"):
        gb.close_the_loop(bad, est.y, est.u, val.y, val.u, Q=QD, R=RM, dt=DT)


def test_continuous_model_without_dt_and_wrong_dt_are_refused():
    est, val = data()
    with pytest.raises(ModelError, match="give the sampling period dt"):
        gb.close_the_loop(pendulum(), est.y, est.u, val.y, val.u, Q=QD, R=RM)
    disc = gb.discretize_nonlinear(pendulum(), DT, substeps=1)
    with pytest.raises(ModelError, match="disagrees with the discrete model"):
        gb.close_the_loop(disc, est.y, est.u, val.y, val.u, Q=QD, R=RM, dt=0.02)


@pytest.mark.parametrize("kw, err, match", [
    ({"nonlinear": 1}, DataError, "nonlinear must be True or False"),
    ({"parsimony": 0.5}, DataError, "parsimony >= 1"),
    ({"Q": np.eye(3)}, DimensionError, "Q"),
], ids=["flag", "parsimony", "Q-shape"])
def test_bad_options_are_refused(kw, err, match):
    est, val = data()
    args = dict(Q=QD, R=RM, dt=DT)
    args.update(kw)
    with pytest.raises(err, match=match):
        gb.close_the_loop(pendulum(), est.y, est.u, val.y, val.u, **args)


def test_the_retired_parsimony_warns_that_it_has_no_effect():
    """The choice is the output-error criterion's; a parsimony other than the old default
    warns instead of being silently ignored (the call then stops on the bad alpha)."""
    est, val = data()
    with pytest.warns(DeprecationWarning, match="parsimony no longer has an effect"):
        with pytest.raises(DataError, match="alpha"):
            gb.close_the_loop(pendulum(), est.y, est.u, val.y, val.u, Q=QD, R=RM, dt=DT,
                              parsimony=1.3, alpha=5.0)


def test_short_or_misshaped_records_are_refused():
    est, val = data()
    with pytest.raises(DimensionError, match="y"):
        gb.close_the_loop(pendulum(), est.y[:1], est.u, val.y, val.u, Q=QD, R=RM, dt=DT)
    with pytest.raises(DataError, match="samples"):
        gb.close_the_loop(pendulum(), est.y[:, :50], est.u[:, :50], val.y, val.u, Q=QD, R=RM,
                          dt=DT)


# --------------------------------------------------------------------------- model helpers
def test_linearize_at_matches_the_analytic_jacobian():
    th0 = 0.3
    lin = gb.linearize_at(pendulum(C3), [th0, 0.4], [0.0])
    A = np.array([[0.0, 1.0], [-9.81 * np.cos(th0), -0.2 - 3 * C3 * 0.4 ** 2]])
    np.testing.assert_allclose(lin.A, A, atol=1e-7)  # central differences, h = 1e-6
    np.testing.assert_allclose(lin.B, [[0.0], [1.0]], atol=1e-7)
    np.testing.assert_allclose(lin.C, np.eye(2), atol=1e-7)
    assert lin.dt == 0 and list(lin.state_labels) == ["theta", "omega"]


def test_with_unknown_inputs_and_add_law_agree_with_the_plant():
    nom = pendulum()
    wd = gb.with_unknown_inputs(nom, [0.0, 1.0], ["d_omega"])
    assert list(wd.input_labels) == ["T", "d_omega"]
    x = np.array([0.2, 1.5])
    upd = gb.add_law(nom, [0.0, 1.0], lambda x, u: -C3 * np.asarray(x)[1:2] ** 3)
    want = pendulum(C3).updfcn(0.0, x, np.array([0.7]), {})
    np.testing.assert_allclose(upd.updfcn(0.0, x, np.array([0.7]), {}), want, rtol=1e-14)
    d = -C3 * x[1] ** 3
    np.testing.assert_allclose(wd.updfcn(0.0, x, np.array([0.7, d]), {}), want, rtol=1e-14)
    # a batch of states goes through in one call (vectorized sigma points)
    X = np.array([[0.2, 0.1], [1.5, -1.0]])
    out = upd.updfcn(0.0, X, np.array([[0.7, 0.7]]), {})
    assert out.shape == (2, 2)
    # a StateSpace is wrapped first
    ss = gb.named_ss([[0, 1], [-1, 0]], [[0], [1]], np.eye(2), np.zeros((2, 1)), 0,
                     states=["a", "b"], inputs=["u"], outputs=["a", "b"])
    nl = gb.add_law(ss, [0, 1], lambda x, u: -np.asarray(x)[1:2] ** 3)
    np.testing.assert_allclose(nl.updfcn(0.0, np.array([1.0, 2.0]), np.array([0.0]), {}),
                               [2.0, -1.0 - 8.0], rtol=1e-14)


def test_model_helpers_refuse_bad_input():
    nom = pendulum()
    with pytest.raises(DimensionError, match=r"G has shape \(3, 1\)"):
        gb.with_unknown_inputs(nom, [0.0, 1.0, 0.0])
    with pytest.raises(DimensionError, match="labels has 2 names"):
        gb.with_unknown_inputs(nom, [0.0, 1.0], ["a", "b"])
    with pytest.raises(ModelError, match="clash with inputs"):
        gb.with_unknown_inputs(nom, [0.0, 1.0], ["T"])
    with pytest.raises(DataError, match="NaN or inf"):
        gb.add_law(nom, [0.0, np.nan], lambda x, u: x[:1])
    with pytest.raises(ModelError, match="law must be callable"):
        gb.add_law(nom, [0.0, 1.0], 3.0)
    logm = ct.nlsys(lambda t, x, u, p: np.array([np.log(np.abs(x[0])), x[1] + u[0]]), None,
                    states=["a", "b"], inputs=["u"], outputs=["a", "b"], name="log")
    with pytest.raises(ModelError, match="linearization of log is not finite"):
        gb.linearize_at(logm, [0.0, 1.0], [0.0])


# ------------------------------------------------------------------ greybox update MODEL.py
MODEL_PY = '''\
import control as ct
import numpy as np

def f(t, x, u, p):
    return np.array([x[1], -9.81 * np.sin(x[0]) - 0.2 * x[1] + u[0]])

model = ct.nlsys(f, lambda t, x, u, p: x, states=["theta", "omega"], inputs=["T"],
                 outputs=["theta", "omega"], name="pendulum")
Q = np.diag([1e-8, 1e-6])
R = np.diag([1e-4, 1e-4])
Ts = 0.01
'''


def _csv(path, y, u):
    data_ = np.vstack([np.arange(y.shape[1]) * DT, u, y])
    lines = ["time,T,theta,omega"] + [",".join(f"{v:.12g}" for v in row) for row in data_.T]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_cli_update_with_a_nonlinear_model_py(tmp_path, capsys):
    from greybox.cli import main
    from greybox.model_io import read_model

    est, val = data()
    model = tmp_path / "pendulum.py"
    model.write_text(MODEL_PY)
    out = tmp_path / "report"
    code = main(["update", str(model), str(_csv(tmp_path / "est.csv", est.y, est.u)),
                 "--validate", str(_csv(tmp_path / "val.csv", val.y, val.u)),
                 "--out", str(out), "--json", "--no-plots", "--quiet"])
    assert code == 0
    s = json.loads(capsys.readouterr().out)
    assert s["updated"] is True and s["channels"] == ["omega"]
    assert "omega^3" in s["effect"]["formula"]
    assert s["table"]["nominal"]["se"] / s["table"]["updated"]["se"] > 100
    assert set(s["nonlinear"]) >= {"x_op", "u_op", "operating_point", "linearization"}
    lin = read_model(out / "updated_model.json")  # the linearization, readable back
    np.testing.assert_allclose(np.asarray(lin.sys.A), s["nonlinear"]["linearization"]["A"])
    assert "linearization" in (out / "report.md").read_text()


@pytest.mark.parametrize("text, match", [
    ("raise ValueError('boom')", "raised ValueError while being executed: boom"),
    ("model = 3\nQ = R = 1", "'model' must be a control.NonlinearIOSystem"),
    (MODEL_PY.replace("Q = np.diag", "QQ = np.diag"), r"defines no \['Q'\]"),
    (MODEL_PY.replace("Ts = 0.01", ""), "continuous-time; define Ts"),
    (MODEL_PY.replace("Ts = 0.01", "Ts = -1"), "'Ts' must be a number > 0"),
    (MODEL_PY.replace("lambda t, x, u, p: x,", "lambda t, x, u, p: x ** 2,"),
     "output map .* is not linear"),
    (MODEL_PY.replace('outputs=["theta", "omega"]', 'outputs=["T", "omega"]'),
     "named both as input and as output"),
    (MODEL_PY.replace("R = np.diag([1e-4, 1e-4])", "R = np.eye(3)"), "R"),
    (MODEL_PY.replace('name="pendulum")', 'name="pendulum", dt=0.02)'),
     "Ts = 0.01 s disagrees with the discrete model's dt = 0.02 s"),
], ids=["raises", "not-a-model", "no-Q", "no-Ts", "bad-Ts", "nonlinear-h", "clash", "R-shape",
        "dt-mismatch"])
def test_model_py_errors_are_one_clear_line(tmp_path, text, match):
    from greybox.model_io import read_model

    path = tmp_path / "MODEL.py"
    path.write_text(text)
    with pytest.raises(ModelError, match=match):
        read_model(path)


def test_model_py_that_is_not_python_is_one_clear_line(tmp_path):
    """A MODEL.py that does not parse: one ModelError naming the file and the line."""
    from greybox.model_io import read_model

    path = tmp_path / "MODEL.py"
    path.write_text("import numpy as np\nmodel = (\n")
    with pytest.raises(ModelError, match=r"MODEL.py: Python syntax error at line [23]"):
        read_model(path)


def test_a_candidate_simulation_diverging_to_finite_huge_values_scores_as_diverged():
    """SE inf (and an SE reason on validation), not a DataError from the metrics.

    Found on the cascaded tanks (tutorial 09, nominal with the sensor offset): a
    candidate law's simulation reached 4e215, finite, and the metrics refused it
    as data "above 1e150" instead of the candidate being scored as diverged.
    """
    from greybox.plant_adapter import NonlinearPlant, validation
    from greybox.workflow_nonlinear import SKIP, _se_from

    huge = ct.nlsys(lambda t, x, u, p: np.minimum(10.0 * x + u, 1e200),
                    lambda t, x, u, p: x, dt=1.0, states=["x"], inputs=["u"],
                    outputs=["y"], name="huge")
    N = 300
    u = np.ones((1, N))
    y = np.ones((1, N))
    C, D = np.eye(1), np.zeros((1, 1))
    assert _se_from(huge, u, np.ones(1), y, C, D) == np.inf
    row = validation(NonlinearPlant(huge, np.eye(1), order=1, x0=np.ones(1)), y, u,
                     Q=np.eye(1), R=np.eye(1), name="updated", lags=5, alpha=1e-3, skip=SKIP)
    assert not row.se_defined and "diverged" in row.se_reason
