"""Closed-loop-consistent subspace identification: predictor-based PBSID.

Public: :func:`pbsid`, returning the same :class:`~greybox.ident.N4SIDResult`
as :func:`~greybox.ident.n4sid`.

The algorithm of :func:`pbsid` (PBSID_opt, Chiuso 2007, Sec. 4). Predictor form:
:math:`x[k+1] = \\bar A x[k] + \\bar B u[k] + K y[k]` with :math:`\\bar A = A - K C`,
:math:`\\bar B = B - K D`. With :math:`z = [u; y]` and :math:`\\tilde B = [\\bar B, K]`,
:math:`x[k] = \\sum_{j=1}^{p} \\bar A^{j-1} \\tilde B z[k-j] + \\bar A^p x[k-p]`, so
:math:`y[k] = \\sum_j \\Xi_j z[k-j] + D u[k] + e[k]` with
:math:`\\Xi_j = C \\bar A^{j-1} \\tilde B` (VARX). The matrix with block (a, j) equal
to :math:`\\Xi_{a+j}` (zero beyond ``p``) estimates :math:`\\Gamma_f \\mathcal{K}_p`;
the SVD of it times the past data gives the states ``X_k`` and, with the same map on the
shifted window, ``X_{k+1}``. Then ``y_k = C X_k + D u_k + e_k`` and
``X_{k+1} = A X_k + B u_k + K e_k`` by least squares.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..exceptions import DimensionError, IdentificationError
from ._hankel import hankel_r, small_blas
from .n4sid import (
    DEFAULT_RTOL,
    N4SIDResult,
    _Setup,
    _check_choice,
    _check_pe,
    choose_horizon,
    common_setup,
    _fit_orders,
    _finish,
    _regress,
)

__all__ = ["pbsid"]


def pbsid(
    y: ArrayLike | Sequence[ArrayLike],
    u: ArrayLike | Sequence[ArrayLike] | None = None,
    *,
    order: int | None = None,
    horizon: int | None = None,
    future: int | None = None,
    dt: float = 1.0,
    feedthrough: bool | Sequence[int | str] = False,
    criterion: Literal["bic", "aic"] = "bic",
    max_order: int | None = None,
    input_labels: Sequence[str] | None = None,
    output_labels: Sequence[str] | None = None,
    state_prefix: str = "z",
    rtol: float = DEFAULT_RTOL,
    chunk_size: int | None = None,
) -> N4SIDResult:
    """Identify a state-space model from closed-loop data (predictor-based subspace).

    PBSID ("optimized" variant): a high-order VARX regression of ``y[k]`` on
    the past ``p`` samples of ``[u; y]`` (and on ``u[k]`` for the inputs with
    feedthrough) estimates the Markov parameters of the Kalman predictor;
    they form the product of the predictor's extended observability and
    controllability matrices, whose SVD gives the order and a state
    sequence; (C, D) and then (A, B, K) follow by least squares. Every step
    is a causal regression, so the estimates stay consistent when the
    inputs depend on past outputs (feedback), unlike :func:`n4sid`.

    Parameters
    ----------
    y : array_like, shape (noutputs, nsteps), or list of such arrays
        Outputs; time is the last axis; a list gives several experiments.
    u : array_like, shape (ninputs, nsteps), list of such arrays, or None
        Inputs (may be fed back from past outputs).
    order : int, optional
        Number of states, 0 allowed (static map ``y = D u + e`` with
        feedthrough). None: chosen by ``criterion`` in ``0..max_order``.
    horizon : int, optional
        Past horizon ``p`` (VARX lags); default 20 (reduced for short data).
        The predictor's ``(A - K C)^p`` is neglected: choose ``p`` so that it
        is small.
    future : int, optional
        Future horizon ``f <= p`` of the SVD; default ``p``. The order is
        limited to ``f * noutputs``.
    dt : float
        Sampling period [s].
    feedthrough : bool or sequence of int or str
        Inputs (all if True) whose direct term ``D[:, j]`` is estimated.
        Under feedback, ``D[:, j]`` is identifiable only if ``u_j[k]`` is
        uncorrelated with the innovation ``e[k]`` (causal feedback: ``u[k]``
        depends on ``y`` up to ``k - 1``). If ``u_j[k]`` depends on ``y[k]``
        (e.g. a filtered state ``x[k|k]``) leave ``j`` out of the list; the
        estimate would be biased (the regression mixes D with the feedback).
    criterion : {"bic", "aic"}
        As in :func:`n4sid`; ``Re(n)`` is the covariance of the output
        residual of the order-n state regression.
    max_order : int, optional
        Largest order tried; default ``min(10, f * noutputs)``.
    input_labels, output_labels : sequence of str, optional
        Signal names for the returned model.
    state_prefix : str
        States are named ``f"{state_prefix}[k]"``.
    rtol : float
        Relative tolerance of least-squares rank cut-offs (scaled data).
    chunk_size : int, optional
        Block-Hankel columns accumulated at a time.

    Returns
    -------
    N4SIDResult
        With ``method="pbsid"``, ``weighting="PBSID"``; ``Q = K Re K^T +
        Qw``, ``S = K Re``, ``R = Re`` where ``Qw`` is the (small) residual
        covariance of the state regression.

    Raises
    ------
    DimensionError, DataError
        As :func:`n4sid`.
    IdentificationError
        If the fitted matrices are not finite.

    Warns
    -----
    GreyboxWarning
        If the inputs are not persistently exciting of order ``p + 1``.

    Notes
    -----
    The predictor form, the VARX regression and the states are written out in the module
    docstring (:mod:`greybox.ident.closedloop`). As in :func:`n4sid`, everything uses the
    chunk-accumulated R factor of the ``p + 1`` block-row Hankel matrix of ``[u; y]``.

    References
    ----------
    A. Chiuso, "The role of vector autoregressive modeling in predictor-based
    subspace identification", Automatica 43(6), 2007, Sec. 4 (PBSID_opt).
    M. Jansson, "Subspace identification and ARX modeling", IFAC SYSID 2003
    (SSARX). A. Chiuso and G. Picci, "Consistency analysis of some
    closed-loop subspace identification methods", Automatica 41(3), 2005.

    Examples
    --------
    >>> import numpy as np
    >>> from greybox.ident import pbsid
    >>> rng = np.random.default_rng(0)
    >>> N = 4000
    >>> r, e = rng.standard_normal(N), 0.1 * rng.standard_normal(N)
    >>> y, u, x = np.zeros(N), np.zeros(N), 0.0
    >>> for k in range(N):  # plant x+ = 0.9 x + u, y = x + e; feedback u = r - 0.5 y
    ...     y[k] = x + e[k]
    ...     u[k] = r[k] - 0.5 * y[k - 1] if k else r[k]
    ...     x = 0.9 * x + u[k]
    >>> res = pbsid(y, u, order=1)
    >>> round(float(res.sys.poles()[0].real), 2)
    0.9
    """
    _check_choice("criterion", criterion, ("bic", "aic"))
    s = _Setup(*common_setup(y, u, dt, input_labels, output_labels, feedthrough, order,
                              max_order, rtol))
    return _pbsid_run(s, horizon, future, chunk_size, criterion, state_prefix)


def _pbsid_run(s: _Setup, horizon, future, chunk_size, criterion, state_prefix):
    """The horizons, block-Hankel factor and model of :func:`pbsid` from its checked setup."""
    p = choose_horizon(horizon, s.order, s.lengths, s.m, s.l, s.max_order, lambda k: k + 1,
                        default=20)
    if future is None:
        f = p
    else:
        from .._validation import check_positive

        f = check_positive(future, "future", integer=True)
        if f > p:
            raise DimensionError(f"future={f} exceeds the past horizon {p}; expected future <= horizon")
    h = hankel_r(s.ys, s.us, s.sy, s.su, p + 1, chunk_size=chunk_size)
    with small_blas():
        return _pbsid_from_factor(h, p, f, s.ys, s.us, s.l, s.m, s.dt, s.input_labels,
                                  s.output_labels, s.fed, s.order, s.max_order, s.rtol, s.sy,
                                  s.su, criterion, state_prefix)


def _pbsid_from_factor(h, p, f, ys, us, l, m, dt, input_labels, output_labels, fed, order,
                       max_order, rtol, sy, su, criterion, state_prefix):
    _check_pe(h, p + 1, input_labels, "The Markov parameters")
    nz = m + l
    Zp = h.z(0, p)            # past window of x[k]
    Zp1 = h.z(1, p + 1)       # past window of x[k+1]
    uk = h.rows("u", p, p + 1)
    yk = h.rows("y", p, p + 1)
    ukf = uk[list(fed)]
    # 1. VARX: y_k on [Z_p; u_k(fed)]
    T = _regress(yk, np.vstack([Zp, ukf]), rtol)
    Xi = T[:, :p * nz]
    # Markov parameter of lag j (1..p) is the block of time block p - j
    mk = np.zeros((p + f + 1, l, nz))
    for j in range(1, p + 1):
        t = p - j
        mk[j] = Xi[:, t * nz:(t + 1) * nz]
    GK = np.zeros((f * l, p * nz))
    for a in range(f):
        for t in range(p):
            lag = p - t
            if a + lag <= p:
                GK[a * l:(a + 1) * l, t * nz:(t + 1) * nz] = mk[a + lag]
    M = GK @ Zp
    U, s, _ = np.linalg.svd(M, full_matrices=False)
    nmax = f * l
    order, fit, crit, auto = _fit_orders(
        order, max_order, nmax,
        f"order={order} is too large for future horizon f={f}: at most f * noutputs = "
        f"{nmax}. Increase horizon/future",
        lambda n: _pbsid_fit(n, U, s, GK, Zp, Zp1, uk, yk, fed, m, l, rtol),
        lambda n, fit_: fit_["Re"], criterion, l, m, len(fed), h.ncols)
    for name in ("A", "B", "C", "D", "K"):
        if not np.all(np.isfinite(fit[name])):
            raise IdentificationError(
                f"PBSID produced non-finite {name}; check the excitation and the horizon"
            )
    Re, K = fit["Re"], fit["K"]
    Q = K @ Re @ K.T + fit["Qw"]
    S = K @ Re
    return _finish(
        A=fit["A"], B=fit["B"], C=fit["C"], D=fit["D"], Q=Q, R=Re.copy(), S=S, K=K, Re=Re,
        su=su, sy=sy, ys=ys, us=us, dt=dt, input_labels=input_labels,
        output_labels=output_labels, state_prefix=state_prefix, singular_values=s, horizon=p,
        weighting="PBSID", method="pbsid", criterion=criterion if auto else None,
        criterion_values=crit, nsamples=h.ncols, feedthrough=fed, scale_u=su, scale_y=sy,
    )


def _pbsid_fit(n, U, s, GK, Zp, Zp1, uk, yk, fed, m, l, rtol) -> dict[str, NDArray]:
    """Order-n model from the PBSID SVD (scaled coordinates)."""
    ukf = uk[list(fed)]
    if n > 0:
        sn = np.maximum(s[:n], rtol * max(s[0], np.finfo(float).tiny))
        Tx = (U[:, :n] / np.sqrt(sn)).T @ GK     # state map, (n, p nz)
        Xk, Xk1 = Tx @ Zp, Tx @ Zp1
    else:
        Xk = Xk1 = np.zeros((0, Zp.shape[1]))
    # output equation: y_k = C x_k + D_fed u_k(fed) + e_k
    T = _regress(yk, np.vstack([Xk, ukf]), rtol)
    C = T[:, :n]
    D = np.zeros((l, m))
    D[:, list(fed)] = T[:, n:]
    E = yk - T @ np.vstack([Xk, ukf])
    Re = E @ E.T
    Re = 0.5 * (Re + Re.T)
    if n > 0:
        T2 = _regress(Xk1, np.vstack([Xk, uk, E]), rtol)
        A, B, K = T2[:, :n], T2[:, n:n + m], T2[:, n + m:]
        W = Xk1 - T2 @ np.vstack([Xk, uk, E])
        Qw = W @ W.T
    else:
        A, B, K, Qw = np.zeros((0, 0)), np.zeros((0, m)), np.zeros((0, l)), np.zeros((0, 0))
    return {"A": A, "B": B, "C": C, "D": D, "K": K, "Re": Re, "Qw": 0.5 * (Qw + Qw.T)}
