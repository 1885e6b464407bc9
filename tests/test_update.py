"""Model updating on systems whose missing effect is known."""

from __future__ import annotations

import numpy as np
import pytest

import greybox as gb
from greybox import DataError
from greybox.update import augment_model, delta_update, identify_subsystem
from greybox.validate import validate_model

DT = 0.01
M, C_DAMP, K_SPRING = 1.0, 0.4, 4.0
Q = np.diag([1e-8, 1e-6])
R = np.diag([1e-6, 1e-6])


def _msd(with_spring: bool, extra_input: bool):
    """Mass-damper [x (m), v (m/s)] driven by force F [N]; spring optional."""
    A = np.array([[0.0, 1.0], [-(K_SPRING if with_spring else 0.0) / M, -C_DAMP / M]])
    B = np.array([[0.0], [1.0 / M]])
    inputs = ["F"]
    if extra_input:
        B = np.hstack([B, [[0.0], [1.0 / M]]])
        inputs.append("d")
    sys = gb.named_ss(A, B, np.eye(2), np.zeros((2, B.shape[1])), 0, states=["x", "v"],
                      inputs=inputs, outputs=["x", "v"])
    return gb.discretize(sys, DT)


def _data(true, seed, N=8000, Qs=Q):
    rng = np.random.default_rng(seed)
    u = gb.random_binary(N, amplitude=1.0, hold=50, rng=rng)
    return gb.simulate(true, u, Q=Qs, R=R, rng=rng)


@pytest.fixture(scope="module")
def spring_case():
    true = _msd(True, False)
    nominal = _msd(False, True)
    est = _data(true, 10)
    res = gb.uikf(nominal, est.y, est.u, unknown="d", Q=Q, R=R)
    return true, nominal, est, res


def test_static_missing_spring_is_found(spring_case):
    true, nominal, est, res = spring_case
    sub = identify_subsystem(res, max_order=2)
    assert sub.order == 0 and sub.is_static
    # d = -k x (force of the missing spring). The discrete-time law carries a
    # half-sample effect of order k*dt*v ~ 1e-2 relative, and the noise adds
    # ~1e-3: 3 % on the spring constant, 0.1 N s/m on the velocity coefficient.
    np.testing.assert_allclose(sub.Ddx[0, 0], -K_SPRING, rtol=0.03)
    assert abs(sub.Ddx[0, 1]) < 0.1
    assert abs(sub.Ddu[0, 0]) < 0.05
    upd = augment_model(nominal, sub, unknown="d", Q=Q, R=R)
    assert upd.kind == "static" and upd.order == 2
    assert upd.sys.state_labels == ["x", "v"] and upd.sys.input_labels == ["F"]
    # the updated A matches the true discrete A to the same relative accuracy
    np.testing.assert_allclose(np.linalg.eigvals(upd.sys.A), np.linalg.eigvals(true.A),
                               rtol=5e-3)


def test_static_update_reduces_validation_error(spring_case):
    true, nominal, est, res = spring_case
    val = _data(true, 11, Qs=None)
    base = gb.split_inputs(nominal, "d").sys
    upd = augment_model(nominal, identify_subsystem(res, order=0), unknown="d", Q=Q, R=R)
    v0 = validate_model(base, val.y, val.u, Q=Q, R=R)
    v1 = validate_model(upd.sys, val.y, val.u, Q=upd.Q, R=upd.R)
    vt = validate_model(true, val.y, val.u, Q=Q, R=R)
    assert v1.se.value < v0.se.value / 10  # a missing spring is a gross error
    # Close to the true-model floor (measurement noise only, ~0.2 %): the
    # identified law is good to ~0.5 % (eigenvalue test above), which in this
    # lightly damped oscillator adds a few tenths of a percent of SE.
    assert v1.se.value < vt.se.value + 0.5


