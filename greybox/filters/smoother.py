"""Fixed-interval (Rauch-Tung-Striebel type) smoother for states and unknown inputs.

The unbiased minimum-variance filter is the Kalman filter of a model in which
d[k] is white noise of variance s^2 I, in the limit s -> inf (Kitanidis 1987;
Gillijns & De Moor 2007). Taking the same limit in the RTS smoother gives,
with ``Pb = P[k+1|k] = A P[k|k] A^T + Q`` of the unknown-input filter,

.. math::

    W = G^T P_b^{-1} G,\\quad N = W^{-1} G^T P_b^{-1},\\quad
    \\Pi = P_b^{-1} (I - G N),\\quad J = P_{k|k} A^T \\Pi

    \\hat x_{k|N} = \\hat x_{k|k} + J (\\hat x_{k+1|N} - \\hat x_{k+1|k}),\\quad
    P_{k|N} = P_{k|k} + J P_{k+1|N} J^T - P_{k|k} A^T \\Pi A P_{k|k}

    \\hat d_{k|N} = N (\\hat x_{k+1|N} - \\hat x_{k+1|k}),\\quad
    P^d_{k|N} = W^{-1} + N P_{k+1|N} N^T

(``x^[k+1|k] = A x^[k|k] + B u[k]``, the filter's prediction without d).
At k = N - 2 this reproduces the filter's own d^[N-2] and Pd (16); earlier
samples gain the information of the later outputs. ``Pb`` must be
invertible (Q positive definite on range(G) suffices in practice).

For relative degree r >= 2 the smoother runs on the shifted state of
:mod:`greybox.filters.delayed` and maps back the same way as the filter.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import control as ct
import numpy as np
from numpy.typing import ArrayLike

from .._lti import lti_states
from ..exceptions import CovarianceError
from .delayed import _delayed_parts, _unshift
from .feedthrough import (
    _check_feedthrough_rank,
    _feedthrough_gains,
    _predict_cov,
    _run_feedthrough,
    feedthrough_schedule,
    joint_block,
    _unknown_feedthrough,
    _use_feedthrough,
)
from ._memo import MEMO
from .kernels import FilterResult, _check_options, _measurement_gains, _prepare, _run

__all__ = ["smooth_uikf"]


def _filtered_covariances(A, C, G, Q, R, P0, nsteps):
    """``P[k|k]`` of :func:`_run` for k < nsteps (the same kernels, so the same numbers)."""
    n = A.shape[0]
    out = np.empty((n, n, nsteps))
    if nsteps == 0:
        return out
    Pf = _measurement_gains(P0, C, np.zeros((n, 0)), R)[4]
    out[:, :, 0] = Pf
    F = C @ G
    for k in range(1, nsteps):
        Pp = A @ Pf @ A.T + Q
        Pp = 0.5 * (Pp + Pp.T)
        Pf = _measurement_gains(Pp, C, G, R, F)[4]
        out[:, :, k] = Pf
    return out


def _backward_gains(A, G, Q, Pf):
    """(J, N, W^-1, Pf A' Pi A Pf) of one backward step from ``P[k|k]``."""
    Pb = A @ Pf @ A.T + Q
    Pb = 0.5 * (Pb + Pb.T)
    n = Pb.shape[0]
    try:
        S = np.linalg.solve(Pb, np.concatenate((np.eye(n), G), axis=1))
    except np.linalg.LinAlgError as e:
        raise CovarianceError(
            "P[k+1|k] = A P[k|k] A^T + Q is singular, so the smoother gain is undefined; "
            "give Q a (small) positive-definite part"
        ) from e
    Pbi, PbiG = S[:, :n], S[:, n:]
    W = G.T @ PbiG
    Wi = np.linalg.inv(W)
    Wi = 0.5 * (Wi + Wi.T)
    Nk = Wi @ PbiG.T
    Pi = Pbi - PbiG @ Nk
    Pi = 0.5 * (Pi + Pi.T)
    J = Pf @ A.T @ Pi
    T = J @ A @ Pf
    return J, Nk, Wi, 0.5 * (T + T.T)


def _backward_states(J, xf, xp, kc):
    """``x^[k|N-1]`` for k = kc..N-1 of ``x^[k|N] = x^[k|k] + J (x^[k+1|N] - x^[k+1|k])``.

    Run as a forward LTI recursion in reversed time i = N-1-k (no Python loop):
    ``s[i+1] = J s[i] + (x^[k|k] - J x^[k+1|k])`` with k = N-2-i.
    """
    n, N = xf.shape
    L = N - 1 - kc
    v = np.zeros((n, L + 1))
    v[:, :L] = xf[:, N - 2:kc - 1 if kc > 0 else None:-1] - J @ xp[:, N - 1:kc:-1]
    s = lti_states(J, v, xf[:, N - 1])
    return s[:, ::-1]


def _smooth(fwd: FilterResult, A, G, Q, R, C, P0, tol, store_covariances):
    """Backward pass over a forward :func:`_run` record; returns the smoothed record."""
    n, N = fwd.x_filt.shape
    md = G.shape[1]
    xf, xp = fwd.x_filt, fwd.x_pred
    kc = fwd.period_converged if fwd.period_converged is not None else N
    Pf_tv = MEMO.call(_filtered_covariances, A, C, G, Q, R, P0, min(kc, N))
    xs = np.empty((n, N))
    ds = np.full((md, N), np.nan)
    dv = np.full((md, N), np.nan)
    Phist = np.empty((n, n, N)) if store_covariances else None
    xs[:, N - 1] = xf[:, N - 1]
    Ps = fwd.P_filt if kc < N else Pf_tv[:, :, N - 1]
    if Phist is not None:
        Phist[:, :, N - 1] = Ps
    Pd_last = None
    k = N - 2
    if kc <= N - 2:
        # constant gains: covariance loop until P[k|N] settles, states without a loop
        Pf = fwd.P_filt
        J, Nk, Wi, T = _backward_gains(A, G, Q, Pf)
        k_settled = kc
        for k in range(N - 2, kc - 1, -1):
            Pd = Wi + Nk @ Ps @ Nk.T
            dv[:, k] = Pd.diagonal()
            Pd_last = Pd if Pd_last is None else Pd_last
            Pn = Pf + J @ Ps @ J.T - T
            Pn = 0.5 * (Pn + Pn.T)
            settled = np.max(np.abs(Pn - Ps)) <= tol * max(np.max(np.abs(Pn)), 1e-300)
            Ps = Pn
            if Phist is not None:
                Phist[:, :, k] = Ps
            if settled:
                k_settled = k
                break
        if k_settled > kc:
            dv[:, kc:k_settled] = (Wi + Nk @ Ps @ Nk.T).diagonal()[:, None]
            if Phist is not None:
                Phist[:, :, kc:k_settled] = Ps[:, :, None]
        xs[:, kc:] = _backward_states(J, xf, xp, kc)
        ds[:, kc:N - 1] = Nk @ (xs[:, kc + 1:] - xp[:, kc + 1:])
        k = kc - 1
    for k in range(k, -1, -1):
        J, Nk, Wi, T = _backward_gains(A, G, Q, Pf_tv[:, :, k])
        delta = xs[:, k + 1] - xp[:, k + 1]
        xs[:, k] = xf[:, k] + J @ delta
        ds[:, k] = Nk @ delta
        Pd = Wi + Nk @ Ps @ Nk.T
        dv[:, k] = Pd.diagonal()
        Pd_last = Pd if Pd_last is None else Pd_last
        Ps = Pf_tv[:, :, k] + J @ Ps @ J.T - T
        Ps = 0.5 * (Ps + Ps.T)
        if Phist is not None:
            Phist[:, :, k] = Ps
    if not (np.all(np.isfinite(xs)) and np.all(np.isfinite(ds[:, :N - 1]))):
        raise CovarianceError(
            "the smoother's backward recursion overflowed (a badly conditioned P[k+1|k]); "
            "check Q and the model's stability"
        )
    return replace(fwd, x_filt=xs, d_est=ds, d_var=dv,
                   d_cov=Pd_last if Pd_last is not None else fwd.d_cov,
                   P_filt_history=Phist, smoothed=True)


def _joint_gains(AG, Q, Jk):
    """(L, Pp) of the RTS step for s[k] = (x[k], d[k]) of the feedthrough filter;
    ``AG = [A G]``."""
    Pp = AG @ Jk @ AG.T + Q
    Pp = 0.5 * (Pp + Pp.T)
    try:
        L = np.linalg.solve(Pp, AG @ Jk).T  # J [A G]^T Pp^-1, Pp and J symmetric
    except np.linalg.LinAlgError as e:
        raise CovarianceError(
            "P[k+1|k] of the feedthrough filter is singular, so the smoother gain is "
            "undefined; give Q a (small) positive-definite part"
        ) from e
    return L, Pp


def _joint_covariances(A, C, G, H, Q, R, P0, nsteps):
    """``[[P[k|k], P^xd], [P^dx, Pd]]`` of the feedthrough filter for k < nsteps (the
    forward gain schedule's ``joint`` where it kept them)."""
    n, md = G.shape
    out = np.empty((n + md, n + md, nsteps))
    AG = np.hstack([A, G])
    Pp = P0
    for k in range(nsteps):
        _, _, Pd, _, Pf, Pxd = _feedthrough_gains(Pp, C, H, R)
        out[:, :, k] = J = joint_block(Pf, Pxd, Pd)
        Pp = _predict_cov(AG, J, Q)
    return out


def _smooth_feedthrough(fwd: FilterResult, A, C, G, H, Q, R, P0, tol, store_covariances,
                        auto: bool = True):
    """RTS on s[k] = (x[k], d[k]): s^[k|N] = s^[k|k] + L (x^[k+1|N] - x^[k+1|k]).

    With feedthrough, Pd of the filter is finite, so this is the plain RTS
    smoother of the pair (x[k], d[k]) whose successor is x[k+1] = [A G] s[k] + w
    (d[k+1], d[k+2], ... are independent of s[k]).
    """
    n, N = fwd.x_filt.shape
    md = G.shape[1]
    xf, xp, df = fwd.x_filt, fwd.x_pred, fwd.d_est
    kc = fwd.period_converged if fwd.period_converged is not None else N
    # the forward filter's own recursion (memoized): the same steps, computed once
    sc = feedthrough_schedule(A, C, G, H, Q, R, P0, N, auto, tol)
    J_tv = sc.joint if sc.joint is not None and sc.kconv == fwd.period_converged and \
        sc.joint.shape[2] >= min(kc, N) else \
        MEMO.call(_joint_covariances, A, C, G, H, Q, R, P0, min(kc, N))
    AG = np.hstack([A, G])
    if kc < N:
        _, _, Pd, _, Pf, Pxd = _feedthrough_gains(fwd.P_pred, C, H, R)
        J_c = joint_block(Pf, Pxd, Pd)
    xs = np.empty((n, N))
    ds = np.empty((md, N))
    dv = np.empty((md, N))
    Phist = np.empty((n, n, N)) if store_covariances else None
    Jlast = J_c if kc <= N - 1 else J_tv[:, :, N - 1]
    xs[:, N - 1], ds[:, N - 1] = xf[:, N - 1], df[:, N - 1]
    Ps = Jlast
    dv[:, N - 1] = Ps[n:, n:].diagonal()
    if Phist is not None:
        Phist[:, :, N - 1] = Ps[:n, :n]
    Pd_last = Ps[n:, n:]
    k = N - 2
    if kc <= N - 2:
        L, Pp = _joint_gains(AG, Q, J_c)
        k_settled = kc
        for k in range(N - 2, kc - 1, -1):
            Pn = J_c + L @ (Ps[:n, :n] - Pp) @ L.T
            Pn = 0.5 * (Pn + Pn.T)
            settled = np.max(np.abs(Pn - Ps)) <= tol * max(np.max(np.abs(Pn)), 1e-300)
            Ps = Pn
            dv[:, k] = Ps[n:, n:].diagonal()
            if Phist is not None:
                Phist[:, :, k] = Ps[:n, :n]
            if settled:
                k_settled = k
                break
        if k_settled > kc:
            dv[:, kc:k_settled] = Ps[n:, n:].diagonal()[:, None]
            if Phist is not None:
                Phist[:, :, kc:k_settled] = Ps[:n, :n, None]
        xs[:, kc:] = _backward_states(L[:n], xf, xp, kc)
        ds[:, kc:N - 1] = df[:, kc:N - 1] + L[n:] @ (xs[:, kc + 1:] - xp[:, kc + 1:])
        k = kc - 1
    for k in range(k, -1, -1):
        Jk = J_tv[:, :, k]
        L, Pp = _joint_gains(AG, Q, Jk)
        delta = xs[:, k + 1] - xp[:, k + 1]
        xs[:, k] = xf[:, k] + L[:n] @ delta
        ds[:, k] = df[:, k] + L[n:] @ delta
        Ps = Jk + L @ (Ps[:n, :n] - Pp) @ L.T
        Ps = 0.5 * (Ps + Ps.T)
        dv[:, k] = Ps[n:, n:].diagonal()
        if Phist is not None:
            Phist[:, :, k] = Ps[:n, :n]
    return replace(fwd, x_filt=xs, d_est=ds, d_var=dv, d_cov=Pd_last,
                   P_filt_history=Phist, smoothed=True)


def smooth_feedthrough_of(fwd: FilterResult, sys: ct.StateSpace, y, u, *, unknown, Q,
                           R) -> FilterResult:
    """``smooth_uikf(sys, y, u, unknown=unknown, Q=Q, R=R, relative_degree=0)``, from
    ``fwd = feedthrough_uikf(sys, y, u, unknown=unknown, Q=Q, R=R)`` (default options):
    the forward filter is not run a second time.
    """
    model, A, B, C, D, G, labels, y, u, Q, R, x0, P0 = _prepare(
        sys, y, u, unknown, Q, R, None, None, allow_no_unknown=False, check_rank=False)
    H = _unknown_feedthrough(sys, labels)
    _check_feedthrough_rank(H, labels)
    return _smooth_feedthrough(fwd, A, C, G, H, Q, R, P0, 1e-12, False, True)


def smooth_uikf(sys: ct.StateSpace, y: ArrayLike, u: ArrayLike | None = None, *,
                unknown: int | str | Sequence[int | str], Q: ArrayLike, R: ArrayLike,
                relative_degree: int | str = 1, x0: ArrayLike | None = None,
                P0: ArrayLike | None = None, level: float = 0.95, gain: str = "auto",
                tol: float = 1e-12, store_covariances: bool = False) -> FilterResult:
    """Fixed-interval smoothed states and unknown inputs over the whole record.

    Runs :func:`~greybox.uikf` (or :func:`~greybox.delayed_uikf` for
    ``relative_degree`` >= 2, :func:`~greybox.feedthrough_uikf` for 0) forward,
    then the backward recursion of the module docstring (for feedthrough: the
    plain RTS smoother of the pair (x[k], d[k])), so ``d_est[:, k]`` uses all
    of y[0..N-1].

    Parameters
    ----------
    sys : control.StateSpace
        Discrete model with inputs ``[u, d]``.
    y : array_like, shape (noutputs, nsteps)
        Measured outputs.
    u : array_like, shape (ninputs_known, nsteps), optional
        Measured known inputs.
    unknown : label(s) or index(es)
        Unknown-input channels of ``sys``.
    Q : array_like, shape (nstates, nstates)
        Process-noise covariance; ``A P A^T + Q`` must be invertible.
    R : array_like, shape (noutputs, noutputs)
        Measurement-noise covariance (PD).
    relative_degree : int or "auto"
        1: the plain filter; r >= 2 as in :func:`~greybox.delayed_uikf`; 0: the
        filter with direct feedthrough (:func:`~greybox.feedthrough_uikf`,
        y = C x + D u + H d + v, H = the D columns of d). "auto": 0 if the
        unknown inputs feed through, else detected as in
        :func:`~greybox.detect_relative_degree`.
    x0 : array_like, shape (nstates,), optional
        Prior mean of x[0].
    P0 : array_like, shape (nstates, nstates), optional
        Prior covariance of x[0].
    level : float
        Confidence level of ``d_lower``/``d_upper``.
    gain : {"auto", "time-varying"}
        "auto": constant-gain fast paths forward and backward once the
        covariances have converged (no per-sample Python loop there).
    tol : float
        Relative change that counts as converged (forward and backward).
    store_covariances : bool
        Keep every smoothed ``P[k|N-1]`` in ``P_filt_history``.

    Returns
    -------
    FilterResult
        With ``smoothed = True``: ``x_filt[:, k] = x^[k|N-1]``,
        ``d_est[:, k] = d^[k|N-1]`` with variances ``d_var``, ``d_cov`` the
        full covariance of the last estimate (``d_est[:, N-1-r]``); the last
        r columns of ``d_est`` are NaN as in the filter (none for r = 0). ``x_pred``, ``innovations``,
        ``K``, ``M``, ``P_pred`` and ``P_filt`` are those of the forward
        filter.

    Raises
    ------
    CovarianceError
        ``P[k+1|k]`` singular (Q singular and the filter certain along it).
    RankConditionError, ModelError, DimensionError, DataError
        As for the filter.

    References
    ----------
    H. E. Rauch, F. Tung and C. T. Striebel, "Maximum likelihood estimates of
    linear dynamic systems", AIAA J. 3 (1965) 1445-1450; P. K. Kitanidis,
    "Unbiased minimum-variance linear state estimation", Automatica 23 (1987)
    775-778 (the unknown input as infinite-variance noise); S. Gillijns and
    B. De Moor, Automatica 43 (2007) 111-116.

    Examples
    --------
    >>> import numpy as np, greybox as gb
    >>> sys = gb.tape_drive_nominal(dt=1e-4)
    >>> sim = gb.simulate(gb.tape_drive_true(dt=1e-4), np.ones((2, 300)), rng=0)
    >>> res = gb.smooth_uikf(sys, sim.y, sim.u, unknown="T", Q=gb.TAPE_DRIVE_Q * 1e-3,
    ...                      R=gb.TAPE_DRIVE_R)
    >>> bool(res.smoothed), res.d_est.shape
    (True, (1, 300))
    """
    level, gain, tol = _check_options(level, gain, tol)
    if _use_feedthrough(sys, unknown, relative_degree):
        model, A, B, C, D, G, labels, y, u, Q, R, x0, P0 = _prepare(
            sys, y, u, unknown, Q, R, x0, P0, allow_no_unknown=False, check_rank=False)
        H = _unknown_feedthrough(sys, labels)
        _check_feedthrough_rank(H, labels)
        fwd = _run_feedthrough(model, A, B, C, D, G, H, labels, y, u, Q, R, x0, P0,
                               level=level, gain=gain, tol=tol, store_covariances=False)
        return _smooth_feedthrough(fwd, A, C, G, H, Q, R, P0, tol, store_covariances,
                                   gain == "auto")
    parts, r, Gt, G = _delayed_parts(sys, y, u, unknown, Q, R, x0, P0, relative_degree)
    fwd = _run(*parts, level=level, gain=gain, tol=tol, store_covariances=False)
    A, C, Gr, Q, R, P0 = parts[1], parts[3], parts[5], parts[9], parts[10], parts[12]
    res = _smooth(fwd, A, Gr, Q, R, C, P0, tol, store_covariances)
    if r == 1:
        return res
    return _unshift(res, A, Gt, r, G)
