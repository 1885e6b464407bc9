"""Unscented Kalman filter and unknown-input UKF (Gillijns & De Moor, section IV).

The model (34)-(35)::

    x[k+1] = F(x[k], u[k], d[k]) + w[k] ~ f(x[k], u[k]) + G d[k] + w[k],   w ~ N(0, Q)
    y[k]   = C x[k] + D u[k] + v[k],                                       v ~ N(0, R)

``sys`` is a discrete-time python-control model whose inputs are ``[u, d]``:
a ``NonlinearIOSystem`` (e.g. from :func:`greybox.discretize_nonlinear`) or
a linear ``StateSpace``. The output map must be linear (the paper's (33));
:func:`greybox.linear_output_map` checks it.

One step (k >= 1): sigma points of (x^[k-1|k-1], P[k-1|k-1]) go through F
with the unknown input held at its previous estimate d^[k-2] (zero for the
first step), which gives x^[k|k-1] and P[k|k-1] (unscented transform); then
(8)-(10) with the linear C exactly as in :func:`greybox.uikf` estimate the
*correction* of d and update the state. For a model affine in d (every
linear model, the paper's (34)) this is the paper's filter exactly;
linearizing at the previous estimate instead of at d = 0 only removes the
second-order terms in d of a model that is not (e.g. an RK4-discretized
model, where d acts through the sub-steps).

G: the columns of B for d (linear models), a constant matrix passed as
``G``, or by default the Jacobian ``dF/dd`` of the *discretized* model at
(x^[k-1|k-1], u[k-1], d^[k-2]), by central differences, evaluated in the
same batch as the sigma points. Taking G from the discretized model (not the
continuous input vector times dt) keeps the part of the discrete model error
that the sub-steps spread over other states inside range(G)
(PAPER_NOTES §8.9).

Loss of positive definiteness: P[k|k] is factored by LAPACK's Cholesky
(``dpotrf``, which reads its lower triangle only, so the loop does not
symmetrize it); if that fails, by
:func:`greybox.filters.sigma_points.robust_cholesky` (symmetrize, then jitter
from eps times the mean variance upward; a truly indefinite P raises
:class:`CovarianceError`). The recorded covariances are symmetrized.

Speed (issue 10, item 6; ``bench/ukf.py``): inputs are validated once on
entry; each sample then costs one batch call of F on the sigma points and
the G probes, one Cholesky, one positive-definite solve and a few small
products (see ``_run_ukf``).

The record is the same :class:`FilterResult` as :func:`uikf`'s, with the
same alignment (``d_est[:, j]`` estimates d[j]; the last column is NaN). Its
``sys`` is the known-input model linearized at the last filtered state
(exact C and D: the output map is linear), since ``FilterResult.sys`` must
be a ``StateSpace``; ``converged`` is False and ``period_converged`` None
(the gains of a nonlinear filter are recomputed at every sample).
"""

from __future__ import annotations

from collections.abc import Sequence
from math import isfinite
from dataclasses import dataclass

import control as ct
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg.lapack import dposv as _dposv
from scipy.linalg.lapack import dpotrf as _dpotrf

from .._validation import (
    check_covariance,
    check_matrix,
    check_same_length,
    check_signal,
    check_vector,
    resolve_channels,
)
from ..exceptions import DataError, DimensionError, ModelError
from ..nonlinear import linear_output_map, state_map
from ..system import named_ss
from .sigma_points import MerweScaledSigmaPoints, robust_cholesky
from .kernels import FilterResult, _check_options, _measurement_gains, _split, check_rank_condition

__all__ = ["ukf", "ui_ukf"]


@dataclass(frozen=True)
class _Problem:
    """Everything a nonlinear filter run needs, validated once."""

    sys: object
    fun: object          # batch state map F(t, X, U_full)
    known: tuple         # indices of the known inputs among sys's inputs
    unknown: tuple       # indices of the unknown inputs
    labels: tuple        # their names
    G: NDArray | None    # constant G, or None for the per-step Jacobian
    C: NDArray
    D: NDArray           # known-input feedthrough
    y: NDArray
    u: NDArray           # known inputs
    Q: NDArray
    R: NDArray
    x0: NDArray
    P0: NDArray
    dt: float


