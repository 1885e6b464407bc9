"""Close the loop on a nonlinear nominal model (section IV): UKF residual, UI-UKF trace, law.

:func:`greybox.close_the_loop` calls :func:`close_the_loop_nonlinear` when its
model is a ``control.NonlinearIOSystem`` (continuous or discrete, with a
linear output map, the paper's (33)). The stages mirror the linear pipeline:

1. **Residual.** Ljung-Box test of the one-step innovations of the
   unscented Kalman filter (:func:`greybox.ukf`) of the nominal model.
2. **Trace.** For every candidate channel (the channels of
   :func:`greybox.trace.resolve_channel_spec`, built on the model's
   linearization at the operating point: each state equation, each input
   entering two or more equations, pairs where p allows) the model gets the
   unknown input ``G d`` (:func:`greybox.with_unknown_inputs`) and the
   unknown-input UKF (:func:`greybox.ui_ukf`) estimates d^; the static law
   ``d = law(x, u)`` is fitted on d^ by the same d^-regression as the linear
   pipeline (forward selection with a BIC stopping rule over x, u, x^3,
   sign(x), |x|). Dynamic (unstructured subsystem) laws are not offered for
   a nonlinear nominal: the subsystem identification is linear.
   A channel that no output sees in the next sample (rank(C G) = 0, e.g. the
   upper of two tanks when only the lower is measured), or whose delayed
   estimate has a 100x smaller steady-state variance on the linearization at
   the operating point (:func:`greybox.detect_relative_degree`, as the linear
   trace chooses), is traced by the delayed filter
   :func:`greybox.delayed_ui_ukf` (relative degree 2). Its d^ is noisy: the
   law's terms include saturation hinges ``max(x - c, 0)``, ``min(x - c, 0)``
   (:func:`greybox.trace.law_terms`), its coefficients are refined by output
   error before the channels are compared, and a law holding a hinge also
   competes reduced to its hinge(s), coefficients and levels refined by output
   error.
3. **Choose and gate** as the linear pipeline: lowest estimation SE of the
   updated model, within ``parsimony`` the fewest parameters; update only if
   some output rejects whiteness, the law's evidence exceeds ``bic_factor``
   times its BIC penalty (k log N) and the SE drops below ``min_se_drop``
   times the nominal one. The evidence is the likelihood-ratio statistic of
   the law on d^ (its BIC gain plus the penalty), except for a delayed
   channel (r = 2) whose law was refined by output error: there d^ is mostly
   estimation noise and the coefficients were estimated on y, so the
   evidence is the Gaussian likelihood ratio of the updated model against
   the nominal on the estimation outputs' simulation error,
   ``Ny log(SE_nom^2 / SE_upd^2)``, divided by the updated residual's colour
   c (its long-run variance over its variance, >= 1: ~Ny / c independent
   samples, a quasi-likelihood ratio), and the penalty is ``k log(Ny / c)``
   with k counting the hinge levels too (they are searched). Not the Wald
   statistic of the fitted coefficients (recorded as ``gate["oe_wald"]``):
   the simulation is far from linear in a stiff hinge's coefficient, barely
   determined while "no hinge" is far worse. The gate records which
   evidence (``gate["evidence"]``) and the ratio of the updated model's mean
   squared simulation error to the noise model's (``gate["oe_floor_ratio"]``;
   above ``FLOOR_NOTE**2`` a note says the law may be partial).
4. **Before/after.** The updated model is ``f(x, u) + G law(x, u)``
   (:func:`greybox.add_law`) in the nominal model's own time base; nominal
   and updated are simulated with the same RK4 discretization
   (:func:`greybox.discretize_nonlinear`, one sub-step count for both); PE
   and whiteness come from each model's own UKF predictor.

Initial state of every simulation: the model's own (UI-)UKF filtered state at
sample ``skip`` = 20; the simulation starts there and SE, PE and the
whiteness tests leave out the first 20 samples (the first 20 columns of
``y_sim`` hold the filter's estimates).

The law is fitted in the units of d: for a continuous model d is held over
each sample like u (zero-order hold) and enters ``dx/dt`` through the
continuous G, so the law's coefficients are continuous-time coefficients
(PAPER_NOTES §9.5) and the updated model evaluates the law at every RK4
stage (exactly, not held).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import control as ct
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from ._validation import (
    check_covariance,
    check_positive,
    check_same_length,
    check_signal,
)
from .exceptions import DataError, GreyboxError, ModelError, RankConditionError
from .filters import (
    FilterResult,
    delayed_ui_ukf,
    detect_relative_degree,
    input_weights,
    ui_ukf,
    ukf,
)
from .metrics import (
    autocorrelation,
    correlation_band,
    cross_correlation,
    relative_error,
    whiteness_test,
)
from .nonlinear import (
    add_law,
    as_nonlinear,
    discretize_nonlinear,
    linear_output_map,
    linearize_at,
    rk4_substeps,
    simulate_nonlinear,
    with_unknown_inputs,
)
from .progress import ProgressClock
from .trace import ChannelTrace, resolve_channel_spec
from .trace.intervals import hac_covariance
from .trace.laws import _eval_terms, _fit_static, _law_line, hinge_name
from .trace.oe import _noise_floor
from .update import UpdatedModel
from .validate import ModelValidation, describe_before_after, undefined_error
from .workflow import CRITERION, CandidateScore, Effect, LoopReport

__all__ = ["NonlinearUpdate", "close_the_loop_nonlinear", "nonlinear_update_of_linear"]

SKIP = 20
"""Leading samples left out of SE, PE and whiteness (the filters' transient)."""
_ALTERNATING = -0.5
"""Below this lag-1 autocorrelation d^ is taken to alternate sign (as in the linear trace)."""
FLOOR_NOTE = 2.0
"""An update whose estimation RMS simulation error is above this many times the noise
model's (:func:`greybox.trace.oe._noise_floor`) gets a note: the law may be partial."""
OE_MAX_TERMS = 3
"""Laws with at most this many terms are refined by output error on y (cost ~ terms)."""


@dataclass(frozen=True)
class NonlinearUpdate:
    """The updated model when it is nonlinear (a nonlinear nominal, or a nonlinear law).

    Attributes
    ----------
    model : control.NonlinearIOSystem
        The updated model in the nominal model's own time base (continuous
        if the nominal is): ``f(x, u) + G law(x, u)``; the nominal model
        itself when nothing was changed.
    discrete : control.NonlinearIOSystem
        The discrete model the table's "updated" row simulates exactly (RK4
        sub-steps of ``model``, or ``A x + B u + G law(x, u)`` for a law
        fitted in discrete time on a linear nominal).
    linearization : control.StateSpace
        ``discrete`` linearized at (x_op, u_op): a StateSpace for
        ``control.dlqr`` / ``control.dlqe`` (the drift ``F(x_op, u_op) -
        x_op`` is not part of it).
    x_op : ndarray, shape (nstates,)
        Operating point of the linearization.
    u_op : ndarray, shape (ninputs,)
        Inputs at the operating point.
    operating_point : str
        How (x_op, u_op) was chosen, in words.
    substeps : int
        RK4 sub-steps per sample of ``discrete`` (0 when no RK4 is involved).
    """

    model: ct.NonlinearIOSystem = field(repr=False)
    discrete: ct.NonlinearIOSystem = field(repr=False)
    linearization: ct.StateSpace = field(repr=False)
    x_op: NDArray[np.float64]
    u_op: NDArray[np.float64]
    operating_point: str
    substeps: int = 0

    def as_dict(self) -> dict:
        """JSON-ready summary (the linearization's matrices, the operating point)."""
        lin = self.linearization
        return {"model": self.model.name, "x_op": self.x_op.tolist(),
                "u_op": self.u_op.tolist(), "operating_point": self.operating_point,
                "substeps": self.substeps, "dt": float(lin.dt),
                "linearization": {k: np.asarray(getattr(lin, k), float).tolist()
                                  for k in ("A", "B", "C", "D")}}


_OP_TEXT = ("the mean of the {what} filtered states and of the inputs over the estimation "
            "record")


def _flag(value, name):
    if not isinstance(value, (bool, np.bool_)):
        raise DataError(f"{name} must be True or False; found {value!r}")
    return bool(value)


def _validation_row(model_d, y, u, *, Q, R, x0, P0, name, lags, alpha, order,
                    ) -> tuple[ModelValidation, FilterResult]:
    """SE (simulation from the UKF's state at SKIP), PE and whiteness of the UKF predictor."""
    C, D = linear_output_map(model_d)
    kf = ukf(model_d, y, u, Q=Q, R=R, x0=x0, P0=P0)
    y_pred = C @ kf.x_pred + D @ u
    e = y - y_pred
    y_sim = C @ kf.x_filt + D @ u
    se_reason = ""
    try:
        sim = simulate_nonlinear(model_d, u[:, SKIP:], x0=kf.x_filt[:, SKIP])
        y_sim[:, SKIP:] = C @ sim.x + D @ u[:, SKIP:]
    except (GreyboxError, FloatingPointError) as ex:
        se_reason = f"the simulation diverged ({ex}): its simulation error is undefined"
    if not se_reason and not np.all(np.isfinite(y_sim)):
        se_reason = "the simulation diverged: its simulation error is undefined"
    if se_reason:
        y_sim = np.full(y.shape, np.nan)
    m = u.shape[0]
    row = ModelValidation(
        name=name, order=order,
        se=undefined_error(y.shape[0]) if se_reason else relative_error(y, y_sim, skip=SKIP),
        pe=relative_error(y, y_pred, skip=SKIP),
        whiteness=whiteness_test(e[:, SKIP:], lags, alpha=alpha),
        autocorr=autocorrelation(e[:, SKIP:], lags),
        crosscorr=cross_correlation(u[:, SKIP:], e[:, SKIP:], lags) if m else
        np.zeros((0, y.shape[0], 2 * lags + 1)),
        band=correlation_band(y.shape[1] - SKIP, 0.99), y_sim=y_sim, y_pred=y_pred,
        residuals=e, output_labels=tuple(model_d.output_labels), se_reason=se_reason)
    return row, kf


def _se_from(model_d, u, x_start, y, C, D) -> float:
    """Estimation SE [%] of a model simulated from x_start at sample SKIP (inf: diverged)."""
    try:
        sim = simulate_nonlinear(model_d, u[:, SKIP:], x0=x_start)
    except GreyboxError:
        return np.inf
    ys = C @ sim.x + D @ u[:, SKIP:]
    if not np.all(np.isfinite(ys)):
        return np.inf
    return float(relative_error(y[:, SKIP:], ys).value)


def _prior(C: NDArray, D: NDArray, y: NDArray, u: NDArray) -> tuple[NDArray, NDArray]:
    """x0 from the first sample (least squares through C), P0 = I."""
    n = C.shape[1]
    x0 = np.linalg.lstsq(C, y[:, 0] - D @ u[:, 0], rcond=None)[0]
    return x0, np.eye(n)


def _delay_of(model_cd, labels, x_op, u_op, Q, R):
    """(r, G, align) for a channel: the delay chosen as the linear trace chooses it.

    The discrete model with unknown inputs is linearized at the operating point;
    :func:`greybox.detect_relative_degree` (r <= 2) keeps r = 1 unless rank(C G)
    < md or the delayed estimate's steady-state variance is 100x smaller. G is
    the linearization's input matrix of d (it defines the shift of
    :func:`greybox.delayed_ui_ukf`); ``align`` (md, r) the weights of d[j..j+r-1]
    in what d^[j] estimates (:func:`greybox.input_weights`).
    """
    md, m = len(labels), model_cd.ninputs - len(labels)
    lin = linearize_at(model_cd, x_op, np.concatenate([u_op, np.zeros(md)]))
    G = np.asarray(lin.B, dtype=float)[:, m:]
    try:  # a covariance recursion that does not converge is a candidate's inf, not a warning
        with np.errstate(all="ignore"):
            r = detect_relative_degree(lin, unknown=labels, Q=Q, R=R, max_degree=2).r
    except GreyboxError:  # not observable at r <= 2: the r = 1 filter names the condition
        return 1, G, np.ones((md, 1))
    if r == 1:
        return 1, G, np.ones((md, 1))
    w, _ = input_weights(lin, unknown=labels, r=r)
    return r, G, np.einsum("icc->ci", w)


def _refine_law_oe(law, base, ch, disc, y, u, x_start, C, D, noise=None):
    """The law's selected coefficients refitted by output error on y.

    Residual: the outputs simulated from ``x_start`` at sample SKIP, each scaled
    by its standard deviation; a diverging simulation counts as a large
    residual. Covariance of the fitted parameters (:func:`_oe_covariance`):
    per parameter the larger variance of the autocorrelation-robust one of
    the linear pipeline (:func:`greybox.trace.intervals.hac_covariance`) and
    the sandwich under the noise model ``noise = (Q, R, P_start)`` along the
    fitted simulation. Returns ``(law, model, (wald, nfree))`` with the
    law's 95 % half-widths in ``ci``, ``wald`` the Wald statistic of "all
    coefficients zero" and ``nfree`` the parameters fitted (coefficients and
    hinge levels); None when the fit fails.
    """
    sel = [(c, j) for c in range(law.coef.shape[0]) for j in np.flatnonzero(law.coef[c])]
    if not sel:
        return None
    rows, cols = (np.array(v) for v in zip(*sel))
    # the levels of the selected saturation hinges are refined with the coefficients
    hinges = sorted({int(j) for j in cols if law.spec[j][1] in _HINGE_KINDS})
    nc = len(sel)
    yy, uu = y[:, SKIP:], u[:, SKIP:]
    scale = np.maximum(np.std(yy, axis=1), 1e-300)[:, None]
    big = np.full(yy.size, 1e3)

    def law_at(theta):
        coef = law.coef.copy()
        coef[rows, cols] = theta[:nc]
        spec = list(law.spec)
        for j, level in zip(hinges, theta[nc:]):
            nm, kind, (i, _) = spec[j]
            spec[j] = (_hinge_name(nm, kind, float(level)), kind, (i, float(level)))
        return replace(law, coef=coef, spec=tuple(spec))

    def resid(theta):
        model = disc(add_law(base, ch.G, law_at(theta).evaluate))
        try:
            sim = simulate_nonlinear(model, uu, x0=x_start)
        except GreyboxError:
            return big
        r = ((yy - C @ sim.x - D @ uu) / scale).ravel()
        return r if np.all(np.isfinite(r)) else big

    theta0 = np.concatenate([law.coef[rows, cols], [law.spec[j][2][1] for j in hinges]])
    try:  # a term that vanishes on the record (a hinge above every x) has a zero Jacobian
        with np.errstate(all="ignore"):  # column: x_scale="jac" then divides by zero
            sol = least_squares(resid, theta0, x_scale="jac", max_nfev=20, ftol=1e-4,
                                xtol=1e-4)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(sol.x)) or sol.fun is big:
        return None
    cov = hac_covariance(sol.jac, sol.fun, yy.shape[0])
    if noise is not None:
        model = disc(add_law(base, ch.G, law_at(sol.x).evaluate))
        try:
            xs = simulate_nonlinear(model, uu, x0=x_start).x
        except GreyboxError:
            xs = None
        if xs is not None:
            cov = _oe_covariance(cov, sol.jac, sol.fun, model, xs, uu, C, scale[:, 0],
                                 *noise)
    half = np.full_like(law.coef, np.nan)
    half[rows, cols] = 1.96 * np.sqrt(np.clip(np.diag(cov), 0, None))[:nc]
    new = law_at(sol.x)
    lines = []
    for c in range(new.coef.shape[0]):
        idx = np.flatnonzero(new.coef[c])
        lines.append(_law_line(ch.labels[c], new.coef[c, idx], [new.spec[j][0] for j in idx],
                               ch.units[c] if c < len(ch.units) else "", half[c, idx]))
    new = replace(new, ci=half, formula="; ".join(lines), time_base="continuous"
                  if base.isctime(strict=True) else "discrete")
    evidence = (_wald_zero(sol.x[:nc], cov[:nc, :nc]), int(sol.x.size))
    return new, add_law(base, ch.G, new.evaluate, name=f"{base.name}_updated"), evidence


