"""The output-error engine's Jacobian: the sensitivity recursions against differences."""

from __future__ import annotations

import numpy as np
import pytest

from greybox._lti import lti_output, lti_output_sensitivities
from greybox.trace.oe import OutputError, zoh


def _system(rng, n=5, m=2, p=3, rho=0.9):
    A = rng.standard_normal((n, n))
    A *= rho / np.max(np.abs(np.linalg.eigvals(A)))
    return A, rng.standard_normal((n, m)), rng.standard_normal((p, n))


@pytest.mark.parametrize("kind", ["modal", "diagonal"])
def test_output_sensitivities_match_central_differences(kind):
    rng = np.random.default_rng(3)
    A, B, C = _system(rng)
    if kind == "diagonal":
        A = np.diag([0.5, 0.9, -0.3, 0.1, 0.7])
    else:  # a random real matrix: complex pairs and real modes
        assert np.any(np.abs(np.linalg.eigvals(A).imag) > 0)
    u, x0 = rng.standard_normal((2, 500)), rng.standard_normal(5)
    dA, dB = rng.standard_normal((3, 5, 5)), rng.standard_normal((3, 5, 2))
    cx, dcx = lti_output_sensitivities(A, B, C, u, x0, dA, dB)
    D = np.zeros((3, 2))
    np.testing.assert_allclose(cx, lti_output(A, B, C, D, u, x0), rtol=1e-10, atol=1e-10)
    h = 1e-6
    for j in range(3):
        fd = (lti_output(A + h * dA[j], B + h * dB[j], C, D, u, x0)
              - lti_output(A - h * dA[j], B - h * dB[j], C, D, u, x0)) / (2 * h)
        # central differences: truncation ~h^2 |y'''| ~1e-12, round-off ~eps |y| / h ~1e-10
        # relative to the largest sensitivity; 1e-7 leaves a margin of 1000
        assert np.max(np.abs(fd - dcx[j])) <= 1e-7 * np.max(np.abs(fd))


def test_output_sensitivities_decline_a_defective_matrix():
    # a Jordan block has no eigenvector basis: the caller falls back to differences
    A = np.array([[0.9, 1.0], [0.0, 0.9]])
    out = lti_output_sensitivities(A, np.ones((2, 1)), np.eye(2), np.ones((1, 50)),
                                   np.zeros(2), np.ones((1, 2, 2)), np.ones((1, 2, 1)))
    assert out is None


def _engine(rng):
    """A continuous 3-state model with two parameters in A and one in B, data from theta*."""
    dt = 0.05
    A0 = np.array([[0.0, 1.0, 0.0], [-4.0, -0.4, 1.0], [0.0, 0.0, -2.0]])
    B0 = np.array([[0.0], [0.0], [2.0]])
    C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

    def matrices(theta, grow=1.0):
        A = A0.copy()
        A[1, 0] -= theta[0]
        A[1, 1] -= theta[1] * grow
        return A, B0 * (1 + theta[2])

    u = rng.standard_normal((1, 800))
    Ad, Bd = zoh(*matrices(np.array([1.0, 0.3, 0.1])), dt)
    y = lti_output(Ad, Bd, C, np.zeros((2, 1)), u, np.zeros(3)) \
        + 0.01 * rng.standard_normal((2, 800))
    eng = OutputError(matrices, C, np.zeros((2, 1)), y, u, np.zeros(3), 20, dt=dt)
    return eng


def test_engine_jacobian_matches_differences_of_the_residual():
    rng = np.random.default_rng(8)
    eng = _engine(rng)
    theta = np.array([0.7, 0.2, -0.05])
    J = eng.jac(theta, 1.0)
    Jd = eng._difference_jac(theta, 1.0)
    assert J.shape == Jd.shape == (2 * 780, 3)
    # forward differences of step sqrt(eps) are good to ~1e-7 relative; the sensitivities
    # to ~1e-10: 1e-5 of the column's size bounds the difference with a margin of 100
    for j in range(3):
        assert np.max(np.abs(J[:, j] - Jd[:, j])) <= 1e-5 * np.max(np.abs(Jd[:, j]))


def test_engine_fit_recovers_the_parameters_with_the_analytic_jacobian():
    rng = np.random.default_rng(9)
    eng = _engine(rng)
    sol = eng.fit(np.array([0.7, 0.2, -0.05]), 1.0)
    # 1560 residuals at 1 % noise: standard errors ~1e-3 relative; 2e-2 absolute is many
    # sigma and far below the start's error (0.3, 0.1, 0.15)
    np.testing.assert_allclose(sol.x, [1.0, 0.3, 0.1], atol=2e-2)
    assert sol.njev is not None  # the engine's own Jacobian was used


def test_engine_jacobian_of_a_diverged_simulation_is_zero_not_nan():
    rng = np.random.default_rng(10)
    eng = _engine(rng)
    # a damping of -200 makes the continuous model explode within the window
    J = eng.jac(np.array([1.0, -200.0, 0.0]), 1.0)
    assert np.all(np.isfinite(J))
    r = eng.resid(np.array([1.0, -200.0, 0.0]), 1.0)
    assert np.any(np.abs(r) >= 1e6)  # the case is real: the simulation left the clip
    assert np.all(J[np.abs(r) >= 1e6] == 0.0)
