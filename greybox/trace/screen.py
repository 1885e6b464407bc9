"""Screen every state equation at once with one joint unknown-input filter.

When the outputs determine the whole state in one step (rank C = n, e.g.
all positions and velocities measured), the unknown-input filter with one
unknown input per state equation (G = I) satisfies (17) and estimates every
equation's error d_i jointly: an error in one equation does not leak into
another's estimate, as it does when one channel is traced at a time with the
others assumed right. Its excess variance over the filter's own Pd_ii says
which equations carry an error. One filter replaces n single-channel filters
before the laws are fitted: the search then costs one joint filter plus a
fixed number of traced channels, whatever n is.
"""

from __future__ import annotations

from dataclasses import dataclass

import control as ct
import numpy as np
from numpy.typing import NDArray

from ..filters import uikf
from .channels import Channel, channel_model

__all__ = ["EquationScreen", "screen_equations"]


@dataclass(frozen=True)
class EquationScreen:
    """Which state equations carry a model error.

    Attributes
    ----------
    available : bool
        False when rank C < n (the joint filter's rank condition fails).
    reason : str
        Why the screen is unavailable ("" otherwise).
    states : tuple of str
        State names, one per equation.
    excess : ndarray, shape (nstates,)
        ``mean(d_i^2) / Pd_ii - 1``: 0 for an equation the model gets right.
    score : ndarray, shape (nstates,)
        ``excess`` in units of its standard error under "no error",
        ``sqrt(2 / N)`` (a chi-square z-score).
    """

    available: bool
    reason: str = ""
    states: tuple[str, ...] = ()
    excess: NDArray[np.float64] | None = None
    score: NDArray[np.float64] | None = None

    def ranked(self, k: int, min_score: float = 5.0) -> list[str]:
        """The (at most k) states whose equations score highest, above ``min_score``."""
        if not self.available:
            return []
        order = np.argsort(-self.score)
        return [self.states[i] for i in order[:k] if self.score[i] > min_score]


def screen_equations(sys: ct.StateSpace, y: NDArray, u: NDArray, *, Q: NDArray, R: NDArray,
                     dt: float | None = None, skip: int = 20) -> EquationScreen:
    """Excess variance of every equation's jointly estimated error.

    Parameters
    ----------
    sys : control.StateSpace
        Nominal model (continuous with ``dt``, or discrete).
    y, u : ndarray, shapes (noutputs, nsteps), (ninputs, nsteps)
    Q, R : ndarray
        Noise covariances of the discrete nominal model.
    dt : float, optional
        Sampling period [s] for a continuous ``sys``.
    skip : int
        Leading samples left out (at least the filter's transient).

    Returns
    -------
    EquationScreen
    """
    n = sys.nstates
    C = np.asarray(sys.C, dtype=float)
    if np.linalg.matrix_rank(C) < n:
        return EquationScreen(False, f"rank C = {np.linalg.matrix_rank(C)} < n = {n}: the "
                                     f"outputs do not determine every equation's error")
    names = tuple(sys.state_labels)
    ch = Channel(name="all equations", G=np.eye(n), labels=tuple(f"d_{s}" for s in names),
                 equations=names)
    model = channel_model(sys, ch, dt)
    res = uikf(model, y, u, unknown=list(ch.labels), Q=Q, R=R)
    N = y.shape[1] - 1
    k0 = max(skip, res.period_converged or skip)
    d = res.d_est[:, k0:N]
    pd = np.maximum(np.diag(np.atleast_2d(res.d_cov)), 1e-300)
    excess = np.mean(d**2, axis=1) / pd - 1.0
    score = excess / np.sqrt(2.0 / max(d.shape[1], 1))
    return EquationScreen(True, "", names, excess, score)