def _state_jacobians(model, x: NDArray, u: NDArray) -> NDArray[np.float64]:
    """``dF/dx`` of a discrete model along a trajectory, shape (nsteps, n, n) (central diff.).

    The states of every sample go through ``updfcn`` in one call where the
    model takes a batch (greybox's own models do), else one sample at a time
    (a user's MODEL.py written for one state).
    """
    n, T = x.shape

    def F(X):
        with np.errstate(all="ignore"):
            try:
                out = np.asarray(model.updfcn(0.0, X, u, {}), dtype=float)
                if out.shape in ((n, T), (n * T,)) and T > 1:
                    return out.reshape(n, T)
            except (TypeError, ValueError, IndexError):
                pass
            return np.stack([np.asarray(model.updfcn(0.0, X[:, t], u[:, t], {}),
                                        dtype=float).reshape(n) for t in range(T)], axis=1)

    out = np.empty((T, n, n))
    for i in range(n):
        h = 1e-6 * np.maximum(1.0, np.abs(x[i]))
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        out[:, :, i] = ((F(xp) - F(xm)) / (2 * h)).T
    return out


def _oe_covariance(cov_hac, jac, resid, model, x, u, C, scale, Q, R, P_start):
    """Covariance of output-error coefficients: the HAC one or the noise model's, the larger.

    Under the noise model the scaled output error of the right law is
    ``r[t] = S^-1 (C e[t] + v[t])`` with ``e[t+1] = A_t e[t] + w[t]``
    (``A_t`` the discrete model's Jacobian along the fitted simulation x,
    ``w ~ N(0, Q)``, ``v ~ N(0, R)``, ``e[0] ~ N(0, P_start)``: the error of
    the filtered state the simulation starts from). Then
    ``Cov(J^T r) = sum_t J_t^T S^-1 R S^-1 J_t + sum_s lam_s^T Q lam_s + g^T
    P_start g`` with the adjoint ``lam_s = A_{s+1}^T lam_{s+1} + h_{s+1}``,
    ``h_t = C^T S^-1 J_t``, ``g = h_0 + A_0^T lam_0``, and the sandwich
    ``(J^T J)^-1 Cov(J^T r) (J^T J)^-1`` is calibrated when (Q, R) are right.
    The state error's part is used only where the residual agrees with it:
    the residual's mean square beyond R's, over what the noise model predicts
    for the state error (``C P_t C^T`` with ``P_{t+1} = A_t P_t A_t^T + Q``,
    P_0 = P_start), at least ``FLOOR_NOTE**-2`` (the state error no less
    than half, in RMS, what Q predicts); that part is then scaled by the
    ratio, as least squares estimates sigma^2 from its residual (more error
    than the noise model explains, e.g. the law's own approximation, widens
    the intervals). Below it Q is contradicted (e.g. an overstated Q on a
    plant without process noise predicts far more coloured error than the
    fit leaves, and would inflate the intervals ~10x): Q's part is dropped,
    R's and the initial state's kept (the latter is what HAC alone misses on
    a slow plant: the simulated soft overflow's intervals were ~2x too
    narrow). The HAC covariance (data-driven) guards against an understated
    Q's colour. As in
    :mod:`greybox.trace.oe`, the result keeps the noise model's correlations
    with, per parameter, the larger of the two variances.
    """
    jac = np.asarray(jac, dtype=float)
    p, T = C.shape[0], x.shape[1]
    k = jac.shape[1]
    if not (np.all(np.isfinite(jac)) and np.all(np.isfinite(x))):
        return cov_hac
    J = jac.reshape(p, T, k) / scale[:, None, None]          # S^-1 J_t, (p, T, k)
    Rs = R / np.outer(scale, scale)
    M_r = np.einsum("otk,oq,qtl->kl", J, Rs, J)             # measurement noise's part
    A = _state_jacobians(model, x, u)
    if not np.all(np.isfinite(A)):
        return cov_hac
    # the residual's mean square the noise model predicts: R's part and the part of the
    # state error (process noise, initial state); the latter is scaled to what the residual
    # leaves beyond R's, or dropped if that is under 1/FLOOR_NOTE of it in RMS (Q contradicted)
    P, pred_x = np.array(P_start, dtype=float), 0.0
    with np.errstate(all="ignore"):  # an unstable linearization: inf, then HAC alone
        for t in range(T):
            pred_x += float(np.sum(np.einsum("on,nm,om->o", C, P, C) / scale**2))
            P = A[t] @ P @ A[t].T + Q
    if not np.isfinite(pred_x):
        return cov_hac
    pred_r = T * float(np.sum(np.diag(R) / scale**2))
    left = float(np.sum(np.asarray(resid, dtype=float) ** 2)) - pred_r
    lam_scale = left / pred_x if pred_x > 0 else 0.0
    contradicted = not lam_scale >= FLOOR_NOTE ** -2
    h = np.einsum("on,otk->tnk", C, J)                        # h_t, (T, n, k)
    lam = np.zeros_like(h[0])
    M_q = np.zeros_like(M_r)
    with np.errstate(all="ignore"):
        for s in range(T - 2, -1, -1):                         # lam_s, s = T-2 .. 0
            lam = A[s + 1].T @ lam + h[s + 1]
            M_q += lam.T @ Q @ lam
        g = h[0] + A[0].T @ lam
        M_p = g.T @ P_start @ g
    if not (np.all(np.isfinite(M_q)) and np.all(np.isfinite(M_p))):
        return cov_hac
    Ji = np.linalg.pinv(jac.T @ jac)
    # Q contradicted by the residual: its part dropped, R's and the initial state's kept
    M = M_r + M_p if contradicted else M_r + lam_scale * (M_q + M_p)
    cn = Ji @ M @ Ji
    vh, vn = np.diag(cov_hac), np.diag(cn)
    if not (np.all(np.isfinite(vn)) and np.all(vn > 0)):
        return cov_hac
    gsc = np.sqrt(np.maximum(vh, vn) / vn)
    return cn * np.outer(gsc, gsc)