def _prepare_nl(sys, y, u, unknown, Q, R, x0, P0, G, *, allow_no_unknown, check_rank):
    """Validate a (non)linear discrete model, data and covariances once."""
    if isinstance(sys, ct.StateSpace):
        model, A, B, C, D, Gs, labels = _split(sys, unknown, allow_no_unknown, check_rank)
        if G is not None:
            raise DimensionError("G: a StateSpace model already fixes G (its columns of B "
                                 "for the unknown inputs); do not pass G")
        fun = state_map(model).fun
        n, m = model.nstates, model.ninputs
        known = tuple(range(m))
        unk = tuple(range(Gs.shape[1])) if check_rank else ()  # d enters through Gc
        Gc = Gs if check_rank else np.zeros((n, 0))
        labels = labels if check_rank else ()
        full_sys = model
    elif isinstance(sys, ct.NonlinearIOSystem):
        smap = state_map(sys)
        fun, n = smap.fun, sys.nstates
        idx = resolve_channels(unknown, sys.input_labels, "unknown")
        if not idx and not allow_no_unknown:
            raise DimensionError("unknown: name at least one unknown-input channel of sys "
                                 f"(its inputs are {sys.input_labels})")
        known = tuple(i for i in range(sys.ninputs) if i not in idx)
        unk = tuple(idx) if check_rank else ()
        Cf, Df = linear_output_map(sys)
        if check_rank and unk and np.any(Df[:, list(unk)] != 0):
            raise ModelError(f"the unknown inputs {[sys.input_labels[i] for i in unk]} feed "
                             f"through to the outputs; the filter assumes y = C x + D u + v")
        C, D = Cf, Df[:, list(known)]
        labels = tuple(sys.input_labels[i] for i in unk) if check_rank else ()
        m = len(known)
        Gc = None
        if G is not None and check_rank:
            Gc = check_matrix(G, (n, len(unk)), "G")
        elif not check_rank:
            Gc = np.zeros((n, 0))
        full_sys = sys
    else:
        raise ModelError(f"sys must be a control.StateSpace or control.NonlinearIOSystem; "
                         f"found {type(sys).__name__}")
    p = C.shape[0]
    y = check_signal(y, p, "y", min_steps=2)
    if u is None:
        if m:
            raise DimensionError(f"the model has {m} known inputs; pass u with shape "
                                 f"({m}, nsteps)")
        u = np.zeros((0, y.shape[1]))
    u = check_signal(u, m, "u")
    check_same_length(("y", y), ("u", u))
    Q = check_covariance(Q, n, "Q", definite=False)
    R = check_covariance(R, p, "R", definite=True)
    x0 = np.zeros(n) if x0 is None else check_vector(x0, n, "x0", what="nstates = ")
    P0 = check_covariance(np.eye(n) if P0 is None else P0, n, "P0", definite=False)
    return _Problem(full_sys, fun, known, unk, labels, Gc, C, D, y, u, Q, R, x0, P0,
                    float(full_sys.dt))


def _full_input(pb: _Problem, uk: NDArray, d: NDArray) -> NDArray:
    """Input vector of the model: known inputs uk, unknown inputs d (zero if ignored)."""
    if isinstance(pb.sys, ct.StateSpace):
        return uk  # the known-input model of a split StateSpace
    out = np.zeros(pb.sys.ninputs)
    out[list(pb.known)] = uk
    if pb.unknown:
        out[list(pb.unknown)] = d
    return out


def _d_steps(d: NDArray) -> NDArray:
    """Central-difference steps for dF/dd: 1e-4 of the level, at least 1e-4 (units of d)."""
    return 1e-4 * np.maximum(1.0, np.abs(d))


def _propagate(pb: _Problem, k: int, X: NDArray, uk: NDArray, dlin: NDArray, xc: NDArray,
               jac: bool):
    """F at the points X and, if ``jac``, the Jacobian dF/dd at xc; checks finiteness.

    Returns (FX (n, npoints), G (n, md) or None).
    """
    npts = X.shape[1]
    md = len(pb.unknown)
    ufull = _full_input(pb, uk, dlin)
    if jac and md:
        h = _d_steps(dlin)
        cols = [X]
        U = [np.repeat(ufull[:, None], npts, axis=1)]
        for j in range(md):
            for s in (1.0, -1.0):
                uj = ufull.copy()
                uj[pb.unknown[j]] += s * h[j]
                cols.append(xc[:, None])
                U.append(uj[:, None])
        Xall, Uall = np.concatenate(cols, axis=1), np.concatenate(U, axis=1)
    else:
        Xall, Uall = X, ufull
    t = (k - 1) * pb.dt
    try:
        with np.errstate(all="ignore"):
            FX = pb.fun(t, Xall, Uall)
    except Exception as e:  # a user function: report where it failed, chain the cause
        raise ModelError(f"the state update of {pb.sys.name} failed at step {k} (time "
                         f"{t:g} s) on a sigma point or ensemble member: {e}") from e
    if not np.all(np.isfinite(FX)):
        raise _nonfinite_error(pb, k, FX, Xall, npts)
    if isinstance(pb.sys, ct.StateSpace) and md:
        FX = FX + (pb.G @ dlin)[:, None]  # the split linear model takes known inputs only
    if jac and md:
        G = (FX[:, npts::2] - FX[:, npts + 1::2]) / (2 * h)[None, :]
        return FX[:, :npts], G
    return FX, None


