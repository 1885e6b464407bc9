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

from ..exceptions import GreyboxError
from ..filters import delayed_uikf, uikf
from .channels import Channel, channel_model

__all__ = ["EquationScreen", "screen_equations", "SensorScreen", "screen_sensors",
           "SensorLawScreen", "screen_sensor_laws"]

# Samples per block mean in the screen's regression.
BLOCK = 10


@dataclass(frozen=True)
class EquationScreen:
    """Which state equations carry a model error.

    Attributes
    ----------
    available : bool
        False when the outputs cannot determine every (non-kinematic)
        equation's error.
    reason : str
        Why the screen is unavailable ("" otherwise).
    states : tuple of str
        Names of the screened equations' states (all states when rank C = n;
        the non-kinematic ones, screened with delayed estimation, when only
        positions are measured).
    excess : ndarray, shape (nstates,)
        ``mean(d_i^2) / Pd_ii - 1``: 0 for an equation the model gets right.
    score : ndarray, shape (nstates,)
        z-score of the Lagrange-multiplier statistic ``N_b R^2`` of the
        regression of d^_i on (x^, u, 1), on block means of ``BLOCK`` samples
        (N_b blocks; x^ from the blocks two before and two after, see
        :func:`screen_equations`): ``(N_b R^2 - k) / sqrt(2 k)``, about
        N(0, 1) or a little below (d^'s block means are not quite white) when
        the equation is right.
    coef : ndarray, shape (len(states), nstates + ninputs + 1)
        That regression's coefficients on the scaled block means (for the
        direction of one force shared by two equations).
    """

    available: bool
    reason: str = ""
    states: tuple[str, ...] = ()
    excess: NDArray[np.float64] | None = None
    score: NDArray[np.float64] | None = None
    coef: NDArray[np.float64] | None = None

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
    names = tuple(sys.state_labels)
    rank = np.linalg.matrix_rank(C)
    if rank == n:
        eqs = list(range(n))
        filt = uikf
    else:
        # positions only: screen the equations that are not kinematic (dp/dt = v rows are
        # exact), with delayed estimation (the error shows in y two samples later)
        A = np.asarray(sys.A, dtype=float)
        eqs = [i for i in range(n) if np.count_nonzero(A[i]) != 1] \
            if not ct.isdtime(sys, strict=True) else []
        if not eqs or len(eqs) > rank:
            return EquationScreen(False, f"rank C = {rank} < n = {n} and {len(eqs)} "
                                         f"non-kinematic equations: the outputs do not "
                                         f"determine every equation's error")
        filt = delayed_uikf
    G = np.eye(n)[:, eqs]
    ch = Channel(name="all equations", G=G, labels=tuple(f"d_{names[i]}" for i in eqs),
                 equations=tuple(names[i] for i in eqs))
    model = channel_model(sys, ch, dt)
    try:
        res = filt(model, y, u, unknown=list(ch.labels), Q=Q, R=R)
    except GreyboxError as e:
        return EquationScreen(False, f"the joint filter failed: {e}")
    N = y.shape[1] - res.relative_degree
    k0 = res.settled(skip)
    d = res.d_est[:, k0:N]
    if not np.all(np.isfinite(d)):
        return EquationScreen(False, "the joint filter's estimates are not finite")
    pd = np.maximum(np.diag(np.atleast_2d(res.d_cov)), 1e-300)
    excess = np.mean(d**2, axis=1) / pd - 1.0
    # a law in the states and inputs shows as correlation of d^_i with (x^, u): the
    # Lagrange-multiplier statistic N R^2 of that regression, on block means of BLOCK
    # samples (d^ is noisy but white-ish, a law is slow: averaging keeps the law). The
    # states are not taken from d^'s own block: x^ and d^ of the same samples share
    # their measurement noise (d^_k ~ y_{k+1} - A x^_k), and a regression on many
    # collinear states finds that noise (a spring stencil's second difference cancels
    # the motion and keeps it): a right 32-state model scored z ~ 230 on every
    # equation. The block two before and the block two after are averaged instead (a
    # one-block gap covers the filter's memory); the inputs are exact and stay.
    nb = d.shape[1] // BLOCK
    nx = res.x_filt.shape[0]
    if nb - 4 <= 2 * (nx + u.shape[0] + 1):
        return EquationScreen(False, f"{d.shape[1]} samples are too few to screen "
                                     f"{len(eqs)} equations")

    def blocks(a):
        return a[:, :nb * BLOCK].reshape(a.shape[0], nb, BLOCK).mean(axis=2)

    db = blocks(d)[:, 2:nb - 2]
    xb = blocks(res.x_filt[:, k0:N])
    xb = 0.5 * (xb[:, :nb - 4] + xb[:, 4:])
    wb = np.vstack([xb, blocks(u[:, k0:N])[:, 2:nb - 2], np.ones(nb - 4)])
    wb /= np.sqrt(np.mean(wb**2, axis=1, keepdims=True)) + 1e-300
    coef = np.linalg.lstsq(wb.T, db.T, rcond=None)[0]
    r2 = 1.0 - np.sum((db - coef.T @ wb) ** 2, axis=1) / np.maximum(np.sum(db**2, axis=1),
                                                                       1e-300)
    k = wb.shape[0]
    score = ((nb - 4) * r2 - k) / np.sqrt(2.0 * k)
    return EquationScreen(True, "", ch.equations, excess, score, coef.T)