def _noise_of(res: FilterResult, Q: NDArray, R: NDArray, P_nominal: NDArray):
    """(Q, R, P_start) for :func:`_oe_covariance`: P_start a filter's converged P[k|k].

    The channel's own filter's for r = 1; for a delayed filter (r = 2) its P
    describes z = x - G~ d (d's whole uncertainty folded in, far larger than
    the error of the smoothed x^[k|k+1] the simulation starts from): the
    nominal UKF's ``P_nominal`` stands in.
    """
    n = Q.shape[0]
    P = np.asarray(res.P_filt if getattr(res, "relative_degree", 1) == 1 else P_nominal,
                   dtype=float)
    P = P[:n, :n] if P.ndim == 2 and P.shape[0] >= n else np.zeros((n, n))
    return Q, R, np.where(np.isfinite(P), P, 0.0)


def _floor_ratio(model_d, se: float, y: NDArray, x_op, u_op, C, Q, R) -> float:
    """Mean squared simulation error (from SE [%]) over the noise model's, worst output.

    The noise model's is :func:`greybox.trace.oe._noise_floor` on the model's
    linearization at the operating point (1: the simulation is as good as
    (Q, R) allow).
    """
    if not np.isfinite(se):
        return np.inf
    try:
        A = np.asarray(linearize_at(model_d, x_op, u_op).A, dtype=float)
    except GreyboxError:
        return np.nan
    N = y.shape[1] - SKIP
    ms = (se / 100) ** 2 * np.mean(y[:, SKIP:] ** 2, axis=1)
    fl = _noise_floor(A, C, Q, R, SKIP, N)
    with np.errstate(all="ignore"):
        return float(np.max(ms / fl))