def _check_d(dh: NDArray, k: int, labels) -> None:
    if not np.all(np.isfinite(dh)):
        j = int(np.flatnonzero(~np.isfinite(dh))[0])
        raise DataError(f"the unknown-input estimate {labels[j]!r} is not finite at step "
                        f"{k - 1}; the filter diverged (check Q, R and the model)")


def _linearized_record_sys(pb: _Problem, xf: NDArray) -> ct.StateSpace:
    """Known-input model linearized at xf (for FilterResult.sys: exact C and D)."""
    if isinstance(pb.sys, ct.StateSpace):
        return pb.sys
    n, m = xf.size, len(pb.known)
    d0 = np.zeros(len(pb.unknown))
    uk = np.zeros(m)
    hx = 1e-6 * np.maximum(1.0, np.abs(xf))
    X = np.concatenate([xf[:, None] + np.diag(hx), xf[:, None] - np.diag(hx)], axis=1)
    with np.errstate(all="ignore"):
        FX = pb.fun(0.0, X, _full_input(pb, uk, d0))
    A = (FX[:, :n] - FX[:, n:]) / (2 * hx)[None, :]
    B = np.zeros((n, m))
    for j in range(m):
        e = np.zeros(m)
        e[j] = 1e-6
        with np.errstate(all="ignore"):
            Fp = pb.fun(0.0, xf[:, None], _full_input(pb, e, d0))[:, 0]
            Fm = pb.fun(0.0, xf[:, None], _full_input(pb, -e, d0))[:, 0]
        B[:, j] = (Fp - Fm) / 2e-6
    A = np.where(np.isfinite(A), A, 0.0)
    B = np.where(np.isfinite(B), B, 0.0)
    s = pb.sys
    return named_ss(A, B, pb.C, pb.D, pb.dt, states=list(s.state_labels),
                    inputs=[s.input_labels[i] for i in pb.known],
                    outputs=list(s.output_labels), name=f"{s.name}_linearized")


def _nonfinite_error(pb: _Problem, k: int, FX: NDArray, Xall: NDArray, npts: int):
    """The ModelError for a state update that returned NaN or inf (names state and step)."""
    t = (k - 1) * pb.dt
    bad = np.argwhere(~np.isfinite(FX))[0]
    state = list(pb.sys.state_labels)[bad[0]]
    which = f"point {bad[1]}" if bad[1] < npts else "the G Jacobian probe"
    return ModelError(
        f"the state update of {pb.sys.name} returned NaN or inf for state {state!r} at "
        f"step {k} (time {t:g} s, {which} of {npts}); the model is not defined there. "
        f"Check f near x = {np.array2string(Xall[:, bad[1]], precision=4)} or reduce the "
        f"sigma-point spread (alpha) / P0")


def _as_index(idx: tuple):
    """A slice for contiguous indices (cheap row assignment), else the index list."""
    if idx and list(idx) == list(range(idx[0], idx[-1] + 1)):
        return slice(idx[0], idx[-1] + 1)
    return list(idx)


