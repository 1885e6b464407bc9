"""Which poles make a model marginal: only those of the states the inputs reach.

Truth: small models built by hand, whose reach from the input is known.
"""

from __future__ import annotations

import numpy as np

from greybox.system import named_ss
from greybox.validate import has_marginal_pole


def _model(A, B):
    n = A.shape[0]
    return named_ss(A, B, np.eye(n), np.zeros((n, B.shape[1])), 0.1,
                    states=[f"x{i}" for i in range(n)], inputs=["u"],
                    outputs=[f"y{i}" for i in range(n)])


def test_a_constant_offset_state_no_input_reaches_is_not_marginal():
    # a stable plant (poles 0.9, 0.5) read with a constant sensor offset (pole 1, no input)
    A = np.diag([0.9, 0.5, 1.0])
    A[0, 1] = 0.2
    B = np.array([[0.0], [1.0], [0.0]])
    assert not has_marginal_pole(_model(A, B))
    # a drift: offset and rate (a double pole at 1), reached by nothing
    A2 = np.zeros((4, 4))
    A2[:2, :2] = [[0.9, 0.2], [0.0, 0.5]]
    A2[2:, 2:] = [[1.0, 0.1], [0.0, 1.0]]
    assert not has_marginal_pole(_model(A2, np.array([[0.0], [1.0], [0.0], [0.0]])))


def test_an_integrator_the_input_reaches_is_marginal_directly_or_through_a_state():
    A = np.array([[1.0, 0.1], [0.0, 0.5]])  # a position integrating a velocity
    assert has_marginal_pole(_model(A, np.array([[0.0], [1.0]])))  # through the velocity
    assert has_marginal_pole(_model(np.diag([1.0, 0.5]), np.array([[1.0], [0.0]])))
    # the same integrator, fed by nothing the input reaches: its value is its initial state
    assert not has_marginal_pole(_model(np.diag([1.0, 0.5]), np.array([[0.0], [1.0]])))
    # an unstable pole the input reaches through a chain of two states
    A3 = np.array([[1.05, 0.3, 0.0], [0.0, 0.5, 0.2], [0.0, 0.0, 0.4]])
    assert has_marginal_pole(_model(A3, np.array([[0.0], [0.0], [1.0]])))