def test_dynamic_subsystem_is_found():
    # true: d = z, z' = -a z - b v (a lagged viscous force driven by the velocity)
    a, b = 2.0, 4.0
    A = np.array([[0.0, 1.0, 0.0], [0.0, -C_DAMP / M, 1.0 / M], [0.0, -b, -a]])
    Bt = np.array([[0.0], [1.0 / M], [0.0]])
    true3 = gb.discretize(gb.named_ss(A, Bt, np.eye(3)[:2], np.zeros((2, 1)), 0,
                                      states=["x", "v", "z"], inputs=["F"],
                                      outputs=["x", "v"]), DT)
    nominal = _msd(False, True)
    Q3 = np.diag([1e-8, 1e-6, 1e-8])
    est = _data(true3, 20, N=10000, Qs=Q3)
    res = gb.uikf(nominal, est.y, est.u, unknown="d", Q=Q, R=R)
    sub = identify_subsystem(res, max_order=2)
    assert sub.order >= 1, sub.criterion
    upd = augment_model(nominal, sub, unknown="d", Q=Q, R=R)
    assert upd.sys.state_labels[:2] == ["x", "v"] and upd.sys.state_labels[2] == "z[0]"
    val = _data(true3, 21, N=10000, Qs=None)
    base = gb.split_inputs(nominal, "d").sys
    v0 = validate_model(base, val.y, val.u, Q=Q, R=R)
    v1 = validate_model(upd.sys, val.y, val.u, Q=upd.Q, R=upd.R)
    assert v1.se.value < v0.se.value / 3
    # The augmented model's poles match the true closed-loop poles (the lag is
    # coupled into the mass, so compare whole spectra, not the lag pole alone).
    # Measured distance ~3e-4; 2e-3 is a sixth of these poles' distance from
    # the unit circle (~0.012), so a wrong damping or lag would fail.
    poles = np.linalg.eigvals(upd.sys.A)
    true_poles = np.linalg.eigvals(true3.A)
    dist = np.abs(true_poles[:, None] - poles[None, :]).min(axis=1)
    assert dist.max() < 2e-3, (true_poles, poles)


def test_paper_structure_without_feedthrough_is_delayed(spring_case):
    _, nominal, _, res = spring_case
    sub = identify_subsystem(res, order=1, feedthrough=False)
    assert sub.order == 1 and np.allclose(sub.Ddx, 0) and np.allclose(sub.Ddu, 0)
    with pytest.raises(DataError, match="order 0 without feedthrough"):
        identify_subsystem(res, order=0, feedthrough=False)


def test_identify_subsystem_rejects_kalman_result(spring_case):
    true, nominal, est, _ = spring_case
    kf = gb.kalman_filter(nominal, est.y, est.u, unknown="d", Q=Q, R=R)
    with pytest.raises(DataError, match="needs the FilterResult of greybox.uikf"):
        identify_subsystem(kf)


def test_delta_update_is_stable_and_helps(spring_case):
    true, nominal, est, _ = spring_case
    base = gb.split_inputs(nominal, "d").sys
    dm = delta_update(base, est.y, est.u, Q=Q, R=R, max_order=4)
    assert dm.updated.order == 2 + dm.order
    assert dm.updated.sys.state_labels[:2] == ["x", "v"]
    assert np.max(np.abs(np.linalg.eigvals(dm.delta.A))) <= 1 + 1e-6
    val = _data(true, 12, Qs=None)
    v0 = validate_model(base, val.y, val.u, Q=Q, R=R)
    v1 = validate_model(dm.updated.sys, val.y, val.u, Q=dm.updated.Q, R=dm.updated.R)
    assert v1.se.value < v0.se.value


def test_augment_model_checks_the_channel(spring_case):
    _, nominal, _, res = spring_case
    sub = identify_subsystem(res, order=0)
    # the same shapes with another channel called unknown must not pass silently
    with pytest.raises(gb.DimensionError, match="identified with unknown inputs"):
        augment_model(nominal, sub, unknown="F", Q=Q, R=R)


def test_estimate_initial_state_validates_and_recovers_x0(spring_case):
    true, *_ = spring_case
    x0 = np.array([0.3, -0.2])
    u = np.zeros((1, 200))
    sim = gb.simulate(true, u, x0=x0)
    # noise-free response: least squares returns x0 to round-off
    np.testing.assert_allclose(gb.estimate_initial_state(true, sim.y, u), x0, atol=1e-9)
    continuous = gb.named_ss(true.A, true.B, true.C, true.D, 0, states=["x", "v"],
                             inputs=["F"], outputs=["x", "v"])
    with pytest.raises(gb.ModelError, match="continuous-time"):
        gb.estimate_initial_state(continuous, sim.y, u)
    with pytest.raises(gb.DimensionError, match="time must be the last axis"):
        gb.estimate_initial_state(true, sim.y.T, u)