@dataclass(frozen=True)
class SensorScreen:
    """Which sensors a constant error in the innovations points to.

    Attributes
    ----------
    outputs : tuple of str
        The outputs ranked, best first (the lowest misfit of one constant
        offset on that sensor alone to the innovations' mean).
    misfit : ndarray, shape (len(outputs),)
        Each one's weighted misfit (chi-square on ``noutputs - 1`` degrees of
        freedom when the offset is the whole error).
    offset : ndarray, shape (len(outputs),)
        Each one's fitted offset, in the output's units.
    null : float
        The weighted misfit without any offset (chi-square on ``noutputs``
        degrees of freedom when the mean is zero): ``null - misfit[j]`` is the
        likelihood-ratio evidence of sensor j's offset (chi-square on 1).
    """

    outputs: tuple[str, ...]
    misfit: NDArray[np.float64]
    offset: NDArray[np.float64]
    null: float = 0.0


def screen_sensors(sys_d: ct.StateSpace, K: NDArray, e: NDArray, n_eff: NDArray
                   ) -> SensorScreen:
    """Rank the sensors by how well one constant offset on each explains the mean of the
    Kalman filter's innovations (their DC signature).

    With the filter's gain K (x^_k|k = x^_k|k-1 + K e_k), a constant offset b
    on output j leaves the prediction error at ``x~ = -M^-1 A K b e_j``,
    ``M = I - A (I - K C)`` (stable filter: M invertible), and the innovation
    mean at ``t_j b = (I - C M^-1 A K) e_j b``. Each sensor's ``b`` is fitted
    to the innovations' mean by weighted least squares (weights: the mean's
    variance, ``var(e_i) / n_eff_i``); the misfit ranks them. One n x n solve
    for all sensors: the cost of one filter step, whatever the record length.

    Parameters
    ----------
    sys_d : control.StateSpace
        The discrete nominal model the innovations come from.
    K : ndarray, shape (nstates, noutputs)
        The filter's (steady-state) measurement-update gain.
    e : ndarray, shape (noutputs, nsteps)
        Its innovations, after the transient.
    n_eff : ndarray, shape (noutputs,)
        Effective samples of each output's innovations.

    Returns
    -------
    SensorScreen
    """
    A, C = np.asarray(sys_d.A, dtype=float), np.asarray(sys_d.C, dtype=float)
    n, p = A.shape[0], C.shape[0]
    M = np.eye(n) - A @ (np.eye(n) - K @ C)
    try:
        X = np.linalg.solve(M, A @ K)
    except np.linalg.LinAlgError:
        X = np.linalg.lstsq(M, A @ K, rcond=None)[0]
    T = np.eye(p) - C @ X                      # column j: sensor j's innovation signature
    m = e.mean(axis=1)
    w = np.asarray(n_eff, dtype=float) / np.maximum(e.var(axis=1), 1e-300)
    tw = (T * w[:, None])
    den = np.einsum("ij,ij->j", tw, T)
    b = np.where(den > 0, tw.T @ m / np.where(den > 0, den, 1.0), 0.0)
    r = m[:, None] - T * b[None, :]
    mis = np.einsum("ij,ij->j", r * w[:, None], r)
    order = np.argsort(mis, kind="stable")
    labels = list(sys_d.output_labels)
    return SensorScreen(outputs=tuple(labels[j] for j in order), misfit=mis[order],
                        offset=b[order], null=float(np.sum(w * m ** 2)))


@dataclass(frozen=True)
class SensorLawScreen:
    """How much of each output's simulation error a law of that sensor alone explains.

    Attributes
    ----------
    outputs : tuple of str
        The outputs ranked, best first (the largest explained share).
    explained : ndarray, shape (len(outputs),)
        Each one's sum of squares explained by its own sensor terms, in units of the
        output's mean square (the simulation error's SE^2 scale), per sample.
    total : float
        The nominal simulation error's sum of squares over every output, in the same
        units: a sensor error alone is explained almost whole by its own output's share.
    """

    outputs: tuple[str, ...]
    explained: NDArray[np.float64]
    total: float


def screen_sensor_laws(y: NDArray, ysim: NDArray, dt: float, labels, skip: int = 20
                       ) -> SensorLawScreen:
    """Rank the sensors by how much of the nominal model's simulation error the terms of a
    sensor law on that output alone explain: its gain and offset (``y^_j``, 1), its lag
    (``dy^_j/dt``) and its drift (t), fitted by least squares to ``y_j - y^_j``.

    A sensor error is read by its own output only and does not move the simulated states,
    so it stays in that output's simulation error; a state-equation error spreads over
    every output the states reach. One least-squares fit of four columns per output: the
    cost of a few passes over the record.

    Parameters
    ----------
    y, ysim : ndarray, shape (noutputs, nsteps)
        The measured outputs and the nominal model's simulation of them.
    dt : float
        Sampling period [s].
    labels : sequence of str
        The output names.
    skip : int
        Leading samples left out (the simulation's start).

    Returns
    -------
    SensorLawScreen
    """
    y, ysim = np.asarray(y, dtype=float)[:, skip:], np.asarray(ysim, dtype=float)[:, skip:]
    p, N = y.shape
    if N < 8:
        return SensorLawScreen(tuple(labels), np.zeros(p), 0.0)
    t = np.linspace(-1.0, 1.0, N)
    expl, tot = np.zeros(p), 0.0
    for j in range(p):
        scale = float(np.mean(y[j] ** 2)) + 1e-300
        r = y[j] - ysim[j]
        W = np.column_stack([ysim[j], np.ones(N), np.gradient(ysim[j], dt), t])
        coef = np.linalg.lstsq(W, r, rcond=None)[0]
        fitted = W @ coef
        expl[j] = float(np.sum(r ** 2) - np.sum((r - fitted) ** 2)) / (scale * N)
        tot += float(np.sum(r ** 2)) / (scale * N)
    order = np.argsort(-expl, kind="stable")
    return SensorLawScreen(tuple(labels[j] for j in order), expl[order], tot)