def _run_ukf(pb: _Problem, points, *, level: float, store_covariances: bool,
             d_lin: str = "previous") -> FilterResult:
    """The filter loop, written for small n: one batch call of F per sample.

    Per sample: one LAPACK Cholesky of P[k-1|k-1] (jitter path only on
    failure), the sigma points and ui_ukf's two G probes per unknown input as
    one array ``x + S E`` (E = the strategy's offsets plus zero columns), one
    call of F on all of them with a preassembled input array, one product
    ``FX W`` for the mean, G and the covariance square root, and one LAPACK
    positive-definite solve ``Rt^-1 [C P, C G, e]`` whose product ``T`` with
    ``[C P, C G, e]'`` holds every term of (8)-(10) (the algebra of
    :func:`greybox.filters.kernels._measurement_gains`). Inputs were validated
    once on entry; inside the loop only finiteness is checked (F's output and
    d^).
    """
    n, N = pb.x0.size, pb.y.shape[1]
    C, D, R = pb.C, pb.D, pb.R
    Q = 0.5 * (pb.Q + pb.Q.T)
    p, m, md = C.shape[0], pb.u.shape[0], len(pb.unknown)
    wm, wc = points.weights(n)
    npts = wm.size
    linear, jac = isinstance(pb.sys, ct.StateSpace), md > 0 and pb.G is None
    nj = md if jac else 0  # the G probes: two columns per unknown input
    ncol = npts + 2 * nj
    E = _offsets(points, n, npts, ncol)
    sqrt_wc = np.sqrt(wc) if np.all(wc >= 0) else None
    W = _batch_weights(wm, sqrt_wc, ncol, nj)
    c_eye = C.shape == (n, n) and bool(np.array_equal(C, np.eye(n)))  # all states measured
    # inputs of the batch call: known rows once per step, unknown rows at d_lin (+-h probes)
    Ubuf = np.zeros((m if linear else pb.sys.ninputs, ncol))
    krows = _as_index(tuple(range(m)) if linear else pb.known)
    urows = [] if linear else list(pb.unknown)
    zeros_check = np.zeros(n * ncol)
    # rows per sample, transposed at the end; x_pred = xp - G d_lin and the innovations
    # e + C G d_lin are formed after the loop from the rows xp, e and G d_lin
    rows = _Rows.empty(N, n, p, md, store_covariances)
    x_filt, xp_rows, e_rows, Phist = rows.x_filt, rows.xp, rows.e, rows.Phist
    gd_rows, g_rows, dl_rows, d_est, d_var = rows.gd, rows.g, rows.dl, rows.d_est, rows.d_var
    pd = np.inf  # Pd when md = 1 (stays inf if d is never seen)
    y, u, has_D = pb.y, pb.u, m > 0 and bool(np.any(D))
    yT = np.ascontiguousarray(((y - D @ u) if has_D else y).T)  # y - D u, a row per sample
    # k = 0: measurement update of the prior
    K, _, _, Rt, Pf = _measurement_gains(pb.P0, C, np.zeros((n, 0)), R)
    e = yT[0] - C @ pb.x0
    xf = pb.x0 + K @ e
    xp_rows[0], e_rows[0], x_filt[0] = pb.x0, e, xf
    if Phist is not None:
        Phist[:, :, 0] = Pf
    Pp, M, Pd = pb.P0, np.zeros((md, p)), np.zeros((md, md))
    dlin, dlf = np.zeros(md), 0.0  # dlf: d_lin when md = 1, as a Python float
    G = pb.G if pb.G is not None else np.zeros((n, md))
    F = G if c_eye else C @ G
    h2, Sol = np.ones(md), None
    with np.errstate(all="ignore"):  # non-finite values are checked and reported below
        for k in range(1, N):
            Xall = _sigma_columns(points, E, xf, Pf, ncol, npts)
            if m:
                Ubuf[krows] = u[:, k - 1:k]
            if jac:
                _probe_inputs(Ubuf, urows, (dlf,) if md == 1 else dlin, npts, h2)
            elif urows and d_lin == "previous":
                Ubuf[urows] = dlin[:, None]
            FX = _batch_update(pb, k, Xall, Ubuf, zeros_check, npts)
            out = FX @ W
            xp = out[:, 0]
            if jac:
                G = out[:, 1:1 + nj] / h2  # central differences dF/dd
                F = G if c_eye else C @ G
            Pp = _predicted_covariance(out, FX, xp, wc, sqrt_wc, nj, npts, Q)
            if linear and md:
                xp = xp + G @ dlin  # the split linear model takes the known inputs only
            Rt, e, Sol, T = _innovation_products(Pp, C, R, F, yT[k], xp, c_eye)
            unseen = md == 1 and not T[n, n] > 0
            if md > 1:
                try:
                    Pd = np.linalg.inv(T[n:n + md, n:n + md])  # (F' Rt^-1 F)^-1
                except np.linalg.LinAlgError:
                    unseen = True
            if unseen or not md:  # the plain UKF update
                xf = xp + T[:n, -1]
                Pf = Pp - T[:n, :n]
            if unseen:  # C G = 0 here (e.g. a sqrt or a clip at its limit): y[k] says
                # nothing of d[k-1]; d^ stays NaN, the state gets the plain UKF update
                # with d at its linearization value, which then restarts from 0
                d_var[k - 1] = np.inf
                if md == 1:
                    g_rows[k], dl_rows[k] = G[:, 0], dlf
                    dlf = 0.0
                else:
                    gd_rows[k] = G @ dlin
                dlin = np.zeros(md)
            elif md == 1:  # the common case in scalars: fewer numpy calls, same algebra
                xf, Pf, pd, dh1 = _scalar_d_update(T, xp, Pp, G, dlf, n, k, pb.labels)
                d_est[k - 1, 0] = dh1
                d_var[k - 1, 0] = pd
                g_rows[k], dl_rows[k] = G[:, 0], dlf  # G d_lin is formed after the loop
                if d_lin == "previous":
                    dlf = dh1
                    dlin[0] = dh1
            elif md:
                xf, Pf, Pd, dh = _vector_d_update(T, xp, Pp, G, Pd, dlin, n, k, pb.labels)
                d_est[k - 1] = dh
                d_var[k - 1] = Pd.diagonal()
                gd_rows[k] = G @ dlin
                if d_lin == "previous":
                    dlin = dh
            xp_rows[k] = xp
            e_rows[k] = e
            x_filt[k] = xf
            if Phist is not None:
                Phist[:, :, k] = 0.5 * (Pf + Pf.T)
    return _ukf_record(pb, rows, level, Pf, Pp, Rt, K, M, Pd, pd, Sol, G, xf)


