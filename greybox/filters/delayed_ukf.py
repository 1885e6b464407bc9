"""Delayed unknown-input estimation for a nonlinear model (unscented, relative degree 2).

:func:`~greybox.ui_ukf` needs rank(C G) = md: d[k-1] must show in y[k]. When
the unknown input drives a state that no output sees (the upper tank of two
cascaded tanks with only the lower one measured, a force with only positions
measured), C G = 0 and d[k] first shows in y[k+2] (relative degree r = 2).

Method: the state shift of :mod:`greybox.filters.delayed` applied to the
sigma-point propagation. With ``G`` the unknown-input matrix ``dF/dd`` of the
discrete model and ``G~ = (I - C^+ C) G`` its part no output sees, the filter
carries

.. math::

    z_k = x_k - \\tilde G\\, d_{k-1}

whose update is

.. math::

    z_{k+1} = F_z(z_k, u_k, d_{k-1}) = F(z_k + \\tilde G d_{k-1},\\ u_k,\\ 0)

with ``d[k]``'s own effect left out (it first shows in y[k+2]), as the
linear filter leaves out ``(G - G~) d[k]``; F is evaluated at d = 0, not at
the latest estimate: a delayed d^ is noisy, and inside an RK4 step a noisy
d moves the sub-steps far from the record. The unknown input of this model is
``d[k-1]``, it enters through ``dF_z/dd = (dF/dx) G~`` and ``C (dF/dx) G~``
has full rank where rank(C G) = 0: the unscented unknown-input filter of
:func:`~greybox.ui_ukf` (its sigma points, its per-step Jacobian by central
differences, eqs. (8)-(10)) runs unchanged on ``F_z`` and gives d[k-2] from
y[k]. The states are mapped back, ``x^[k|k+1] = z^[k|k] + G~ d^[k-1]``.

When ``C G = 0`` exactly (a discrete model ``F(x, u) + G d`` whose d drives
only unmeasured states) the shift is exact and ``d_est[:, j]`` estimates
d[j]. When C G is small but not zero (d held over the sample inside RK4
sub-steps) it estimates ``w[0] d[j] + w[1] d[j+1]`` with the weights of
:func:`~greybox.input_weights` on the model linearized at the operating
point, as the linear delayed filter does. On a linear model ``F_z`` is the linear shifted model exactly, so the
filter equals :func:`~greybox.delayed_uikf` with ``relative_degree=2`` and
``gain="time-varying"`` (the unscented transform is exact for linear maps).
Larger relative degrees are not offered: for r > 2 the shift needs the
unknown inputs d[k-1] .. d[k-r+2] inside F, and only the linear model makes
them cancel.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import control as ct
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..exceptions import DimensionError, GreyboxError, RankConditionError
from ..nonlinear import as_nonlinear
from .delayed import _choose, _unshift
from .sigma_points import MerweScaledSigmaPoints
from .kernels import FilterResult, _check_options, check_rank_condition
from .ukf import _initial_G, _points, _prepare_nl, _propagate, _run_ukf

__all__ = ["delayed_ui_ukf"]

#: Relative tolerance of "C G = 0" (as the linear rank checks).
_RANK_TOL = 1e-9


def _state_jacobian(pb, x: NDArray, uk: NDArray) -> NDArray:
    """dF/dx at (x, uk, d = 0) by central differences (steps 1e-6 of the level, >= 1e-6)."""
    n = x.size
    hx = 1e-6 * np.maximum(1.0, np.abs(x))
    X = np.concatenate([x[:, None] + np.diag(hx), x[:, None] - np.diag(hx)], axis=1)
    FX, _ = _propagate(pb, 1, X, uk, np.zeros(len(pb.unknown)), x, False)
    return (FX[:, :n] - FX[:, n:]) / (2 * hx)[None, :]


def _sees(C: NDArray, G: NDArray) -> bool:
    """rank(C G) = md, relative to |C| |G| (the test of check_rank_condition)."""
    md = G.shape[1]
    if C.shape[0] < md:
        return False
    s = np.linalg.svd(C @ G, compute_uv=False)
    scale = np.linalg.norm(C, 2) * max(np.linalg.norm(G, 2), np.finfo(float).tiny)
    return bool(s[md - 1] > _RANK_TOL * scale)


def choose_nonlinear_degree(pb, G: NDArray) -> int:
    """1 or 2 for the problem ``pb`` with input matrix G, as the linear trace chooses.

    r = 2 when rank(C G) < md; otherwise the steady-state input variances of
    r = 1 and r = 2 of the model linearized at the prior (x0, u[0]) are
    compared by :func:`greybox.filters.delayed._choose` (r = 2 only if its
    variance is 100x smaller or r = 1 does not converge).
    """
    if not _sees(pb.C, G):
        return 2
    A = _state_jacobian(pb, pb.x0, pb.u[:, 0])
    if not np.all(np.isfinite(A)):
        return 1
    try:  # a linearization far from the record (e.g. at a sqrt's 0) may not converge
        with np.errstate(all="ignore"):
            return _choose(A, pb.C, G, pb.Q, pb.R, pb.labels, 2, 100.0, 5000).r
    except (GreyboxError, np.linalg.LinAlgError):
        return 1


def _shifted_problem(pb, G: NDArray):
    """The problem of z = x - G~ d[k-1] (unknown input d[k-1]); returns (pb_z, G~)."""
    C = pb.C
    Gt = G - np.linalg.pinv(C) @ (C @ G)  # the part of G no output sees
    unk = list(pb.unknown)
    fun = pb.fun

    def fz(t, Z, U):
        U = np.array(U, dtype=float)  # a copy: d[k] is set to zero below
        dp = U[unk]  # d' = d[k-1] of every point (the G probes differ in d' only)
        U[unk] = 0.0  # d[k]'s own effect is not modelled (it shows at k + 2)
        shift = Gt @ dp
        return fun(t, Z + (shift[:, None] if shift.ndim == 1 else shift), U)

    return replace(pb, fun=fz, G=None), Gt


def delayed_ui_ukf(sys, y: ArrayLike, u: ArrayLike | None = None, *,
                   unknown: int | str | Sequence[int | str], Q: ArrayLike, R: ArrayLike,
                   relative_degree: int | str = "auto", x0: ArrayLike | None = None,
                   P0: ArrayLike | None = None, G: ArrayLike | None = None,
                   points: MerweScaledSigmaPoints | None = None, level: float = 0.95,
                   store_covariances: bool = False) -> FilterResult:
    """Unknown-input unscented filter with a delayed estimate (relative degree 1 or 2).

    Estimates d[k-2] and ``x^[k-1|k]`` from y[0..k] for the model of
    :func:`~greybox.ui_ukf` when d drives no measured state directly
    (rank(C G) = 0): the filter of :func:`~greybox.ui_ukf` on the shifted
    state ``z = x - G~ d[k-1]`` (module :mod:`greybox.filters.delayed_ukf`).

    Parameters
    ----------
    sys : control.NonlinearIOSystem or control.StateSpace
        Discrete-time model with inputs ``[u, d]`` and a linear output map; d
        must not feed through.
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
    relative_degree : {"auto", 1, 2}
        The delay r. "auto": 2 when rank(C G) < md, else as
        :func:`~greybox.detect_relative_degree` chooses on the model
        linearized at (x0, u[0]) (2 only if its steady-state input variance
        is 100x smaller). r = 1 is :func:`~greybox.ui_ukf` exactly.
    x0 : array_like, shape (nstates,), optional
        Prior mean of x[0] (zero by default).
    P0 : array_like, shape (nstates, nstates), optional
        Prior covariance of x[0] (identity by default).
    G : array_like, shape (nstates, md), optional
        Unknown-input matrix ``dF/dd`` that defines the shift ``G~``; by
        default the Jacobian of the discretized model at (x0, u[0], d = 0).
        For r = 2 the filter's own input matrix ``(dF/dx) G~`` is recomputed
        at every step.
    points : MerweScaledSigmaPoints, optional
        Sigma-point strategy (``MerweScaledSigmaPoints()`` by default).
    level : float
        Confidence level of ``d_lower``/``d_upper`` (0.95).
    store_covariances : bool
        Keep every ``P[k|k]`` (of z for r = 2) in ``P_filt_history``.

    Returns
    -------
    FilterResult
        With ``relative_degree = r``. ``d_est[:, j]`` estimates d[j] from
        y[0..j+r] (its last r columns are NaN); ``x_filt[:, k]`` is
        ``x^[k|k+r-1]`` (last r - 1 columns NaN). For r = 2, ``x_pred``,
        ``innovations``, ``P_pred``, ``P_filt``, ``K`` describe z; since
        ``C z = C x`` the innovations are the usual one-step output
        prediction errors. ``G`` is the unshifted input matrix.

    Raises
    ------
    RankConditionError
        Neither r = 1 nor r = 2 satisfies the rank condition (d drives no
        state an output sees within two steps), or the given r does not.
    GreyboxError
        ``relative_degree`` is not "auto", 1 or 2.
    ModelError
        Continuous-time model; non-linear output map; d feeds through to y;
        F fails or returns NaN/inf.
    DimensionError, DataError, CovarianceError
        Wrong shapes, non-finite data or estimates, invalid covariances.

    Notes
    -----
    With :math:`\\tilde G = (I - C^+ C) G` and :math:`z_k = x_k - \\tilde G d_{k-1}`:

    .. math::

        z_{k+1} = F(z_k + \\tilde G d_{k-1}, u_k, 0), \\qquad
        y_k = C z_k + D u_k + v_k

    and :func:`~greybox.ui_ukf` estimates the input :math:`d_{k-1}` of this
    model with the per-step matrix :math:`\\partial F_z / \\partial d_{k-1}`.

    References
    ----------
    S. Sundaram and C. N. Hadjicostis, IEEE TAC 52(2) (2007) 334-339 (delayed
    estimation); S. Gillijns and B. De Moor, CDC 2006, section IV (the
    unscented unknown-input filter run on the shifted state).

    Examples
    --------
    >>> import numpy as np, control as ct, greybox as gb
    >>> tanks = ct.nlsys(lambda t, x, u, p: np.array(
    ...     [x[0] + 0.1 * (u[0] + u[1] - np.sqrt(abs(x[0]))),
    ...      x[1] + 0.1 * (np.sqrt(abs(x[0])) - np.sqrt(abs(x[1])))]),
    ...     lambda t, x, u, p: x[1:], states=["x1", "x2"], inputs=["u", "d"],
    ...     outputs=["y"], dt=1.0)
    >>> y = 1 + 1e-3 * np.random.default_rng(0).standard_normal((1, 100))
    >>> res = gb.delayed_ui_ukf(tanks, y, np.ones((1, 100)), unknown="d",
    ...                         Q=1e-6 * np.eye(2), R=[[1e-6]], x0=[1, 1])
    >>> res.relative_degree, res.d_est.shape
    (2, (1, 100))
    """
    level, _, _ = _check_options(level, "auto", 1.0)
    pts = _points(points)
    if isinstance(sys, ct.StateSpace):
        sys = as_nonlinear(sys)
    _check_degree(relative_degree)
    pb = _prepare_nl(sys, y, u, unknown, Q, R, x0, P0, G, allow_no_unknown=False,
                     check_rank=True)
    G0 = _initial_G(pb)
    if not np.all(np.isfinite(G0)):
        raise DimensionError(f"dF/dd of {pb.sys.name} is not finite at the prior; pass G")
    r = choose_nonlinear_degree(pb, G0) if relative_degree == "auto" else int(relative_degree)
    if r == 1:
        check_rank_condition(pb.C, G0, pb.labels)
        return replace(_run_ukf(pb, pts, level=level, store_covariances=store_covariances),
                       relative_degree=1)
    return _run_shifted(pb, G0, pts, level, store_covariances)


def _check_degree(relative_degree) -> None:
    """GreyboxError unless ``relative_degree`` is "auto", 1 or 2."""
    if isinstance(relative_degree, str):
        if relative_degree != "auto":
            raise GreyboxError(f"relative_degree must be 'auto', 1 or 2; found "
                               f"{relative_degree!r}")
    elif (not isinstance(relative_degree, (int, np.integer)) or isinstance(relative_degree, bool)
          or relative_degree not in (1, 2)):
        raise GreyboxError(f"relative_degree must be 'auto', 1 or 2 (the nonlinear shift is "
                           f"exact for r = 2 only); found {relative_degree!r}")


def _run_shifted(pb, G0: NDArray, pts, level: float, store_covariances: bool) -> FilterResult:
    """The r = 2 filter: ui_ukf's loop on ``z = x - G~ d[k-1]``, its record mapped back to x."""
    pbz, Gt = _shifted_problem(pb, G0)
    try:
        check_rank_condition(pb.C, _initial_G(pbz), pb.labels)
    except RankConditionError as e:
        raise RankConditionError(
            f"Unknown input {list(pb.labels)} not observable with relative degree 2 either: "
            f"rank(C (dF/dx) G~) < md = {len(pb.unknown)} at the prior (G~ = the part of G "
            f"no output sees). Measure a state that d drives within two steps, or choose "
            f"other channels") from e
    res = _run_ukf(pbz, pts, level=level, store_covariances=store_covariances)
    return _unshift(res, np.eye(pb.x0.size), Gt, 2, G0)