def _oe_likelihood_ratio(model_d, x_start, y, u, C, D, se_nom: float,
                         se_upd: float) -> tuple[float, float]:
    """(quasi likelihood ratio, colour) of an updated model against the nominal, by output error.

    ``Ny log(se_nom^2 / se_upd^2) / c`` with Ny the residuals after SKIP: the
    Gaussian likelihood ratio of two output-error fits (per output: exact for
    one output, the mean relative error otherwise), divided by ``c >= 1``, the
    updated model's residual's long-run variance over its variance (the
    Bartlett-weighted sum of its autocorrelations, the bandwidth of
    :func:`greybox.trace.intervals.hac_covariance`): a coloured residual carries
    ~Ny / c independent samples. Unlike the Wald statistic at the fitted
    coefficients it does not assume the simulation linear in them (a stiff
    saturation hinge's coefficient is barely determined while "no hinge" is
    far worse).
    """
    if not (np.isfinite(se_upd) and se_upd > 0) or np.isnan(se_nom):
        return 0.0, np.nan
    try:
        sim = simulate_nonlinear(model_d, u[:, SKIP:], x0=x_start)
    except GreyboxError:
        return 0.0, np.nan
    r = y[:, SKIP:] - C @ sim.x - D @ u[:, SKIP:]
    if not np.all(np.isfinite(r)):
        return 0.0, np.nan
    r = r / np.maximum(np.std(r, axis=1, keepdims=True), 1e-300)
    T = r.shape[1]
    # long-run variance of the mean residual per output: hac_covariance of a constant fit
    lr = [float(hac_covariance(np.ones((T, 1)), ro, 1)[0, 0]) * T for ro in r]
    colour = max(1.0, float(np.mean(lr)) / float(np.mean(r**2)))
    # a diverging nominal (SE inf) against a finite update: an infinite ratio
    return float(r.size * 2 * np.log(se_nom / se_upd) / colour), colour


def _wald_zero(theta: NDArray, cov: NDArray) -> float:
    """``theta^T cov^-1 theta``: the Wald statistic of "no law" (0 when cov is unusable)."""
    if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(theta))):
        return 0.0
    try:
        w = float(theta @ np.linalg.solve(cov, theta))
    except np.linalg.LinAlgError:
        return 0.0
    return w if np.isfinite(w) and w > 0 else 0.0


_HINGE_KINDS = ("x_hi", "x_lo")


def _hinge_name(name: str, kind: str, level: float) -> str:
    """The name of a hinge term (:func:`greybox.trace.laws.hinge_name`) at a new level."""
    return hinge_name(name[4:-4].rsplit(" ", 2)[0], kind, level)