@dataclass(frozen=True)
class _Rows:
    """The per-sample rows of :func:`_run_ukf` (filled in place, transposed at the end):
    filtered and predicted states, innovations, ``G d_lin`` (or, for md = 1, G and d_lin
    apart), d^ and its variance, and P[k|k] when kept."""

    x_filt: NDArray[np.float64]
    xp: NDArray[np.float64]
    e: NDArray[np.float64]
    gd: NDArray[np.float64] | None
    g: NDArray[np.float64] | None
    dl: NDArray[np.float64]
    d_est: NDArray[np.float64]
    d_var: NDArray[np.float64]
    Phist: NDArray[np.float64] | None

    @classmethod
    def empty(cls, N: int, n: int, p: int, md: int, store_covariances: bool) -> _Rows:
        """Rows for N samples (d^ NaN until estimated; ``dl``: d_lin at each step, md = 1)."""
        return cls(x_filt=np.empty((N, n)), xp=np.empty((N, n)), e=np.empty((N, p)),
                   gd=np.zeros((N, n)) if md else None, g=np.zeros((N, n)) if md == 1 else None,
                   dl=np.zeros(N), d_est=np.full((N, md), np.nan),
                   d_var=np.full((N, md), np.nan),
                   Phist=np.empty((n, n, N)) if store_covariances else None)


def _ukf_record(pb: _Problem, rows: _Rows, level: float, Pf, Pp, Rt, K, M, Pd, pd, Sol, G,
                xf) -> FilterResult:
    """The FilterResult of :func:`_run_ukf` from its rows and its last step's matrices."""
    n, N, md, C = pb.x0.size, pb.y.shape[1], len(pb.unknown), pb.C
    y, u, gd_rows = pb.y, pb.u, rows.gd
    Pf = 0.5 * (Pf + Pf.T)
    if md == 1:  # d_lin at step k (d^[k-2], or 0 after a step where d was not seen)
        gd_rows = rows.g * rows.dl[:, None]
    x_pred = rows.xp - gd_rows if md else rows.xp  # f(x, u) without d, as uikf's x_pred
    innov = rows.e + gd_rows @ C.T if md else rows.e
    if Sol is not None:  # the gains of the last step, for the record
        K = Sol[:, :n].T
        if md == 1:
            Pd = np.array([[pd]])
        if md:
            M = Pd @ Sol[:, n:n + md].T
    Rt = 0.5 * (Rt + Rt.T)
    return FilterResult(
        t=np.arange(N) * pb.dt, x_filt=np.ascontiguousarray(rows.x_filt.T),
        x_pred=np.ascontiguousarray(x_pred.T), d_est=np.ascontiguousarray(rows.d_est.T),
        d_var=np.ascontiguousarray(rows.d_var.T), d_cov=Pd, level=level,
        innovations=np.ascontiguousarray(innov.T), innovation_cov=Rt, P_filt=Pf, P_pred=Pp,
        P_filt_history=rows.Phist, K=K, M=M, converged=False, period_converged=None,
        sys=_linearized_record_sys(pb, xf), G=G, unknown_labels=tuple(pb.labels), u=u, y=y)


def _offsets(points, n: int, npts: int, ncol: int) -> NDArray | None:
    """E of the batch ``x + S E``: MerweScaledSigmaPoints' offsets then zero columns (the
    probes); None for another strategy (its own points, :func:`_sigma_columns`)."""
    if not isinstance(points, MerweScaledSigmaPoints):
        return None
    E = np.zeros((n, ncol))
    E[:, :npts] = points.offsets(n)
    return E


