"""Unknown-input filter with direct feedthrough (Gillijns & De Moor 2007, Automatica 43:934).

The model::

    x[k+1] = A x[k] + B u[k] + G d[k] + w[k],   w ~ N(0, Q)
    y[k]   = C x[k] + D u[k] + H d[k] + v[k],   v ~ N(0, R)

with rank(H) = md. This is the place for errors on the sensor side: an
offset, a gain error, sensor dynamics or a static nonlinearity of one output
are ``H = e_i`` (the i-th unit vector) and ``G = 0``; d[k] is then
"what output i shows beyond C x[k] + D u[k]". G may be nonzero when the
same unknown input also drives the states.

Time alignment: y[k] yields d[k] (no delay), so ``d_est`` has no NaN column.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import control as ct
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._lti import lti_states
from .._validation import check_statespace, resolve_channels
from ..exceptions import DimensionError, RankConditionError
from ..system import named_ss, split_inputs
from ._memo import schedule
from .kernels import FilterResult, GainSchedule, _check_options, _prepare

#: [bytes] Largest record of the covariances of (x[k|k], d[k]) a feedthrough filter's gain
#: schedule keeps for its smoother (beyond it, the smoother runs the recursion again).
JOINT_BYTES = 32 * 2**20

__all__ = ["feedthrough_uikf", "with_sensor_error"]


def with_sensor_error(sys: ct.StateSpace, outputs: int | str | Sequence[int | str], *,
                      names: Sequence[str] | None = None) -> ct.StateSpace:
    """Append one unknown input per named output that adds to that output only.

    The candidate "the error is on sensor i" for :func:`feedthrough_uikf`:
    a new input ``d_i`` with a zero column in B and the unit vector e_i in D,
    so ``y_i = C_i x + D_i u + d_i + v_i``. Then ``feedthrough_uikf(aug, y,
    u, unknown=names)`` gives d^[k] = what sensor i shows beyond the model
    (offset, gain error ``g C_i x``, sensor dynamics, ``|.|``, saturation).

    Parameters
    ----------
    sys : control.StateSpace
        The model (any inputs; discrete or continuous).
    outputs : label(s) or index(es)
        Outputs that get an error channel.
    names : sequence of str, optional
        Names of the new inputs (default ``"<output>_err"``).

    Returns
    -------
    control.StateSpace
        ``sys`` with the new inputs appended after its own.

    Raises
    ------
    DimensionError
        Unknown output, or a name that clashes with an existing input.

    Examples
    --------
    >>> import greybox as gb
    >>> aug = gb.with_sensor_error(gb.tape_drive_nominal(dt=1e-4), "p1")
    >>> aug.input_labels
    ['V1', 'V2', 'T', 'p1_err']
    """
    sys = check_statespace(sys)
    idx = resolve_channels(outputs, sys.output_labels, "outputs")
    if not idx:
        raise DimensionError("outputs: name at least one output")
    names = [f"{sys.output_labels[i]}_err" for i in idx] if names is None else list(names)
    if len(names) != len(idx):
        raise DimensionError(f"names has {len(names)} entries; expected {len(idx)} (one per "
                             f"output)")
    clash = [s for s in names if s in sys.input_labels]
    if clash:
        raise DimensionError(f"names {clash} are already inputs of sys; choose other names")
    n, p = sys.nstates, sys.noutputs
    H = np.zeros((p, len(idx)))
    H[idx, range(len(idx))] = 1.0
    return named_ss(sys.A, np.hstack([np.asarray(sys.B), np.zeros((n, len(idx)))]), sys.C,
                    np.hstack([np.asarray(sys.D), H]), sys.dt, states=sys.state_labels,
                    inputs=list(sys.input_labels) + names, outputs=sys.output_labels,
                    name=sys.name)


def _feedthrough_gains(Pp, C, H, R):
    """Gains from ``P[k|k-1]``: (K, M, Pd, Rt, Pf, Pxd) of the filter with feedthrough."""
    CP = C @ Pp
    Rt = CP @ C.T + R
    Rt = 0.5 * (Rt + Rt.T)
    n = Pp.shape[0]
    S = np.linalg.solve(Rt, np.concatenate((CP, H), axis=1))  # Rt^-1 [C Pp, H]
    K = S[:, :n].T
    RiH = S[:, n:]
    Pd = np.linalg.inv(H.T @ RiH)
    Pd = 0.5 * (Pd + Pd.T)
    M = Pd @ RiH.T
    Pf = Pp - K @ (Rt - H @ Pd @ H.T) @ K.T
    Pxd = -K @ H @ Pd
    return K, M, Pd, Rt, 0.5 * (Pf + Pf.T), Pxd


def joint_block(Pf, Pxd, Pd):
    """``[[Pf, Pxd], [Pxd^T, Pd]]``: the covariance of (x[k|k], d[k]) (the numbers and
    layout ``np.block`` gives, without its per-call checks: it ran once per sample)."""
    n = Pf.shape[0]
    J = np.empty((n + Pd.shape[0],) * 2)
    J[:n, :n], J[:n, n:], J[n:, :n], J[n:, n:] = Pf, Pxd, Pxd.T, Pd
    return J


def _predict_cov(AG, J, Q):
    """``P[k+1|k]`` from ``J`` (:func:`joint_block`) and ``AG = [A G]``."""
    Pp = AG @ J @ AG.T + Q
    return 0.5 * (Pp + Pp.T)


def _use_feedthrough(sys, unknown, relative_degree) -> bool:
    """True for ``relative_degree=0``, or "auto" when the unknown inputs feed through."""
    if isinstance(relative_degree, str):
        return relative_degree == "auto" and bool(np.any(split_inputs(sys, unknown).H))
    return (isinstance(relative_degree, (int, np.integer))
            and not isinstance(relative_degree, bool) and relative_degree == 0)


def _unknown_feedthrough(sys, labels):
    """H: the columns of ``sys.D`` for the unknown inputs."""
    return np.asarray(sys.D, dtype=float)[:, [sys.input_labels.index(s) for s in labels]]


def _check_feedthrough_rank(H, labels):
    md = H.shape[1]
    s = np.linalg.svd(H, compute_uv=False)
    if H.shape[0] < md or s[md - 1] <= 1e-9 * max(s[0], np.finfo(float).tiny):
        raise RankConditionError(
            f"rank(H) < md = {md}: the unknown inputs {list(labels)} do not all feed through "
            f"to the outputs separably (H = the D columns of d). Use uikf or delayed_uikf "
            f"for channels that enter the states only"
        )


def feedthrough_uikf(sys: ct.StateSpace, y: ArrayLike, u: ArrayLike | None = None, *,
                     unknown: int | str | Sequence[int | str], Q: ArrayLike, R: ArrayLike,
                     x0: ArrayLike | None = None, P0: ArrayLike | None = None,
                     level: float = 0.95, gain: str = "auto", tol: float = 1e-12,
                     store_covariances: bool = False) -> FilterResult:
    """Unbiased minimum-variance input and state filter with direct feedthrough.

    Estimates x and d of ``x[k+1] = A x + B u + G d + w``,
    ``y = C x + D u + H d + v``, where G and H are the columns of ``sys.B``
    and ``sys.D`` for the unknown inputs and rank(H) = md.

    Parameters
    ----------
    sys : control.StateSpace
        Discrete model with inputs ``[u, d]``; its D columns for d are H.
    y : array_like, shape (noutputs, nsteps)
        Measured outputs.
    u : array_like, shape (ninputs_known, nsteps), optional
        Measured known inputs.
    unknown : label(s) or index(es)
        Unknown-input channels of ``sys``.
    Q : array_like, shape (nstates, nstates)
        Process-noise covariance (PSD).
    R : array_like, shape (noutputs, noutputs)
        Measurement-noise covariance (PD).
    x0 : array_like, shape (nstates,), optional
        Prior mean of x[0] (zero by default).
    P0 : array_like, shape (nstates, nstates), optional
        Prior covariance of x[0] (identity by default).
    level : float
        Confidence level of ``d_lower``/``d_upper``.
    gain : {"auto", "time-varying"}
        "auto" switches to the constant-gain filter (no per-sample Python
        loop) once ``P[k|k-1]`` has converged.
    tol : float
        Relative change of ``P[k|k-1]`` that counts as converged.
    store_covariances : bool
        Keep every ``P[k|k]`` in ``P_filt_history``.

    Returns
    -------
    FilterResult
        With ``relative_degree = 0``: ``d_est[:, k]`` estimates d[k] from
        y[0..k] (no NaN column). ``K`` and ``M`` are the last gains below.

    Raises
    ------
    RankConditionError
        rank(H) < md.
    ModelError
        ``sys`` is continuous-time.
    DimensionError, DataError, CovarianceError
        Wrong shapes, NaN/inf data, invalid covariances.

    Notes
    -----
    For k = 0, 1, ... (the prior x0, P0 is ``x^[0|-1]``, ``P[0|-1]``):

    .. math::

        \\tilde R = C P_{k|k-1} C^T + R,\\quad
        P_d = (H^T \\tilde R^{-1} H)^{-1},\\quad M = P_d H^T \\tilde R^{-1}

        \\hat d_k = M (y_k - C \\hat x_{k|k-1} - D u_k),\\quad
        K = P_{k|k-1} C^T \\tilde R^{-1}

        \\hat x_{k|k} = \\hat x_{k|k-1} + K (y_k - C \\hat x_{k|k-1} - D u_k - H \\hat d_k)

        P_{k|k} = P_{k|k-1} - K (\\tilde R - H P_d H^T) K^T,\\quad
        P^{xd}_k = -K H P_d

        \\hat x_{k+1|k} = A \\hat x_{k|k} + B u_k + G \\hat d_k,\\quad
        P_{k+1|k} = [A\\ G] \\begin{bmatrix} P_{k|k} & P^{xd}_k \\\\
        P^{dx}_k & P_d \\end{bmatrix} [A\\ G]^T + Q

    References
    ----------
    S. Gillijns and B. De Moor, "Unbiased minimum-variance input and state
    estimation for linear discrete-time systems with direct feedthrough",
    Automatica 43 (2007) 934-937, Section 3 (input estimation: Theorem 1;
    measurement update: Theorem 2; time update eq. (15)).

    Examples
    --------
    >>> import numpy as np, greybox as gb
    >>> sys = gb.named_ss([[0.9]], [[1.0, 0.0]], [[1.0], [1.0]], [[0, 0], [0, 1]], 0.1,
    ...                   states=["x"], inputs=["u", "offset"], outputs=["y1", "y2"])
    >>> y = np.vstack([np.zeros(50), np.full(50, 0.3)])
    >>> res = gb.feedthrough_uikf(sys, y, np.zeros((1, 50)), unknown="offset",
    ...                           Q=[[1e-4]], R=np.eye(2) * 1e-4)
    >>> round(float(res.d_est[0, -1]), 6)
    0.3
    """
    level, gain, tol = _check_options(level, gain, tol)
    model, A, B, C, D, G, labels, y, u, Q, R, x0, P0 = _prepare(
        sys, y, u, unknown, Q, R, x0, P0, allow_no_unknown=False, check_rank=False)
    H = _unknown_feedthrough(sys, labels)
    _check_feedthrough_rank(H, labels)
    return _run_feedthrough(model, A, B, C, D, G, H, labels, y, u, Q, R, x0, P0,
                            level=level, gain=gain, tol=tol,
                            store_covariances=store_covariances)


@dataclass(frozen=True)
class _FeedthroughSchedule(GainSchedule):
    """:class:`~greybox.filters.kernels.GainSchedule` of :func:`_run_feedthrough`: the
    gains of steps k < ``kend`` (from :func:`_feedthrough_gains`); ``final`` (K, M, Pd,
    Rt, Pf, Pxd); ``joint`` (n + md, n + md, kend) the covariances of (x[k|k], d[k]) at
    those steps, or None where they would take more than ``JOINT_BYTES``."""

    joint: NDArray | None = None


def _feedthrough_schedule(A, C, G, H, Q, R, P0, N: int, auto: bool, tol: float,
                          keep_pf: bool) -> _FeedthroughSchedule:
    """The covariance recursion of :func:`_run_feedthrough` (no data); its ``joint`` the
    covariances of (x[k|k], d[k]) of the steps k < ``kend`` (:func:`joint_block`) that the
    smoother reads (:mod:`greybox.filters.smoother`), while they take at most
    ``JOINT_BYTES``."""
    n, md = A.shape[0], G.shape[1]
    Phist = np.empty((n, n, N)) if keep_pf else None
    tiny = np.finfo(float).tiny
    Ks, Ms, dv = [], [], np.empty((N, md))
    Pp, Pp_prev, kconv = P0, None, None
    AG = np.hstack([A, G])
    joint, keep = [], 8 * (n + md) ** 2  # [bytes] per step
    k = 0
    while k < N:
        if auto and Pp_prev is not None and np.max(np.abs(Pp - Pp_prev)) <= \
                tol * max(np.max(np.abs(Pp)), tiny):
            kconv = k
            break
        K, M, Pd, Rt, Pf, Pxd = _feedthrough_gains(Pp, C, H, R)
        Ks.append(K)
        Ms.append(M)
        dv[k] = Pd.diagonal()
        if Phist is not None:
            Phist[:, :, k] = Pf
        Pp_prev = Pp
        J = joint_block(Pf, Pxd, Pd)
        if joint is not None:
            joint = joint if keep * (k + 1) <= JOINT_BYTES else None
            if joint is not None:
                joint.append(J)
        Pp = _predict_cov(AG, J, Q)
        k += 1
    converged = kconv is not None
    if not auto and Pp_prev is not None:
        converged = bool(np.max(np.abs(Pp - Pp_prev)) <= tol * max(np.max(np.abs(Pp)), tiny))
    if kconv is not None:
        K, M, Pd, Rt, Pf, Pxd = _feedthrough_gains(Pp, C, H, R)
        if Phist is not None:
            Phist[:, :, kconv:] = Pf[:, :, None]
    return _FeedthroughSchedule(
        K=tuple(Ks), M=tuple(Ms), d_var=dv[:k], kend=k, kconv=kconv, converged=converged,
        P_pred=Pp_prev if kconv is None else Pp, final=(K, M, Pd, Rt, Pf, Pxd),
        Pf_history=Phist,
        joint=None if joint is None else np.stack(joint, axis=2) if joint else
        np.empty((n + md, n + md, 0)))


def feedthrough_schedule(A, C, G, H, Q, R, P0, N: int, auto: bool, tol: float,
                         keep_pf: bool = False) -> _FeedthroughSchedule:
    """:func:`_feedthrough_schedule`, computed once per model, (Q, R, P0) and options in a
    process (:func:`greybox.filters._memo.schedule`; not the P history ``keep_pf``
    asks for): the forward filter and its smoother read the same one."""
    def compute():
        return _feedthrough_schedule(A, C, G, H, Q, R, P0, N, auto, tol, keep_pf)

    return compute() if keep_pf else \
        schedule(compute, ("feedthrough gains", A, C, G, H, Q, R, P0, auto, tol), N)


def _run_feedthrough(model, A, B, C, D, G, H, labels, y, u, Q, R, x0, P0, *, level, gain,
                     tol, store_covariances) -> FilterResult:
    n, N = A.shape[0], y.shape[1]
    p, m, md = C.shape[0], B.shape[1], G.shape[1]
    x_filt = np.empty((n, N))
    x_pred = np.empty((n, N))
    innov = np.empty((p, N))
    d_est = np.empty((md, N))
    d_var = np.empty((md, N))
    yk_all = y - D @ u if m and np.any(D) else y
    auto = gain == "auto"

    sc = feedthrough_schedule(A, C, G, H, Q, R, P0, N, auto, tol, store_covariances)
    xp = x0
    for k in range(sc.kend):
        K, M = sc.K[k], sc.M[k]
        e = yk_all[:, k] - C @ xp
        dh = M @ e
        xf = xp + K @ (e - H @ dh)
        x_pred[:, k], innov[:, k], x_filt[:, k] = xp, e, xf
        d_est[:, k] = dh
        xp = A @ xf + G @ dh
        if m:
            xp = xp + B @ u[:, k]
    d_var[:, :sc.kend] = sc.d_var.T
    K, M, Pd, Rt, Pf, Pxd = sc.final
    kconv = sc.kconv
    if kconv is not None:
        # constant gains: x^[k+1|k] = (A - L C) x^[k|k-1] + L (y - D u) + B u,
        # L = A K (I - H M) + G M; then e, d^ = M e and x^[k|k] = x^[k|k-1] + K (I - H M) e
        KT = K @ (np.eye(p) - H @ M)
        L = A @ KT + G @ M
        drive = L @ yk_all[:, kconv:]
        if m:
            drive += B @ u[:, kconv:]
        xs = lti_states(A - L @ C, drive, xp)
        e = yk_all[:, kconv:] - C @ xs
        x_pred[:, kconv:] = xs
        innov[:, kconv:] = e
        x_filt[:, kconv:] = xs + KT @ e
        d_est[:, kconv:] = M @ e
        d_var[:, kconv:] = Pd.diagonal()[:, None]
    t = np.arange(N) * float(model.dt)
    return FilterResult(
        t=t, x_filt=x_filt, x_pred=x_pred, d_est=d_est, d_var=d_var, d_cov=Pd, level=level,
        innovations=innov, innovation_cov=Rt, P_filt=Pf, P_pred=sc.P_pred,
        P_filt_history=sc.Pf_history, K=K, M=M, converged=sc.converged,
        period_converged=kconv, sys=model, G=G, unknown_labels=labels, u=u, y=y,
        relative_degree=0,
    )