def _hinge_law(law, d, x, u, sys, labels, units, align, relative):
    """The law reduced to its saturation hinges (refitted on d^), or None without one."""
    idx = [j for j, sp in enumerate(law.spec) if sp[1] in _HINGE_KINDS and
           np.any(law.coef[:, j])]
    if not idx or len(idx) == law.npar:
        return None
    terms = _eval_law_terms(law, x, u)[idx]
    return _fit_static(d, x, u, sys, True, labels, units, align, relative, whiten=True,
                       prebuilt=(terms, [law.spec[j] for j in idx], law.eps))


def _eval_law_terms(law, x, u):
    """Every candidate term of ``law`` on (x, u), shape (nterms, nsteps)."""
    return _eval_terms(law.spec, law.eps, x, u)


def _weak_terms(law) -> list[str]:
    """Names of the law's selected terms whose 95 % interval contains zero."""
    if law.ci is None:
        return []
    out = []
    for c in range(law.coef.shape[0]):
        for j in np.flatnonzero(law.coef[c]):
            if np.isfinite(law.ci[c, j]) and abs(law.coef[c, j]) <= law.ci[c, j]:
                out.append(law.spec[j][0])
    return out


def close_the_loop_nonlinear(sys: ct.NonlinearIOSystem, y, u, y_val, u_val, *, Q, R,
                             dt: float | None = None, channels=None, nonlinear: bool = True,
                             alpha: float = 1e-3, lags: int = 20, parsimony: float = 1.1,
                             min_se_drop: float = 0.8, bic_factor: float = 10.0,
                             substeps: int | None = None, progress=None) -> LoopReport:
    """Residual, trace, law and before/after for a nonlinear nominal model.

    Called by :func:`greybox.close_the_loop` for a ``NonlinearIOSystem``;
    the parameters mean the same there.

    Parameters
    ----------
    sys : control.NonlinearIOSystem
        Nominal model with named signals and a linear output map;
        continuous (then ``dt`` is needed) or discrete.
    y, u : array_like, shapes (noutputs, nsteps), (ninputs, nsteps)
        Estimation record.
    y_val, u_val : array_like
        Validation record.
    Q : array_like, shape (nstates, nstates)
        Process-noise covariance of the discrete model.
    R : array_like, shape (noutputs, noutputs)
        Measurement-noise covariance.
    dt : float, optional
        Sampling period [s] (required for a continuous ``sys``).
    channels : optional
        Candidate channels (see :func:`greybox.trace.resolve_channel_spec`;
        a G matrix is in the model's own time base).
    nonlinear : bool
        Offer x^3, sign(x) and |x| terms to the laws.
    alpha : float
        Significance level of the whiteness tests.
    lags : int
        Lags of the whiteness tests and correlations.
    parsimony : float
        Candidates within this factor of the lowest estimation SE count as
        equally good; the fewest parameters wins.
    min_se_drop : float
        The update must bring the estimation SE below this fraction.
    bic_factor : float
        The law's evidence must exceed this many times its BIC penalty: its
        likelihood ratio on d^, or for a delayed channel (r = 2) its quasi
        likelihood ratio on the output error (see the module's stage 3).
    substeps : int, optional
        RK4 sub-steps per sample for a continuous model (default from
        :func:`greybox.rk4_substeps` at the operating point).
    progress : callable, optional
        Progress callback (see :func:`greybox.close_the_loop`).

    Returns
    -------
    LoopReport
        With ``nonlinear`` (a :class:`NonlinearUpdate`) set: the updated
        nonlinear model, its discretization and its linearization.
        ``nominal`` and ``model.sys`` are linearizations at the operating
        point (StateSpace, for control design); the table's rows simulate
        the nonlinear models.

    Raises
    ------
    ModelError
        Not a NonlinearIOSystem with declared signals, a nonlinear output
        map, a continuous model without dt, dt disagreeing with a discrete
        model.
    DimensionError, DataError, CovarianceError
        Bad shapes or data.
    """
    tick = ProgressClock(progress)
    base = as_nonlinear(sys)
    if isinstance(sys, ct.StateSpace):
        raise ModelError("close_the_loop_nonlinear expects a control.NonlinearIOSystem; use "
                         "greybox.close_the_loop for a StateSpace")
    C, D = linear_output_map(base)
    n, m, p = base.nstates, base.ninputs, base.noutputs
    cont = base.isctime(strict=True)
    if not cont:
        if base.dt is True:
            raise ModelError(f"{base.name} is discrete with an unspecified dt (True); give it "
                             f"the sampling period")
        if dt is not None and abs(float(dt) - float(base.dt)) > 1e-9 * float(base.dt):
            raise ModelError(f"dt = {dt} disagrees with the discrete model's dt = {base.dt}")
        dt = float(base.dt)
    elif dt is None:
        raise ModelError("sys is continuous-time; give the sampling period dt [s] of the data "
                         "so that it can be discretized (RK4 with the inputs held per sample)")
    dt = check_positive(dt, "dt")
    lags = check_positive(lags, "lags", integer=True)
    y = check_signal(y, p, "y", min_steps=max(200, 10 * (n + m) + 4 * lags))
    u = check_signal(u, m, "u")
    check_same_length(("y", y), ("u", u))
    y_val = check_signal(y_val, p, "y_val", min_steps=max(100, 2 * lags + 2 + SKIP))
    u_val = check_signal(u_val, m, "u_val")
    check_same_length(("y_val", y_val), ("u_val", u_val))
    Q = check_covariance(Q, n, "Q", definite=False)
    R = check_covariance(R, p, "R", definite=True)
    nonlinear = _flag(nonlinear, "nonlinear")
    parsimony = check_positive(parsimony, "parsimony")
    alpha = check_positive(alpha, "alpha")
    min_se_drop = check_positive(min_se_drop, "min_se_drop")
    bic_factor = check_positive(bic_factor, "bic_factor")
    if not parsimony >= 1 or not 0 < alpha < 1 or not 0 < min_se_drop <= 1:
        raise DataError(f"need parsimony >= 1, 0 < alpha < 1, 0 < min_se_drop <= 1; found "
                        f"{parsimony}, {alpha}, {min_se_drop}")
    if substeps is not None:
        substeps = check_positive(substeps, "substeps", integer=True)

    # operating point of the channels' linearization and of the RK4 sub-step count
    x_guess, P0 = _prior(C, D, y, u)
    u_mean = u.mean(axis=1) if m else np.zeros(0)
    x_mean_y = np.linalg.lstsq(C, y.mean(axis=1) - D @ u_mean, rcond=None)[0]
    if cont:
        nsub = substeps or rk4_substeps(base, dt, x_op=x_mean_y, u_op=u_mean)

        def disc(s):
            return discretize_nonlinear(s, dt, substeps=nsub)
    else:
        nsub = 0

        def disc(s):
            return s
    nominal_d = disc(base)
    notes = []
    if cont:
        notes.append(f"continuous model discretized with RK4, {nsub} sub-step(s) per sample "
                     f"(inputs and d held over the sample); every model in the table uses it")

    # 1. residual of the nominal model: the UKF's innovations
    tick("residual of the nominal model", 0, 1)
    val_nom, _ = _validation_row(nominal_d, y_val, u_val, Q=Q, R=R,
                                 x0=_prior(C, D, y_val, u_val)[0], P0=P0, name="nominal",
                                 lags=lags, alpha=alpha, order=n)
    kf = ukf(nominal_d, y, u, Q=Q, R=R, x0=x_guess, P0=P0)
    white = whiteness_test(kf.innovations[:, SKIP:], lags, alpha=alpha)
    se_nom = _se_from(nominal_d, u, kf.x_filt[:, SKIP], y, C, D)
    x_op = kf.x_filt[:, SKIP:].mean(axis=1)
    op_text = _OP_TEXT.format(what="nominal UKF's")
    lin_nom = linearize_at(nominal_d, x_op, u_mean)
    lin_cont = linearize_at(base, x_op, u_mean) if cont else lin_nom
    crit = CRITERION.format(pct=100 * (parsimony - 1))
    gate = {"whiteness_pvalue": white.pvalue, "alpha": alpha, "se_estimation_nominal": se_nom,
            "measure": "SE"}
    tick("residual of the nominal model", 1, 1)

    def _report(msg, detected, updated=False, effect=None, ch=None, cands=(), tr=None,
                table=None, model=None, nl=None):
        nl = nl or NonlinearUpdate(model=sys, discrete=nominal_d, linearization=lin_nom,
                                   x_op=x_op, u_op=u_mean, operating_point=op_text,
                                   substeps=nsub)
        model = model or UpdatedModel(sys=lin_nom, Q=Q, R=R, order=n, kind="nominal")
        return LoopReport(model_error_detected=detected, updated=updated, message=msg,
                          residual=white, effect=effect or Effect(kind="none"), channel=ch,
                          candidates=tuple(cands), gate=gate, criterion=crit, nominal=lin_nom,
                          model=model, table=table or {"nominal": val_nom, "updated": val_nom},
                          trace=tr, notes=tuple(notes), nonlinear=nl)

    if white.all_white:
        gate["passed"] = {"whiteness": False}
        return _report("no significant model error: the nominal UKF's one-step innovations "
                       f"are white on every output (Ljung-Box, {lags} lags, all p >= "
                       f"{alpha:g}); model unchanged", False)

    # 2. trace every channel with the unknown-input UKF; static laws on d^
    chans = resolve_channel_spec(lin_cont, channels)
    notes.append("nonlinear nominal: candidate channels from its linearization at the "
                 "operating point; static laws only (dynamic subsystem laws are linear and "
                 "not offered)")
    cands, scored = [], []
    N = y.shape[1]
    for kc, ch in enumerate(chans):
        tick("trace candidate channels", kc, len(chans))
        labels = list(ch.labels)
        r = 1
        try:
            model_cd = disc(with_unknown_inputs(base, ch.G, labels))
            r, G_op, align = _delay_of(model_cd, labels, x_op, u_mean, Q, R)
            if r == 1:
                res = ui_ukf(model_cd, y, u, unknown=labels, Q=Q, R=R, x0=x_guess, P0=P0)
            else:
                res = delayed_ui_ukf(model_cd, y, u, unknown=labels, Q=Q, R=R, x0=x_guess,
                                     P0=P0, G=G_op, relative_degree=r)
        except RankConditionError as e:  # (17) fails: d is not observable in this channel
            cands.append(CandidateScore(ch.name, "-", 0, np.inf, 0, "skipped", str(e)))
            continue
        except (GreyboxError, np.linalg.LinAlgError) as e:
            cands.append(CandidateScore(ch.name, "-", 0, np.inf, 0, "failed",
                                        (f"delayed (r = {r}) estimate: " if r > 1 else "")
                                        + str(e)))
            continue
        # d^[:, j] estimates sum_i align[:, i] d[j + i]; x and u carry r - 1 more columns
        d = res.d_est[:, SKIP:N - r]
        x = res.x_filt[:, SKIP:N - 1]
        uw = u[:, SKIP:N - 1]
        if r == 1:
            x = x[:, :d.shape[1]]
            uw = uw[:, :d.shape[1]]
        # d^ alternating sign (a channel seen through a ZOH zero near z = -1, e.g. a
        # velocity equation through positions only) from the r = 1 filter (the delayed
        # one was not better): fit on the mean of consecutive samples, as the linear
        # trace does
        r1 = float(np.min(autocorrelation(d, 1)[:, 1])) if r == 1 and d.shape[1] > 2 else 0.0
        alt = r1 < _ALTERNATING  # then the mean of two samples, terms weighted alike
        d_fit = 0.5 * (d[:, 1:] + d[:, :-1]) if alt else d
        al = np.full((d.shape[0], 2), 0.5) if alt else (align if r > 1 else None)
        try:
            law = _fit_static(d_fit, x, uw, lin_cont, nonlinear, labels, ch.units, al,
                              ch.relative, whiten=r > 1, saturation=nonlinear and r > 1)
        except (GreyboxError, np.linalg.LinAlgError) as e:  # e.g. no finite d^ left
            cands.append(CandidateScore(ch.name, "static", 0, np.inf, 0, "failed",
                                        f"static law on d^: {e}"))
            continue
        if alt:
            notes.append(f"{ch.name}: d^ alternates sign (lag-1 autocorrelation {r1:.2f}): "
                         f"the static law is fitted on the mean of consecutive samples")
        if r > 1:
            notes.append(f"{ch.name}: relative degree {r} (delayed unscented estimate, "
                         f"greybox.delayed_ui_ukf): d^[j] estimates "
                         + ", ".join(f"{labels[c]}: " + " + ".join(
                             f"{align[c, i]:.3g}*d[j+{i}]" for i in range(r))
                             for c in range(len(labels))))
        tr = ChannelTrace(channel=ch, status="ok", model=model_cd, filter_result=res,
                          static=law, relative_degree=r)
        if law.npar == 0:
            cands.append(CandidateScore(ch.name, "static", 0, np.inf, 0, "skipped",
                                        "no law term explains d^"))
            continue
        if ch.md > 1 and bool(np.any(np.all(law.coef == 0, axis=1))):
            cands.append(CandidateScore(ch.name, "static", 0, np.inf, law.npar, "redundant",
                                        "a component of d has no term"))
            continue
        upd = add_law(base, ch.G, law.evaluate, name=f"{base.name}_updated")
        se = _se_from(disc(upd), u, res.x_filt[:, SKIP], y, C, D)
        refined, evidence = False, None
        if r > 1 and law.npar <= OE_MAX_TERMS:
            # a delayed d^ is noisy (d shows in y only through C A G~): its law's
            # coefficients are refined by output error before the channels are compared
            ref_d = _refine_law_oe(law, base, ch, disc, y, u, res.x_filt[:, SKIP], C, D,
                                   _noise_of(res, Q, R, kf.P_filt))
            if ref_d is not None:
                se_d = _se_from(disc(ref_d[1]), u, res.x_filt[:, SKIP], y, C, D)
                if se_d < se:
                    law, upd, se, refined = ref_d[0], ref_d[1], se_d, True
                    evidence = ref_d[2]
                    tr = replace(tr, static=law)
        cands.append(CandidateScore(ch.name, "static", 0, se, law.npar, "ok",
                                    "delayed d^ law refined by output error" if refined
                                    else ""))
        scored.append((se, law.npar, tr, upd, refined, evidence))
        # a law with a saturation hinge beside other terms: the hinges alone, their
        # coefficients and levels refined by output error, compete as a sparser candidate
        # (d^ of a delayed estimate is noisy and correlated with x^: its other terms are
        # often the closed-loop artefacts of PAPER_NOTES 8.4)
        try:
            hl = _hinge_law(law, d_fit, x, uw, lin_cont, labels, ch.units, al, ch.relative)
        except (GreyboxError, np.linalg.LinAlgError):
            hl = None
        if hl is not None and hl.npar and (ch.md == 1 or np.all(np.any(hl.coef, axis=1))):
            ref_h = _refine_law_oe(hl, base, ch, disc, y, u, res.x_filt[:, SKIP], C, D,
                                   _noise_of(res, Q, R, kf.P_filt))
            if ref_h is not None:
                hl, upd_h, ev_h = ref_h
                se_h = _se_from(disc(upd_h), u, res.x_filt[:, SKIP], y, C, D)
                cands.append(CandidateScore(ch.name, "static", 0, se_h, hl.npar, "ok",
                                            "saturation hinge(s) only, coefficient(s) and "
                                            "level(s) refined by output error"))
                scored.append((se_h, hl.npar, replace(tr, static=hl), upd_h, True, ev_h))
    tick("trace candidate channels", len(chans), len(chans))
    finite = [s for s in scored if np.isfinite(s[0])]
    if not finite:
        gate["passed"] = {"whiteness": True, "trace": False}
        return _report("model error detected, but no candidate channel could explain it "
                       "(see candidates)", True, cands=cands)
    best = min(s[0] for s in finite)
    near = [s for s in finite if s[0] <= parsimony * best]
    se_c, npar, tr, upd, refined, evidence = min(near,
                                                 key=lambda s: (s[1], s[2].channel.md, s[0]))
    ch, law = tr.channel, tr.static
    # refine the law's coefficients by output error on y, in the nominal's time base with
    # the same RK4 (PAPER_NOTES §9.3, §9.5); kept only if the estimation SE drops
    tick("output-error refinement", 0, 1)
    ref = None
    if refined and any(law.spec[j][1] in _HINGE_KINDS for j in np.flatnonzero(law.coef.any(0))):
        notes.append(f"{ch.name}: the law's saturation hinges alone, refined by output error "
                     f"on y (coefficients and levels), were chosen over the full d^ law")
    elif refined:
        notes.append(f"{ch.name}: the delayed d^ law was refined by output error on y before "
                     f"the channels were compared")
    elif law.npar <= OE_MAX_TERMS:
        ref = _refine_law_oe(law, base, ch, disc, y, u, tr.filter_result.x_filt[:, SKIP], C, D,
                             _noise_of(tr.filter_result, Q, R, kf.P_filt))
    else:
        notes.append(f"{ch.name}: the law has {law.npar} terms (> {OE_MAX_TERMS}): not refined "
                     f"by output error (each term costs a simulation per iteration)")
    if ref is not None:
        law_r, upd_r, ev_r = ref
        se_r = _se_from(disc(upd_r), u, tr.filter_result.x_filt[:, SKIP], y, C, D)
        if se_r < se_c:
            notes.append(f"{ch.name}: law refined by output error on y: estimation SE "
                         f"{se_c:.3g}% -> {se_r:.3g}%")
            law, upd, se_c, evidence = law_r, upd_r, se_r, ev_r
            tr = replace(tr, static=law)
    tick("output-error refinement", 1, 1)

    # 3. gate. The evidence for the law: its likelihood-ratio statistic on d^ (the BIC gain
    # plus its penalty), or for a delayed channel whose law was refined by output error, its
    # quasi likelihood ratio on the output error: a delayed d^ is mostly estimation noise,
    # and the coefficients were estimated on y, where the evidence is (module stage 3)
    Nd = N - 1 - SKIP
    if tr.relative_degree > 1 and evidence is not None:
        wald, nfree = evidence
        Ny = p * (N - SKIP)
        gain, colour = _oe_likelihood_ratio(disc(upd), tr.filter_result.x_filt[:, SKIP], y, u,
                                            C, D, se_nom, se_c)
        # BIC's log n with n the independent samples, Ny / colour
        n_eff = Ny / colour if np.isfinite(colour) else Ny
        penalty = float(nfree * np.log(max(n_eff, 2.0)))
        gate.update({"oe_wald": float(wald), "oe_colour": colour})
        gate["evidence"] = ("output error: likelihood ratio of the law against the nominal "
                            f"on the estimation outputs' simulation, divided by the residual's "
                            f"colour ({colour:.3g}); {nfree} free parameter(s), {Ny} residuals "
                            f"({n_eff:.0f} independent)")
    else:
        gain = float(law.bic_gain + law.npar * np.log(Nd))
        penalty = float(npar * np.log(Nd))
        gate["evidence"] = "d^: likelihood ratio of the law against d = 0 (BIC gain + penalty)"
    gain = float(gain)
    # the updated model's simulation error against what the noise model alone allows
    # (a diagnostic, not a criterion: real data rarely reach their noise model)
    floor_ratio = _floor_ratio(disc(upd), se_c, y, x_op, u_mean, C, Q, R)
    gate["oe_floor_ratio"] = floor_ratio
    passed = {"whiteness": True, "bic": gain > bic_factor * penalty,
              "se_drop": se_c < min_se_drop * se_nom}
    gate.update({"bic_gain": gain, "bic_penalty": penalty, "bic_factor": bic_factor,
                 "se_estimation_updated": se_c, "min_se_drop": min_se_drop, "passed": passed})
    effect = Effect(kind="static", order=0, formula=law.formula, channel=ch.name,
                    equations=ch.equations, nonlinear=law.nonlinear, linearized=False, law=law)
    if not (passed["bic"] and passed["se_drop"]):
        failed = [k for k, v in passed.items() if not v]
        return _report(f"model error detected (UKF innovations not white), but the best "
                       f"candidate ({ch.name}, static) failed the gate: {', '.join(failed)}; "
                       f"model unchanged", True, cands=cands, tr=tr)

    if floor_ratio > FLOOR_NOTE ** 2:
        notes.append(f"{ch.name}: the updated model's simulation error on the estimation data "
                     f"is {np.sqrt(floor_ratio):.1f}x (RMS) what the noise model (Q, R) "
                     f"allows: the law explains part of the error; it may be incomplete, or a "
                     f"proxy for another law (e.g. a term of the right one missing)")
    weak = _weak_terms(law)
    if weak:
        notes.append(f"{ch.name}: {len(weak)} of the law's {law.npar} terms ({', '.join(weak)}) "
                     f"have 95 % intervals containing 0: d^ is mostly estimation noise in this "
                     f"channel (e.g. a velocity equation seen through positions only) and the "
                     f"law may be spurious; measure the state the suspected equation drives, "
                     f"or name the channel (channels=...)")

    # 4. before/after on validation data, both simulated with the same RK4
    tick("validation", 0, 1)
    upd_d = disc(upd)
    row, _ = _validation_row(upd_d, y_val, u_val, Q=Q, R=R, x0=_prior(C, D, y_val, u_val)[0],
                             P0=P0, name="updated", lags=lags, alpha=alpha, order=n)
    table = {"nominal": val_nom, "updated": row}
    kf_u = ukf(upd_d, y, u, Q=Q, R=R, x0=x_guess, P0=P0)
    x_op_u = kf_u.x_filt[:, SKIP:].mean(axis=1)
    lin_u = linearize_at(upd_d, x_op_u, u_mean)
    nl = NonlinearUpdate(model=upd, discrete=upd_d, linearization=lin_u, x_op=x_op_u,
                         u_op=u_mean, operating_point=_OP_TEXT.format(what="updated UKF's"),
                         substeps=nsub)
    tick("validation", 1, 1)
    notes.append(f"the 'nominal' and 'updated' rows simulate the nonlinear models"
                 f"{' (RK4)' if cont else ''}; report.model.sys (updated_model.json) is the "
                 f"updated model's linearization at x_op = "
                 f"{np.array2string(x_op_u, precision=4)}, u_op = "
                 f"{np.array2string(u_mean, precision=4)} ({nl.operating_point}), not a row "
                 f"of the table")
    notes.append("the parallel delta baseline (linear) is not computed for a nonlinear "
                 "nominal model")
    for name, r in table.items():
        if not r.se_defined:
            notes.append(f"{name}: SE n/a: {r.se_reason}")
    where = ", ".join(f"eq({s})" for s in ch.equations) or ch.name
    if ch.kind == "input":
        where = f"input {ch.input} (it enters {where})"
    msg = f"model error found in {where}: static effect; {describe_before_after(table)}"
    return _report(msg, True, updated=True, effect=effect, ch=ch, cands=cands, tr=tr,
                   table=table, model=UpdatedModel(sys=lin_u, Q=Q, R=R, order=n, kind="static"),
                   nl=nl)