def _batch_weights(wm: NDArray, sqrt_wc: NDArray | None, ncol: int, nj: int) -> NDArray:
    """W with one product ``FX @ W`` giving the predicted mean (column 0), the ``nj`` probe
    differences F(+h) - F(-h) and, when the covariance weights are >= 0 (``sqrt_wc``),
    Z = (FX - xp 1') diag(sqrt(wc)) with P[k|k-1] = Z Z' + Q (the columns of
    (I - wm 1') sum to zero: a common shift of the points, such as G d for a linear
    model, leaves Z unchanged)."""
    npts = wm.size
    W = np.zeros((ncol, 1 + nj + (npts if sqrt_wc is not None else 0)))
    W[:npts, 0] = wm
    for j in range(nj):
        W[npts + 2 * j, 1 + j], W[npts + 2 * j + 1, 1 + j] = 1.0, -1.0
    if sqrt_wc is not None:
        W[:npts, 1 + nj:] = (np.eye(npts) - wm[:, None]) * sqrt_wc
    return W


def _sigma_columns(points, E: NDArray | None, xf: NDArray, Pf: NDArray, ncol: int,
                   npts: int) -> NDArray:
    """The sigma points of (xf, Pf) and the probe columns (at xf): ``xf + S E`` with one
    LAPACK Cholesky (``E`` the offsets of MerweScaledSigmaPoints), else the strategy's
    own points."""
    if E is not None:
        S, info = _dpotrf(Pf, lower=1, clean=1)  # reads the lower triangle
        if info:
            S = robust_cholesky(Pf)  # symmetrize + jitter, or CovarianceError
        return xf[:, None] + S @ E
    X = points.points(xf, Pf)
    return np.concatenate([X] + [xf[:, None]] * (ncol - npts), axis=1)


def _probe_inputs(Ubuf: NDArray, urows, dlin, npts: int, h2: NDArray) -> None:
    """The unknown rows of the batch input at d_lin, with the +-h probes of each unknown
    input in its two probe columns (central-difference step ``h2 / 2`` in units of d)."""
    for j, r in enumerate(urows):
        dj = float(dlin[j])
        hj = 1e-4 * max(1.0, abs(dj))  # central-difference step, units of d
        Ubuf[r] = dj
        Ubuf[r, npts + 2 * j] = dj + hj
        Ubuf[r, npts + 2 * j + 1] = dj - hj
        h2[j] = 2 * hj


def _batch_update(pb: _Problem, k: int, Xall: NDArray, Ubuf: NDArray, zeros_check: NDArray,
                  npts: int) -> NDArray:
    """F on every column at step k (a user function's error chained), checked finite."""
    try:
        FX = pb.fun((k - 1) * pb.dt, Xall, Ubuf)
    except Exception as exc:  # a user function: report where it failed, chain it
        raise ModelError(f"the state update of {pb.sys.name} failed at step {k} "
                         f"(time {(k - 1) * pb.dt:g} s) on a sigma point or ensemble "
                         f"member: {exc}") from exc
    if not isfinite(zeros_check @ FX.reshape(-1)):  # 0 * (nan or inf) is nan
        raise _nonfinite_error(pb, k, FX, Xall, npts)
    return FX


def _predicted_covariance(out: NDArray, FX: NDArray, xp: NDArray, wc: NDArray,
                          sqrt_wc: NDArray | None, nj: int, npts: int, Q: NDArray) -> NDArray:
    """P[k|k-1]: Z Z' + Q from the batch product, or the weighted sum for negative
    covariance weights."""
    if sqrt_wc is not None:
        Z = out[:, 1 + nj:]
        return Z @ Z.T + Q
    dX = FX[:, :npts] - xp[:, None]
    Pp = (dX * wc) @ dX.T + Q
    return 0.5 * (Pp + Pp.T)


def _innovation_products(Pp, C, R, F, yk, xp, c_eye: bool):
    """``(Rt, e, Sol, T)``: the innovation covariance and innovation, and one solve
    ``Sol = Rt^-1 [C Pp, F, e]`` whose product ``T = [C Pp, F, e]' Sol`` holds every term
    of (8)-(10): K C Pp, K F, K e, F' Rt^-1 F, ... (LU when Rt is not positive definite in
    floating point, as uikf does)."""
    if c_eye:
        CP, Rt, e = Pp, Pp + R, yk - xp
    else:
        CP = C @ Pp
        Rt = CP @ C.T + R
        e = yk - C @ xp
    B = np.concatenate((CP, F, e[:, None]), axis=1)
    _, Sol, info = _dposv(Rt, B, lower=1)
    if info:  # Rt not positive definite in floating point: LU as uikf does
        Sol = np.linalg.solve(Rt, B)
    return Rt, e, Sol, B.T @ Sol


