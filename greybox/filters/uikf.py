"""Unbiased minimum-variance input and state filter (Gillijns & De Moor, eqs. 7-18).

The model (5)-(6)::

    x[k+1] = A x[k] + B u[k] + G d[k] + w[k],   w ~ N(0, Q)
    y[k]   = C x[k] + D u[k]          + v[k],   v ~ N(0, R)

with an unknown input ``d`` (the model error) of dimension md. The Kalman
filter that ignores d is the same recursion with G = 0 (:func:`kalman_filter`).

Time alignment: the measurement y[k] yields the estimate of d[k-1]. The
result stores ``d_est[:, j]`` as the estimate of d[j]; its last column is
NaN because d[N-1] would need y[N].

Missing data: a NaN sample in ``y`` or ``u`` raises :class:`DataError`. The
unknown-input filter has no prior on d, so a skipped measurement leaves
x[k] with unbounded uncertainty along G; interpolate, or split the record.

This module is the dispatch by relative degree: d seen one step later (the
kernel, :mod:`greybox.filters.kernels`), through the sensors
(:mod:`greybox.filters.feedthrough`) or several steps later
(:mod:`greybox.filters.delayed`). The kernel's names are re-exported here.
"""

from __future__ import annotations

from collections.abc import Sequence

import control as ct
import numpy as np
from numpy.typing import ArrayLike

from .delayed import delayed_uikf
from .feedthrough import _use_feedthrough, feedthrough_uikf
from .kernels import (  # noqa: F401  (re-exported: the kernel's public names under uikf)
    FilterResult,
    SteadyStateFilter,
    _check_options,
    _prepare,
    _run,
    check_rank_condition,
    kalman_filter,
    steady_state_filter,
)

__all__ = [
    "FilterResult",
    "SteadyStateFilter",
    "uikf",
    "kalman_filter",
    "steady_state_filter",
    "check_rank_condition",
]


def uikf(sys: ct.StateSpace, y: ArrayLike, u: ArrayLike | None = None, *,
         unknown: int | str | Sequence[int | str], Q: ArrayLike, R: ArrayLike,
         x0: ArrayLike | None = None, P0: ArrayLike | None = None, level: float = 0.95,
         gain: str = "auto", tol: float = 1e-12, store_covariances: bool = False,
         relative_degree: int | str = 1) -> FilterResult:
    """Unbiased minimum-variance input and state filter (Gillijns & De Moor 2007).

    Estimates the states x and the unknown input d of::

        x[k+1] = A x[k] + B u[k] + G d[k] + w[k]
        y[k]   = C x[k] + D u[k] + v[k]

    Parameters
    ----------
    sys : control.StateSpace
        Discrete-time model (ZOH-discretized) whose inputs are the known inputs
        ``u`` and the unknown inputs ``d``; the columns of its B for ``d`` are G.
    y : array_like, shape (noutputs, nsteps)
        Measured outputs.
    u : array_like, shape (ninputs_known, nsteps), optional
        Measured known inputs (omit if the model has none).
    unknown : label(s) or index(es)
        Which inputs of ``sys`` are unknown (md >= 1 of them).
    Q : array_like, shape (nstates, nstates)
        Process-noise covariance (PSD).
    R : array_like, shape (noutputs, noutputs)
        Measurement-noise covariance (PD).
    x0 : array_like, shape (nstates,), optional
        Prior mean of x[0] (zero by default).
    P0 : array_like, shape (nstates, nstates), optional
        Prior covariance of x[0] (identity by default).
    level : float
        Confidence level of the intervals ``d_lower``/``d_upper`` (0.95).
    gain : {"auto", "time-varying"}
        "auto" switches to the constant-gain filter, run without a
        per-sample Python loop, once ``P[k|k-1]`` has converged;
        "time-varying" runs the full recursion at every sample.
    tol : float
        Relative change of ``P[k|k-1]`` (max norm) that counts as converged.
    store_covariances : bool
        Keep every ``P[k|k]`` in ``P_filt_history`` (memory n^2 N).
    relative_degree : int or "auto"
        1 (default): the filter of eqs. (7)-(18), d[k-1] from y[k]. An int
        r >= 2 or "auto" (detect r from the model and Q, R, and report it in
        ``FilterResult.relative_degree``) runs :func:`~greybox.delayed_uikf`;
        0, or "auto" when d feeds through to y, runs
        :func:`~greybox.feedthrough_uikf` (d[k] from y[k]).

    Returns
    -------
    FilterResult

    Raises
    ------
    ModelError
        ``sys`` is continuous-time, or d feeds through to y (unless
        relative_degree is 0 or "auto").
    RankConditionError
        rank(C G) = rank(G) = md (17) fails (for relative_degree = 1).
    DimensionError, DataError, CovarianceError
        Wrong shapes, NaN/inf data, non-symmetric or indefinite Q, R, P0.

    Notes
    -----
    Steps for k >= 1 (eqs. 7-18, covariance update from PAPER_NOTES §2):

    .. math::

        \\hat x_{k|k-1} = A \\hat x_{k-1|k-1} + B u_{k-1},\\quad
        P_{k|k-1} = A P_{k-1|k-1} A^T + Q

        \\tilde R = C P_{k|k-1} C^T + R,\\ F = C G,\\
        P_d = (F^T \\tilde R^{-1} F)^{-1},\\ M = P_d F^T \\tilde R^{-1}

        \\hat d_{k-1} = M (y_k - C \\hat x_{k|k-1} - D u_k),\\quad
        \\hat x^*_{k|k} = \\hat x_{k|k-1} + G \\hat d_{k-1}

        K = P_{k|k-1} C^T \\tilde R^{-1},\\quad
        \\hat x_{k|k} = \\hat x^*_{k|k} + K (y_k - C \\hat x^*_{k|k} - D u_k)

        P_{k|k} = P_{k|k-1} - K \\tilde R K^T + (G - K F) P_d (G - K F)^T

    At k = 0 the prior (x0, P0) gets a plain Kalman measurement update.

    References
    ----------
    S. Gillijns and B. De Moor, "Unbiased minimum-variance input and state
    estimation for linear discrete-time systems", Automatica 43 (2007) 111-116;
    "Data-based subsystem identification for dynamic model updating",
    CDC 2006, eqs. (7)-(18).

    Examples
    --------
    >>> import numpy as np, greybox as gb
    >>> sys = gb.tape_drive_nominal(dt=1e-4)
    >>> sim = gb.simulate(gb.tape_drive_true(dt=1e-4), np.ones((2, 500)), rng=0)
    >>> res = gb.uikf(sys, sim.y, sim.u, unknown="T", Q=gb.TAPE_DRIVE_Q * 1e-3,
    ...               R=gb.TAPE_DRIVE_R)
    >>> res.d_est.shape
    (1, 500)
    """
    if not (isinstance(relative_degree, (int, np.integer)) and relative_degree == 1):
        if _use_feedthrough(sys, unknown, relative_degree):
            return feedthrough_uikf(sys, y, u, unknown=unknown, Q=Q, R=R, x0=x0, P0=P0,
                                    level=level, gain=gain, tol=tol,
                                    store_covariances=store_covariances)

        return delayed_uikf(sys, y, u, unknown=unknown, Q=Q, R=R,
                            relative_degree=relative_degree, x0=x0, P0=P0, level=level,
                            gain=gain, tol=tol, store_covariances=store_covariances)
    level, gain, tol = _check_options(level, gain, tol)
    parts = _prepare(sys, y, u, unknown, Q, R, x0, P0, allow_no_unknown=False)
    return _run(*parts, level=level, gain=gain, tol=tol, store_covariances=store_covariances)
