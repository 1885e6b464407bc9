"""The linear stand-in of a law's simulation step (greybox.trace.laws.step_matrix).

The noise model of a nonlinear law's output-error intervals propagates the process
noise through the model with the law replaced by its linear part. A continuous-time
law (one carrying a first-order hold) is simulated by the Heun step; its stand-in is
the continuous model with the law's linear part added, discretized exactly, which is
the truth checked here.
"""

from types import SimpleNamespace

import numpy as np
from scipy.linalg import expm

from greybox.filters.delayed import first_order_hold
from greybox.trace.laws import step_matrix


def _two_masses(c=0.05):
    """A lightly damped two-mass chain (x = p1, v1, p2, v2), the force inside the pair."""
    Ac = np.array([[0, 1, 0, 0], [-40, -c, 20, 0], [0, 0, 0, 1], [25, 0, -25, -c]], float)
    Gc = np.array([[0, 0], [1, 0], [0, 0], [0, 1]], float)
    return Ac, Gc


def test_a_held_law_s_stand_in_is_the_continuous_model_with_its_linear_part_discretized():
    Ac, Gc = _two_masses()
    dt = 0.02
    D = np.array([[-12.0, 0, 12.0, 0], [9.0, 0, -9.0, 0]])  # a stiffer spring, linear part
    law = SimpleNamespace(Ddx=D, hold=first_order_hold(Ac, Gc, dt))
    want = expm((Ac + Gc @ D) * dt)
    got = step_matrix(expm(Ac * dt), None, law)
    # both are exact discretizations of one matrix: agreement to rounding (the matrix
    # logarithm's ~1e-12 relative on these entries of order 1)
    assert np.allclose(got, want, rtol=1e-9, atol=1e-11), np.abs(got - want).max()
    # the Heun step's own linearization differs by O(dt^3): the exact stand-in is a choice
    G0, G1 = law.hold
    A = expm(Ac * dt)
    heun = A + G0 @ D + G1 @ D @ (A + (G0 + G1) @ D)
    assert np.abs(heun - want).max() > 1e-9


def test_a_law_held_over_the_sample_adds_its_linear_part_one_sample_late():
    Ac, Gc = _two_masses()
    A, G = expm(Ac * 0.02), np.random.default_rng(0).normal(size=(4, 2))
    D = np.random.default_rng(1).normal(size=(2, 4))
    law = SimpleNamespace(Ddx=D, hold=None)
    assert np.array_equal(step_matrix(A, G, law), A + G @ D)


def test_a_stiffer_spring_held_one_sample_late_can_be_unstable_where_the_plant_is_not():
    """Why the stand-in matters: the same stiffer spring added with d held over the sample
    (ZOH: the force from x[k] for the whole step) gives a lightly damped chain a pole
    outside the unit circle, where the continuous model with the spring is stable."""
    Ac, Gc = _two_masses(c=0.01)
    dt = 0.05
    D = np.array([[-200.0, 0, 200.0, 0], [160.0, 0, -160.0, 0]])
    M = expm(np.block([[Ac, Gc], [np.zeros((2, 6))]]) * dt)
    G = M[:4, 4:]  # the zero-order hold's input matrix
    held = SimpleNamespace(Ddx=D, hold=None)
    foh = SimpleNamespace(Ddx=D, hold=first_order_hold(Ac, Gc, dt))
    A = expm(Ac * dt)
    assert np.max(np.real(np.linalg.eigvals(Ac + Gc @ D))) < 0   # the plant: stable
    assert np.max(np.abs(np.linalg.eigvals(step_matrix(A, G, held)))) > 1.0
    assert np.max(np.abs(np.linalg.eigvals(step_matrix(A, G, foh)))) < 1.0