def _scalar_d_update(T, xp, Pp, G, dlf: float, n: int, k: int, labels):
    """``(x^[k|k], P[k|k], Pd, d^[k-1])`` for one unknown input seen at step k, in scalars
    (fewer numpy calls, the algebra of :func:`_vector_d_update`)."""
    pd = 1.0 / float(T[n, n])  # (F' Rt^-1 F)^-1
    dd1 = pd * float(T[n, -1])  # M e
    dh1 = dlf + dd1  # d^[k-1]
    if not isfinite(dh1):
        _check_d(np.array([dh1]), k, labels)
    GKF = G[:, 0] - T[:n, n]  # G - K F
    xf = xp + GKF * dd1 + T[:n, -1]  # x^[k|k-1] + G dd + K (e - F dd)
    Pf = np.multiply.outer(pd * GKF, GKF)  # (G - K F) Pd (G - K F)'
    Pf -= T[:n, :n]  # - K C Pp
    Pf += Pp  # lower triangle used only: not symmetrized in the loop
    return xf, Pf, pd, dh1


def _vector_d_update(T, xp, Pp, G, Pd, dlin, n: int, k: int, labels):
    """``(x^[k|k], P[k|k], Pd, d^[k-1])`` for md > 1 unknown inputs seen at step k, ``Pd``
    = (F' Rt^-1 F)^-1 (symmetrized here), ``dlin`` d's linearization value."""
    md = Pd.shape[0]
    Pd = 0.5 * (Pd + Pd.T)
    dd = Pd @ T[n:n + md, -1]  # M e
    dh = dlin + dd
    if not isfinite(dh @ dh):
        _check_d(dh, k, labels)
    GKF = G - T[:n, n:n + md]  # G - K F
    xf = xp + GKF @ dd + T[:n, -1]  # x^[k|k-1] + G dd + K (e - F dd)
    # not symmetrized: the next Cholesky reads the lower triangle only
    Pf = Pp - T[:n, :n] + GKF @ Pd @ GKF.T
    return xf, Pf, Pd, dh


def _points(points):
    if points is None:
        return MerweScaledSigmaPoints()
    if not all(hasattr(points, a) for a in ("weights", "points")):
        raise DimensionError(f"points must be a sigma-point strategy such as "
                             f"MerweScaledSigmaPoints(); found {type(points).__name__}")
    return points


def _initial_G(pb: _Problem) -> NDArray:
    """G at the prior (x0, u[0], d = 0), for the rank condition (17)."""
    if pb.G is not None:
        return pb.G
    _, G = _propagate(pb, 1, pb.x0[:, None], pb.u[:, 0], np.zeros(len(pb.unknown)), pb.x0,
                      True)
    return G


