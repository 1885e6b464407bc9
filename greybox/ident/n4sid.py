"""Combined deterministic-stochastic subspace identification (N4SID family).

Public: :func:`n4sid` and its record :class:`N4SIDResult`. The record and the
model-completion helpers here are shared with the closed-loop method in
:mod:`greybox.ident.closedloop`.

Every step works on the triangular factor of the block Hankel matrix, which
is accumulated in chunks (:mod:`greybox.ident._hankel`), so memory does not
grow with the number of samples.

The algorithm of :func:`n4sid` (robust combined variant, Van Overschee & De Moor
1996, Fig. 4.8). Let ``W_p = [U_p; Y_p]`` be the past and ``U_f, Y_f`` the future
block Hankel matrices (``i`` block rows each). With the oblique projection
:math:`O_i = Y_f /_{U_f} W_p` and the SVD
:math:`W_1 O_i W_2 = U_1 S_1 V_1^T + U_2 S_2 V_2^T`, the observability
matrix is :math:`\\Gamma_i = W_1^{-1} U_1 S_1^{1/2}`. Weights:
N4SID ``W1 = I, W2 = I``; MOESP ``W1 = I, W2 = Pi_{U_f^perp}``; CVA
``W1 = ((Y_f/U_f^perp)(Y_f/U_f^perp)^T)^{-1/2}, W2 = Pi_{U_f^perp}``.
A and C follow from :math:`\\underline{\\Gamma_i} A = \\overline{\\Gamma_i}`;
then :math:`\\Gamma_i, \\Gamma_{i-1}` are recomputed from (A, C) and B, D
solve the linear least-squares problem

.. math::

    \\begin{bmatrix} \\Gamma_{i-1}^\\dagger Z_{i+1} \\\\ Y_{i|i} \\end{bmatrix}
    - \\begin{bmatrix} A \\\\ C \\end{bmatrix} \\Gamma_i^\\dagger Z_i
    = \\mathcal{K}(B, D)\\, U_f + \\begin{bmatrix} \\rho_w \\\\ \\rho_v \\end{bmatrix},

whose residual covariance gives Q, S, R; K follows from the Riccati
equation.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import control as ct
import numpy as np
import scipy.linalg as sla
from numpy.typing import ArrayLike, NDArray

from .._validation import check_positive, resolve_channels
from ..exceptions import DataError, DimensionError, GreyboxWarning, IdentificationError
from ._hankel import HankelR, channel_rms, hankel_r, ncolumns, prepare_data, small_blas

__all__ = ["N4SIDResult", "n4sid"]

#: Default relative tolerance of rank decisions (least squares cut-offs) on the
#: scaled data, where every channel has unit RMS.
DEFAULT_RTOL = 1e-10

#: Relative singular value below which the input Hankel matrix counts as
#: rank deficient (input not persistently exciting).
PE_RTOL = 1e-8


@dataclass(frozen=True, eq=False)
class N4SIDResult:
    """Record of a subspace identification.

    The model is in innovation form

    .. math::

        x[k+1] = A x[k] + B u[k] + K e[k], \\qquad y[k] = C x[k] + D u[k] + e[k],

    with ``e`` white of covariance ``innovation_cov``.

    Attributes
    ----------
    sys : control.StateSpace
        Discrete-time model (A, B, C, D) with ``dt`` set, states named
        ``f"{state_prefix}[i]"``, and the given input/output labels.
    K : ndarray, shape (nstates, noutputs)
        Steady-state Kalman gain of the innovation form.
    innovation_cov : ndarray, shape (noutputs, noutputs)
        Covariance of the innovations ``e`` [output units squared].
    Q : ndarray, shape (nstates, nstates)
        Process-noise covariance of ``x[k+1] = A x + B u + w``.
    R : ndarray, shape (noutputs, noutputs)
        Measurement-noise covariance of ``y = C x + D u + v``.
    S : ndarray, shape (nstates, noutputs)
        Cross covariance ``E[w v^T]``.
    singular_values : ndarray, shape (nsv,)
        Singular values used to choose the order, computed on internally
        scaled data (unit RMS per channel) and normalised by the square root
        of the number of Hankel columns, so they do not grow with ``nsteps``.
    order : int
        Number of states.
    x0 : ndarray, shape (nstates,)
        Initial state of the first experiment (least-squares fit of the
        one-step predictor to the first samples).
    x0_experiments : ndarray, shape (nstates, nexperiments)
        Initial state of every experiment.
    horizon : int
        Number of block rows (past horizon).
    weighting : str
        ``"N4SID"``, ``"MOESP"``, ``"CVA"`` or ``"PBSID"``.
    method : str
        ``"n4sid"`` or ``"pbsid"``.
    criterion : str or None
        Order-selection criterion, or None if the order was fixed.
    criterion_values : ndarray, shape (max_order + 1,)
        Criterion for orders 0..max_order (NaN where not evaluated).
    nsamples : int
        Number of block-Hankel columns (regression samples) used.
    feedthrough : tuple of int
        Indices of the inputs whose direct term ``D[:, j]`` was estimated.
    scale_u : ndarray, shape (ninputs,)
        RMS of each input used for internal scaling.
    scale_y : ndarray, shape (noutputs,)
        RMS of each output used for internal scaling.
    """

    sys: ct.StateSpace
    K: NDArray[np.float64]
    innovation_cov: NDArray[np.float64]
    Q: NDArray[np.float64]
    R: NDArray[np.float64]
    S: NDArray[np.float64]
    singular_values: NDArray[np.float64]
    order: int
    x0: NDArray[np.float64]
    x0_experiments: NDArray[np.float64]
    horizon: int
    weighting: str
    method: str
    criterion: str | None
    criterion_values: NDArray[np.float64]
    nsamples: int
    feedthrough: tuple[int, ...]
    scale_u: NDArray[np.float64]
    scale_y: NDArray[np.float64]

    @property
    def dt(self) -> float:
        """Sampling period [s]."""
        return self.sys.dt

    def plot(self, ax=None):
        """Plot the singular values and the chosen order.

        See :func:`greybox.plotting.plot_singular_values`.
        """
        from ..plotting import plot_singular_values

        return plot_singular_values(self, ax=ax)


# ---------------------------------------------------------------------------
# small linear-algebra helpers on Q-coordinate matrices (rows = signals)
# ---------------------------------------------------------------------------


def _regress(Yc: NDArray, Xc: NDArray, rtol: float) -> NDArray:
    """Coefficients ``T`` minimising ``||Yc - T Xc||_F`` (minimum norm)."""
    if Xc.shape[0] == 0:
        return np.zeros((Yc.shape[0], 0))
    if Yc.shape[0] == 0:
        return np.zeros((0, Xc.shape[0]))
    sol = sla.lstsq(Xc.T, Yc.T, cond=rtol, lapack_driver="gelsd", check_finite=False)[0]
    return sol.T


def _project(Yc: NDArray, Xc: NDArray, rtol: float) -> NDArray:
    """Orthogonal projection of the row space of ``Yc`` onto that of ``Xc``."""
    return _regress(Yc, Xc, rtol) @ Xc


def _pinv(M: NDArray, rtol: float) -> NDArray:
    if M.size == 0:
        return np.zeros((M.shape[1], M.shape[0]))
    return np.linalg.pinv(M, rcond=rtol)


def _obsv(A: NDArray, C: NDArray, nblocks: int) -> NDArray:
    """Extended observability matrix [C; CA; ...; CA^(nblocks-1)]."""
    out = []
    M = C
    for _ in range(nblocks):
        out.append(M)
        M = M @ A
    return np.vstack(out) if out else np.zeros((0, A.shape[0]))


def _toeplitz(A, B, C, D, nblocks: int) -> NDArray:
    """Lower block-Toeplitz matrix of Markov parameters [D; CB; CAB; ...]."""
    l, m = D.shape
    mk = np.zeros((nblocks + 1, l, m))
    mk[0] = D
    M = B
    for k in range(1, nblocks):
        mk[k] = C @ M
        M = A @ M
    a = np.arange(nblocks)
    idx = a[:, None] - a[None, :]
    idx[idx < 0] = nblocks  # the zero block
    H = mk[idx]  # (nb, nb, l, m)
    return H.transpose(0, 2, 1, 3).reshape(nblocks * l, nblocks * m)


def _resolve_feedthrough(feedthrough, ninputs: int, input_labels) -> tuple[int, ...]:
    if feedthrough is True:
        return tuple(range(ninputs))
    if feedthrough is False or feedthrough is None:
        return ()
    labels = list(input_labels) if input_labels is not None else [f"u[{i}]" for i in range(ninputs)]
    return tuple(sorted(resolve_channels(feedthrough, labels, "feedthrough")))


def _check_labels(labels, n: int, name: str, what: str):
    if labels is None:
        return None
    if isinstance(labels, str):
        labels = [labels]
    labels = list(labels)
    if len(labels) != n:
        raise DimensionError(f"{name} has {len(labels)} entries; expected {what} = {n}")
    return labels


def _npar(n: int, l: int, m: int, nd: int) -> int:
    """Free parameters of an innovation-form model of order n (modulo similarity)."""
    return n * (m + 2 * l) + l * nd


def _criterion_value(crit: str, Re: NDArray, n: int, l: int, m: int, nd: int, ncols: int) -> float:
    sign, logdet = np.linalg.slogdet(Re)
    if sign <= 0:
        return np.inf
    pen = np.log(ncols) if crit == "bic" else 2.0
    return ncols * logdet + pen * _npar(n, l, m, nd)


def choose_horizon(horizon, order, lengths, m, l, max_order, fixed_min_block, default=10):
    """Validate or choose the number of block rows.

    ``fixed_min_block`` is the number of extra block rows the method needs
    beyond the horizon (N4SID uses 2 * horizon rows, PBSID horizon + 1).
    """
    nz = m + l
    total = int(sum(lengths))

    def ok(i):
        nb = fixed_min_block(i)
        j = ncolumns(lengths, nb)
        return j >= 2 * nb * nz and min(lengths) >= nb

    need_i = 1 if order is None else (int(np.ceil(order / l)) + 1 if order > 0 else 1)
    if horizon is not None:
        i = check_positive(horizon, "horizon", integer=True)
        nb = fixed_min_block(i)
        if not ok(i):
            imax = max((k for k in range(1, min(i, min(lengths) + 1)) if ok(k)), default=0)
            hint = (f"reduce horizon to at most {imax}" if imax >= need_i
                    else "collect more data")
            raise DataError(
                f"horizon={i} is too long for the data: it needs block Hankel matrices with "
                f"{nb * nz} rows and at least {2 * nb * nz} columns (about "
                f"{2 * nb * nz + nb - 1} samples per experiment), found {min(lengths)} samples "
                f"in the shortest experiment ({total} in all); {hint}"
            )
        if i < need_i:
            raise DimensionError(
                f"order={order} needs horizon >= {need_i} (order <= (horizon - 1) * noutputs "
                f"= {(i - 1) * l}); found horizon={i}. Increase the horizon"
            )
        return i
    target = max(default, need_i, 0 if max_order is None else int(np.ceil(max_order / l)) + 1)
    i = target
    while i >= need_i and not ok(i):
        i -= 1
    if i < max(need_i, 1):
        nb = fixed_min_block(max(need_i, 1))
        raise DataError(
            f"too few samples: found {min(lengths)} in the shortest experiment ({total} in all); "
            f"even the shortest usable horizon ({max(need_i, 1)}) needs about "
            f"{2 * nb * nz + nb - 1} samples per experiment. Collect more data"
            + ("" if order is None else " or lower the order")
        )
    return i


def _check_pe(h: HankelR, nblocks: int, input_labels, what: str):
    """Warn if the inputs are not persistently exciting of order ``nblocks``."""
    m = h.ninputs
    if m == 0:
        return
    labels = input_labels or [f"u[{j}]" for j in range(m)]
    U = h.rows("u", 0, nblocks)
    s = np.linalg.svd(U, compute_uv=False)
    if s.size and s[-1] > PE_RTOL * max(s[0], np.finfo(float).tiny):
        return
    rank = int(np.sum(s > PE_RTOL * s[0])) if s.size and s[0] > 0 else 0
    bad = []
    nz = m + h.noutputs
    for j in range(m):
        rows = h.L[[t * nz + j for t in range(nblocks)]]
        sj = np.linalg.svd(rows, compute_uv=False)
        if sj[0] == 0 or sj[-1] <= PE_RTOL * sj[0]:
            bad.append(labels[j])
    which = (f"input(s) {bad} are" if bad else "the inputs are jointly (collinear inputs)")
    warnings.warn(
        f"{which} not persistently exciting of order {nblocks}: the input block Hankel matrix "
        f"has rank {rank} < {nblocks * m}. {what} are not uniquely determined (a minimum-norm "
        f"solution is returned). Use a richer input (white noise, PRBS, multisine with more "
        f"frequencies), drop constant or redundant inputs, or shorten the horizon",
        GreyboxWarning,
        stacklevel=4,
    )


def _stable_kalman(A, C, Q, R, S):
    """Kalman gain and innovation covariance from (Q, R, S); fall back to S R^-1."""
    n, l = A.shape[0], C.shape[0]
    if n == 0:
        return np.zeros((0, l)), R.copy()
    try:
        P = sla.solve_discrete_are(A.T, C.T, Q, R, s=S)
        Re = C @ P @ C.T + R
        K = np.linalg.solve(Re.T, (A @ P @ C.T + S).T).T
        if np.all(np.isfinite(K)):
            return K, 0.5 * (Re + Re.T)
    except (np.linalg.LinAlgError, ValueError):
        pass
    K = np.linalg.lstsq(R.T, S.T, rcond=None)[0].T
    return K, R.copy()


def _initial_states(A, B, C, D, K, ys, us, nmax: int = 1000) -> NDArray:
    """Least-squares initial states of the one-step predictor, per experiment."""
    n = A.shape[0]
    out = np.zeros((n, len(ys)))
    if n == 0:
        return out
    Abar = A - K @ C
    Bbar = B - K @ D
    for e, (ye, ue) in enumerate(zip(ys, us)):
        M = min(ye.shape[1], nmax)
        l = ye.shape[0]
        x = np.zeros(n)
        Phi = np.zeros((M, l, n))
        Ak = C.copy()
        res = np.zeros((M, l))
        used = M
        with np.errstate(over="ignore", invalid="ignore"):
            for k in range(M):
                uk, yk = ue[:, k], ye[:, k]
                res[k] = yk - C @ x - D @ uk
                Phi[k] = Ak
                if not ((np.abs(res[k]) < _MAX_RMS).all() and (np.abs(Ak) < _MAX_RMS).all()):
                    # an unstable predictor overflows: fit on the rows before that
                    # (LAPACK must never see NaN, inf, or numbers whose squares overflow)
                    used = k
                    break
                x = Abar @ x + Bbar @ uk + K @ yk
                Ak = Ak @ Abar
        if used == 0:
            continue
        out[:, e] = np.linalg.lstsq(Phi[:used].reshape(used * l, n), res[:used].reshape(-1),
                                    rcond=None)[0]
    return out


def _make_ss(A, B, C, D, dt, states, kw) -> ct.StateSpace:
    """``ct.ss`` that also builds models without inputs.

    python-control 0.10.2 rejects ``D`` of shape (noutputs, 0); a zero-input
    model is built with one dummy input that is then removed.
    """
    if B.shape[1] > 0:
        return ct.ss(A, B, C, D, dt, states=states, **kw)
    kw = {k: v for k, v in kw.items() if k != "inputs"}
    sys = ct.ss(A, np.zeros((A.shape[0], 1)), C, np.zeros((C.shape[0], 1)), dt, states=states,
                **kw)
    sys.B = np.zeros((A.shape[0], 0))
    sys.D = np.zeros((C.shape[0], 0))
    sys.ninputs = 0
    sys.input_index = {}
    return sys


def _finish(
    *, A, B, C, D, Q, R, S, K=None, Re=None, su, sy, ys, us, dt, input_labels, output_labels,
    state_prefix, **fields,
) -> N4SIDResult:
    """Unscale a model found on scaled data and build the record."""
    n = A.shape[0]
    Du = np.diag(1.0 / su) if su.size else np.zeros((0, 0))
    Sy = np.diag(sy)
    B = B @ Du
    C = Sy @ C
    D = Sy @ D @ Du
    R = Sy @ R @ Sy
    S = S @ Sy
    Q = 0.5 * (Q + Q.T)
    R = 0.5 * (R + R.T)
    if K is None:
        K, Re = _stable_kalman(A, C, Q, R, S)
    else:
        K = K @ np.diag(1.0 / sy)
        Re = Sy @ Re @ Sy
        Re = 0.5 * (Re + Re.T)
    x0s = _initial_states(A, B, C, D, K, ys, us)
    kw = {}
    if input_labels is not None:
        kw["inputs"] = input_labels
    if output_labels is not None:
        kw["outputs"] = output_labels
    sys = _make_ss(A, B, C, D, dt, [f"{state_prefix}[{k}]" for k in range(n)], kw)
    return N4SIDResult(
        sys=sys, K=K, innovation_cov=Re, Q=Q, R=R, S=S, order=n, x0=x0s[:, 0].copy(),
        x0_experiments=x0s, **fields,
    )


#: Largest (and inverse of the smallest) channel RMS accepted: the noise covariances
#: scale with its square, and 1e150 squared is still far from float64's 1.8e308.
_MAX_RMS = 1e150


def common_setup(y, u, dt, input_labels, output_labels, feedthrough, order, max_order, rtol,
                  weighting_ok=True):
    """The arguments of :func:`n4sid` and :func:`greybox.pbsid` checked once: the scaled
    records, their sizes, labels, feedthrough, orders, tolerance and channel RMS (a
    :class:`~greybox.exceptions.GreyboxError` that names the argument otherwise)."""
    ys, us, l, m = prepare_data(y, u)
    dt = check_positive(dt, "dt")
    input_labels = _check_labels(input_labels, m, "input_labels", "ninputs")
    output_labels = _check_labels(output_labels, l, "output_labels", "noutputs")
    fed = _resolve_feedthrough(feedthrough, m, input_labels)
    if order is not None:
        order = check_positive(order, "order", integer=True, allow_zero=True)
    if max_order is not None:
        max_order = check_positive(max_order, "max_order", integer=True, allow_zero=True)
    rtol = check_positive(rtol, "rtol")
    sy = channel_rms(ys)
    su = channel_rms(us) if m else np.zeros(0)
    for name, s, lab in (("y", sy, output_labels), ("u", su, input_labels)):
        zero = np.flatnonzero(s == 0)
        if zero.size and name == "y":
            raise DataError(
                f"output(s) {[(lab or [f'y[{k}]' for k in range(l)])[k] for k in zero]} are "
                f"identically zero; there is nothing to identify. Remove them"
            )
        bad = np.flatnonzero((s > 0) & ((s > _MAX_RMS) | (s < 1.0 / _MAX_RMS)))
        if bad.size:
            raise DataError(
                f"{name}[{bad[0]}] has RMS {s[bad[0]]:.3g}: outside 1e-150..1e150 its "
                f"covariances would overflow or underflow float64; rescale the data (change "
                f"units) before identification")
    su = np.where(su > 0, su, 1.0)
    return ys, us, l, m, dt, input_labels, output_labels, fed, order, max_order, rtol, sy, su


@dataclass(frozen=True)
class _Setup:
    """The checked data and options of :func:`n4sid` and :func:`~greybox.ident.pbsid`
    (:func:`common_setup`): experiments, sizes, labels and channel scales."""

    ys: list
    us: list
    l: int
    m: int
    dt: float
    input_labels: Sequence[str] | None
    output_labels: Sequence[str] | None
    fed: tuple[int, ...]
    order: int | None
    max_order: int | None
    rtol: float
    sy: NDArray[np.float64]
    su: NDArray[np.float64]

    @property
    def lengths(self) -> list[int]:
        """Samples of each experiment."""
        return [a.shape[1] for a in self.ys]


# ---------------------------------------------------------------------------
# N4SID
# ---------------------------------------------------------------------------


def n4sid(
    y: ArrayLike | Sequence[ArrayLike],
    u: ArrayLike | Sequence[ArrayLike] | None = None,
    *,
    order: int | None = None,
    horizon: int | None = None,
    dt: float = 1.0,
    feedthrough: bool | Sequence[int | str] = False,
    weighting: Literal["N4SID", "MOESP", "CVA"] = "N4SID",
    criterion: Literal["bic", "aic"] = "bic",
    max_order: int | None = None,
    input_labels: Sequence[str] | None = None,
    output_labels: Sequence[str] | None = None,
    state_prefix: str = "z",
    rtol: float = DEFAULT_RTOL,
    chunk_size: int | None = None,
) -> N4SIDResult:
    """Identify a discrete-time state-space model with subspace method N4SID.

    Combined deterministic-stochastic identification in the robust variant
    of Van Overschee & De Moor (1996), Fig. 4.8: the order and the column
    space of the extended observability matrix come from a weighted oblique
    projection; A and C from its shift invariance; B and D by least squares
    on the orthogonal projections Z_i and Z_{i+1}; the noise covariances from
    the residuals. Valid for open-loop data (inputs uncorrelated with the
    noise); for closed-loop data use :func:`greybox.ident.pbsid`.

    Parameters
    ----------
    y : array_like, shape (noutputs, nsteps), or list of such arrays
        Measured outputs; time is the last axis. A list gives several
        experiments (each with its own length).
    u : array_like, shape (ninputs, nsteps), list of such arrays, or None
        Inputs; None or 0 rows identifies a purely stochastic model.
    order : int, optional
        Model order (number of states), 0 allowed (a static map
        ``y = D u + e`` with ``feedthrough=True``, white noise otherwise).
        If None the order is chosen by ``criterion`` in ``0..max_order``.
    horizon : int, optional
        Number of block rows ``i`` (past and future horizon). Default 10,
        reduced when the data are too short, raised when ``order`` or
        ``max_order`` need it (``order <= (i - 1) * noutputs``).
    dt : float
        Sampling period [s] stored in the model.
    feedthrough : bool or sequence of int or str
        Estimate the direct term D (True: all inputs; a sequence: only these
        inputs, by index or label). Otherwise D = 0.
    weighting : {"N4SID", "MOESP", "CVA"}
        Weights ``W1, W2`` of the oblique projection before the SVD
        (Van Overschee & De Moor 1996, Sec. 4.3.2).
    criterion : {"bic", "aic"}
        Order-selection criterion ``nsamples * log det(Re(n)) + c * npar(n)``
        with ``Re(n)`` the output residual covariance of the order-n fit,
        ``npar(n) = n (ninputs + 2 noutputs) + noutputs * nfeedthrough`` and
        ``c = log(nsamples)`` (BIC) or 2 (AIC).
    max_order : int, optional
        Largest order tried when ``order`` is None; default
        ``min(10, (horizon - 1) * noutputs)``.
    input_labels, output_labels : sequence of str, optional
        Signal names for the returned model.
    state_prefix : str
        States are named ``f"{state_prefix}[k]"``.
    rtol : float
        Relative tolerance of every least-squares rank cut-off, on data
        scaled to unit RMS per channel.
    chunk_size : int, optional
        Block-Hankel columns accumulated at a time (memory vs speed).

    Returns
    -------
    N4SIDResult
        Model in innovation form, noise covariances, singular values.

    Raises
    ------
    DimensionError
        Wrong shapes, mismatched lengths, order too large for the horizon.
    DataError
        NaN/inf, too few samples, horizon too long, zero outputs.
    IdentificationError
        No usable model (e.g. non-finite matrices).

    Warns
    -----
    GreyboxWarning
        If the inputs are not persistently exciting of order ``2 * horizon``.

    Notes
    -----
    The oblique projection, its weights and the least-squares steps for (A, C), (B, D)
    and the noise covariances are in the module docstring (:mod:`greybox.ident.n4sid`).
    All projections are computed from the lower factor ``L`` of ``H H^T / ncols = L L^T``
    of the scaled block Hankel matrix ``H`` (2 i block rows), accumulated over chunks of
    columns, so memory is ``O((2 i (ninputs + noutputs))^2)`` whatever ``nsteps``. The
    data are not detrended: remove means or trends first if needed.

    References
    ----------
    P. Van Overschee and B. De Moor, *Subspace Identification for Linear
    Systems: Theory, Implementation, Applications*, Kluwer, 1996,
    Sec. 4.3 (Theorem 12), Fig. 4.8 (robust combined algorithm), Sec. 6.1
    (implementation with the R factor).

    Examples
    --------
    >>> import numpy as np, control as ct
    >>> from greybox.ident import n4sid
    >>> rng = np.random.default_rng(0)
    >>> plant = ct.ss([[0.8, 0.2], [0.0, 0.5]], [[0.0], [1.0]], [[1.0, 0.0]], 0, 1.0)
    >>> u = rng.standard_normal((1, 2000))
    >>> y = ct.forced_response(plant, U=u).y + 0.01 * rng.standard_normal((1, 2000))
    >>> res = n4sid(y, u, order=2)
    >>> np.round(np.sort(res.sys.poles().real), 2)
    array([0.5, 0.8])
    """
    _check_choice("weighting", weighting, ("N4SID", "MOESP", "CVA"))
    _check_choice("criterion", criterion, ("bic", "aic"))
    s = _Setup(*common_setup(y, u, dt, input_labels, output_labels, feedthrough, order,
                              max_order, rtol))
    return _n4sid_run(s, horizon, chunk_size, weighting, criterion, state_prefix)


def _check_choice(name: str, value, allowed: tuple[str, ...]) -> None:
    """DimensionError unless ``value`` is one of ``allowed`` (an option's name)."""
    if value not in allowed:
        expected = ", ".join(repr(a) for a in allowed[:-1]) + f" or {allowed[-1]!r}"
        raise DimensionError(f"{name}={value!r} is unknown; expected {expected}")


def _n4sid_run(s: _Setup, horizon, chunk_size, weighting, criterion, state_prefix):
    """The horizon, block-Hankel factor and model of :func:`n4sid` from its checked setup."""
    i = choose_horizon(horizon, s.order, s.lengths, s.m, s.l, s.max_order, lambda k: 2 * k)
    h = hankel_r(s.ys, s.us, s.sy, s.su, 2 * i, chunk_size=chunk_size)
    with small_blas():
        return n4sid_from_factor(h, i, s.ys, s.us, s.l, s.m, s.dt, s.input_labels,
                                  s.output_labels, s.fed, s.order, s.max_order, s.rtol, s.sy,
                                  s.su, weighting, criterion, state_prefix)


def _fit_orders(order, max_order, nmax, too_large, fit, residual_cov, criterion, l, m, nfed,
                ncols):
    """Fit the given order, or every order 0..max and choose one by the criterion.

    Shared by :func:`n4sid` and :func:`greybox.ident.pbsid`. ``fit(n)`` returns
    a fit record, ``residual_cov(n, fit)`` the residual covariance the
    criterion is computed from. Returns ``(order, fit, criterion_values, auto)``.
    """
    auto = order is None
    if not auto:
        if order > nmax:
            raise DimensionError(too_large)
        orders = [order]
    else:
        mo = min(10, nmax) if max_order is None else min(max_order, nmax)
        orders = list(range(mo + 1))
    crit = np.full(max(orders) + 1, np.nan)
    fits = {}
    for n in orders:
        fits[n] = fit(n)
        if auto:
            crit[n] = _criterion_value(criterion, residual_cov(n, fits[n]), n, l, m, nfed,
                                       ncols)
    if auto:
        order = int(np.nanargmin(crit))
    return order, fits[order], crit, auto


def n4sid_from_factor(h, i, ys, us, l, m, dt, input_labels, output_labels, fed, order,
                       max_order, rtol, sy, su, weighting, criterion, state_prefix):
    """N4SID's fit from the block-Hankel factor ``h`` (horizon ``i``) and the arguments
    :func:`common_setup` checked: the identification result of :func:`n4sid`."""
    _check_pe(h, 2 * i, input_labels, "B and D")

    core = _N4SIDCore(h, i, weighting, fed, rtol)
    nmax = (i - 1) * l
    order, fit, crit_vals, auto = _fit_orders(
        order, max_order, nmax,
        f"order={order} is too large for horizon={i}: at most (horizon - 1) * noutputs "
        f"= {nmax}. Increase the horizon",
        core.fit, lambda n, _fit: core.state_residual_cov(n), criterion, l, m, len(fed),
        h.ncols)
    A, B, C, D, Sig = fit["A"], fit["B"], fit["C"], fit["D"], fit["Sigma"]
    n = order
    for name, M in (("A", A), ("B", B), ("C", C), ("D", D)):
        if not np.all(np.isfinite(M)):
            raise IdentificationError(
                f"N4SID produced non-finite {name}; the data may be degenerate (check the "
                f"excitation and scaling) or try another weighting"
            )
    return _finish(
        A=A, B=B, C=C, D=D, Q=Sig[:n, :n], R=Sig[n:, n:], S=Sig[:n, n:], su=su, sy=sy, ys=ys,
        us=us, dt=dt, input_labels=input_labels, output_labels=output_labels,
        state_prefix=state_prefix, singular_values=core.sv, horizon=i, weighting=weighting,
        method="n4sid", criterion=criterion if auto else None,
        criterion_values=crit_vals, nsamples=h.ncols, feedthrough=fed, scale_u=su, scale_y=sy,
    )


class _N4SIDCore:
    """Projections and SVD of the robust N4SID algorithm, shared by all orders."""

    def __init__(self, h: HankelR, i: int, weighting: str, fed, rtol: float):
        self.h, self.i, self.fed, self.rtol = h, i, tuple(fed), rtol
        m, l = h.ninputs, h.noutputs
        self.m, self.l = m, l
        Up, Uf = h.rows("u", 0, i), h.rows("u", i, 2 * i)
        Yp, Yf = h.rows("y", 0, i), h.rows("y", i, 2 * i)
        Wp = np.vstack([Up, Yp])
        # Y_f / [W_p; U_f]: oblique part along U_f and the full projection Z_i
        T = _regress(Yf, np.vstack([Wp, Uf]), rtol)
        Oi = T[:, :Wp.shape[0]] @ Wp
        self.Zi = T @ np.vstack([Wp, Uf])
        if i > 1:
            Wpp = np.vstack([h.rows("u", 0, i + 1), h.rows("y", 0, i + 1)])
            Ufm, Yfm = h.rows("u", i + 1, 2 * i), h.rows("y", i + 1, 2 * i)
            self.Zip1 = _project(Yfm, np.vstack([Wpp, Ufm]), rtol)
        else:
            self.Zip1 = np.zeros((0, h.L.shape[1]))
        self.Yii = h.rows("y", i, i + 1)
        self.Uf = Uf
        # weights W1, W2 (Van Overschee & De Moor 1996, Table 4.1 / Sec. 4.3.2)
        Oi_perp = Oi - _project(Oi, Uf, rtol) if m else Oi
        Yf_perp = Yf - _project(Yf, Uf, rtol) if m else Yf
        G = Yf_perp @ Yf_perp.T
        w, V = np.linalg.eigh(0.5 * (G + G.T))
        w = np.maximum(w, rtol * max(w.max(), np.finfo(float).tiny))
        W1 = (V / np.sqrt(w)) @ V.T
        Ucva, scva, _ = np.linalg.svd(W1 @ Oi_perp, full_matrices=False)
        # canonical-variate states (functions of the past only), used for the order criterion
        self.Xcva = Ucva.T @ W1 @ Oi
        self.W1inv = None
        if weighting == "N4SID":
            U, s, _ = np.linalg.svd(Oi, full_matrices=False)
        elif weighting == "MOESP":
            U, s, _ = np.linalg.svd(Oi_perp, full_matrices=False)
        else:
            U, s = Ucva, scva
            self.W1inv = (V * np.sqrt(w)) @ V.T
        self.U, self.sv = U, s
        self.Uii_fed = h.rows("u", i, i + 1)[list(self.fed)]
        # a thin factor of U_f for the B, D least squares
        if m:
            q, r = np.linalg.qr(Uf.T)
            self.Ufq, self.Ufr = q, r.T  # Uf = Ufr @ q.T
        self._cache = {}

    def state_residual_cov(self, n: int) -> NDArray:
        """Residual covariance of ``Y_{i|i}`` regressed on an order-n state and ``U_{i|i}``.

        The order-n state sequence is taken as the first n canonical variates
        of the past (CVA weighting, whatever the weighting of the model
        estimate: the N4SID and MOESP bases are not ordered by predictive
        power and over-estimated MIMO orders in our tests), a function of the
        past data only; the residual is then the innovation covariance of the
        order-n predictor. It drives ``criterion``.
        """
        X = np.vstack([self.Xcva[:n], self.Uii_fed])
        E = self.Yii - _project(self.Yii, X, self.rtol) if X.shape[0] else self.Yii
        return E @ E.T

    def gamma(self, n):
        G = self.U[:, :n] * np.sqrt(self.sv[:n])
        if self.W1inv is not None:
            G = self.W1inv @ G
        return G

    def fit(self, n: int) -> dict:
        i, l, m, rtol = self.i, self.l, self.m, self.rtol
        if n > 0:
            G = self.gamma(n)
            A = np.linalg.lstsq(G[:-l], G[l:], rcond=rtol)[0]
            C = G[:l].copy()
            Gi = _obsv(A, C, i)
            Gim1 = Gi[:-l]
            Gi_p, Gim1_p = _pinv(Gi, rtol), _pinv(Gim1, rtol)
            Xi = Gi_p @ self.Zi
            P = np.vstack([Gim1_p @ self.Zip1 - A @ Xi, self.Yii - C @ Xi])
        else:
            A = np.zeros((0, 0))
            C = np.zeros((l, 0))
            P = self.Yii.copy()
            Gi_p = Gim1_p = None
        nb_unknown = [("B", p, q) for p in range(n) for q in range(m)]
        nb_unknown += [("D", p, q) for q in self.fed for p in range(l)]
        B = np.zeros((n, m))
        D = np.zeros((l, m))
        if nb_unknown:
            cols = []
            for kind, p, q in nb_unknown:
                Bk = np.zeros((n, m))
                Dk = np.zeros((l, m))
                (Bk if kind == "B" else Dk)[p, q] = 1.0
                cols.append(self._kmap(A, Bk, C, Dk, Gi_p, Gim1_p, n) @ self.Ufr)
            Phi = np.stack([c.reshape(-1) for c in cols], axis=1)
            rhs = (P @ self.Ufq).reshape(-1)
            theta = sla.lstsq(Phi, rhs, cond=rtol, lapack_driver="gelsd")[0]
            for t, (kind, p, q) in zip(theta, nb_unknown):
                (B if kind == "B" else D)[p, q] = t
            resid = P - self._kmap(A, B, C, D, Gi_p, Gim1_p, n) @ self.Uf
        else:
            resid = P
        Sig = resid @ resid.T
        Sig = 0.5 * (Sig + Sig.T)
        return {"A": A, "B": B, "C": C, "D": D, "Sigma": Sig, "Rv": Sig[n:, n:]}

    def _kmap(self, A, B, C, D, Gi_p, Gim1_p, n):
        """The linear map K(B, D) of the robust algorithm, shape (n + l, m i)."""
        i, l, m = self.i, self.l, self.m
        bottom = np.zeros((l, m * i))
        bottom[:, :m] = D
        if n == 0:
            return bottom
        Hi = _toeplitz(A, B, C, D, i)
        top = np.zeros((n, m * i))
        top[:, :m] = B
        if i > 1:
            top[:, m:] = Gim1_p @ Hi[:l * (i - 1), :m * (i - 1)]
        GH = Gi_p @ Hi
        top -= A @ GH
        bottom -= C @ GH
        return np.vstack([top, bottom])
