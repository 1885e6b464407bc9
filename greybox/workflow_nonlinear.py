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
   **Terms chosen by output error.** For a delayed channel, or an r = 1
   channel whose d^ variance is less than 10 % above its estimation
   variance, d^ is mostly noise and its regression picks terms at random; the
   terms are then also chosen by output error on y (:func:`_select_law_oe`:
   forward selection over every candidate term, hinges at a fine grid of
   levels, each fitted on the nonlinear model's simulation error, a term
   added while its quasi likelihood ratio exceeds ``bic_factor`` times its
   BIC penalty on the effective sample count Ny / c; terms whose interval
   contains 0, or that do not improve the simulation of held-out samples,
   are dropped), one more start beside d^'s law: the lower output-error BIC
   (on Ny / c) of the two is kept. That channel's simulations start from the
   state (its filter's or the nominal UKF's at SKIP) whose nominal
   simulation follows y best over the first samples.
3. **Choose and gate** as the linear pipeline: lowest estimation SE of the
   updated model, within ``parsimony`` the fewest parameters (a model that
   declares ``params``: the candidates within ``parsimony`` are refitted
   jointly with the parameters, from the nominal the trace ran on and from
   the declared one, and the lowest output-error BIC of those refits
   chooses, :func:`_pick_after_refit`); update only if
   some output rejects whiteness, the law's evidence exceeds ``bic_factor``
   times its BIC penalty (k log N) and the SE drops below ``min_se_drop``
   times the nominal one. The evidence is the likelihood-ratio statistic of
   the law on d^ (its BIC gain plus the penalty), except for a delayed
   channel (r = 2) whose law was refined by output error, or a law whose
   terms were chosen by output error: there d^ is mostly
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

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import control as ct
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from ._blas import one_blas_thread
from ._validation import (
    MAX_MAGNITUDE,
    check_covariance,
    check_positive,
    check_records,
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
from .nominal_refit import free_parameters, law_coordinates, refit_jointly
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
from .trace.intervals import hac_covariance, residual_colour, undetermined
from .trace.laws import (LINEAR_KINDS, _eval_terms, _fit_static, _law_line,
                         hinge_name, linear_part)
from .trace.oe import _noise_floor, forward_select_oe
from .update import UpdatedModel
from .validate import ModelValidation, describe_before_after, undefined_error
from .records import CRITERION, CandidateScore, Effect, LoopReport

__all__ = ["NonlinearUpdate", "close_the_loop_nonlinear", "nonlinear_update_of_linear"]

SKIP = 20
"""Leading samples left out of SE, PE and whiteness (the filters' transient)."""
_ALTERNATING = -0.5
"""Below this lag-1 autocorrelation d^ is taken to alternate sign (as in the linear trace)."""
FLOOR_NOTE = 2.0
"""An update whose estimation RMS simulation error is above this many times the noise
model's (:func:`greybox.trace.oe._noise_floor`) gets a note: the law may be partial."""
OE_MAX_TERMS = 3
"""Laws with at most this many terms are refined by output error on y (cost ~ terms), and
an output-error term selection stops at this many."""
_OE_TOP = 3
"""Candidate terms fitted per step of an output-error selection (the score test's best)."""
_GRID = 10.0 ** np.arange(-3.0, 0.75, 0.5)
"""Relative coefficients tried per candidate term (both signs) by the output-error selection's
line search, in units of d^'s spread over the term's RMS."""
_FINE = 10.0 ** np.linspace(-0.25, 0.25, 21)
"""Factors around the best coarse coefficient tried before a candidate's fit."""
_FINE_HI = np.linspace(0.5, 0.99, 9)
_FINE_LO = np.linspace(0.01, 0.5, 9)
"""Quantiles of a state's filtered record where the output-error selection offers upper and
lower saturation hinges (the d^ law's are at ``greybox.trace.laws.SAT_QUANTILES``)."""
_LS_WINDOW = 1000
"""Samples simulated by the output-error selection's line search (a ranking: its cost is
then bounded; the fits use the whole record)."""
_START_WINDOW = 50
"""Samples after SKIP over which the start of a noisy channel's simulations is chosen."""
_LOW_SNR = 0.1
"""An r = 1 d^ whose variance is less than this fraction above its own estimation variance
(the filter's Pd) is mostly noise: its law's terms are chosen by output error too (as
:mod:`greybox.trace.channel_trace` does)."""


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
    parameters : tuple of ParameterChange
        The nominal model's declared ``params`` refitted jointly with the law
        (stage 2c: nominal value, refitted value, 95 % half-width); empty when
        they were kept (none declared, ``refit_parameters=False``, or the
        joint refit lost to the law on the fixed nominal).
    spill : tuple of (state, ratio, 95 % half-width)
        The law's entries in other state equations found by the joint refit,
        relative to its channel's entry (empty: none).
    refused : JointRefit or None
        When the gate refused the best law refitted jointly with the nominal's
        parameters: that refit (its model, parameters, spill, estimation SE),
        for inspection; None otherwise.
    """

    model: ct.NonlinearIOSystem = field(repr=False)
    discrete: ct.NonlinearIOSystem = field(repr=False)
    linearization: ct.StateSpace = field(repr=False)
    x_op: NDArray[np.float64]
    u_op: NDArray[np.float64]
    operating_point: str
    substeps: int = 0
    parameters: tuple = ()
    spill: tuple = ()
    refused: object = field(default=None, repr=False)

    def as_dict(self) -> dict:
        """JSON-ready summary (the linearization's matrices, the operating point)."""
        lin = self.linearization
        return {"model": self.model.name, "x_op": self.x_op.tolist(),
                "u_op": self.u_op.tolist(), "operating_point": self.operating_point,
                "substeps": self.substeps, "dt": float(lin.dt),
                "parameters": [p.as_dict() for p in self.parameters],
                "spill": [{"state": s, "ratio": g, "halfwidth": h} for s, g, h in self.spill],
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
    if not se_reason and not _bounded(y_sim):
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
    if not _bounded(ys):
        return np.inf
    return float(relative_error(y[:, SKIP:], ys).value)


def _bounded(y_sim: NDArray) -> bool:
    """Finite and below the magnitude the metrics accept (else: a diverged simulation).

    A simulation that diverges slowly can stay finite (e.g. 4e215 on the cascaded
    tanks with a candidate law) and would make the metrics refuse it as bad data.
    """
    return bool(np.all(np.isfinite(y_sim)) and np.max(np.abs(y_sim), initial=0.0)
                <= MAX_MAGNITUDE)


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
    theta0, law_at, sel, hinges = law_coordinates(law)
    if not sel:
        return None
    nc = len(sel)
    yy, uu = y[:, SKIP:], u[:, SKIP:]
    scale = np.maximum(np.std(yy, axis=1), 1e-300)[:, None]
    big = np.full(yy.size, 1e3)

    last = {}

    def resid(theta):
        key = np.asarray(theta, dtype=float).tobytes()
        if key in last:
            return last[key]
        model = disc(add_law(base, ch.G, law_at(theta).evaluate))
        try:
            sim = simulate_nonlinear(model, uu, x0=x_start)
        except GreyboxError:
            return big
        r = ((yy - C @ sim.x - D @ uu) / scale).ravel()
        last.clear()
        last[key] = r if np.all(np.isfinite(r)) else big
        return last[key]

    cols = _LawColumns([law_at(theta0)])
    model_k = disc(add_law(base, ch.G, cols))

    def jac(theta):
        """Forward differences, every column in one simulation of a batch of laws."""
        theta = np.asarray(theta, dtype=float)
        r0 = resid(theta)
        h = _FD_STEP * np.maximum(1.0, np.abs(theta))
        cols.laws = [law_at(t) for t in theta + np.diag(h)]
        xs = _run_columns(model_k, np.repeat(np.asarray(x_start, float)[:, None], theta.size,
                                             axis=1), uu)
        cols.laws = two[:1]
        R = np.einsum("pn,tnk->kpt", C, xs) + (D @ uu)[None]
        R = ((yy[None] - R) / scale[None]).reshape(theta.size, -1)
        R[~np.all(np.isfinite(R), axis=1)] = big  # a diverged column, as resid counts it
        return ((R - r0) / h[:, None]).T

    two = [law_at(theta0), law_at(theta0 + _FD_STEP * 1e4 * np.maximum(1.0, np.abs(theta0)))]
    batched = _takes_batch(model_k, np.repeat(np.asarray(x_start, float)[:, None], 2, axis=1),
                           uu, lambda c: setattr(cols, "laws", [two[i] for i in c]))
    cols.laws = two[:1]
    try:  # a term that vanishes on the record (a hinge above every x) has a zero Jacobian
        with np.errstate(all="ignore"):  # column: x_scale="jac" then divides by zero
            sol = least_squares(resid, theta0, jac=jac if batched else "2-point",
                                x_scale="jac", max_nfev=20, ftol=1e-4, xtol=1e-4)
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
    new = _with_intervals(law_at(sol.x), sel, hinges,
                          1.96 * np.sqrt(np.clip(np.diag(cov), 0, None)), ch, base)
    evidence = (_wald_zero(sol.x[:nc], cov[:nc, :nc]), int(sol.x.size))
    return new, add_law(base, ch.G, new.evaluate, name=f"{base.name}_updated"), evidence


def _with_intervals(law, sel, hinges, hw, ch, base):
    """``law`` with its 95 % half-widths ``hw`` (coefficients of ``sel``, then hinge levels).

    The half-widths go into ``ci``; the formula is rewritten with them (the
    hinge levels' intervals shown in their terms, :func:`_level_text`).
    """
    nc = len(sel)
    half = np.full_like(law.coef, np.nan)
    for q, (c, j) in enumerate(sel):
        half[c, j] = hw[q]
    shown = {j: _level_text(law.spec[j], h) for j, h in zip(hinges, hw[nc:])}
    lines = []
    for c in range(law.coef.shape[0]):
        idx = np.flatnonzero(law.coef[c])
        lines.append(_law_line(ch.labels[c], law.coef[c, idx],
                               [shown.get(j, law.spec[j][0]) for j in idx],
                               ch.units[c] if c < len(ch.units) else "", half[c, idx]))
    return replace(law, ci=half, formula="; ".join(lines), time_base="continuous"
                   if base.isctime(strict=True) else "discrete")


_FD_STEP = 1.49e-8  # forward-difference step relative to max(1, |coordinate|) (sqrt(eps))


class _LawColumns:
    """``law(x, u)`` of several static laws at once: state column k under ``laws[k]``.

    With one law (or a single state vector) every column takes ``laws[0]``.
    Columns whose laws select the same terms (the same hinge levels) share one
    evaluation of those terms; their coefficients differ per column. Lets a
    forward-difference Jacobian of an output-error fit cost one simulation of
    a batch of states instead of one simulation per coordinate.
    """

    def __init__(self, laws):
        self.laws = laws

    @property
    def laws(self):
        return self._laws

    @laws.setter
    def laws(self, laws):
        self._laws = list(laws)
        self._eps = self._laws[0].eps
        groups: dict = {}
        for k, lw in enumerate(self._laws):
            groups.setdefault(lw._selected[1], []).append(k)
        K = len(self._laws)
        # per group: (spec, columns (None: all), coefficients (md, nsel, ncolumns))
        self._groups = [(spec, None if len(ks) == K else np.asarray(ks),
                         np.stack([self._laws[k]._selected[0] for k in ks], axis=2))
                        for spec, ks in groups.items()]

    def __call__(self, x, u):
        if x.ndim == 1 or len(self._laws) == 1:
            return self._laws[0].evaluate(x, u)
        if len(self._groups) == 1:
            spec, _, coef = self._groups[0]
            return np.einsum("cjk,jk->ck", coef, _eval_terms(spec, self._eps, x, u))
        out = np.empty((self._groups[0][2].shape[0], x.shape[1]))
        for spec, ks, coef in self._groups:
            out[:, ks] = np.einsum("cjk,jk->ck", coef,
                                   _eval_terms(spec, self._eps, x[:, ks], u[:, ks]))
        return out


def _run_columns(model, X0: NDArray, uu: NDArray, T: int | None = None) -> NDArray:
    """States (T, n, K) of the discrete ``model`` run from the K columns of X0 (n, K) on uu.

    One call of the update per sample for all columns (the caller has checked
    that the model takes a batch, :func:`_takes_batch`); K = 1 passes one state
    vector, as any model (a user's MODEL.py) takes it. A column that diverges
    (non-finite or above 1e100) stays NaN from there on.
    """
    upd, par = model.updfcn, dict(model.params or {})
    n, K = X0.shape
    T = uu.shape[1] if T is None else T
    xs = np.full((T, n, K), np.nan)
    X = X0
    with np.errstate(all="ignore"):
        for k in range(T):
            xs[k] = X
            if K == 1:
                X = np.asarray(upd(0.0, X[:, 0], uu[:, k], par), dtype=float).reshape(n, 1)
            else:
                X = np.asarray(upd(0.0, X, np.repeat(uu[:, k:k + 1], K, axis=1), par),
                               dtype=float).reshape(n, K)
            bad = ~np.all(np.isfinite(X) & (np.abs(X) < 1e100), axis=0)
            if bad.any():
                if bad.all():
                    break
                X[:, bad] = np.nan
    return xs


def _takes_batch(model, X: NDArray, uu: NDArray, select: Callable) -> bool:
    """Whether ``model``'s update of two state columns X (n, 2) equals its update of each.

    ``select(cols)`` points the model's law at the coefficients of those columns
    (both, then each); it is left pointing at both.
    """
    upd, par = model.updfcn, dict(model.params or {})
    u2 = np.repeat(uu[:, :1], 2, axis=1)
    try:
        one = []
        for i in range(2):
            select([i])
            one.append(np.asarray(upd(0.0, X[:, i:i + 1], u2[:, :1], par),
                                  dtype=float).reshape(-1))
        select([0, 1])
        two = np.asarray(upd(0.0, X, u2, par), dtype=float)
    except Exception:  # noqa: BLE001 - a model that cannot take a batch is run column by column
        select([0, 1])
        return False
    one = np.stack(one, axis=1)
    return two.shape == X.shape and bool(np.allclose(
        two, one, rtol=1e-12, atol=1e-12 * (float(np.max(np.abs(one))) + 1e-300)))



class _LawOutputError:
    """Output error on y of ``f(x, u) + G law(x, u)`` for a law on the terms ``sel``.

    The nonlinear counterpart of :class:`greybox.trace.oe._OutputErrorLaw`
    (its protocol: ``resid``, ``fit``, ``halfwidths``, for
    :func:`greybox.trace.oe.forward_select_oe`). The law's coefficients
    ``theta`` on the terms ``sel`` (pairs (component of d, term index) of
    ``law.spec``) enter the nominal model in its own time base; the model is
    discretized by ``disc`` (RK4 as everywhere in this module) and simulated
    from ``x_start`` at sample SKIP. Several coefficient vectors are simulated
    at once, one per column of the state, when the model's update function
    takes a batch of states (then a forward-difference Jacobian, or the score
    of every candidate term, costs one simulation); else column by column.
    Residual: the outputs' error after SKIP, each scaled by its standard
    deviation, as :func:`_refine_law_oe`; a diverging simulation counts 1e3
    per residual.
    """

    def __init__(self, law, base, G, disc, y, u, x_start, C, D, noise=None):
        self.law, self.noise, self.C, self.D = law, noise, C, D
        self.yy, self.uu = y[:, SKIP:], u[:, SKIP:]
        self.scale = np.maximum(np.std(self.yy, axis=1), 1e-300)
        self.x_start = np.asarray(x_start, dtype=float)
        self.nres = self.yy.size
        self._spec, self._mask, self._th = [], np.zeros((law.coef.shape[0], 0)), None

        def lawfun(x, u):  # the terms of the current sel at the current coefficient columns
            terms = _eval_terms(self._spec, law.eps, x, u)
            th = self._th if terms.ndim == 2 else self._th[:, 0]
            return self._mask @ (th * terms)

        self.model = disc(add_law(base, G, lawfun))
        self._par = dict(self.model.params or {})  # the model's declared parameters
        self._batched = None
        self._cache = (None, None, None)

    def _set(self, sel, TH):
        self._spec = [self.law.spec[j] for _, j in sel]
        self._mask = np.zeros((self.law.coef.shape[0], len(sel)))
        for q, (c, _) in enumerate(sel):
            self._mask[c, q] = 1.0
        self._th = TH

    def _run(self, X0, TH, T=None):
        """States (T, n, K) from X0 (n, K), the coefficient columns TH (nsel, K)."""
        self._th = TH
        return _run_columns(self.model, X0, self.uu, T)

    def simulate(self, sel, TH, T=None):
        """States (T, nstates, K) for the coefficient columns TH (nsel, K): T samples (all)."""
        self._set(sel, TH[:, :1])
        K = TH.shape[1]
        X0 = np.repeat(self.x_start[:, None], K, axis=1)
        if self._batched is None and K > 1:  # does the model take a batch of states?
            self._batched = _takes_batch(self.model, X0[:, :2], self.uu,
                                         lambda c: setattr(self, "_th", TH[:, c]))
        if K == 1 or self._batched:
            return self._run(X0, TH, T)
        return np.concatenate([self._run(X0[:, i:i + 1], TH[:, i:i + 1], T)
                               for i in range(K)], axis=2)

    def _resids(self, xs):
        """Scaled flat residuals (K, noutputs * T) of the simulated states (first T samples)."""
        T = xs.shape[0]
        Y = np.einsum("pn,tnk->kpt", self.C, xs) + (self.D @ self.uu[:, :T])[None]
        r = ((self.yy[None, :, :T] - Y) / self.scale[None, :, None]).reshape(xs.shape[2], -1)
        return np.where(np.isfinite(r), np.clip(r, -1e3, 1e3), 1e3)

    def _eval(self, theta, sel):
        """(residual, Jacobian) at theta, in one simulation of 1 + len(sel) columns."""
        theta = np.asarray(theta, dtype=float)
        key = (tuple(sel), theta.tobytes())
        if self._cache[0] == key:
            return self._cache[1], self._cache[2]
        h = _FD_STEP * np.maximum(1.0, np.abs(theta))
        TH = np.c_[theta, theta[:, None] + np.diag(h)] if sel else np.zeros((0, 1))
        R = self._resids(self.simulate(sel, TH))
        J = ((R[1:] - R[0]) / h[:, None]).T
        self._cache = (key, R[0], J)
        return R[0], J

    def resid(self, theta, sel):
        """Scaled output error at theta on the terms sel, flat."""
        if not len(sel):
            return self._resids(self.simulate([], np.zeros((0, 1))))[0]
        return self._eval(theta, sel)[0]

    def fit(self, sel, start, max_nfev=20):
        """Levenberg-Marquardt from ``start`` (Jacobian by one batched simulation)."""
        return least_squares(self.resid, np.asarray(start, dtype=float), args=(sel,),
                             jac=lambda th, s: self._eval(th, s)[1], method="lm",
                             x_scale="jac", max_nfev=max_nfev, ftol=1e-4, xtol=1e-4)

    def halfwidths(self, sol, sel):
        """95 % half-widths of the fitted coefficients (:func:`_oe_covariance`)."""
        jac, fun = np.asarray(sol.jac, dtype=float), np.asarray(sol.fun, dtype=float)
        if not (np.all(np.isfinite(jac)) and np.max(np.abs(fun)) < 1e3):
            return np.full(sol.x.size, np.nan)
        cov = hac_covariance(jac, fun, self.yy.shape[0])
        if self.noise is not None:
            xs = self.simulate(sel, np.asarray(sol.x, dtype=float)[:, None])[:, :, 0].T
            self._set(sel, np.asarray(sol.x, dtype=float)[:, None])
            if np.all(np.isfinite(xs)):
                cov = _oe_covariance(cov, jac, fun, self.model, xs, self.uu, self.C,
                                     self.scale, *self.noise)
        h = 1.96 * np.sqrt(np.clip(np.diag(cov), 0, None))
        h[undetermined(jac)] = np.inf  # "not determined", never a half-width of a singular fit
        return h

    def line_search(self, sel, theta, cands, steps):
        """Each candidate's best coefficient on a grid, the current law held: (RSS, start).

        ``steps`` (ncands, ngrid): the coefficient values tried per candidate,
        all simulated at once over the first ``_LS_WINDOW`` samples (a global version of the score test: the
        missing law's simulation is far from linear in a coefficient started
        at 0, and a delayed d^ can give it the wrong sign).
        """
        theta = np.asarray(theta, dtype=float)
        k, nc, ng = len(sel), len(cands), steps.shape[1]
        TH = np.zeros((k + nc, nc * ng))
        TH[:k] = theta[:, None]
        for q in range(nc):
            TH[k + q, q * ng:(q + 1) * ng] = steps[q]
        R = self._resids(self.simulate(list(sel) + list(cands), TH, _LS_WINDOW))
        rss = np.einsum("kt,kt->k", R, R).reshape(nc, ng)
        best = np.argmin(rss, axis=1)
        return rss[np.arange(nc), best], steps[np.arange(nc), best]


def _state_jacobians(model, x: NDArray, u: NDArray) -> NDArray[np.float64]:
    """``dF/dx`` of a discrete model along a trajectory, shape (nsteps, n, n) (central diff.).

    The states of every sample go through ``updfcn`` in one call where the
    model takes a batch (greybox's own models do), else one sample at a time
    (a user's MODEL.py written for one state).
    """
    n, T = x.shape
    par = dict(model.params or {})  # the model's declared parameters

    def F(X):
        with np.errstate(all="ignore"):
            try:
                out = np.asarray(model.updfcn(0.0, X, u, par), dtype=float)
                if out.shape in ((n, T), (n * T,)) and T > 1:
                    return out.reshape(n, T)
            except (TypeError, ValueError, IndexError):
                pass
            return np.stack([np.asarray(model.updfcn(0.0, X[:, t], u[:, t], par),
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
    colour = _residual_colour(r)
    # a diverging nominal (SE inf) against a finite update: an infinite ratio
    return float(r.size * 2 * np.log(se_nom / se_upd) / colour), colour


_residual_colour = residual_colour  # moved to greybox.trace.intervals (the linear trace uses it)


def _select_law_oe(law, base, ch, disc, y, u, x_start, C, D, noise, d, x, uw, align,
                   factor):
    """The law's terms chosen by output error on y (forward selection, BIC on Ny / c).

    For a channel whose d^ is mostly estimation noise (delayed, r = 2, or an
    r = 1 estimate barely above its own variance): regressions on d^ then
    choose terms at random (on the positions-only pendulum a linear damping
    instead of the cubic drag, or a law in the kinematic equation), and
    refining their coefficients by output error cannot repair a wrong
    choice. Candidates: every term of ``law.spec`` (x, u, x^3, tanh, |x|,
    products, the offset), the saturation hinges at a fine grid of levels
    (the quantiles ``_FINE_HI``, ``_FINE_LO`` of the filtered state: a stiff
    clip's level matters). Each step ranks the candidates by the simulation
    error at their best coefficient on a grid (``_GRID`` times d^'s spread
    over the term's RMS, both signs; the current terms held; one batched
    simulation, :meth:`_LawOutputError.line_search`: a global version of the
    score test, which at the nominal model, far from the law, ranks at
    random), keeps the best ``_OE_TOP`` (one level per hinge), refines each
    start on a finer grid (``_FINE``) and fits them by Levenberg-Marquardt on
    the simulation error of the nonlinear model with the law. The best is
    added while its likelihood ratio exceeds ``factor`` (the gate's
    ``bic_factor``) times its BIC penalty, with n the residuals' effective
    count Ny / c (c: the colour of the residual, :func:`_residual_colour`,
    the larger of the two models'; a simulation error integrates the process
    noise, and a BIC on Ny would take terms that fit its colour) and a hinge
    counting 2 parameters (its level was searched); then terms whose 95 %
    interval contains 0 are dropped (:func:`greybox.trace.oe.forward_select_oe`,
    shared with the linear trace). Returns the law on the chosen terms
    (coefficients as fitted, no intervals yet: :func:`_refine_law_oe` refines
    them with the hinge levels), or None when no term is chosen.
    """
    # saturation hinges at a fine grid of levels (a stiff clip's level matters: the
    # law's five quantile levels may miss it by more than the hinge can make up)
    # a model that takes one state vector at a time (a user's MODEL.py) simulates every grid
    # point apart: then the law's own hinge levels, every other grid point, a shorter fine
    # grid (the real tanks: 100 s -> see README)
    probe = _LawOutputError(law, base, ch.G, disc, y, u, x_start, C, D)
    th0 = np.zeros((0, 2))
    batched = _takes_batch(probe.model, np.repeat(np.asarray(x_start, float)[:, None], 2, axis=1),
                           probe.uu, lambda c: setattr(probe, "_th", th0[:, c]))
    base_spec = [sp for sp in law.spec if sp[1] not in _HINGE_KINDS] if batched else \
        list(law.spec)
    states = sorted({sp[2][0] for sp in law.spec if sp[1] in _HINGE_KINDS}) if batched else []
    hinges = []
    names = list(base.state_labels)
    for i in states:
        for kind, qs in (("x_hi", _FINE_HI), ("x_lo", _FINE_LO)):
            for lv in np.unique(np.nanquantile(x[i], qs)):
                hinges.append((hinge_name(names[i], kind, float(lv)), kind, (i, float(lv))))
    spec = tuple(base_spec[:-1] + hinges + base_spec[-1:]) if base_spec and \
        base_spec[-1][1] == "const" else tuple(base_spec + hinges)
    law = replace(law, spec=spec, coef=np.zeros((law.coef.shape[0], len(spec))))
    prob = _LawOutputError(law, base, ch.G, disc, y, u, x_start, C, D, noise)
    cands = [(c, j) for c in range(law.coef.shape[0]) for j in range(len(law.spec))]
    p = y.shape[0]
    # the grid of each candidate's coefficient: d^'s spread over the term's RMS, times
    # +-10^(-3 .. 0.5) (d^ of a delayed channel is mostly noise: its spread bounds d's)
    sd = np.std(d[:, np.all(np.isfinite(d), axis=0)], axis=1)
    ok = np.all(np.isfinite(x), axis=0) & np.all(np.isfinite(uw), axis=0)
    rms = law.term_scale(x[:, ok], uw[:, ok])  # (a delayed x^ ends in NaN)
    grid = np.r_[-_GRID, _GRID] if batched else np.r_[-_GRID[::2], _GRID[::2]]
    fine_f = _FINE if batched else _FINE[::2]
    starts = {}

    def rank(sel, theta, cs):  # the _OE_TOP terms whose best coefficient lowers the RSS most
        steps = np.array([sd[c] / max(rms[j], 1e-300) * grid for c, j in cs])
        rss, st = prob.line_search(sel, theta, cs, steps)
        order, seen = [], set()
        for q in np.argsort(rss):  # one level per hinge (state, side): the best
            sp = law.spec[cs[q][1]]
            key = (cs[q][0], sp[1], sp[2][0]) if sp[1] in _HINGE_KINDS else cs[q]
            if key not in seen:
                seen.add(key)
                order.append(q)
            if len(order) == _OE_TOP:
                break
        # each kept term's start on a fine grid around its best coarse value (the
        # simulation error of a swinging plant is rough in a coefficient: a start 10 % off
        # can converge to a local minimum far above the right law's)
        top = [cs[q] for q in order]
        fine = np.array([st[q] * fine_f for q in order])
        _, st2 = prob.line_search(sel, theta, top, fine)
        starts.update({cj: float(v) for cj, v in zip(top, st2)})
        return top

    sel, theta, _ = forward_select_oe(
        prob, cands, OE_MAX_TERMS, prob.nres, rank=rank,
        colour=lambda r: _residual_colour(np.asarray(r).reshape(p, -1)), max_nfev=20,
        start=lambda sl, th, cj: starts[cj],
        cost=lambda cj: 2 if law.spec[cj[1]][1] in _HINGE_KINDS else 1, factor=factor)
    if not sel:
        return None
    coef = np.zeros_like(law.coef)
    for (c, j), t in zip(sel, theta):
        coef[c, j] = t
    nonlin = any(law.spec[j][1] not in LINEAR_KINDS for _, j in sel)
    Ddx, Ddu = linear_part(law.spec, coef, law.Ddx.shape[1], law.Ddu.shape[1])
    return replace(law, coef=coef, npar=len(sel), ci=None, nonlinear=nonlin, Ddx=Ddx, Ddu=Ddu)


def _held_out_terms(chosen, base, ch, disc, y, u, x_start, C, D, noise, notes):
    """Drop the terms of a law chosen by output error that do not predict held-out samples.

    With process noise a nonlinear simulation can be so sensitive to a few
    samples (a pendulum swinging over) that output error takes a term that
    only fits this record's path, e.g. a stiff limiter on a velocity (the
    lesson of :func:`greybox.trace.oe._refine_nonlinear_oe`). Each term is
    put to the test: the law with and without it, fitted on the first half of
    the estimation samples, simulated on through the second; the term is
    dropped (and the rest refined again) when the law without it simulates
    the held-out half as well. ``chosen`` is ``(law, model, evidence)`` of
    :func:`_refine_law_oe`.
    """
    law = chosen[0]
    N = y.shape[1]
    half = SKIP + (N - SKIP) // 2
    first = _LawOutputError(law, base, ch.G, disc, y[:, :half], u[:, :half], x_start, C, D)
    whole = _LawOutputError(law, base, ch.G, disc, y, u, x_start, C, D)
    sel = [(int(c), int(j)) for c, j in zip(*np.nonzero(law.coef))]
    theta = np.array([law.coef[c, j] for c, j in sel])

    def held(sl, th):
        sol = first.fit(sl, th)
        r = whole.resid(sol.x, sl).reshape(y.shape[0], -1)[:, half - SKIP:]
        return float(np.sum(r**2))

    try:
        full = held(sel, theta)
        for q in range(len(sel)):
            keep = [k for k in range(len(sel)) if k != q]
            if held([sel[k] for k in keep], theta[keep]) <= full:
                c, j = sel[q]
                notes.append(f"{ch.name}: the term {law.spec[j][0]} chosen by output error "
                             f"does not improve the simulation of held-out samples: dropped")
                coef = law.coef.copy()
                coef[c, j] = 0.0
                return _refine_pruned(replace(law, coef=coef, npar=law.npar - 1), base, ch,
                                      disc, y, u, x_start, C, D, noise)
    except (GreyboxError, np.linalg.LinAlgError, ValueError):
        return chosen
    return chosen


def _refine_pruned(law, base, ch, disc, y, u, x_start, C, D, noise):
    """:func:`_refine_law_oe`, then its weakest term dropped while an interval contains 0.

    The refinement moves the hinge levels with the coefficients and can leave
    a term the selection kept without support; each drop is refitted. Hinges
    are not dropped on their interval (:func:`_held_out_terms` and the gate
    weigh them). None when a fit fails.
    """
    ref = _refine_law_oe(law, base, ch, disc, y, u, x_start, C, D, noise)
    while ref is not None and ref[0].npar > 1:
        new = ref[0]
        t = np.abs(new.coef) / np.where(np.isfinite(new.ci) & (new.ci > 0), new.ci, np.inf)
        # not a hinge: a stiff hinge's simulation is far from linear in its coefficient
        # (barely determined while no hinge is far worse; the selection's BIC took it)
        hinge = np.array([sp[1] in _HINGE_KINDS for sp in new.spec])[None, :]
        t = np.where((new.coef != 0) & ~hinge, t, np.inf)
        c, j = np.unravel_index(int(np.argmin(t)), t.shape)
        if not t[c, j] < 1.0:
            break
        coef = new.coef.copy()
        coef[c, j] = 0.0
        ref = _refine_law_oe(replace(new, coef=coef, npar=new.npar - 1), base, ch, disc, y, u,
                             x_start, C, D, noise)
    return ref


def _start_state(model_d, starts, y, u, C, D) -> NDArray[np.float64]:
    """Of the candidate states at sample SKIP, the one whose simulation follows y best early.

    The simulation error of ``model_d`` (the nominal) over the first
    ``_START_WINDOW`` samples after SKIP, where a missing law has not yet
    moved the simulation far: a wrong start (e.g. a delayed filter's
    velocity before it converged) shows there, and an output-error fit from
    it takes terms that make up for the start (a stiff limiter).
    """
    W = min(_START_WINDOW, y.shape[1] - SKIP)
    best, out = np.inf, np.asarray(starts[0], dtype=float)
    for x0 in starts:
        x0 = np.asarray(x0, dtype=float)
        if not np.all(np.isfinite(x0)):
            continue
        try:
            sim = simulate_nonlinear(model_d, u[:, SKIP:SKIP + W], x0=x0)
        except GreyboxError:
            continue
        e = float(np.sum((y[:, SKIP:SKIP + W] - C @ sim.x - D @ u[:, SKIP:SKIP + W]) ** 2))
        if e < best:
            best, out = e, x0
    return out


def _excess(res: FilterResult, d: NDArray) -> float:
    """var(d^) over its estimation variance (the filter's Pd), minus 1 (inf: not known)."""
    dv = np.asarray(getattr(res, "d_var", np.full((1, 1), np.nan)), dtype=float)
    noise = float(np.nanmean(dv[:, SKIP:])) if dv.size and np.any(np.isfinite(dv)) else np.nan
    if not (np.isfinite(noise) and noise > 0):
        return np.inf
    return float(np.mean(np.var(d, axis=1)) / noise - 1.0)


def _oe_bic(oe, entry, y, u, disc, x0, C, D) -> bool:
    """Whether the law chosen by output error ``oe`` has a lower output-error BIC than ``entry``.

    ``n log(SE^2) + k log(n)`` for each (SE [%] of the estimation simulation, k
    the free parameters: coefficients and hinge levels), n = Ny / c with c the
    colour of the chosen law's residual (:func:`_residual_colour`).
    """
    def nfree(e):
        law = e[2].static
        return int(e[5][1]) if e[5] is not None else int(law.npar)

    se_o, se_e = oe[0], entry[0]
    if not np.isfinite(se_o):
        return False
    if not np.isfinite(se_e):
        return True
    try:
        sim = simulate_nonlinear(disc(oe[3]), u[:, SKIP:], x0=x0)
        colour = _residual_colour(y[:, SKIP:] - C @ sim.x - D @ u[:, SKIP:])
    except GreyboxError:
        colour = 1.0
    n = y[:, SKIP:].size / colour
    return bool(n * np.log(se_o**2) + nfree(oe) * np.log(n)
                < n * np.log(se_e**2) + nfree(entry) * np.log(n))


def _joint_refit(base, disc, law, ch, y, u, x_start, C, D, se_fixed: float, nfree_fixed: int,
                 notes: list, declared: dict, alone=None, jr=None):
    """Stage 2c: ``(alone, joint)`` refits of the nominal's declared parameters, or None.

    ``alone``: the parameters (and the initial state) refitted by output error
    without a law; ``joint``: with the law's coefficients, hinge levels and
    spill ratios (:func:`greybox.nominal_refit.refit_jointly`). The joint
    refit replaces the law on the fixed nominal when its output-error BIC
    (``n log SE^2 + k log n``, n = Ny / colour of its residual, k its free
    parameters) is lower; the gate then weighs the law against ``alone``. ``base``
    may already hold ``alone``'s parameters (stage 1b); the changes are reported
    against the values the model ``declared``. ``jr``: this joint refit when it was
    already made (:func:`_pick_after_refit`, same law, start and nominal).
    """
    yy, uu = y[:, SKIP:], u[:, SKIP:]
    if alone is None:
        alone = refit_jointly(base, disc, yy, uu, x_start, C, D)
    if jr is None:
        jr = refit_jointly(base, disc, yy, uu, x_start, C, D, law=law, G=ch.G)
    if jr is not None:
        jr = replace(jr, parameters=tuple(replace(pc, nominal=declared.get(pc.name, pc.nominal))
                                          for pc in jr.parameters))
    if alone is None or jr is None or jr.law is None:
        notes.append(f"{ch.name}: the nominal's declared parameters could not be refitted "
                     f"with the law (the output-error fit failed); kept")
        return None
    n = yy.size / _residual_colour(jr.residual)
    bic_j = n * np.log(jr.se**2) + jr.nfree * np.log(n)
    bic_f = n * np.log(se_fixed**2) + nfree_fixed * np.log(n) if np.isfinite(se_fixed) \
        else np.inf
    text = (f"{ch.name}: nominal parameters refitted with the law by output error "
            f"(estimation SE {jr.se:.3g} %, the law on the fixed nominal {se_fixed:.3g} %, "
            f"the parameters alone {alone.se:.3g} %): {jr.parameter_text()}")
    if jr.spill:
        text += f"; the law also enters {jr.spill_text()}"
    if not bic_j < bic_f:
        notes.append(text + " -- not kept: higher output-error BIC than the law on the fixed "
                     "nominal")
        return None
    notes.append(text)
    return alone, jr


_REFIT_NEAR = 3  # candidates within the parsimony margin refitted with the parameters


def _pick_after_refit(near, starts, disc, y, u, x0_of, C, D, notes):
    """``(candidate, start, joint refit or None)``: of the candidates within the parsimony margin (sparsest
    first), the one whose law, refitted jointly with the nominal's declared parameters,
    has the lowest output-error BIC, and the nominal its refit started from.

    The final model carries the refitted parameters, so the candidates are compared
    on it: on the fixed nominal a law that stands in for a parameter's error can look
    as good as the right one and win on one term fewer (the spill plant, seed 6: an
    input hinge with k2 and k3 at 2.4x their truth, validation SE 5 % instead of 1 %).
    Each refit starts from every nominal of ``starts`` (the one the trace ran on, whose
    parameters were refitted alone, and the declared one: refitted alone, the
    parameters can absorb part of the missing effect and hold the joint fit in that
    basin); the lower SE is kept. BIC ``n log SE^2 + k log n``, k the joint fit's free
    parameters, n = Ny / c with c the largest residual colour of the refits (one sample
    count for all). At most ``_REFIT_NEAR`` candidates; a failed refit counts as
    infinite; all failed: the sparsest, from the first start.
    """
    yy, uu = y[:, SKIP:], u[:, SKIP:]
    starts = [b for i, b in enumerate(starts) if all(b is not a for a in starts[:i])]
    fits = []
    for s in near[:_REFIT_NEAR]:
        ch = s[2].channel
        best = (None, starts[0])
        for b in starts:
            try:
                jr = refit_jointly(b, disc, yy, uu, x0_of[ch.name], C, D, law=s[2].static,
                                   G=ch.G)
            except (GreyboxError, np.linalg.LinAlgError, ValueError):
                jr = None
            if jr is not None and jr.law is not None and np.isfinite(jr.se) and (
                    best[0] is None or jr.se < best[0].se):
                best = (jr, b)
        fits.append(best)
    done = [jr for jr, _ in fits if jr is not None]
    if not done:
        return near[0], starts[0], None
    n = yy.size / max(_residual_colour(jr.residual) for jr in done)
    bic = [n * np.log(jr.se ** 2) + jr.nfree * np.log(n) if jr is not None else np.inf
           for jr, _ in fits]
    i = int(np.argmin(bic))
    notes.append("candidates within the parsimony margin compared with the nominal's declared "
                 "parameters refitted with each law (output-error BIC, lower is better): "
                 + ", ".join(f"{s[2].channel.name} {b:.1f} (SE {f[0].se:.3g} %)"
                             if f[0] is not None else f"{s[2].channel.name} failed"
                             for s, b, f in zip(near, bic, fits))
                 + f"; chosen {near[i][2].channel.name}")
    return near[i], fits[i][1], fits[i][0]


def _updated(upd, disc, y, u, y_val, u_val, Q, R, P0, lags, alpha, n, nsub, val_nom, u_mean,
             C, D, **changes) -> tuple[dict, NonlinearUpdate]:
    """(table, NonlinearUpdate) of an updated nonlinear model: its validation row beside the
    nominal's, and its linearization at the mean of its UKF's states on the estimation record.

    ``changes``: the NonlinearUpdate's ``parameters`` and ``spill``.
    """
    upd_d = disc(upd)
    row, _ = _validation_row(upd_d, y_val, u_val, Q=Q, R=R, x0=_prior(C, D, y_val, u_val)[0],
                             P0=P0, name="updated", lags=lags, alpha=alpha, order=n)
    kf_u = ukf(upd_d, y, u, Q=Q, R=R, x0=_prior(C, D, y, u)[0], P0=P0)
    x_op_u = kf_u.x_filt[:, SKIP:].mean(axis=1)
    nl = NonlinearUpdate(model=upd, discrete=upd_d, linearization=linearize_at(upd_d, x_op_u,
                                                                               u_mean),
                         x_op=x_op_u, u_op=u_mean,
                         operating_point=_OP_TEXT.format(what="updated UKF's"), substeps=nsub,
                         **changes)
    return {"nominal": val_nom, "updated": row}, nl


def _refit_evidence(residual, se_null: float, se_alt: float, k: int
                    ) -> tuple[float, float, float]:
    """(likelihood ratio, BIC penalty, colour) of an output-error refit against its null.

    ``Ny log(se_null^2 / se_alt^2) / c`` against ``k log(Ny / c)``, c the colour
    of the refit's ``residual`` (noutputs, nsteps) (:func:`_residual_colour`).
    """
    Ny = residual.size
    colour = _residual_colour(residual)
    gain = float(Ny * 2 * np.log(se_null / se_alt) / colour)
    return gain, float(k * np.log(max(Ny / colour, 2.0))), colour


def _changed(parameters) -> list[str]:
    """Texts of the refitted parameters whose change exceeds their 95 % interval, or (no
    interval: a stiff law's degenerate covariance) exceeds 1 % of the declared value,
    then said "(no interval)"."""
    out = []
    for pc in parameters:
        move = abs(pc.refitted - pc.nominal)
        if np.isfinite(pc.halfwidth) and move > pc.halfwidth:
            out.append(pc.text())
        elif not np.isfinite(pc.halfwidth) and move > 0.01 * abs(pc.nominal):
            out.append(pc.text() + " (no interval)")
    return out


def _refit_notes(jr) -> tuple[str, ...]:
    """``Effect.parameter_notes`` of a refit: each declared parameter's change, the spill."""
    out = [f"nominal parameter refitted: {p.text()}" for p in jr.parameters]
    out += [f"the law also enters eq({s}) at {g:.3g}" + (f" ± {h:.2g}" if np.isfinite(h) else "")
            + " times its value" for s, g, h in jr.spill]
    if jr.unidentifiable:
        out.append(f"not separately identifiable: {', '.join(jr.unidentifiable)}")
    if jr.dropped:
        out.append(f"law term(s) left to a declared parameter: {', '.join(jr.dropped)}")
    return tuple(out)


def _parameters_only(alone, se_nom, gate, bic_factor, min_se_drop, disc, y, u, y_val, u_val,
                     Q, R, P0, lags, alpha, n, nsub, val_nom, u_mean, C, D, report, notes,
                     why="the refitted model's UKF innovations are white", law_gate=None,
                     cands=(), tr=None):
    """The report when the declared parameters refitted alone leave white innovations.

    Gate: the likelihood ratio of the refitted parameters against the declared
    ones on the estimation outputs' simulation, divided by the residual's
    colour, above ``bic_factor`` times ``k log(Ny / c)`` (k the parameters),
    and the estimation SE below ``min_se_drop`` times the nominal's. Reached
    also when the best law failed its gate against the refitted parameters
    (``law_gate``: then None when this gate fails too, and the law's evidence
    is kept as ``gate["law_bic_gain"]``, ``gate["law_bic_penalty"]``).
    """
    if law_gate is not None:
        gate["law_bic_gain"] = float(law_gate["bic_gain"])
        gate["law_bic_penalty"] = float(law_gate["bic_penalty"])
    gain, penalty, colour = _refit_evidence(alone.residual, se_nom, alone.se,
                                            len(alone.parameters))
    passed = {"whiteness": True, "bic": gain > bic_factor * penalty,
              "se_drop": alone.se < min_se_drop * se_nom}
    gate.update({"bic_gain": gain, "bic_penalty": penalty, "bic_factor": bic_factor,
                 "oe_colour": colour, "se_estimation_updated": alone.se,
                 "se_estimation_parameters_only": alone.se, "min_se_drop": min_se_drop,
                 "passed": passed,
                 "evidence": "output error: likelihood ratio of the refitted parameters against "
                             "the declared ones, divided by the residual's colour"})
    changed = _changed(alone.parameters)
    if not (passed["bic"] and passed["se_drop"]):
        if law_gate is not None:
            return None
        failed = [k for k, v in passed.items() if not v]
        return report("model error detected (UKF innovations not white); the declared "
                      f"parameters refitted alone failed the gate: {', '.join(failed)} ({why}); "
                      "model unchanged", True, cands=cands, tr=tr, gate_used=gate)
    table, nl = _updated(alone.model, disc, y, u, y_val, u_val, Q, R, P0, lags, alpha, n,
                         nsub, val_nom, u_mean, C, D, parameters=alone.parameters)
    lin_u = nl.linearization
    what = ", ".join(changed) if changed else "none beyond its 95 % interval"
    return report(f"model error found in the nominal's parameters (no law needed: {why}): "
                  f"{what}; {describe_before_after(table)}", True, updated=True, cands=cands,
                  tr=tr, gate_used=gate,
                  effect=Effect(kind="parameters", formula=alone.parameter_text(),
                                parameter_notes=_refit_notes(alone)),
                  table=table, model=UpdatedModel(sys=lin_u, Q=Q, R=R, order=n,
                                                  kind="parameters"), nl=nl)


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


def _level_text(spec_j, h: float) -> str:
    """A hinge's name with its level's 95 % interval: ``max(x1 - (7.995 ± 0.012), 0)``.

    The half-width is the output-error covariance's (:func:`_refine_law_oe`,
    the level fitted with the coefficients); the plain name when it is not
    finite or wider than ``max(|level|, 1)`` (a degenerate covariance: a hinge
    that already clips barely moves the simulation, e.g. ``± 1.6e+70`` on
    the simulated overflow's seed 3).
    """
    name, kind, (_, level) = spec_j
    if not (np.isfinite(h) and h <= max(abs(level), 1.0)):
        return name
    state = name[4:-4].rsplit(" ", 2)[0]
    return f"{kind[2:].replace('hi', 'max').replace('lo', 'min')}({state} - ({level:.4g} ± " \
           f"{h:.2g}), 0)"


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


@one_blas_thread
def close_the_loop_nonlinear(sys: ct.NonlinearIOSystem, y, u, y_val, u_val, *, Q, R,
                             dt: float | None = None, channels=None, nonlinear: bool = True,
                             alpha: float = 1e-3, lags: int = 20, parsimony: float = 1.1,
                             min_se_drop: float = 0.8, bic_factor: float = 10.0,
                             substeps: int | None = None, refit_parameters: bool = True,
                             progress=None) -> LoopReport:
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
    refit_parameters : bool
        Refit the parameters the model declares (``control.nlsys(...,
        params={...})``, finite real scalars read by its update function)
        jointly with the law by output error (stage 2c,
        :mod:`greybox.nominal_refit`): declare the nominal parameters that were
        themselves fitted on data, so that the law is not judged against
        parameters that absorbed part of the missing effect. The law's
        evidence is then weighed against the parameters refitted alone, and
        the report lists each parameter's change with its 95 % interval
        (``report.nonlinear.parameters``). No effect without declared params.
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
    y, u, y_val, u_val = check_records(base, y, u, y_val, u_val, R,
                                       min_steps=max(200, 10 * (n + m) + 4 * lags),
                                       min_val_steps=max(100, 2 * lags + 2 + SKIP))
    Q = check_covariance(Q, n, "Q", definite=False)
    R = check_covariance(R, p, "R", definite=True)
    nonlinear = _flag(nonlinear, "nonlinear")
    refit_parameters = _flag(refit_parameters, "refit_parameters")
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
                table=None, model=None, nl=None, gate_used=None):
        nl = nl or NonlinearUpdate(model=sys, discrete=nominal_d, linearization=lin_nom,
                                   x_op=x_op, u_op=u_mean, operating_point=op_text,
                                   substeps=nsub)
        model = model or UpdatedModel(sys=lin_nom, Q=Q, R=R, order=n, kind="nominal")
        return LoopReport(model_error_detected=detected, updated=updated, message=msg,
                          residual=white, effect=effect or Effect(kind="none"), channel=ch,
                          candidates=tuple(cands), gate=gate if gate_used is None else
                          gate_used, criterion=crit, nominal=lin_nom,
                          model=model, table=table or {"nominal": val_nom, "updated": val_nom},
                          trace=tr, notes=tuple(notes), nonlinear=nl)

    if white.all_white:
        gate["passed"] = {"whiteness": False}
        return _report("no significant model error: the nominal UKF's one-step innovations "
                       f"are white on every output (Ljung-Box, {lags} lags, all p >= "
                       f"{alpha:g}); model unchanged", False)

    # 1b. the parameters the model declares, refitted alone by output error: a nominal that
    # is only mis-calibrated is said so (and the trace then runs on the refitted nominal)
    declared, alone, base_declared = free_parameters(base), None, base
    if refit_parameters and declared:
        tick("nominal parameters refitted alone", 0, 1)
        alone = refit_jointly(base, disc, y[:, SKIP:], u[:, SKIP:], kf.x_filt[:, SKIP], C, D)
        if alone is not None and alone.se < se_nom:
            notes.append(f"the nominal's declared parameters refitted alone by output error: "
                         f"estimation SE {se_nom:.3g} % -> {alone.se:.3g} % "
                         f"({alone.parameter_text()}); the trace runs on this refitted nominal")
            base = alone.model
            kf = ukf(disc(base), y, u, Q=Q, R=R, x0=x_guess, P0=P0)
            white_p = whiteness_test(kf.innovations[:, SKIP:], lags, alpha=alpha)
            if white_p.all_white:
                return _parameters_only(alone, se_nom, gate, bic_factor, min_se_drop, disc,
                                        y, u, y_val, u_val, Q, R, P0, lags, alpha, n, nsub,
                                        val_nom, u_mean, C, D, _report, notes)
        else:
            alone = None
        tick("nominal parameters refitted alone", 1, 1)

    # 2. trace every channel with the unknown-input UKF; static laws on d^
    chans = resolve_channel_spec(lin_cont, channels)
    notes.append("nonlinear nominal: candidate channels from its linearization at the "
                 "operating point; static laws only (dynamic subsystem laws are linear and "
                 "not offered)")
    cands, scored = [], []
    x0_of = {}  # where each channel's simulations start
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
        noise_ch = _noise_of(res, Q, R, kf.P_filt)
        # d^ mostly estimation noise (delayed, or an r = 1 estimate barely above its own
        # variance): the law's terms are chosen by output error too, one more start beside
        # d^'s law (the linear trace's rule, trace.channel_trace)
        noisy = r > 1 or _excess(res, d) < _LOW_SNR
        # where the channel's simulations start: for a noisy channel the state (the
        # channel's filter's or the nominal UKF's) whose nominal simulation follows y best
        # over the first samples (a delayed filter's x^ at SKIP can be far off)
        x0c = _start_state(nominal_d, (res.x_filt[:, SKIP], kf.x_filt[:, SKIP]), y, u, C, D) \
            if noisy else res.x_filt[:, SKIP]
        x0_of[ch.name] = x0c
        chosen = None
        if noisy:
            tick("output-error term selection", kc, len(chans))
            try:
                chosen = _select_law_oe(law, base, ch, disc, y, u, x0c, C, D,
                                        noise_ch, d_fit, x, uw, al, bic_factor)
            except (GreyboxError, np.linalg.LinAlgError, ValueError):
                chosen = None
            if chosen is not None:
                chosen = _refine_pruned(chosen, base, ch, disc, y, u, x0c, C,
                                        D, noise_ch)
            if chosen is not None and chosen[0].npar > 1:
                chosen = _held_out_terms(chosen, base, ch, disc, y, u, x0c, C,
                                         D, noise_ch, notes)
        if law.npar == 0 and chosen is None:
            cands.append(CandidateScore(ch.name, "static", 0, np.inf, 0, "skipped",
                                        "no law term explains d^" + (
                                            ", nor any by output error" if noisy else "")))
            continue
        if ch.md > 1 and bool(np.any(np.all(law.coef == 0, axis=1))) and chosen is None:
            cands.append(CandidateScore(ch.name, "static", 0, np.inf, law.npar, "redundant",
                                        "a component of d has no term"))
            continue
        entry = None
        if law.npar and not (ch.md > 1 and bool(np.any(np.all(law.coef == 0, axis=1)))):
            upd = add_law(base, ch.G, law.evaluate, name=f"{base.name}_updated")
            se = _se_from(disc(upd), u, x0c, y, C, D)
            refined, evidence = False, None
            if r > 1 and law.npar <= OE_MAX_TERMS:
                # a delayed d^ is noisy (d shows in y only through C A G~): its law's
                # coefficients are refined by output error before the channels are compared
                ref_d = _refine_law_oe(law, base, ch, disc, y, u, x0c, C, D,
                                       noise_ch)
                if ref_d is not None:
                    se_d = _se_from(disc(ref_d[1]), u, x0c, y, C, D)
                    if se_d < se:
                        law, upd, se, refined = ref_d[0], ref_d[1], se_d, True
                        evidence = ref_d[2]
                        tr = replace(tr, static=law)
            entry = (se, law.npar, tr, upd, refined, evidence, False)
            why = "delayed d^ law refined by output error" if refined else ""
        if chosen is not None:
            law_o, upd_o, ev_o = chosen
            se_o = _se_from(disc(upd_o), u, x0c, y, C, D)
            oe = (se_o, law_o.npar, replace(tr, static=law_o), upd_o, True, ev_o, True)
            # d^'s law against the one chosen by output error: the lower BIC of the output
            # error (effective sample count Ny / c, c the chosen law's residual colour)
            if entry is None or _oe_bic(oe, entry, y, u, disc, x0c, C, D):
                if entry is not None:
                    cands.append(CandidateScore(ch.name, "static", 0, entry[0], entry[1],
                                                "replaced", "d^ law: higher output-error BIC "
                                                "than the terms chosen by output error"))
                entry, why = oe, "terms chosen by output error on y"
            else:
                cands.append(CandidateScore(ch.name, "static", 0, se_o, law_o.npar,
                                            "replaced", "terms chosen by output error: higher "
                                            "output-error BIC than d^'s law"))
        se, npar_e, tr, upd = entry[:4]
        law = tr.static
        cands.append(CandidateScore(ch.name, "static", 0, se, npar_e, "ok", why))
        scored.append(entry)
        # a law with a saturation hinge beside other terms: the hinges alone, their
        # coefficients and levels refined by output error, compete as a sparser candidate
        # (d^ of a delayed estimate is noisy and correlated with x^: its other terms are
        # often the closed-loop artefacts of PAPER_NOTES 8.4)
        try:
            hl = _hinge_law(law, d_fit, x, uw, lin_cont, labels, ch.units, al, ch.relative)
        except (GreyboxError, np.linalg.LinAlgError):
            hl = None
        if hl is not None and hl.npar and (ch.md == 1 or np.all(np.any(hl.coef, axis=1))):
            ref_h = _refine_law_oe(hl, base, ch, disc, y, u, x0c, C, D,
                                   noise_ch)
            if ref_h is not None:
                hl, upd_h, ev_h = ref_h
                se_h = _se_from(disc(upd_h), u, x0c, y, C, D)
                cands.append(CandidateScore(ch.name, "static", 0, se_h, hl.npar, "ok",
                                            "saturation hinge(s) only, coefficient(s) and "
                                            "level(s) refined by output error"))
                scored.append((se_h, hl.npar, replace(tr, static=hl), upd_h, True, ev_h,
                               entry[6]))
    tick("trace candidate channels", len(chans), len(chans))
    finite = [s for s in scored if np.isfinite(s[0])]
    if not finite:
        gate["passed"] = {"whiteness": True, "trace": False}
        return _report("model error detected, but no candidate channel could explain it "
                       "(see candidates)", True, cands=cands)
    best = min(s[0] for s in finite)
    near = sorted((s for s in finite if s[0] <= parsimony * best),
                  key=lambda s: (s[1], s[2].channel.md, s[0]))
    pick, start, jr_pick = near[0], base, None
    if refit_parameters and declared and len(near) > 1:
        tick("candidates refitted with the nominal's parameters", 0, 1)
        pick, start, jr_pick = _pick_after_refit(near, (base, base_declared), disc, y, u,
                                                 x0_of, C, D, notes)
        tick("candidates refitted with the nominal's parameters", 1, 1)
    se_c, npar, tr, upd, refined, evidence, oe_terms = pick
    ch, law = tr.channel, tr.static
    # refine the law's coefficients by output error on y, in the nominal's time base with
    # the same RK4 (PAPER_NOTES §9.3, §9.5); kept only if the estimation SE drops
    tick("output-error refinement", 0, 1)
    ref = None
    if oe_terms:
        notes.append(f"{ch.name}: d^ is mostly estimation noise: the law's terms were chosen by "
                     f"output error on y (forward selection, BIC on the effective sample "
                     f"count Ny / colour), its coefficients and levels refined by output error")
    elif refined and any(law.spec[j][1] in _HINGE_KINDS
                         for j in np.flatnonzero(law.coef.any(0))):
        notes.append(f"{ch.name}: the law's saturation hinges alone, refined by output error "
                     f"on y (coefficients and levels), were chosen over the full d^ law")
    elif refined:
        notes.append(f"{ch.name}: the delayed d^ law was refined by output error on y before "
                     f"the channels were compared")
    elif law.npar <= OE_MAX_TERMS:
        ref = _refine_law_oe(law, base, ch, disc, y, u, x0_of[ch.name], C, D,
                             _noise_of(tr.filter_result, Q, R, kf.P_filt))
    else:
        notes.append(f"{ch.name}: the law has {law.npar} terms (> {OE_MAX_TERMS}): not refined "
                     f"by output error (each term costs a simulation per iteration)")
    if ref is not None:
        law_r, upd_r, ev_r = ref
        se_r = _se_from(disc(upd_r), u, x0_of[ch.name], y, C, D)
        if se_r < se_c:
            notes.append(f"{ch.name}: law refined by output error on y: estimation SE "
                         f"{se_c:.3g}% -> {se_r:.3g}%")
            law, upd, se_c, evidence = law_r, upd_r, se_r, ev_r
            tr = replace(tr, static=law)
    tick("output-error refinement", 1, 1)

    # 2c. the nominal's declared parameters refitted jointly with the law (and its spill
    # into the other state equations), against the parameters refitted alone
    joint = None
    if refit_parameters and free_parameters(base):
        tick("joint refit of the nominal's parameters", 0, 1)
        joint = _joint_refit(start, disc, law, ch, y, u, x0_of[ch.name], C, D, se_c,
                             int(evidence[1]) if evidence is not None else law.npar, notes,
                             declared, alone,
                             jr=jr_pick if law is pick[2].static else None)
        if joint is not None:
            alone, jr = joint
            _, _, sel_j, hinges_j = law_coordinates(jr.law)
            law = _with_intervals(jr.law, sel_j, hinges_j, jr.law_halfwidths, ch, base)
            upd, se_c = jr.model, jr.se
            tr = replace(tr, static=law)
            x0_of[ch.name] = jr.x_start
        tick("joint refit of the nominal's parameters", 1, 1)

    # 3. gate. The evidence for the law: its likelihood-ratio statistic on d^ (the BIC gain
    # plus its penalty), or for a delayed channel whose law was refined by output error, its
    # quasi likelihood ratio on the output error: a delayed d^ is mostly estimation noise,
    # and the coefficients were estimated on y, where the evidence is (module stage 3)
    Nd = N - 1 - SKIP
    if joint is not None:
        Ny = p * (N - SKIP)
        gain, penalty, colour = _refit_evidence(jr.residual, alone.se, jr.se, jr.nlaw)
        n_eff = Ny / colour
        gate.update({"oe_colour": colour, "se_estimation_parameters_only": alone.se})
        gate["evidence"] = ("output error: likelihood ratio of the law (nominal parameters "
                            "refitted with it) against the nominal parameters refitted alone, "
                            f"divided by the residual's colour ({colour:.3g}); {jr.nlaw} free "
                            f"law parameter(s), {Ny} residuals ({n_eff:.0f} independent)")
    elif (tr.relative_degree > 1 or oe_terms) and evidence is not None:
        wald, nfree = evidence
        Ny = p * (N - SKIP)
        gain, colour = _oe_likelihood_ratio(disc(upd), x0_of[ch.name], y, u,
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
    spill = joint[1].spill if joint is not None else ()
    effect = Effect(kind="static", order=0, formula=law.formula, channel=ch.name,
                    equations=tuple(ch.equations) + tuple(s for s, _, _ in spill),
                    nonlinear=law.nonlinear, linearized=False, law=law,
                    parameter_notes=_refit_notes(joint[1]) if joint is not None else ())
    if not (passed["bic"] and passed["se_drop"]):
        failed = [k for k, v in passed.items() if not v]
        if alone is not None:  # the declared parameters refitted alone, under their own gate
            rep_p = _parameters_only(alone, se_nom, dict(gate), bic_factor, min_se_drop, disc,
                                     y, u, y_val, u_val, Q, R, P0, lags, alpha, n, nsub,
                                     val_nom, u_mean, C, D, _report, notes,
                                     why=f"the best law ({ch.name}, static) failed the gate "
                                         f"against them: {', '.join(failed)}",
                                     law_gate=gate, cands=cands, tr=tr)
            if rep_p is not None:
                return rep_p
            notes.append("the declared parameters refitted alone failed their gate too "
                         f"(estimation SE {se_nom:.3g} % -> {alone.se:.3g} %)")
        nl = None
        if joint is not None:  # the refused joint refit, for inspection
            nl = NonlinearUpdate(model=sys, discrete=nominal_d, linearization=lin_nom,
                                 x_op=x_op, u_op=u_mean, operating_point=op_text,
                                 substeps=nsub, refused=joint[1])
        return _report(f"model error detected (UKF innovations not white), but the best "
                       f"candidate ({ch.name}, static) failed the gate: {', '.join(failed)}; "
                       f"model unchanged", True, cands=cands, tr=tr, nl=nl)

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
    table, nl = _updated(upd, disc, y, u, y_val, u_val, Q, R, P0, lags, alpha, n, nsub,
                         val_nom, u_mean, C, D,
                         parameters=joint[1].parameters if joint else (), spill=spill)
    x_op_u, lin_u = nl.x_op, nl.linearization
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
    if spill:
        where += " (and " + ", ".join(f"eq({s}) at {g:.2g}x" for s, g, _ in spill) + ")"
    changed = _changed(joint[1].parameters if joint else ())
    refit = ""
    if joint:
        refit = ("; nominal parameters refitted with it: " + (", ".join(changed) if changed
                                                              else "none changed beyond its "
                                                              "95 % interval"))
    msg = f"model error found in {where}: static effect{refit}; {describe_before_after(table)}"
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
    k0 = res.settled(SKIP)
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