def ui_ukf(sys, y: ArrayLike, u: ArrayLike | None = None, *,
           unknown: int | str | Sequence[int | str], Q: ArrayLike, R: ArrayLike,
           x0: ArrayLike | None = None, P0: ArrayLike | None = None,
           G: ArrayLike | None = None, points: MerweScaledSigmaPoints | None = None,
           d_lin: str = "previous", level: float = 0.95, store_covariances: bool = False
           ) -> FilterResult:
    """Unknown-input unscented Kalman filter (section IV, eqs. 32-35 with 8-10).

    Parameters
    ----------
    sys : control.NonlinearIOSystem or control.StateSpace
        Discrete-time model with inputs ``[u, d]`` and a linear output map.
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
    G : array_like, shape (nstates, md), optional
        Constant unknown-input matrix for a nonlinear model; by default the
        Jacobian dF/dd of the discretized model at every step.
    points : MerweScaledSigmaPoints, optional
        Sigma-point strategy; ``MerweScaledSigmaPoints(alpha=1, beta=2,
        kappa=0)`` by default.
    d_lin : {"previous", "zero"}
        Where the sigma points are propagated in d: at the previous estimate
        d^[k-2] (default; removes the terms of second and higher order in d
        of a model that is not affine in d), or at d = 0, the paper's
        ``f(x, u) + G d`` read literally.
    level : float
        Confidence level of ``d_lower``/``d_upper`` (0.95).
    store_covariances : bool
        Keep every ``P[k|k]`` in ``P_filt_history``.

    Returns
    -------
    FilterResult
        Same record and alignment as :func:`greybox.uikf`. At a step where y
        does not depend on d (``C dF/dd = 0`` there, e.g. a state at a sqrt's
        or a clip's limit) ``d_est`` is NaN and ``d_var`` inf; the state gets
        the plain UKF update there.

    Raises
    ------
    ModelError
        Continuous-time model; non-linear output map; d feeds through to y;
        f fails or returns NaN/inf (naming the state and the step).
    RankConditionError
        rank(C G) = rank(G) = md (17) fails at the prior.
    DataError
        Non-finite data, or the estimate of d becomes non-finite.
    DimensionError, CovarianceError
        Wrong shapes; non-symmetric or indefinite Q, R, P0.

    Notes
    -----
    With sigma points :math:`\\mathcal X_i` of :math:`(\\hat x_{k-1|k-1}, P_{k-1|k-1})`
    and weights :math:`W^m_i, W^c_i`:

    .. math::

        \\hat x_{k|k-1} = \\sum_i W^m_i F(\\mathcal X_i, u_{k-1}, \\hat d_{k-2}),\\quad
        P_{k|k-1} = \\sum_i W^c_i (\\cdot)(\\cdot)^T + Q

    then eqs. (8)-(10) and (14)-(18) as in :func:`greybox.uikf`, estimating
    :math:`\\hat d_{k-1} = \\hat d_{k-2} + M (y_k - C \\hat x_{k|k-1} - D u_k)`.
    On a linear model this is :func:`greybox.uikf` with ``gain="time-varying"``
    up to rounding (the unscented transform is exact for linear maps).

    References
    ----------
    Gillijns & De Moor (CDC 2006), section IV; S. Julier and J. Uhlmann,
    "Unscented filtering and nonlinear estimation", Proc. IEEE 92 (2004) 401-422.

    Examples
    --------
    >>> import numpy as np, greybox as gb
    >>> sys = gb.tape_drive_nominal(dt=1e-4)
    >>> sim = gb.simulate(gb.tape_drive_true(dt=1e-4), np.ones((2, 200)), rng=0)
    >>> res = gb.ui_ukf(sys, sim.y, sim.u, unknown="T", Q=gb.TAPE_DRIVE_Q * 1e-3,
    ...                 R=gb.TAPE_DRIVE_R)
    >>> res.d_est.shape
    (1, 200)
    """
    level, _, _ = _check_options(level, "auto", 1.0)
    if d_lin not in ("previous", "zero"):
        raise DimensionError(f"d_lin must be 'previous' or 'zero'; found {d_lin!r}")
    pts = _points(points)
    pb = _prepare_nl(sys, y, u, unknown, Q, R, x0, P0, G, allow_no_unknown=False,
                     check_rank=True)
    if not isinstance(pb.sys, ct.StateSpace):
        check_rank_condition(pb.C, _initial_G(pb), pb.labels)
    return _run_ukf(pb, pts, level=level, store_covariances=store_covariances, d_lin=d_lin)


def ukf(sys, y: ArrayLike, u: ArrayLike | None = None, *, Q: ArrayLike, R: ArrayLike,
        unknown=None, x0: ArrayLike | None = None, P0: ArrayLike | None = None,
        points: MerweScaledSigmaPoints | None = None, store_covariances: bool = False
        ) -> FilterResult:
    """Unscented Kalman filter that ignores the unknown input (the paper's baseline).

    Same interface and record as :func:`ui_ukf`; inputs listed in
    ``unknown`` are held at zero (their effect is left to the process noise)
    and ``d_est`` has zero rows.

    Parameters
    ----------
    sys : control.NonlinearIOSystem or control.StateSpace
        Discrete-time model with a linear output map.
    y : array_like, shape (noutputs, nsteps)
        Measured outputs.
    u : array_like, shape (ninputs_known, nsteps), optional
        Measured known inputs.
    Q : array_like, shape (nstates, nstates)
        Process-noise covariance.
    R : array_like, shape (noutputs, noutputs)
        Measurement-noise covariance.
    unknown : label(s) or index(es), optional
        Inputs of ``sys`` to ignore (held at zero).
    x0 : array_like, shape (nstates,), optional
        Prior mean.
    P0 : array_like, shape (nstates, nstates), optional
        Prior covariance.
    points : MerweScaledSigmaPoints, optional
        Sigma-point strategy.
    store_covariances : bool
        Keep every ``P[k|k]``.

    Returns
    -------
    FilterResult
    """
    pts = _points(points)
    pb = _prepare_nl(sys, y, u, unknown, Q, R, x0, P0, None, allow_no_unknown=True,
                     check_rank=False)
    return _run_ukf(pb, pts, level=0.95, store_covariances=store_covariances)
