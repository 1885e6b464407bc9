"""The Gillijns & De Moor kernel: records, gains and the recursion (eqs. 7-18).

Shared by every filter of :mod:`greybox.filters` (each imports kernels only;
this module imports no filter). The public unknown-input filter with its
dispatch by relative degree is :func:`greybox.filters.uikf.uikf`.

The model, the time alignment of ``d_est`` and the handling of missing data
are described once, in :mod:`greybox.filters.uikf`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import control as ct
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import norm

from .._lti import CHUNK, LTIRecursion, single_thread_blas
from .._validation import (
    float_array,
    check_covariance,
    check_discrete,
    check_positive,
    check_same_length,
    check_signal,
    check_vector,
)
from ..exceptions import DimensionError, GreyboxError, ModelError, RankConditionError
from ..system import named_ss, split_inputs
from ._memo import MEMO, schedule

__all__ = [
    "FilterResult",
    "SteadyStateFilter",
    "kalman_filter",
    "steady_state_filter",
    "predicted_covariance",
    "check_rank_condition",
]


# --------------------------------------------------------------------------- records
@dataclass(frozen=True)
class SteadyStateFilter:
    """Converged gains of the unknown-input filter (or of the Kalman filter, md = 0).

    Attributes
    ----------
    K : ndarray, shape (nstates, noutputs)
        Measurement-update gain (18).
    M : ndarray, shape (md, noutputs)
        Input-estimation gain (16).
    L : ndarray, shape (nstates, noutputs)
        Combined gain: ``x[k|k] = x[k|k-1] + L (y[k] - C x[k|k-1] - D u[k])``.
    P_pred : ndarray, shape (nstates, nstates)
        Converged ``P[k|k-1]``.
    P_filt : ndarray, shape (nstates, nstates)
        Converged ``P[k|k]``.
    d_cov : ndarray, shape (md, md)
        Converged variance of the input estimate, ``Pd`` (16).
    innovation_cov : ndarray, shape (noutputs, noutputs)
        Converged ``R~ = C P[k|k-1] C^T + R`` (15).
    iterations : int
        Number of covariance iterations until convergence.
    sys : control.StateSpace
        The converged filter as a discrete system: inputs ``[u, y]``, outputs
        ``[x^[k|k], d^[k-1]]`` (see :func:`steady_state_filter`).
    """

    K: NDArray[np.float64]
    M: NDArray[np.float64]
    L: NDArray[np.float64]
    P_pred: NDArray[np.float64]
    P_filt: NDArray[np.float64]
    d_cov: NDArray[np.float64]
    innovation_cov: NDArray[np.float64]
    iterations: int
    sys: ct.StateSpace = field(repr=False)


@dataclass(frozen=True)
class FilterResult:
    """Result of :func:`uikf` or :func:`kalman_filter`.

    Attributes
    ----------
    t : ndarray, shape (nsteps,)
        Time [s].
    x_filt : ndarray, shape (nstates, nsteps)
        Filtered state ``x^[k|k]``.
    x_pred : ndarray, shape (nstates, nsteps)
        Predicted state ``x^[k|k-1]`` (``x_pred[:, 0]`` is the prior x0).
    d_est : ndarray, shape (md, nsteps)
        ``d_est[:, j]`` estimates d[j]; the last column is NaN (d[N-1] needs y[N]);
        in general the last ``relative_degree`` columns are NaN. md = 0 for the
        Kalman filter.
    d_var : ndarray, shape (md, nsteps)
        Variance of each entry of ``d_est`` (diagonal of Pd (16)); NaN where
        d_est is NaN. Units: those of d squared.
    d_cov : ndarray, shape (md, md)
        Full covariance Pd of the last input estimate.
    level : float
        Confidence level of ``d_lower``/``d_upper``.
    innovations : ndarray, shape (noutputs, nsteps)
        ``y[k] - C x^[k|k-1] - D u[k]``: one-step prediction residuals (they
        contain the unknown input's effect ``C G d[k-1]``).
    innovation_cov : ndarray, shape (noutputs, noutputs)
        Last ``R~ = C P[k|k-1] C^T + R``.
    P_filt, P_pred : ndarray, shape (nstates, nstates)
        Last ``P[k|k]`` and ``P[k|k-1]``.
    P_filt_history : ndarray, shape (nstates, nstates, nsteps) or None
        Every ``P[k|k]`` if requested with ``store_covariances=True``.
    K : ndarray, shape (nstates, noutputs)
        Last measurement-update gain.
    M : ndarray, shape (md, noutputs)
        Last input-estimation gain.
    converged : bool
        Whether the covariance recursion converged.
    period_converged : int or None
        First sample index from which the constant gains were used.
    period_settled : int or None
        First sample from which every predicted state variance stays within
        10 % of its converged value (None if the recursion did not converge,
        or where the filter does not track it: feedthrough, unscented and
        ensemble filters; a delayed filter's is that of its shifted-state
        recursion, on the same time axis as ``period_converged``).
    sys : control.StateSpace
        Model from the known inputs (A, B, C, D) with its signal names.
    G : ndarray, shape (nstates, md)
        Unknown-input matrix.
    unknown_labels : tuple of str
        Names of the unknown inputs.
    u, y : ndarray
        The data the filter ran on, shapes (ninputs, nsteps), (noutputs, nsteps).
        When the caller passed float64 2-D arrays these are those arrays (no
        copy is made), so modifying them afterwards changes the record too.
    relative_degree : int
        Delay r (in samples) between d[j] and the first output that sees it:
        ``d_est[:, j]`` is computed from ``y[0..j+r]``. 1 for :func:`uikf`
        (d[k-1] from y[k]); r >= 2 for :func:`~greybox.delayed_uikf` (whose
        ``x_filt[:, k]`` is then ``x^[k|k+r-1]``, see there); 0 for
        :func:`~greybox.feedthrough_uikf` (d[k] from y[k]).
    smoothed : bool
        True if ``x_filt``, ``d_est``, ``d_var`` hold fixed-interval smoothed
        estimates ``x^[k|N-1]``, ``d^[k|N-1]`` (:func:`~greybox.smooth_uikf`);
        ``x_pred`` and ``innovations`` are then those of the forward pass.
    """

    t: NDArray[np.float64]
    x_filt: NDArray[np.float64]
    x_pred: NDArray[np.float64]
    d_est: NDArray[np.float64]
    d_var: NDArray[np.float64]
    d_cov: NDArray[np.float64]
    level: float
    innovations: NDArray[np.float64]
    innovation_cov: NDArray[np.float64]
    P_filt: NDArray[np.float64]
    P_pred: NDArray[np.float64]
    P_filt_history: NDArray[np.float64] | None
    K: NDArray[np.float64]
    M: NDArray[np.float64]
    converged: bool
    period_converged: int | None
    sys: ct.StateSpace = field(repr=False)
    G: NDArray[np.float64] = field(repr=False)
    unknown_labels: tuple[str, ...]
    u: NDArray[np.float64] = field(repr=False)
    y: NDArray[np.float64] = field(repr=False)
    relative_degree: int = 1
    smoothed: bool = False
    period_settled: int | None = None

    @property
    def y_filt(self) -> NDArray[np.float64]:
        """Filtered output ``C x^[k|k] + D u[k]``, shape (noutputs, nsteps)."""
        return np.asarray(self.sys.C) @ self.x_filt + np.asarray(self.sys.D) @ self.u

    @property
    def y_pred(self) -> NDArray[np.float64]:
        """One-step prediction ``C x^[k|k-1] + D u[k]``, shape (noutputs, nsteps)."""
        return self.y - self.innovations

    @property
    def d_halfwidth(self) -> NDArray[np.float64]:
        """Half-width of the ``level`` confidence interval of d_est, shape (md, nsteps)."""
        return norm.ppf(0.5 + self.level / 2) * np.sqrt(self.d_var)

    @property
    def d_lower(self) -> NDArray[np.float64]:
        """Lower bound of the ``level`` confidence interval of d_est, shape (md, nsteps)."""
        return self.d_est - self.d_halfwidth

    @property
    def d_upper(self) -> NDArray[np.float64]:
        """Upper bound of the ``level`` confidence interval of d_est, shape (md, nsteps)."""
        return self.d_est + self.d_halfwidth

    def settled(self, floor: int = 20) -> int:
        """First sample past the filter's transient: where fits on this result start.

        ``period_converged`` (the sample the gains were frozen at), at least
        ``floor``; ``floor`` if the recursion never converged. A recursion
        that converges only in the second half of the record starts at
        ``period_settled`` instead, the first sample from which every
        predicted variance stays within 10 % of its converged value. A
        slowly converging covariance (an unknown-input zero near the unit
        circle, e.g. a force with only positions measured) meets the test
        long after its estimates settled: EMPS's whole estimation file
        (24841 samples) at sample 21969, and every fit started there. Where
        ``period_settled`` is None (feedthrough filters of sensor channels,
        unscented, ensemble) a late convergence still starts the fits at
        ``period_converged``.

        Parameters
        ----------
        floor : int
            Samples skipped at least (the start-up of the initial state).

        Returns
        -------
        int
        """
        kc, ks = self.period_converged, self.period_settled
        if kc is None:
            return floor
        if ks is not None and kc > self.x_filt.shape[1] // 2:
            return max(floor, min(ks, kc))
        return max(floor, kc)

    def plot(self, channel: int | str = 0, *, d_true=None, ax=None):
        """Plot d_est with its confidence band (see :func:`greybox.plotting.plot_unknown_input`)."""
        from ..plotting import plot_unknown_input

        return plot_unknown_input(self, channel, d_true=d_true, ax=ax)


# --------------------------------------------------------------------------- checks
def check_rank_condition(C: NDArray, G: NDArray, labels: Sequence[str] = ()) -> None:
    """Check the existence condition (17): rank(C G) = rank(G) = md.

    Parameters
    ----------
    C : ndarray, shape (noutputs, nstates)
        Output matrix.
    G : ndarray, shape (nstates, md)
        Unknown-input matrix.
    labels : sequence of str, optional
        Names of the unknown inputs, used in the message.

    Raises
    ------
    RankConditionError
        Naming the condition and the offending channels.
    """
    try:
        C, G = np.atleast_2d(float_array(C)), float_array(G)
    except (TypeError, ValueError) as e:
        raise DimensionError(f"C and G must be real numeric arrays; could not convert them "
                             f"({e})") from e
    if G.ndim == 1:
        G = G[:, None]
    if C.ndim != 2 or G.ndim != 2 or C.shape[1] != G.shape[0]:
        raise DimensionError(f"C has shape {np.shape(C)} and G {np.shape(G)}; expected "
                             f"(noutputs, nstates) and (nstates, md)")
    md = G.shape[1]
    if md == 0:
        return
    labels = list(labels) or [f"d[{j}]" for j in range(md)]
    if md > C.shape[0]:
        raise RankConditionError(
            f"{md} unknown inputs {labels} but only {C.shape[0]} outputs: rank(C G) = md "
            f"(17) needs at least md outputs. Use fewer unknown-input channels"
        )
    tol = 1e-9
    sG = np.linalg.svd(G, compute_uv=False)
    rG = int(np.sum(sG > tol * max(sG.max(), np.finfo(float).tiny)))
    if rG < md:
        raise RankConditionError(
            f"rank(G) = {rG} < md = {md}: the unknown-input channels {labels} are linearly "
            f"dependent (17). Merge dependent channels into one"
        )
    F = C @ G
    sF = np.linalg.svd(F, compute_uv=False)
    scale = np.linalg.norm(C, 2) * np.linalg.norm(G, 2)
    rF = int(np.sum(sF > tol * scale))
    if rF < md:
        dead = [labels[j] for j in range(md)
                if np.linalg.norm(F[:, j]) <= tol * scale]
        which = f" channel(s) {dead} do not reach any output" if dead else \
            f" channels {labels} are not separable in the outputs"
        raise RankConditionError(
            f"Unknown input not observable: rank(C @ G) = {rF} < md = {md} (17);{which}. "
            f"Measure a state that the unknown input drives directly, or choose other channels"
        )


def _split(sys, unknown, allow_no_unknown, check_rank=True):
    """Split ``sys`` into the known-input model and G; check (17)."""
    check_discrete(sys)
    if unknown is None or (isinstance(unknown, (list, tuple)) and len(unknown) == 0) or (
            isinstance(unknown, np.ndarray) and unknown.size == 0):
        if not allow_no_unknown:
            raise DimensionError("unknown: name at least one unknown-input channel of sys "
                                 f"(its inputs are {sys.input_labels})")
        model, G, H, labels = sys, np.zeros((sys.nstates, 0)), np.zeros((sys.noutputs, 0)), ()
    else:
        sp = split_inputs(sys, unknown)
        model, G, H, labels = sp.sys, sp.G, sp.H, sp.unknown_labels
    if check_rank and np.any(np.abs(H) > 0):
        raise ModelError(
            f"the unknown inputs {list(labels)} feed through to the outputs (D != 0 on those "
            f"columns); the filter assumes y = C x + D u + v with no direct term from d"
        )
    A, B, C, D = (np.asarray(a, dtype=float) for a in (model.A, model.B, model.C, model.D))
    if check_rank:
        check_rank_condition(C, G, labels)
    return model, A, B, C, D, G, tuple(labels)


def _signal(a, nrows, name, min_steps=1):
    """:func:`check_signal` without the copy when ``a`` is already a float64 2-D array.

    Long records are then used in place (the result's ``u``/``y`` are the
    caller's arrays); finiteness is checked in chunks so no full-length
    temporary is made. Anything else, and every error, goes through
    :func:`check_signal` (same conversions and messages).
    """
    if (type(a) is np.ndarray and a.dtype == np.float64 and a.ndim == 2  # not a masked array
            and a.shape[0] == nrows and a.shape[1] >= min_steps):
        step = max(1, (1 << 18) // max(1, nrows))
        for c0 in range(0, a.shape[1], step):
            if not np.all(np.isfinite(a[:, c0:c0 + step])):
                return check_signal(a, nrows, name, min_steps=min_steps)  # raises
        return a
    return check_signal(a, nrows, name, min_steps=min_steps)


def _prepare(sys, y, u, unknown, Q, R, x0, P0, allow_no_unknown, check_rank=True):
    """Validate everything once; return split model pieces and data arrays."""
    model, A, B, C, D, G, labels = _split(sys, unknown, allow_no_unknown, check_rank)
    n, m, p = model.nstates, model.ninputs, model.noutputs
    y = _signal(y, p, "y", min_steps=2)
    if u is None:
        if m:
            raise DimensionError(f"the model has {m} known inputs {model.input_labels}; "
                                 f"pass u with shape ({m}, nsteps)")
        u = np.zeros((0, y.shape[1]))
    u = _signal(u, m, "u")
    check_same_length(("y", y), ("u", u))
    Q = check_covariance(Q, n, "Q", definite=False)
    R = check_covariance(R, p, "R", definite=True)
    x0 = np.zeros(n) if x0 is None else check_vector(x0, n, "x0", what="nstates = ")
    P0 = np.eye(n) if P0 is None else P0
    P0 = check_covariance(P0, n, "P0", definite=False)
    return model, A, B, C, D, G, labels, y, u, Q, R, x0, P0


# --------------------------------------------------------------------------- kernels
def _measurement_gains(Pp, C, G, R, F=None):
    """Gains of one step from P[k|k-1]: (K, M, Pd, Rt, Pf_from_Pp).

    ``F = C G`` may be passed precomputed. One LAPACK solve per call
    (``Rt^-1 [C Pp, F]``; Rt is symmetric positive definite since R is) and
    plain numpy otherwise: this runs once per sample in the time-varying filter,
    where scipy's per-call wrappers used to dominate.
    """
    n = Pp.shape[0]
    CP = C @ Pp
    Rt = CP @ C.T + R
    Rt = 0.5 * (Rt + Rt.T)
    md = G.shape[1]
    if md:
        if F is None:
            F = C @ G
        S = np.linalg.solve(Rt, np.concatenate((CP, F), axis=1))  # Rt^-1 [C Pp, F]
        K = S[:, :n].T  # Pp C' Rt^-1
        RiF = S[:, n:]
        if md == 1:
            Pd = 1.0 / (F.T @ RiF)  # (1, 1), what inv gives, without its overhead
        else:
            Pd = np.linalg.inv(F.T @ RiF)
            Pd = 0.5 * (Pd + Pd.T)
        M = Pd @ RiF.T
        GKF = G - K @ F
        Pf = Pp - K @ CP + GKF @ Pd @ GKF.T  # K Rt K' = K C Pp
    else:
        K = np.linalg.solve(Rt, CP).T
        Pd = np.zeros((0, 0))
        M = np.zeros((0, C.shape[0]))
        Pf = Pp - K @ CP
    return K, M, Pd, Rt, 0.5 * (Pf + Pf.T)


def _combined_gain(K, M, G, C, F=None):
    """L with x[k|k] = x[k|k-1] + L e, e the innovation (compensation then update)."""
    if F is None:
        F = C @ G
    return G @ M + K - K @ F @ M


def _filter_statespace(A, B, C, D, G, L, M, model, labels):
    """The constant-gain filter as a discrete StateSpace: (u, y) -> (x^[k|k], d^[k-1])."""
    n, m = B.shape
    IL = np.eye(n) - L @ C
    Af = A @ IL
    Bf = np.hstack([B - A @ L @ D, A @ L])
    Cf = np.vstack([IL, -M @ C])
    Df = np.block([[-L @ D, L], [-M @ D, M]])
    ins = [f"{s}" for s in model.input_labels] + [f"{s}_meas" for s in model.output_labels]
    outs = [f"{s}_hat" for s in model.state_labels] + [f"{s}_hat" for s in labels]
    states = [f"{s}_pred" for s in model.state_labels]
    return named_ss(Af, Bf, Cf, Df, model.dt, states=states, inputs=ins, outputs=outs,
                    name="unknown_input_filter" if G.shape[1] else "kalman_filter")


def predicted_covariance(A: NDArray, C: NDArray, Q: NDArray, R: NDArray) -> NDArray | None:
    """The Kalman filter's steady-state predicted covariance ``P[k|k-1]`` (n, n) of a
    discrete model (A, C) under (Q, R), from the Riccati equation (Schur method; an
    unstable A is fine where (A, C) is detectable), or None where it has no stabilizing
    solution. For a model's one-step predictor (gain ``A P C^T (C P C^T + R)^-1``) and a
    filter's settled prior."""
    from scipy.linalg import solve_discrete_are

    try:
        with np.errstate(all="ignore"):
            P = solve_discrete_are(A.T, C.T, Q, R)
    except (np.linalg.LinAlgError, ValueError):
        return None
    return 0.5 * (P + P.T) if np.all(np.isfinite(P)) else None


def _iterate_to_steady_state(A, C, G, Q, R, P0, tol, maxiter):
    Pp = A @ P0 @ A.T + Q if P0 is not None else Q.copy()
    for it in range(1, maxiter + 1):
        K, M, Pd, Rt, Pf = _measurement_gains(Pp, C, G, R)
        Pn = A @ Pf @ A.T + Q
        Pn = 0.5 * (Pn + Pn.T)
        if np.max(np.abs(Pn - Pp)) <= tol * max(np.max(np.abs(Pn)), np.finfo(float).tiny):
            return Pn, it, True
        Pp = Pn
    return Pp, maxiter, False


def steady_state_filter(sys: ct.StateSpace, *, Q: ArrayLike, R: ArrayLike,
                        unknown: int | str | Sequence[int | str] | None = None,
                        tol: float = 1e-12, maxiter: int = 100_000) -> SteadyStateFilter:
    """Converged unknown-input filter (or Kalman filter if ``unknown`` is None).

    The covariance recursion (14)-(18) does not depend on data; for a
    time-invariant model it converges, and the filter becomes a linear
    time-invariant system from ``(u, y)`` to ``(x^[k|k], d^[k-1])``:

    .. math::

        \\hat x[k|k-1]_{+} = A (I - L C) \\hat x[k|k-1] + (B - A L D) u[k] + A L y[k]

    with outputs ``x^[k|k] = (I - L C) x^[k|k-1] - L D u[k] + L y[k]`` and
    ``d^[k-1] = M (y[k] - C x^[k|k-1] - D u[k])``.

    Parameters
    ----------
    sys : control.StateSpace
        Discrete model with inputs ``[u, d]``.
    Q : array_like, shape (nstates, nstates)
        Process-noise covariance (PSD).
    R : array_like, shape (noutputs, noutputs)
        Measurement-noise covariance (PD).
    unknown : label(s) or index(es), optional
        Unknown-input channels of ``sys``; None gives the Kalman filter.
    tol : float
        Relative change of ``P[k|k-1]`` (max norm) that counts as converged.
    maxiter : int
        Iteration limit.

    Returns
    -------
    SteadyStateFilter
        With ``.sys`` a python-control StateSpace: inputs ``u`` then measured
        ``y`` (named ``<output>_meas``), outputs ``<state>_hat`` then
        ``<d>_hat``. Note the d output at step k estimates d[k-1].

    Raises
    ------
    GreyboxError
        If the recursion does not converge within ``maxiter``.
    """
    model, A, B, C, D, G, labels = _split(sys, unknown, allow_no_unknown=True)
    n = sys.nstates
    Q = check_covariance(Q, n, "Q", definite=False)
    R = check_covariance(R, sys.noutputs, "R", definite=True)
    return _steady(A, B, C, D, G, Q, R, model, labels, tol, maxiter, P0=None)


def _steady(A, B, C, D, G, Q, R, model, labels, tol, maxiter, P0):
    Pp, it, ok = MEMO.call(_iterate_to_steady_state, A, C, G, Q, R, P0, tol, maxiter)
    Pp = Pp.copy()  # the user's record: writable (the cache keeps its own, read-only)
    if not ok:
        raise GreyboxError(
            f"the filter's covariance recursion did not converge in {maxiter} iterations; "
            f"check that (A, C) is detectable and that Q is not zero on unstable modes"
        )
    K, M, Pd, Rt, Pf = _measurement_gains(Pp, C, G, R)
    L = _combined_gain(K, M, G, C)
    ss = _filter_statespace(A, B, C, D, G, L, M, model, labels)
    return SteadyStateFilter(K=K, M=M, L=L, P_pred=Pp, P_filt=Pf, d_cov=Pd,
                             innovation_cov=Rt, iterations=it, sys=ss)


@dataclass(frozen=True)
class GainSchedule:
    """The data-independent part of a linear filter's recursion: its gains step by step.

    ``K[k]`` and ``M[k]`` the gains of the time-varying steps, as the filter's gain
    function returned them (a copy in another memory layout would change the products'
    last bits), ``d_var[k]`` (md,) the variances of d^ at those steps, ``kend`` their
    count plus the filter's first; ``kconv`` the step at which P[k|k-1] converged (the
    gains then frozen at ``final``), or None (run to the record's end, ``final`` the last
    step's); ``P_pred`` the filter's last P[k|k-1]; ``Pf_history`` (n, n, N) where asked.
    Each filter extends it with what its own first step needs.
    """

    K: tuple
    M: tuple
    d_var: NDArray
    kend: int
    kconv: int | None
    converged: bool
    P_pred: NDArray
    final: tuple
    Pf_history: NDArray | None


@dataclass(frozen=True)
class _GainSchedule(GainSchedule):
    """:class:`GainSchedule` of :func:`_run`: ``K0`` the gain of step 0 (a plain update of
    the prior), ``K[k-1]``, ``M[k-1]``, ``d_var[k-1]`` those of steps k = 1 .. ``kend`` - 1;
    ``final`` (K, M, Pd, Rt, Pf); ``settled`` the filter's ``period_settled``."""

    K0: NDArray | None = None
    settled: int | None = None


def _gain_schedule(A, C, G, Q, R, P0, N: int, auto: bool, tol: float,
                   keep_pf: bool) -> _GainSchedule:
    """The covariance recursion of :func:`_run` (eqs. 7-18 without the data)."""
    n, p, md = A.shape[0], C.shape[0], G.shape[1]
    F = C @ G
    At = A.T
    tiny = np.finfo(float).tiny
    K0, _, _, Rt, Pf = _measurement_gains(P0, C, np.zeros((n, 0)), R)
    Ks, Ms, dv = [], [], np.empty((max(N - 1, 0), md))
    Phist = np.empty((n, n, N)) if keep_pf else None
    if Phist is not None:
        Phist[:, :, 0] = Pf
    K, M, Pd = K0, np.zeros((md, p)), np.zeros((md, md))
    Pp, Pp_prev, kconv = P0, None, None
    # diag P[k|k-1] until the gains are frozen, every stride-th step (for period_settled;
    # at most ~4096 rows whatever the record's length)
    pdiag, pk, stride = [], [], max(1, -(-N // 4096))
    k = 1
    while k < N:
        Pp = A @ Pf @ At + Q
        Pp = 0.5 * (Pp + Pp.T)
        # (array methods: np.max's wrapper costs more than the reduction, per sample)
        if auto and Pp_prev is not None and np.abs(Pp - Pp_prev).max() <= \
                tol * max(np.abs(Pp).max(), tiny):
            kconv = k
            break
        if auto and k % stride == 0:
            pdiag.append(Pp.diagonal().copy())  # a copy: a view would keep all of Pp
            pk.append(k)
        Pp_prev = Pp
        K, M, Pd, Rt, Pf = _measurement_gains(Pp, C, G, R, F)
        Ks.append(K)
        Ms.append(M)
        dv[k - 1] = Pd.diagonal()
        if Phist is not None:
            Phist[:, :, k] = Pf
        k += 1
    converged = kconv is not None
    if not auto and Pp_prev is not None and N > 2:
        # report convergence of the recursion even though gains were not frozen
        Pn = A @ Pf @ A.T + Q
        converged = bool(np.max(np.abs(Pn - Pp_prev)) <= tol * max(np.max(np.abs(Pn)), 1e-300))
    settled = None
    if kconv is not None:
        settled = _settled_step(pdiag, pk, Pp, kconv, n, tiny)
        K, M, Pd, Rt, Pf = _measurement_gains(Pp, C, G, R, F)
        if Phist is not None:
            Phist[:, :, kconv:] = Pf[:, :, None]
    return _GainSchedule(K0=K0, K=tuple(Ks), M=tuple(Ms), d_var=dv[:k - 1], kend=k,
                         kconv=kconv, converged=converged, settled=settled, P_pred=Pp,
                         final=(K, M, Pd, Rt, Pf), Pf_history=Phist)


def _schedule(A, C, G, Q, R, P0, N: int, auto: bool, tol: float,
              keep_pf: bool) -> _GainSchedule:
    """:func:`_gain_schedule`, computed once per model, (Q, R, P0) and options in a process
    (:mod:`greybox.filters._memo`): a converged schedule serves every record longer than
    its convergence step; one that ran to the record's end serves that length only."""
    if keep_pf:  # the (n, n, N) history is the record's size: not kept
        return _gain_schedule(A, C, G, Q, R, P0, N, auto, tol, keep_pf)
    stride = max(1, -(-N // 4096))  # period_settled's sampling of P depends on it
    return schedule(lambda: _gain_schedule(A, C, G, Q, R, P0, N, auto, tol, keep_pf),
                    ("gains", A, C, G, Q, R, P0, auto, tol, stride), N)


def _run(model, A, B, C, D, G, labels, y, u, Q, R, x0, P0, *, level, gain, tol,
         store_covariances) -> FilterResult:
    n, N = A.shape[0], y.shape[1]
    p, m, md = C.shape[0], B.shape[1], G.shape[1]
    x_filt = np.empty((n, N))
    x_pred = np.empty((n, N))
    innov = np.empty((p, N))
    d_est = np.full((md, N), np.nan)
    d_var = np.full((md, N), np.nan)
    has_D = m > 0 and bool(np.any(D))
    sc = _schedule(A, C, G, Q, R, P0, N, gain == "auto", tol, store_covariances)
    # k = 0: plain measurement update of the prior (no d[-1] to estimate)
    x_pred[:, 0] = x0
    e = y[:, 0] - C @ x0
    if has_D:
        e = e - D @ u[:, 0]
    innov[:, 0] = e
    x_filt[:, 0] = x0 + sc.K0 @ e
    xf = x_filt[:, 0]
    if md and sc.kend > 1:
        d_var[:, :sc.kend - 1] = sc.d_var.T
    for k in range(1, sc.kend):
        K, M = sc.K[k - 1], sc.M[k - 1]
        xp = A @ xf
        if m:
            xp += B @ u[:, k - 1]
        yk = y[:, k] - D @ u[:, k] if has_D else y[:, k]
        e = yk - C @ xp
        x_pred[:, k] = xp
        innov[:, k] = e
        if md:
            dh = M @ e
            d_est[:, k - 1] = dh
            xs = xp + G @ dh
            xf = xs + K @ (yk - C @ xs)
        else:
            xf = xp + K @ e
        x_filt[:, k] = xf
    K, M, Pd, Rt, Pf = sc.final
    if sc.kconv is not None:
        _constant_gain_run(A, B, C, D, G, K, M, C @ G, sc.kconv, y, u, x_filt, x_pred, innov,
                           d_est)
        if md:
            d_var[:, sc.kconv - 1:N - 1] = np.diag(Pd)[:, None]
    t = np.arange(N) * float(model.dt)
    return FilterResult(
        t=t, x_filt=x_filt, x_pred=x_pred, d_est=d_est, d_var=d_var, d_cov=Pd, level=level,
        innovations=innov, innovation_cov=Rt, P_filt=Pf, P_pred=sc.P_pred,
        P_filt_history=sc.Pf_history, K=K, M=M, converged=sc.converged,
        period_converged=sc.kconv, sys=model, G=G, unknown_labels=labels, u=u, y=y,
        period_settled=sc.settled,
    )


def _settled_step(pdiag, pk, Pp, kconv: int, n: int, tiny: float) -> int:
    """The first step from which every variance of P[k|k-1] stays within 10 % of its
    converged value ``diag(Pp)``; ``pdiag`` the diagonals recorded at the steps ``pk``
    before the gains were frozen at ``kconv``."""
    far = np.flatnonzero(np.any(np.abs(np.reshape(pdiag, (-1, n)) - np.diag(Pp)) >
                                0.1 * np.maximum(np.abs(np.diag(Pp)), tiny), axis=1))
    if far.size:
        return pk[far[-1] + 1] if far[-1] + 1 < len(pk) else kconv
    return pk[0] if pk else kconv  # the first recorded step (earlier ones were not checked)


def _constant_gain_run(A, B, C, D, G, K, M, F, kconv: int, y, u, x_filt, x_pred, innov,
                       d_est) -> None:
    """The constant-gain fast path from sample ``kconv`` on, no per-sample Python loop.

    ``x^[k+1|k] = A (I - L C) x^[k|k-1] + A L y[k] + (B - A L D) u[k]``, run in time
    chunks written straight into the outputs ``x_filt, x_pred, innov, d_est``
    (temporaries O(n * chunk)); ``K, M`` the frozen gains.
    """
    n, N = A.shape[0], y.shape[1]
    m, md = B.shape[1], G.shape[1]
    has_D = m > 0 and bool(np.any(D))
    L = _combined_gain(K, M, G, C, F)
    AL = A @ L
    Bf = B - AL @ D if has_D else B
    rec = LTIRecursion(A @ (np.eye(n) - L @ C))
    S = rec.in_map  # fold the modal input transform into the drive matrices
    mapped = S is not None
    if mapped:
        AL, Bf = S @ AL, S @ Bf
    C_is_I = C.shape == (n, n) and np.array_equal(C, np.eye(n))
    xk = A @ x_filt[:, kconv - 1]
    if m:
        xk += B @ u[:, kconv - 1]
    with single_thread_blas():
        for a in range(kconv, N, CHUNK):
            b = min(N, a + CHUNK)
            ys = y[:, a:b]
            drive = AL @ ys
            if m:
                drive += Bf @ u[:, a:b]
            xp = x_pred[:, a:b]
            xk = rec.run(drive, xk, xp, mapped=mapped)
            del drive
            e = innov[:, a:b]
            if C_is_I:
                np.subtract(ys, xp, out=e)
            else:
                np.matmul(C, xp, out=e)
                np.subtract(ys, e, out=e)
            if has_D:
                e -= D @ u[:, a:b]
            xfc = x_filt[:, a:b]
            np.matmul(L, e, out=xfc)
            xfc += xp
            if md:
                np.matmul(M, e, out=d_est[:, a - 1:b - 1])


def _check_options(level, gain, tol):
    level = check_positive(level, "level")
    if not 0 < level < 1:
        raise DimensionError(f"level must be in (0, 1); found {level}")
    if gain not in ("auto", "time-varying"):
        raise DimensionError(f"gain must be 'auto' or 'time-varying'; found {gain!r}")
    tol = check_positive(tol, "tol")
    return level, gain, tol


# --------------------------------------------------------------------------- public
def kalman_filter(sys: ct.StateSpace, y: ArrayLike, u: ArrayLike | None = None, *,
                  Q: ArrayLike, R: ArrayLike, unknown=None, x0: ArrayLike | None = None,
                  P0: ArrayLike | None = None, gain: str = "auto", tol: float = 1e-12,
                  store_covariances: bool = False) -> FilterResult:
    """Kalman filter that ignores the unknown input (the paper's baseline).

    Same interface and record as :func:`uikf`; it is the same recursion with
    G = 0. Inputs of ``sys`` listed in ``unknown`` are dropped (their effect is
    left to the process noise); ``d_est`` then has zero rows.

    Parameters
    ----------
    sys : control.StateSpace
        Discrete-time model.
    y : array_like, shape (noutputs, nsteps)
    u : array_like, shape (ninputs_known, nsteps), optional
    Q : array_like, shape (nstates, nstates)
    R : array_like, shape (noutputs, noutputs)
    unknown : label(s) or index(es), optional
        Inputs of ``sys`` to ignore.
    x0 : array_like, shape (nstates,), optional
    P0 : array_like, shape (nstates, nstates), optional
    gain : {"auto", "time-varying"}
    tol : float
    store_covariances : bool

    Returns
    -------
    FilterResult
    """
    _, gain, tol = _check_options(0.95, gain, tol)
    parts = list(_prepare(sys, y, u, unknown, Q, R, x0, P0, allow_no_unknown=True,
                          check_rank=False))
    parts[5] = np.zeros((parts[1].shape[0], 0))  # G = 0
    parts[6] = ()
    return _run(*parts, level=0.95, gain=gain, tol=tol, store_covariances=store_covariances)