def _add_sensor_law(sys, law, name: str) -> ct.NonlinearIOSystem:
    """``sys`` with a sensor law on output ``i = law.output``: ``y_i = h_i(x, u) + law(x, u)``."""
    base = as_nonlinear(sys)
    e = np.zeros(base.noutputs)
    e[law.output] = 1.0
    h = base.outfcn

    def out(t, x, u, params):
        x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
        y = np.asarray(h(t, x, u, params), dtype=float)
        d = np.asarray(law.evaluate(x.reshape(x.shape[0], -1), u.reshape(u.shape[0], -1)))[0]
        return y + (np.outer(e, d) if y.ndim > 1 else e * d[0])

    return ct.nlsys(base.updfcn, out, states=list(base.state_labels),
                    inputs=list(base.input_labels), outputs=list(base.output_labels),
                    dt=base.dt, params=dict(base.params or {}), name=name)


def nonlinear_update_of_linear(rep: LoopReport) -> LoopReport:
    """Attach the exact nonlinear model to a linear nominal's report with a nonlinear law.

    The table's "updated" row of such a report simulates
    ``x[k+1] = A x + B u + G law(x, u)`` (discrete A, B, G of the traced
    channel); this adds it as a ``NonlinearIOSystem`` (``rep.nonlinear``)
    with its linearization at the mean filtered state and input, and a note
    saying which row is which. Other reports are returned unchanged.

    Parameters
    ----------
    rep : LoopReport
        A report of :func:`greybox.close_the_loop` on a StateSpace.

    Returns
    -------
    LoopReport
    """
    eff, tr = rep.effect, rep.trace
    if not (rep.updated and eff.nonlinear and eff.law is not None and tr is not None
            and tr.filter_result is not None) or rep.nonlinear is not None:
        return rep
    res = tr.filter_result
    if eff.law.output is not None:  # a sensor law adds to one output, not to the states
        model = _add_sensor_law(res.sys, eff.law, f"{rep.nominal.name}_updated")
    else:
        model = add_law(res.sys, res.G, eff.law.evaluate, name=f"{rep.nominal.name}_updated")
    k0 = max(SKIP, res.period_converged or SKIP)
    x_op = res.x_filt[:, k0:].mean(axis=1)
    u = np.asarray(res.u, dtype=float)
    u_op = u[:, k0:].mean(axis=1) if u.shape[0] else np.zeros(0)
    lin = linearize_at(model, x_op, u_op)
    nl = NonlinearUpdate(model=model, discrete=model, linearization=lin, x_op=x_op, u_op=u_op,
                         operating_point=_OP_TEXT.format(what="unknown-input filter's"))
    note = ("which row is which: 'updated' simulates the full nonlinear law "
            "(report.nonlinear.model, a NonlinearIOSystem: " +
            ("A x + B u + G law(x, u)" if eff.law.output is None else
             f"A x + B u, output {rep.nominal.output_labels[eff.law.output]} + law(x, u)") +
            " in discrete time); 'updated (linearized)' is report.model.sys, the StateSpace "
            "holding the law's best linear least-squares surrogate (a fit over the record, not "
            "a local linearization); report.nonlinear.linearization is the local linearization at "
            "the mean filtered state and input" +
            (" (a sign(x) term, smoothed as tanh(x/eps), has slope 1/eps there when x is "
             "near 0: use greybox.linearize_at at your own operating point)"
             if any(s[1] in ("sign", "rel_sign") and np.any(eff.law.coef[:, j])
                    for j, s in enumerate(eff.law.spec)) else ""))
    return replace(rep, nonlinear=nl, notes=tuple(rep.notes) + (note,))