def test_initial_state_window_covers_a_slow_hidden_mode():
    """A measured fast state driven by a hidden slow one (time constant 500 samples): the
    default window (3 time constants) recovers the hidden initial value far better than
    the 50-sample window (slow_modes=False), over 200 noise draws; both are unbiased."""
    dt = 0.05
    A = np.array([[-2.0, 1.0], [0.0, -1.0 / 25.0]])  # x1 measured, x2 hidden, tau 25 s
    sys = gb.discretize(gb.named_ss(A, np.array([[1.0], [0.0]]), np.array([[1.0, 0.0]]),
                                    np.zeros((1, 1)), 0, states=["x1", "x2"], inputs=["u"],
                                    outputs=["x1"]), dt)
    x0 = np.array([0.2, 1.0])
    u = np.zeros((1, 3000))
    y0 = gb.simulate(sys, u, x0=x0).y
    rng = np.random.default_rng(3)
    err_long, err_short = [], []
    for _ in range(200):
        y = y0 + 0.05 * rng.standard_normal(y0.shape)
        err_long.append(gb.estimate_initial_state(sys, y, u)[1] - x0[1])
        err_short.append(gb.estimate_initial_state(sys, y, u, slow_modes=False)[1] - x0[1])
    sd_long, sd_short = np.std(err_long), np.std(err_short)

    def sd_theory(nw):  # least squares on y = O x0 + noise over nw samples
        Ad, Cd = np.asarray(sys.A), np.asarray(sys.C)
        O = np.vstack([Cd @ np.linalg.matrix_power(Ad, k) for k in range(nw)])
        return 0.05 * np.sqrt(np.linalg.inv(O.T @ O)[1, 1])

    # windows: 3 x 500 samples, and 50; each spread within 20 % of least squares' own
    # (200 draws: the spread's relative standard error is 5 %, so 4 sigma)
    np.testing.assert_allclose([sd_long, sd_short], [sd_theory(1500), sd_theory(50)],
                               rtol=0.2)
    assert sd_theory(1500) < sd_theory(50) / 2  # the point: measured 3.2x smaller
    # unbiased within 4 standard errors of the mean
    assert abs(np.mean(err_long)) < 4 * sd_long / np.sqrt(200)
    assert abs(np.mean(err_short)) < 4 * sd_short / np.sqrt(200)
    # a model without a slow mode keeps max(10 n, 50) samples: the same estimate both ways
    fast = gb.discretize(gb.named_ss(np.array([[-2.0, 1.0], [0.0, -5.0]]),
                                     np.array([[1.0], [0.0]]), np.array([[1.0, 0.0]]),
                                     np.zeros((1, 1)), 0, states=["x1", "x2"], inputs=["u"],
                                     outputs=["x1"]), dt)
    yf = gb.simulate(fast, u, x0=x0).y + 0.05 * rng.standard_normal(y0.shape)
    np.testing.assert_array_equal(gb.estimate_initial_state(fast, yf, u),
                                  gb.estimate_initial_state(fast, yf, u, slow_modes=False))


def test_covariances_of_mixed_units_are_accepted():
    # 1e-12 (an encoder in rad^2) next to 1 (a current in A^2) is positive definite
    Rm = np.diag([1e-12, 1.0])
    sys = gb.named_ss(0.5 * np.eye(2), np.eye(2), np.eye(2), np.zeros((2, 2)), 0.1,
                      states=["a", "b"], inputs=["u", "d"], outputs=["a", "b"])
    res = gb.uikf(sys, np.zeros((2, 10)), np.zeros((1, 10)), unknown="d", Q=np.eye(2), R=Rm)
    assert res.d_est.shape == (1, 10)
    with pytest.raises(gb.CovarianceError, match="perfectly correlated"):
        gb.uikf(sys, np.zeros((2, 10)), np.zeros((1, 10)), unknown="d", Q=np.eye(2),
                R=np.ones((2, 2)))


def test_shared_constants_are_read_only():
    with pytest.raises(ValueError, match="read-only"):
        gb.TAPE_DRIVE_R[0, 0] = 1.0


def test_delta_with_factored_integrator_is_exact_without_noise():
    # nominal mass-damper without spring: an integrator (x' = v) the truth lacks;
    # the factored path (identify on the differenced position channel, then an
    # exact integrator in series) must reproduce the exact delta on clean data
    true, base = _msd(True, False), gb.split_inputs(_msd(False, True), "d").sys
    rng = np.random.default_rng(7)
    u = gb.random_binary(4000, amplitude=1.0, hold=50, rng=rng)
    est = gb.simulate(true, u)
    dm = delta_update(base, est.y, est.u, Q=Q, R=R, marginal=True, max_order=4)
    lam = np.linalg.eigvals(dm.delta.A)
    # the fixed integrator is placed exactly (measured: 0.0)
    assert np.min(np.abs(lam - 1.0)) < 1e-12
    uv = gb.random_binary(4000, amplitude=1.0, hold=50, rng=rng)
    val = gb.simulate(true, uv)
    ysim = gb.validate.simulate_output(dm.updated.sys, uv)
    # noise-free data: the exact delta exists at low order; measured SE ~1e-2 %
    assert gb.relative_error(val.y, ysim).value < 0.1
