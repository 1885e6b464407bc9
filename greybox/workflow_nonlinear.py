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
3. **Choose and gate** as the linear pipeline: the lowest output-error
   criterion of the updated model (:func:`greybox.metrics.criterion_scores`; a
   model that declares ``params``: the best candidates by it are refitted
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
    check_covariance,
    check_flag,
    check_parsimony,
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
from .filters.kernels import predicted_covariance
from .nominal_refit import free_parameters, law_coordinates, refit_jointly
from .metrics import (
    OutputFit,
    WhitenessTest,
    autocorrelation,
    criterion_scores,
    innovation_test,
    output_fit,
)
from .nonlinear import (
    add_law,
    as_nonlinear,
    discretize_nonlinear,
    kinematic_identities,
    linear_output_map,
    linearize_at,
    rk4_substeps,
    rk4_substeps_for,
    simulate_nonlinear,
    with_unknown_inputs,
)
from .progress import ProgressClock
from .plant_adapter import NonlinearPlant, bounded, validation
from .recommend import recommend
from .trace import ChannelTrace, resolve_channel_spec
from .trace.intervals import hac_covariance, residual_colour, undetermined
from .terms import HINGE_KINDS, evaluate_terms, evaluator, linear_part, term_kind
from .trace.laws import fit_static, law_line
from .trace.oe import noise_floor, forward_select_oe
from .update import UpdatedModel
from .validate import ModelValidation, describe_before_after
from .records import CRITERION, CandidateScore, Decision, Effect, LoopReport, choice_note

__all__ = ["NonlinearUpdate", "close_the_loop_nonlinear", "nonlinear_update_of_linear"]

SKIP = 20
"""Leading samples left out of SE, PE and whiteness (the filters' transient)."""
_ALTERNATING = -0.5
"""Below this lag-1 autocorrelation d^ is taken to alternate sign (as in the linear trace)."""
FLOOR_NOTE = 2.0
"""An update whose estimation RMS simulation error is above this many times the noise
model's (:func:`greybox.trace.oe.noise_floor`) gets a note: the law may be partial."""
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
"""Quantiles of a state's filtered record where the output-error selection offers upper and
lower saturation hinges (the d^ law's are at ``greybox.trace.laws.SAT_QUANTILES``)."""
_LS_WINDOW = 1000
"""Samples simulated by the output-error selection's line search (a ranking: its cost is
then bounded; the fits use the whole record). A record with fewer samples after SKIP is
searched whole (:meth:`_LawOutputError.ls_window`)."""
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


@dataclass(frozen=True)
class _OEEvidence:
    """What an output-error fit says for its law: ``wald`` the Wald statistic of "all
    coefficients zero", ``nfree`` the parameters fitted (coefficients and hinge levels)."""

    wald: float
    nfree: int


@dataclass(frozen=True)
class _OEFit:
    """A law refined by output error (:func:`_refine_law_oe`): the law with its 95 %
    half-widths in ``ci``, the updated model ``f + G law`` and the fit's evidence."""

    law: object = field(repr=False)
    model: ct.NonlinearIOSystem = field(repr=False)
    evidence: _OEEvidence


@dataclass(frozen=True)
class _LawCandidate:
    """One scored candidate: a channel's static law and its updated model.

    Attributes
    ----------
    se : float
        Estimation SE [%] of the updated model simulated from the channel's
        start state at sample SKIP; inf when the simulation diverged.
    npar : int
        Terms of the law (its penalty on d^ counts them).
    trace : ChannelTrace
        The channel's trace; ``trace.static`` is the law.
    model : control.NonlinearIOSystem
        The updated model ``f(x, u) + G law(x, u)`` in the nominal's time base.
    refined : bool
        The law's coefficients (and hinge levels) were refined by output error.
    evidence : _OEEvidence or None
        The output-error fit's evidence, when the law had one.
    oe_terms : bool
        The law's terms were chosen by output error (d^ mostly estimation noise).
    fit : OutputFit or None
        Its output fit on the estimation record (what the criterion reads).
    """

    se: float
    npar: int
    trace: ChannelTrace = field(repr=False)
    model: ct.NonlinearIOSystem = field(repr=False)
    refined: bool = False
    evidence: _OEEvidence | None = None
    oe_terms: bool = False
    fit: OutputFit | None = field(default=None, repr=False)

    @property
    def law(self):
        """The candidate's static law (``trace.static``)."""
        return self.trace.static

    @property
    def channel(self):
        """The candidate's channel (``trace.channel``)."""
        return self.trace.channel


@dataclass(frozen=True)
class _Pick:
    """The chosen candidate, the nominal its joint refit starts from, and that refit when
    :func:`_pick_after_refit` already made it (a JointRefit; None otherwise)."""

    candidate: _LawCandidate
    start: ct.NonlinearIOSystem = field(repr=False)
    refit: object = field(default=None, repr=False)


@dataclass(frozen=True)
class _JointFit:
    """Stage 2c (:func:`_joint_refit`): the declared parameters refitted alone (``alone``)
    and jointly with the law and its spill (``refit``), both JointRefit records."""

    alone: object = field(repr=False)
    refit: object = field(repr=False)


_OP_TEXT = ("the mean of the {what} filtered states and of the inputs over the estimation "
            "record")


def _se_from(model_d, u, x_start, y, C, D) -> float:
    """Estimation SE [%] of a model simulated from x_start at sample SKIP (inf: diverged)."""
    return _fit_from(model_d, u, x_start, y, C, D).se


def _fit_from(model_d, u, x_start, y, C, D) -> OutputFit:
    """The :class:`~greybox.metrics.OutputFit` of a model simulated from x_start at sample
    SKIP (SE inf: diverged)."""
    try:
        sim = simulate_nonlinear(model_d, u[:, SKIP:], x0=x_start)
        ys = C @ sim.x + D @ u[:, SKIP:]
    except GreyboxError:
        ys = np.full(y[:, SKIP:].shape, np.nan)
    return output_fit(y[:, SKIP:], ys if bounded(ys) else np.full(ys.shape, np.nan))


def _prior(C: NDArray, D: NDArray, y: NDArray, u: NDArray) -> tuple[NDArray, NDArray]:
    """x0 from the first sample (least squares through C), P0 = I."""
    n = C.shape[1]
    x0 = np.linalg.lstsq(C, y[:, 0] - D @ u[:, 0], rcond=None)[0]
    return x0, np.eye(n)


def _settled_prior(model_d, x: NDArray, u: NDArray, Q: NDArray, R: NDArray):
    """The steady-state covariance (n, n) of the Kalman filter of ``model_d``'s linearization
    at ``(x, u)`` (a prior of the filter's own settled size, where P0 = I spreads the sigma
    points too far), or None where the Riccati equation has no solution."""
    lin = linearize_at(model_d, x, u)
    return predicted_covariance(np.asarray(lin.A, dtype=float), np.asarray(lin.C, dtype=float),
                                Q, R)


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
    fitted simulation. Returns an :class:`_OEFit`: the law with its 95 %
    half-widths in ``ci``, the updated model, and the evidence: ``wald`` the
    Wald statistic of "all coefficients zero" and ``nfree`` the parameters
    fitted (coefficients and hinge levels); None when the fit fails.
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
    evidence = _OEEvidence(wald=_wald_zero(sol.x[:nc], cov[:nc, :nc]), nfree=int(sol.x.size))
    return _OEFit(law=new, model=add_law(base, ch.G, new.evaluate, name=f"{base.name}_updated"),
                  evidence=evidence)


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
        lines.append(law_line(ch.labels[c], law.coef[c, idx],
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
        # per group: (evaluator of its terms, columns (None: all), coefficients (md, nsel,
        # ncolumns)); the evaluator built once, not at every sample
        self._groups = [(evaluator(spec, self._eps), None if len(ks) == K else np.asarray(ks),
                         np.stack([self._laws[k]._selected[0] for k in ks], axis=2))
                        for spec, ks in groups.items()]

    def __call__(self, x, u):
        if x.ndim == 1 or len(self._laws) == 1:
            return self._laws[0].evaluate(x, u)
        if len(self._groups) == 1:
            terms, _, coef = self._groups[0]
            return np.einsum("cjk,jk->ck", coef, terms(x, u))
        out = np.empty((self._groups[0][2].shape[0], x.shape[1]))
        for terms, ks, coef in self._groups:
            out[:, ks] = np.einsum("cjk,jk->ck", coef, terms(x[:, ks], u[:, ks]))
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
    T = uu.shape[1] if T is None else min(T, uu.shape[1])  # never past the record's end
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
            bad = ~(np.abs(X) < 1e100).all(axis=0)  # NaN and inf fail the comparison
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
        # the current sel's terms (evaluated at every sample: kinds looked up once per sel)
        self._terms = evaluator([], law.eps)
        self._mask, self._th = np.zeros((law.coef.shape[0], 0)), None

        def lawfun(x, u):  # the terms of the current sel at the current coefficient columns
            terms = self._terms(x, u)
            th = self._th if terms.ndim == 2 else self._th[:, 0]
            return self._mask @ (th * terms)

        self.model = disc(add_law(base, G, lawfun))
        self._par = dict(self.model.params or {})  # the model's declared parameters
        self._batched = None
        self._cache = (None, None, None)

    def _set(self, sel, TH):
        self._terms = evaluator([self.law.spec[j] for _, j in sel], self.law.eps)
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

    def jacobian(self, theta, sel):
        """The Jacobian of :meth:`resid` at theta (one batched simulation)."""
        return self._eval(np.asarray(theta, dtype=float), sel)[1]

    def fit(self, sel, start, max_nfev=20, trial: bool = False):
        """Levenberg-Marquardt from ``start`` (Jacobian by one batched simulation); every fit
        stops at 1e-4 (``trial`` changes nothing here)."""
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

    @property
    def ls_window(self) -> int:
        """Samples the line search simulates: ``_LS_WINDOW``, or the whole record after SKIP
        when it holds fewer (a window for speed, never past the record's end)."""
        return min(_LS_WINDOW, self.uu.shape[1])

    def line_search(self, sel, theta, cands, steps):
        """Each candidate's best coefficient on a grid, the current law held: (RSS, start).

        ``steps`` (ncands, ngrid): the coefficient values tried per candidate,
        all simulated at once over the first :meth:`ls_window` samples (a global version of
        the score test: the missing law's simulation is far from linear in a coefficient
        started at 0, and a delayed d^ can give it the wrong sign).
        """
        theta = np.asarray(theta, dtype=float)
        k, nc, ng = len(sel), len(cands), steps.shape[1]
        TH = np.zeros((k + nc, nc * ng))
        TH[:k] = theta[:, None]
        for q in range(nc):
            TH[k + q, q * ng:(q + 1) * ng] = steps[q]
        R = self._resids(self.simulate(list(sel) + list(cands), TH, self.ls_window))
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

    The noise model's is :func:`greybox.trace.oe.noise_floor` on the model's
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
    fl = noise_floor(A, C, Q, R, SKIP, N)
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
    (the quantiles :attr:`greybox.terms.HingeAbove.fine`, ``HingeBelow.fine`` of the filtered state: a stiff
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
    base_spec = [sp for sp in law.spec if sp[1] not in HINGE_KINDS] if batched else \
        list(law.spec)
    states = sorted({sp[2][0] for sp in law.spec if sp[1] in HINGE_KINDS}) if batched else []
    hinges = []
    names = list(base.state_labels)
    for i in states:
        for kind in HINGE_KINDS:
            hk = term_kind(kind)
            for lv in np.unique(np.nanquantile(x[i], hk.fine)):
                hinges.append(hk.entry(i, names[i], lv))
    spec = tuple(base_spec[:-1] + hinges + base_spec[-1:]) if base_spec and \
        term_kind(base_spec[-1][1]).constant else tuple(base_spec + hinges)
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
            key = (cs[q][0], sp[1], sp[2][0]) if sp[1] in HINGE_KINDS else cs[q]
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
        cost=lambda cj: 2 if law.spec[cj[1]][1] in HINGE_KINDS else 1, factor=factor)
    if not sel:
        return None
    coef = np.zeros_like(law.coef)
    for (c, j), t in zip(sel, theta):
        coef[c, j] = t
    nonlin = any(not term_kind(law.spec[j][1]).linear for _, j in sel)
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
    the held-out half as well. ``chosen`` is the :class:`_OEFit` of
    :func:`_refine_law_oe`.
    """
    law = chosen.law
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
                notes.append(Decision("generate", ch.name, f"the term {law.spec[j][0]} chosen by "
                                      "output error does not improve the simulation of "
                                      "held-out samples: dropped"))
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
    while ref is not None and ref.law.npar > 1:
        new = ref.law
        t = np.abs(new.coef) / np.where(np.isfinite(new.ci) & (new.ci > 0), new.ci, np.inf)
        # not a hinge: a stiff hinge's simulation is far from linear in its coefficient
        # (barely determined while no hinge is far worse; the selection's BIC took it)
        hinge = np.array([sp[1] in HINGE_KINDS for sp in new.spec])[None, :]
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
    """Whether the law chosen by output error ``oe`` has a lower output-error BIC than ``entry``
    (both :class:`_LawCandidate`).

    ``n log(SE^2) + k log(n)`` for each (SE [%] of the estimation simulation, k
    the free parameters: coefficients and hinge levels), n = Ny / c with c the
    colour of the chosen law's residual (:func:`_residual_colour`).
    """
    def nfree(e):
        return int(e.evidence.nfree) if e.evidence is not None else int(e.law.npar)

    se_o, se_e = oe.se, entry.se
    if not np.isfinite(se_o):
        return False
    if not np.isfinite(se_e):
        return True
    try:
        sim = simulate_nonlinear(disc(oe.model), u[:, SKIP:], x0=x0)
        colour = _residual_colour(y[:, SKIP:] - C @ sim.x - D @ u[:, SKIP:])
    except GreyboxError:
        colour = 1.0
    n = y[:, SKIP:].size / colour
    return bool(n * np.log(se_o**2) + nfree(oe) * np.log(n)
                < n * np.log(se_e**2) + nfree(entry) * np.log(n))


def _joint_refit(base, disc, law, ch, y, u, x_start, C, D, se_fixed: float, nfree_fixed: int,
                 notes: list, declared: dict, alone=None, jr=None):
    """Stage 2c: the :class:`_JointFit` of the nominal's declared parameters, or None.

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
        notes.append(Decision("refit", ch.name, "the nominal's declared parameters could not be "
                              "refitted with the law (the output-error fit failed); kept"))
        return None
    n = yy.size / _residual_colour(jr.residual)
    bic_j = n * np.log(jr.se**2) + jr.nfree * np.log(n)
    bic_f = n * np.log(se_fixed**2) + nfree_fixed * np.log(n) if np.isfinite(se_fixed) \
        else np.inf
    text = (f"nominal parameters refitted with the law by output error "
            f"(estimation SE {jr.se:.3g} %, the law on the fixed nominal {se_fixed:.3g} %, "
            f"the parameters alone {alone.se:.3g} %): {jr.parameter_text()}")
    if jr.spill:
        text += f"; the law also enters {jr.spill_text()}"
    if not bic_j < bic_f:
        notes.append(Decision("refit", ch.name, text + " -- not kept: higher output-error BIC "
                                                       "than the law on the fixed nominal"))
        return None
    notes.append(Decision("refit", ch.name, text))
    return _JointFit(alone=alone, refit=jr)


_REFIT_NEAR = 3  # candidates within one parameter's evidence of the best, refitted jointly


def _pick_after_refit(near, starts, disc, y, u, x0_of, C, D, notes):
    """A :class:`_Pick`: of the candidates the criterion does not separate (best first),
    the one whose law, refitted jointly with the nominal's declared parameters, has the
    lowest output-error BIC, the nominal its refit started from, and that refit.

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
        ch = s.channel
        best = (None, starts[0])
        for b in starts:
            try:
                jr = refit_jointly(b, disc, yy, uu, x0_of[ch.name], C, D, law=s.law, G=ch.G)
            except (GreyboxError, np.linalg.LinAlgError, ValueError):
                jr = None
            if jr is not None and jr.law is not None and np.isfinite(jr.se) and (
                    best[0] is None or jr.se < best[0].se):
                best = (jr, b)
        fits.append(best)
    done = [jr for jr, _ in fits if jr is not None]
    if not done:
        return _Pick(candidate=near[0], start=starts[0])
    n = yy.size / max(_residual_colour(jr.residual) for jr in done)
    bic = [n * np.log(jr.se ** 2) + jr.nfree * np.log(n) if jr is not None else np.inf
           for jr, _ in fits]
    i = int(np.argmin(bic))
    notes.append(Decision(
        "choose", "", "candidates the criterion does not separate compared with the nominal's "
        "declared parameters refitted with each law (output-error BIC, lower is better): "
        + ", ".join(f"{s.channel.name} {b:.1f} (SE {f[0].se:.3g} %)"
                    if f[0] is not None else f"{s.channel.name} failed"
                    for s, b, f in zip(near[:_REFIT_NEAR], bic, fits))
        + f"; chosen {near[i].channel.name}"))
    return _Pick(candidate=near[i], start=fits[i][1], refit=fits[i][0])


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


def _wald_zero(theta: NDArray, cov: NDArray) -> float:
    """``theta^T cov^-1 theta``: the Wald statistic of "no law" (0 when cov is unusable)."""
    if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(theta))):
        return 0.0
    try:
        w = float(theta @ np.linalg.solve(cov, theta))
    except np.linalg.LinAlgError:
        return 0.0
    return w if np.isfinite(w) and w > 0 else 0.0


def _level_text(spec_j, h: float) -> str:
    """A hinge's name with its level's 95 % interval: ``max(x1 - (7.995 ± 0.012), 0)``.

    The half-width is the output-error covariance's (:func:`_refine_law_oe`,
    the level fitted with the coefficients); the plain name when it is not
    finite or wider than ``max(|level|, 1)`` (a degenerate covariance: a hinge
    that already clips barely moves the simulation, e.g. ``± 1.6e+70`` on
    the simulated overflow's seed 3).
    """
    return term_kind(spec_j[1]).interval_name(spec_j, h)


def _hinge_law(law, d, x, u, sys, labels, units, align, relative):
    """The law reduced to its saturation hinges (refitted on d^), or None without one."""
    idx = [j for j, sp in enumerate(law.spec) if sp[1] in HINGE_KINDS and
           np.any(law.coef[:, j])]
    if not idx or len(idx) == law.npar:
        return None
    terms = _eval_law_terms(law, x, u)[idx]
    return fit_static(d, x, u, sys, True, labels, units, align, relative, whiten=True,
                       prebuilt=(terms, [law.spec[j] for j in idx], law.eps))


def _eval_law_terms(law, x, u):
    """Every candidate term of ``law`` on (x, u), shape (nterms, nsteps)."""
    return evaluate_terms(law.spec, law.eps, x, u)


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
        Deprecated, no effect (a value other than 1.1 warns): candidates are
        compared by one output-error criterion (``records.CRITERION``).
    min_se_drop : float
        The update must bring the estimation SE below this fraction.
    bic_factor : float
        The law's evidence must exceed this many times its BIC penalty: its
        likelihood ratio on d^, or for a delayed channel (r = 2) its quasi
        likelihood ratio on the output error (see the module's stage 3).
    substeps : int, optional
        RK4 sub-steps per sample for a continuous model (default from
        :func:`greybox.rk4_substeps` at the operating point, doubled by
        :func:`greybox.rk4_substeps_for` until the estimation record's simulation
        moves by less than a tenth of each output's noise deviation).
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
    P = _prepare(sys, y, u, y_val, u_val, Q=Q, R=R, dt=dt, channels=channels,
                 nonlinear=nonlinear, alpha=alpha, lags=lags, parsimony=parsimony,
                 min_se_drop=min_se_drop, bic_factor=bic_factor, substeps=substeps,
                 refit_parameters=refit_parameters, progress=progress)
    s = _NonlinearPass(P)
    r = s.residual()
    if r.white.all_white:
        return s.no_error(r)
    rep = s.parameters_alone(r)
    if rep is not None:  # the refitted parameters alone leave white innovations
        return s.recommended(r, rep)
    s.trace_channels(r)
    pick = s.choose()
    if pick is None:
        return s.unexplained(r)
    v = s.judge(r, s.joint_refit(pick, s.refine(pick)))
    if not v.passed:
        return s.refused(r, v)
    s.caveats(v)
    try:
        ba = s.validate(r, v)
    except ModelError as e:  # the updated model's predictor diverged on the validation record
        return s.diverged(r, v, e)
    return s.recommended(r, s.report(r, v, ba))


# --------------------------------------------------------------------------- the stages
@dataclass(frozen=True)
class _Settings:
    """The options of :func:`close_the_loop_nonlinear`, checked once at the boundary (see
    there)."""

    alpha: float
    lags: int
    parsimony: float
    min_se_drop: float
    bic_factor: float
    nonlinear: bool
    refit_parameters: bool
    channels: object = None  # the user's channel spec; None: every channel


@dataclass(frozen=True)
class _Discretize:
    """A model in the discrete time of the data, as every row of the table simulates it:
    RK4 with ``substeps`` sub-steps per sample (inputs and d held) for a ``continuous``
    model, a discrete model as it is (then ``substeps`` = 0)."""

    continuous: bool
    dt: float
    substeps: int

    def __call__(self, model):
        if self.continuous:
            return discretize_nonlinear(model, self.dt, substeps=self.substeps)
        return model


@dataclass(frozen=True)
class _Problem:
    """One call's checked data: the model as given, its nonlinear form, the records, noise.

    ``sys`` is the model as given, ``base`` the NonlinearIOSystem (``as_nonlinear``) with
    the linear output map ``C, D``; ``disc`` discretizes a model as the table does and
    ``nominal_d`` is ``disc(base)``; ``y, u`` (noutputs/ninputs, nsteps) the estimation
    record, ``y_val, u_val`` the validation record; ``x_guess, P0`` the filters' prior
    from the first sample (:func:`_prior`), ``u_mean`` (ninputs,) the inputs' mean.
    """

    sys: object = field(repr=False)
    base: ct.NonlinearIOSystem = field(repr=False)
    C: NDArray[np.float64] = field(repr=False)
    D: NDArray[np.float64] = field(repr=False)
    y: NDArray[np.float64] = field(repr=False)
    u: NDArray[np.float64] = field(repr=False)
    y_val: NDArray[np.float64] = field(repr=False)
    u_val: NDArray[np.float64] = field(repr=False)
    Q: NDArray[np.float64] = field(repr=False)
    R: NDArray[np.float64] = field(repr=False)
    dt: float
    disc: _Discretize
    nominal_d: ct.NonlinearIOSystem = field(repr=False)
    x_guess: NDArray[np.float64] = field(repr=False)
    P0: NDArray[np.float64] = field(repr=False)
    u_mean: NDArray[np.float64] = field(repr=False)
    settings: _Settings
    tick: object = field(repr=False)

    @property
    def cont(self) -> bool:
        """The model is continuous-time (discretized with RK4)."""
        return self.disc.continuous

    @property
    def nsub(self) -> int:
        """RK4 sub-steps per sample (0 for a discrete model)."""
        return self.disc.substeps


@dataclass(frozen=True)
class _Residual:
    """Stage 1: the nominal UKF's residual on the estimation record.

    ``white`` the Ljung-Box test of its one-step innovations (from SKIP),
    ``se_nom`` the nominal's estimation SE [%], ``val_nom`` its validation row,
    ``x_op`` (nstates,) the mean filtered state (the operating point),
    ``lin_nom`` the discrete nominal's linearization there and ``lin_cont`` the
    model's own (continuous when it is), ``crit`` the stated criterion.
    """

    white: WhitenessTest
    se_nom: float
    val_nom: ModelValidation = field(repr=False)
    x_op: NDArray[np.float64]
    lin_nom: ct.StateSpace = field(repr=False)
    lin_cont: ct.StateSpace = field(repr=False)
    crit: str


@dataclass(frozen=True)
class _DHat:
    """Stage 2 for one channel: its unknown-input filter and d^ aligned with x^ and u.

    ``d`` (md, nsteps') estimates ``sum_i align[:, i] d[j + i]`` (r = 2: x and u
    carry one more column); ``d_fit`` is what the law is fitted on (the mean of
    consecutive samples when d^ alternates sign, ``alt``, its lag-1
    autocorrelation ``r1``) and ``weights`` the alignment that fit uses (None for
    r = 1 without alternation).
    """

    model: ct.NonlinearIOSystem = field(repr=False)
    result: FilterResult = field(repr=False)
    r: int
    align: NDArray[np.float64]
    d: NDArray[np.float64] = field(repr=False)
    x: NDArray[np.float64] = field(repr=False)
    u: NDArray[np.float64] = field(repr=False)
    d_fit: NDArray[np.float64] = field(repr=False)
    weights: NDArray[np.float64] | None
    r1: float
    alt: bool


@dataclass(frozen=True)
class _Evidence:
    """The law's evidence for the gate: its likelihood ratio ``gain`` and BIC ``penalty``."""

    gain: float
    penalty: float


@dataclass(frozen=True)
class _Verdict:
    """Stage 3: the candidate as refined and refitted, the gate's call, and the ratio of its
    mean squared simulation error to the noise model's (a diagnostic)."""

    candidate: _LawCandidate
    passed: bool
    floor_ratio: float


@dataclass(frozen=True)
class _BeforeAfter:
    """Stage 4: the validation table (nominal and updated rows) and the NonlinearUpdate."""

    table: dict = field(repr=False)
    update: NonlinearUpdate = field(repr=False)


def _prepare(sys, y, u, y_val, u_val, *, Q, R, dt, channels, nonlinear, alpha, lags,
             parsimony, min_se_drop, bic_factor, substeps, refit_parameters,
             progress) -> _Problem:
    """Check every argument of :func:`close_the_loop_nonlinear` once; the problem, its
    settings, and the RK4 sub-step count at the operating point the outputs suggest."""
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
    nonlinear = check_flag(nonlinear, "nonlinear")
    refit_parameters = check_flag(refit_parameters, "refit_parameters")
    parsimony = check_parsimony(parsimony)
    alpha = check_positive(alpha, "alpha")
    min_se_drop = check_positive(min_se_drop, "min_se_drop")
    bic_factor = check_positive(bic_factor, "bic_factor")
    if not 0 < alpha < 1 or not 0 < min_se_drop <= 1:
        raise DataError(f"need 0 < alpha < 1, 0 < min_se_drop <= 1; found "
                        f"{alpha}, {min_se_drop}")
    if substeps is not None:
        substeps = check_positive(substeps, "substeps", integer=True)

    # operating point of the channels' linearization and of the RK4 sub-step count
    x_guess, P0 = _prior(C, D, y, u)
    u_mean = u.mean(axis=1) if m else np.zeros(0)
    x_mean_y = np.linalg.lstsq(C, y.mean(axis=1) - D @ u_mean, rcond=None)[0]
    nsub = 0
    if cont:  # the local count, doubled until the record's simulation no longer moves by
        # a tenth of the noise (then discretization is no detectable model error)
        nsub = substeps or rk4_substeps_for(
            base, dt, u, x0=x_guess, tol=0.1 * np.sqrt(np.diag(R)),
            start=rk4_substeps(base, dt, x_op=x_mean_y, u_op=u_mean))
    disc = _Discretize(continuous=cont, dt=dt, substeps=nsub)
    settings = _Settings(alpha=alpha, lags=lags, parsimony=parsimony, min_se_drop=min_se_drop,
                         bic_factor=bic_factor, nonlinear=nonlinear,
                         refit_parameters=refit_parameters, channels=channels)
    return _Problem(sys=sys, base=base, C=C, D=D, y=y, u=u, y_val=y_val, u_val=u_val, Q=Q,
                    R=R, dt=dt, disc=disc, nominal_d=disc(base), x_guess=x_guess, P0=P0,
                    u_mean=u_mean, settings=settings, tick=tick)


def _gate(gate: dict, S: _Settings, gain: float, penalty: float, se_updated: float,
          se_nom: float) -> bool:
    """The gate (module stage 3), recorded in ``gate``: True when the evidence ``gain``
    exceeds ``bic_factor`` times its ``penalty`` and the estimation SE drops below
    ``min_se_drop`` times the nominal's (the innovations are known not to be white)."""
    passed = {"whiteness": True, "bic": gain > S.bic_factor * penalty,
              "se_drop": se_updated < S.min_se_drop * se_nom}
    gate.update({"bic_gain": gain, "bic_penalty": penalty, "bic_factor": S.bic_factor,
                 "se_estimation_updated": se_updated, "min_se_drop": S.min_se_drop,
                 "passed": passed})
    return bool(passed["bic"] and passed["se_drop"])


def _failed(gate: dict) -> list[str]:
    """The conditions a recorded gate failed."""
    return [k for k, ok in gate["passed"].items() if not ok]


class _NonlinearPass:
    """Close the loop on a nonlinear nominal; the stages are methods, called in order by
    :func:`close_the_loop_nonlinear`.

    What they decide is kept in ``cands`` (every candidate's score, for the report),
    ``scored`` (the :class:`_LawCandidate` in play), ``x0_of`` (where each channel's
    simulations start), ``gate`` and ``decisions`` (the decision trail). ``base`` and
    ``kf`` are the nominal the trace runs on and its UKF: the declared parameters
    refitted alone when that lowered the estimation SE (stage 1b, ``alone``);
    ``joint`` the refit of stage 2c when it was kept.
    """

    def __init__(self, P: _Problem):
        self.P, self.S = P, P.settings
        self.base, self.kf = P.base, None
        self.declared, self.alone, self.joint = {}, None, None
        self.cands: list[CandidateScore] = []
        self.scored: list[_LawCandidate] = []
        self.x0_of: dict = {}
        self.gate: dict = {}
        self.decisions: list[Decision] = []
        if P.cont:
            self.note("residual", "", f"continuous model discretized with RK4, {P.nsub} "
                                      f"sub-step(s) per sample (inputs and d held over the "
                                      f"sample); every model in the table uses it")

    def note(self, stage: str, subject: str, reason: str) -> None:
        """Record a decision of ``stage`` about ``subject`` (a channel, or "": the model)."""
        self.decisions.append(Decision(stage, subject, reason))

    # ------------------------------------------------------------------ reports
    def _nominal_update(self, r: _Residual, refused=None) -> NonlinearUpdate:
        """The NonlinearUpdate of the unchanged model (with a refused joint refit, if any)."""
        P = self.P
        return NonlinearUpdate(model=P.sys, discrete=P.nominal_d, linearization=r.lin_nom,
                               x_op=r.x_op, u_op=P.u_mean,
                               operating_point=_OP_TEXT.format(what="nominal UKF's"),
                               substeps=P.nsub, refused=refused)

    def _report(self, r: _Residual, msg, detected, *, updated=False, effect=None, ch=None,
                tr=None, table=None, model=None, nl=None, gate=None) -> LoopReport:
        P = self.P
        nl = nl or self._nominal_update(r)
        model = model or UpdatedModel(sys=r.lin_nom, Q=P.Q, R=P.R, order=P.base.nstates,
                                      kind="nominal")
        return LoopReport(model_error_detected=detected, updated=updated, message=msg,
                          residual=r.white, effect=effect or Effect(kind="none"), channel=ch,
                          candidates=tuple(self.cands),
                          gate=self.gate if gate is None else gate, criterion=r.crit,
                          nominal=r.lin_nom, model=model,
                          table=table or {"nominal": r.val_nom, "updated": r.val_nom},
                          trace=tr, decisions=tuple(self.decisions), nonlinear=nl)

    def recommended(self, r: _Residual, rep: LoopReport) -> LoopReport:
        """6. The update as it is when it predicts the validation record better; else the
        nominal model kept, "not recommended" first (:func:`greybox.recommend.recommend`)."""
        out = recommend(rep, self.P.Q, self.P.R)
        return out if out is rep else replace(out, nonlinear=self._nominal_update(r))

    def no_error(self, r: _Residual) -> LoopReport:
        """The report when the nominal UKF's innovations are white: nothing to find."""
        S = self.S
        self.gate["passed"] = {"whiteness": False}
        return self._report(r, "no significant model error: the nominal UKF's one-step "
                               f"innovations are white and zero-mean on every output "
                               f"(Ljung-Box, {S.lags} lags, and the mean's t-test; all p >= "
                               f"{S.alpha:g}); model unchanged", False)

    def unexplained(self, r: _Residual) -> LoopReport:
        """The report when no candidate channel has a finite estimation SE."""
        self.gate["passed"] = {"whiteness": True, "trace": False}
        return self._report(r, "model error detected, but no candidate channel could explain "
                               "it (see candidates)", True)

    # ------------------------------------------------------------------ 1. residual
    def residual(self) -> _Residual:
        """1. The nominal UKF's innovations (whiteness), its SE, the operating point."""
        P, S = self.P, self.S
        n = P.base.nstates
        P.tick("residual of the nominal model", 0, 1)
        val_nom = validation(NonlinearPlant(P.nominal_d, P.P0, order=n,
                                            x0=_prior(P.C, P.D, P.y_val, P.u_val)[0]),
                             P.y_val, P.u_val, Q=P.Q, R=P.R, name="nominal", lags=S.lags,
                             alpha=S.alpha, skip=SKIP)
        kf = NonlinearPlant(P.nominal_d, P.P0, order=n, x0=P.x_guess).filter(P.y, P.u, Q=P.Q,
                                                                           R=P.R)
        white = innovation_test(kf.innovations[:, SKIP:], S.lags, alpha=S.alpha)
        se_nom = _se_from(P.nominal_d, P.u, kf.x_filt[:, SKIP], P.y, P.C, P.D)
        x_op = kf.x_filt[:, SKIP:].mean(axis=1)
        lin_nom = linearize_at(P.nominal_d, x_op, P.u_mean)
        lin_cont = linearize_at(P.base, x_op, P.u_mean) if P.cont else lin_nom
        self.kf = kf
        self.gate.update({"whiteness_pvalue": white.pvalue, "mean_pvalue": white.mean_pvalue,
                          "alpha": S.alpha, "se_estimation_nominal": se_nom, "measure": "SE"})
        P.tick("residual of the nominal model", 1, 1)
        return _Residual(white=white, se_nom=se_nom, val_nom=val_nom, x_op=x_op,
                         lin_nom=lin_nom, lin_cont=lin_cont,
                         crit=CRITERION)

    # ------------------------------------------------------------------ 1b. parameters
    def parameters_alone(self, r: _Residual) -> LoopReport | None:
        """1b. The declared parameters refitted alone by output error: a nominal that is only
        mis-calibrated is said so (the report), else the trace runs on the refitted nominal
        when it simulates better (None)."""
        P, S = self.P, self.S
        self.declared = free_parameters(P.base)
        if not (S.refit_parameters and self.declared):
            return None
        P.tick("nominal parameters refitted alone", 0, 1)
        alone = refit_jointly(P.base, P.disc, P.y[:, SKIP:], P.u[:, SKIP:],
                              self.kf.x_filt[:, SKIP], P.C, P.D)
        if alone is not None and alone.se < r.se_nom:
            self.note("refit", "", f"the nominal's declared parameters refitted alone by output "
                                   f"error: estimation SE {r.se_nom:.3g} % -> {alone.se:.3g} % "
                                   f"({alone.parameter_text()}); the trace runs on this refitted "
                                   f"nominal")
            self.alone, self.base = alone, alone.model
            self.kf = ukf(P.disc(self.base), P.y, P.u, Q=P.Q, R=P.R, x0=P.x_guess, P0=P.P0)
            white_p = innovation_test(self.kf.innovations[:, SKIP:], S.lags, alpha=S.alpha)
            if white_p.all_white:
                return self.parameters_only(r, self.gate)
        P.tick("nominal parameters refitted alone", 1, 1)
        return None

    def parameters_only(self, r: _Residual, gate: dict,
                        why="the refitted model's UKF innovations are white", law_gate=None,
                        tr=None) -> LoopReport | None:
        """The report when the declared parameters refitted alone are the update.

        Gate (:func:`_gate`, recorded in ``gate``): the likelihood ratio of the
        refitted parameters against the declared ones on the estimation outputs'
        simulation, divided by the residual's colour, above ``bic_factor`` times
        ``k log(Ny / c)`` (k the parameters), and the estimation SE below
        ``min_se_drop`` times the nominal's. Reached also when the best law failed
        its gate against the refitted parameters (``law_gate``: then None when this
        gate fails too, and the law's evidence is kept as ``gate["law_bic_gain"]``,
        ``gate["law_bic_penalty"]``).
        """
        P, alone = self.P, self.alone
        if law_gate is not None:
            gate["law_bic_gain"] = float(law_gate["bic_gain"])
            gate["law_bic_penalty"] = float(law_gate["bic_penalty"])
        gain, penalty, colour = _refit_evidence(alone.residual, r.se_nom, alone.se,
                                                len(alone.parameters))
        gate.update({"oe_colour": colour, "se_estimation_parameters_only": alone.se,
                     "evidence": "output error: likelihood ratio of the refitted parameters "
                                 "against the declared ones, divided by the residual's colour"})
        if not _gate(gate, self.S, gain, penalty, alone.se, r.se_nom):
            if law_gate is not None:
                return None
            return self._report(r, "model error detected (UKF innovations not white); the "
                                   "declared parameters refitted alone failed the gate: "
                                   f"{', '.join(_failed(gate))} ({why}); model unchanged",
                                True, tr=tr, gate=gate)
        changed = _changed(alone.parameters)
        ba = self._updated(r, alone.model, parameters=alone.parameters)
        what = ", ".join(changed) if changed else "none beyond its 95 % interval"
        return self._report(r, f"model error found in the nominal's parameters (no law needed: "
                               f"{why}): {what}; {describe_before_after(ba.table)}", True,
                            updated=True, tr=tr, gate=gate,
                            effect=Effect(kind="parameters", formula=alone.parameter_text(),
                                          parameter_notes=_refit_notes(alone)),
                            table=ba.table, nl=ba.update,
                            model=UpdatedModel(sys=ba.update.linearization, Q=P.Q, R=P.R,
                                               order=P.base.nstates, kind="parameters"))

    # ------------------------------------------------------------------ 2. trace
    def trace_channels(self, r: _Residual) -> None:
        """2. Trace every candidate channel with the unknown-input UKF; static laws on d^."""
        P = self.P
        chans = resolve_channel_spec(r.lin_cont, self.S.channels)
        self.note("screen", "", "nonlinear nominal: candidate channels from its linearization at "
                                "the operating point; static laws only (dynamic subsystem laws are "
                                "linear and not offered)")
        if self.S.channels is None and P.cont:  # a definition is never a candidate channel
            k = np.unique(np.linspace(SKIP, P.y.shape[1] - 1, 64).astype(int))
            defs = set(kinematic_identities(P.base, self.kf.x_filt[:, k], P.u[:, k]))
            if defs:
                chans = [c for c in chans if not set(c.equations) & defs]
                self.note("screen", "", "kinematic identities, definitions rather than candidate "
                                        "channels: " + ", ".join(
                                            f"eq({d})" for d in P.base.state_labels if d in defs))
        for kc, ch in enumerate(chans):
            P.tick("trace candidate channels", kc, len(chans))
            self.trace_channel(r, ch, kc, len(chans))
        P.tick("trace candidate channels", len(chans), len(chans))

    def _dhat(self, r: _Residual, ch) -> _DHat | None:
        """d^ of one channel (the unknown-input UKF, or the delayed one for r = 2) aligned
        with x^ and u; None, the candidate scored, when it cannot be estimated."""
        P = self.P
        labels = list(ch.labels)
        rd = 1
        try:
            model_cd = P.disc(with_unknown_inputs(self.base, ch.G, labels))
            rd, G_op, align = _delay_of(model_cd, labels, r.x_op, P.u_mean, P.Q, P.R)
            if rd == 1:
                res = ui_ukf(model_cd, P.y, P.u, unknown=labels, Q=P.Q, R=P.R, x0=P.x_guess,
                             P0=P.P0)
            else:
                res = delayed_ui_ukf(model_cd, P.y, P.u, unknown=labels, Q=P.Q, R=P.R,
                                     x0=P.x_guess, P0=P.P0, G=G_op, relative_degree=rd)
        except RankConditionError as e:  # (17) fails: d is not observable in this channel
            self.cands.append(CandidateScore(ch.name, "-", 0, np.inf, 0, "skipped", str(e)))
            return None
        except (GreyboxError, np.linalg.LinAlgError) as e:
            self.cands.append(CandidateScore(ch.name, "-", 0, np.inf, 0, "failed",
                                             (f"delayed (r = {rd}) estimate: " if rd > 1 else "")
                                             + str(e)))
            return None
        # d^[:, j] estimates sum_i align[:, i] d[j + i]; x and u carry r - 1 more columns
        N = P.y.shape[1]
        d = res.d_est[:, SKIP:N - rd]
        x = res.x_filt[:, SKIP:N - 1]
        uw = P.u[:, SKIP:N - 1]
        if rd == 1:
            x = x[:, :d.shape[1]]
            uw = uw[:, :d.shape[1]]
        # d^ alternating sign (a channel seen through a ZOH zero near z = -1, e.g. a
        # velocity equation through positions only) from the r = 1 filter (the delayed
        # one was not better): fit on the mean of consecutive samples, as the linear
        # trace does
        r1 = float(np.min(autocorrelation(d, 1)[:, 1])) if rd == 1 and d.shape[1] > 2 else 0.0
        alt = r1 < _ALTERNATING  # then the mean of two samples, terms weighted alike
        if rd == 1 and not alt and P.disc.continuous:
            # d^[j] is held over sample j, so it estimates the continuous law's mean over
            # the sample: its terms at the sample's midpoint state, not at its start (at
            # the start, a law in v picks up c dt / 2 times the acceleration, i.e. every
            # term of the nominal's own equation: -0.445 v came with p, p^3 and F at 0.6 %)
            x = 0.5 * (x + res.x_filt[:, SKIP + 1:SKIP + 1 + x.shape[1]])
        return _DHat(model=model_cd, result=res, r=rd, align=align, d=d, x=x, u=uw,
                     d_fit=0.5 * (d[:, 1:] + d[:, :-1]) if alt else d,
                     weights=np.full((d.shape[0], 2), 0.5) if alt else
                     (align if rd > 1 else None), r1=r1, alt=alt)

    def trace_channel(self, r: _Residual, ch, kc: int, nch: int) -> None:
        """2. One channel: d^ and its static law; when d^ is mostly estimation noise also the
        terms chosen by output error, the lower output-error BIC of the two kept; a law with
        a saturation hinge also competes reduced to its hinges."""
        P, S = self.P, self.S
        dh = self._dhat(r, ch)
        if dh is None:
            return
        labels = list(ch.labels)
        try:
            law = fit_static(dh.d_fit, dh.x, dh.u, r.lin_cont, S.nonlinear, labels, ch.units,
                              dh.weights, ch.relative, whiten=dh.r > 1,
                              saturation=S.nonlinear and dh.r > 1)
        except (GreyboxError, np.linalg.LinAlgError) as e:  # e.g. no finite d^ left
            self.cands.append(CandidateScore(ch.name, "static", 0, np.inf, 0, "failed",
                                             f"static law on d^: {e}"))
            return
        if dh.alt:
            self.note("trace", ch.name, f"d^ alternates sign (lag-1 autocorrelation "
                                        f"{dh.r1:.2f}): the static law is fitted on the mean of "
                                        f"consecutive samples")
        if dh.r > 1:
            self.note("trace", ch.name,
                      f"relative degree {dh.r} (delayed unscented estimate, "
                      f"greybox.delayed_ui_ukf): d^[j] estimates " + ", ".join(
                          f"{labels[c]}: " + " + ".join(
                              f"{dh.align[c, i]:.3g}*d[j+{i}]" for i in range(dh.r))
                          for c in range(len(labels))))
        tr = ChannelTrace(channel=ch, status="ok", model=dh.model, filter_result=dh.result,
                          static=law, relative_degree=dh.r)
        noise_ch = _noise_of(dh.result, P.Q, P.R, self.kf.P_filt)
        # d^ mostly estimation noise (delayed, or an r = 1 estimate barely above its own
        # variance): the law's terms are chosen by output error too, one more start beside
        # d^'s law (the linear trace's rule, trace.channel_trace)
        noisy = dh.r > 1 or _excess(dh.result, dh.d) < _LOW_SNR
        # where the channel's simulations start: for a noisy channel the state (the
        # channel's filter's or the nominal UKF's) whose nominal simulation follows y best
        # over the first samples (a delayed filter's x^ at SKIP can be far off)
        x0c = _start_state(P.nominal_d, (dh.result.x_filt[:, SKIP], self.kf.x_filt[:, SKIP]),
                           P.y, P.u, P.C, P.D) if noisy else dh.result.x_filt[:, SKIP]
        self.x0_of[ch.name] = x0c
        chosen = self._oe_terms(law, ch, dh, x0c, noise_ch, kc, nch) if noisy else None
        dead = ch.md > 1 and bool(np.any(np.all(law.coef == 0, axis=1)))
        if law.npar == 0 and chosen is None:
            self.cands.append(CandidateScore(ch.name, "static", 0, np.inf, 0, "skipped",
                                             "no law term explains d^" + (
                                                 ", nor any by output error" if noisy else "")))
            return
        if dead and chosen is None:
            self.cands.append(CandidateScore(ch.name, "static", 0, np.inf, law.npar,
                                             "redundant", "a component of d has no term"))
            return
        entry = self._dhat_candidate(tr, dh, x0c, noise_ch) if law.npar and not dead else None
        if chosen is not None:
            entry = self._against_oe(entry, chosen, tr, x0c)
        why = ("terms chosen by output error on y" if entry.oe_terms else
               "delayed d^ law refined by output error" if entry.refined else "")
        self.cands.append(CandidateScore(ch.name, "static", 0, entry.se, entry.npar, "ok", why))
        self.scored.append(entry)
        self._hinge_candidate(r, entry, dh, x0c, noise_ch)

    def _oe_terms(self, law, ch, dh: _DHat, x0c, noise_ch, kc: int, nch: int) -> _OEFit | None:
        """The law's terms chosen by output error on y (:func:`_select_law_oe`), refined with
        weak terms pruned, and terms that do not predict held-out samples dropped."""
        P = self.P
        P.tick("output-error term selection", kc, nch)
        try:
            law_o = _select_law_oe(law, self.base, ch, P.disc, P.y, P.u, x0c, P.C, P.D,
                                   noise_ch, dh.d_fit, dh.x, dh.u, dh.weights, self.S.bic_factor)
        except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
            # never dropped silently: the stage says it did not run, and why
            self.note("generate", ch.name, f"the law's terms could not be chosen by output "
                                           f"error on y ({type(e).__name__}: {e}); the "
                                           f"channel competes with d^'s law alone")
            return None
        nls = P.y.shape[1] - SKIP
        if nls < _LS_WINDOW:  # a short record: its line search ran on all of it
            self.note("generate", ch.name,
                      f"the law's terms searched by output error on y on a short record: the "
                      f"line search simulated the whole record after the filter's settling "
                      f"({nls} samples; {_LS_WINDOW} on a longer record): " + (
                          "no term chosen" if law_o is None else f"{law_o.npar} term(s) chosen"))
        if law_o is None:
            return None
        chosen = _refine_pruned(law_o, self.base, ch, P.disc, P.y, P.u, x0c, P.C, P.D,
                                noise_ch)
        if chosen is not None and chosen.law.npar > 1:
            chosen = _held_out_terms(chosen, self.base, ch, P.disc, P.y, P.u, x0c, P.C, P.D,
                                     noise_ch, self.decisions)
        return chosen

    def _dhat_candidate(self, tr, dh: _DHat, x0c, noise_ch) -> _LawCandidate:
        """d^'s law as a candidate (its updated model's estimation SE); a delayed channel's
        coefficients refined by output error first, kept if the SE drops."""
        P, law, ch = self.P, tr.static, tr.channel
        upd = add_law(self.base, ch.G, law.evaluate, name=f"{self.base.name}_updated")
        fit = _fit_from(P.disc(upd), P.u, x0c, P.y, P.C, P.D)
        se = fit.se
        if dh.r > 1 and law.npar <= OE_MAX_TERMS:
            # a delayed d^ is noisy (d shows in y only through C A G~): its law's
            # coefficients are refined by output error before the channels are compared,
            # its weak terms pruned as the output-error choice's are (zoo nonlinear_model
            # 270939893 #1 kept +0.000427*th and +0.000421*T, intervals holding 0, beside
            # the right sign(om))
            ref = _refine_pruned(law, self.base, ch, P.disc, P.y, P.u, x0c, P.C, P.D,
                                 noise_ch)
            if ref is not None:
                fit_d = _fit_from(P.disc(ref.model), P.u, x0c, P.y, P.C, P.D)
                if fit_d.se < se:
                    return _LawCandidate(se=fit_d.se, npar=ref.law.npar,
                                         trace=replace(tr, static=ref.law), model=ref.model,
                                         refined=True, evidence=ref.evidence, fit=fit_d)
        return _LawCandidate(se=se, npar=law.npar, trace=tr, model=upd, fit=fit)

    def _against_oe(self, entry: _LawCandidate | None, chosen: _OEFit, tr,
                    x0c) -> _LawCandidate:
        """d^'s law (``entry``, None: none) against the one chosen by output error: the lower
        BIC of the output error (effective sample count Ny / c, c the chosen law's residual
        colour, :func:`_oe_bic`); the loser is scored "replaced"."""
        P, ch = self.P, tr.channel
        fit_o = _fit_from(P.disc(chosen.model), P.u, x0c, P.y, P.C, P.D)
        se_o = fit_o.se
        oe = _LawCandidate(se=se_o, npar=chosen.law.npar, trace=replace(tr, static=chosen.law),
                           model=chosen.model, refined=True, evidence=chosen.evidence,
                           oe_terms=True, fit=fit_o)
        if entry is None or _oe_bic(oe, entry, P.y, P.u, P.disc, x0c, P.C, P.D):
            if entry is not None:
                self.cands.append(CandidateScore(ch.name, "static", 0, entry.se, entry.npar,
                                                 "replaced", "d^ law: higher output-error BIC "
                                                 "than the terms chosen by output error"))
            return oe
        self.cands.append(CandidateScore(ch.name, "static", 0, se_o, chosen.law.npar,
                                         "replaced", "terms chosen by output error: higher "
                                         "output-error BIC than d^'s law"))
        return entry

    def _hinge_candidate(self, r: _Residual, entry: _LawCandidate, dh: _DHat, x0c,
                         noise_ch) -> None:
        """A law with a saturation hinge beside other terms: the hinges alone, their
        coefficients and levels refined by output error, compete as a sparser candidate
        (d^ of a delayed estimate is noisy and correlated with x^: its other terms are
        often the closed-loop artefacts of PAPER_NOTES 8.4)."""
        P, ch = self.P, entry.channel
        try:
            hl = _hinge_law(entry.law, dh.d_fit, dh.x, dh.u, r.lin_cont, list(ch.labels),
                            ch.units, dh.weights, ch.relative)
        except (GreyboxError, np.linalg.LinAlgError):
            hl = None
        if hl is None or not hl.npar or not (ch.md == 1 or np.all(np.any(hl.coef, axis=1))):
            return
        ref = _refine_law_oe(hl, self.base, ch, P.disc, P.y, P.u, x0c, P.C, P.D, noise_ch)
        if ref is None:
            return
        fit_h = _fit_from(P.disc(ref.model), P.u, x0c, P.y, P.C, P.D)
        se_h = fit_h.se
        self.cands.append(CandidateScore(ch.name, "static", 0, se_h, ref.law.npar, "ok",
                                         "saturation hinge(s) only, coefficient(s) and "
                                         "level(s) refined by output error"))
        self.scored.append(_LawCandidate(se=se_h, npar=ref.law.npar,
                                         trace=replace(entry.trace, static=ref.law),
                                         model=ref.model, refined=True,
                                         evidence=ref.evidence, oe_terms=entry.oe_terms,
                                         fit=fit_h))

    # ------------------------------------------------------------------ 3. choose
    def choose(self) -> _Pick | None:
        """3. The lowest output-error criterion (:func:`greybox.metrics.criterion_scores`, the
        linear pipeline's: ``bic_factor`` times the BIC penalty per parameter, every
        candidate on the effective sample count of the best-fitting one; ties to the
        fewest parameters, then components); for a model that declares parameters, of the
        candidates the criterion does not separate by one parameter's evidence (at most
        ``_REFIT_NEAR``), the lowest output-error BIC refitted jointly with them
        (:func:`_pick_after_refit`). None when no candidate has a finite SE."""
        P, S = self.P, self.S
        finite = [s for s in self.scored if np.isfinite(s.se) and s.fit is not None]
        if not finite:
            return None
        n_eff = min(finite, key=lambda s: s.se).fit.n_eff
        crit = criterion_scores([s.fit for s in finite], [s.npar for s in finite], n_eff=n_eff,
                                factor=S.bic_factor)
        order = sorted(range(len(finite)), key=lambda i: (crit[i], finite[i].npar,
                                                          finite[i].channel.md, finite[i].se))
        one = S.bic_factor * np.log(max(float(np.sum(n_eff)), 2.0))
        near = [finite[i] for i in order if crit[i] <= crit[order[0]] + one]
        self.note("choose", "", choice_note([c.channel.name for c in finite],
                                            [c.npar for c in finite], [c.se for c in finite], crit,
                                            order, n_eff, S.bic_factor))
        if not (S.refit_parameters and self.declared and len(near) > 1):
            return _Pick(candidate=near[0], start=self.base)
        P.tick("candidates refitted with the nominal's parameters", 0, 1)
        pick = _pick_after_refit(near, (self.base, P.base), P.disc, P.y, P.u, self.x0_of,
                                 P.C, P.D, self.decisions)
        P.tick("candidates refitted with the nominal's parameters", 1, 1)
        return pick

    def refine(self, pick: _Pick) -> _LawCandidate:
        """The chosen law's coefficients refined by output error on y, in the nominal's time
        base with the same RK4 (PAPER_NOTES §9.3, §9.5); kept only if the estimation SE
        drops. A law already fitted by output error is kept as it is."""
        P, c = self.P, pick.candidate
        ch, law = c.channel, c.law
        P.tick("output-error refinement", 0, 1)
        ref = None
        if c.oe_terms:
            self.note("generate", ch.name,
                      "d^ is mostly estimation noise: the law's terms were "
                      "chosen by output error on y (forward selection, BIC on the "
                      "effective sample count Ny / colour), its coefficients and "
                      "levels refined by output error")
        elif c.refined and any(law.spec[j][1] in HINGE_KINDS
                               for j in np.flatnonzero(law.coef.any(0))):
            self.note("generate", ch.name,
                      "the law's saturation hinges alone, refined by output "
                      "error on y (coefficients and levels), were chosen over the full "
                      "d^ law")
        elif c.refined:
            self.note("generate", ch.name, "the delayed d^ law was refined by output error on y "
                                           "before the channels were compared")
        elif law.npar <= OE_MAX_TERMS:
            ref = _refine_law_oe(law, self.base, ch, P.disc, P.y, P.u, self.x0_of[ch.name], P.C,
                                 P.D, _noise_of(c.trace.filter_result, P.Q, P.R, self.kf.P_filt))
        else:
            self.note("generate", ch.name,
                      f"the law has {law.npar} terms (> {OE_MAX_TERMS}): not "
                      f"refined by output error (each term costs a simulation per "
                      f"iteration)")
        if ref is not None:
            se_r = _se_from(P.disc(ref.model), P.u, self.x0_of[ch.name], P.y, P.C, P.D)
            if se_r < c.se:
                self.note("generate", ch.name, f"law refined by output error on y: estimation SE "
                                               f"{c.se:.3g}% -> {se_r:.3g}%")
                c = replace(c, se=se_r, trace=replace(c.trace, static=ref.law), model=ref.model,
                            evidence=ref.evidence)
        P.tick("output-error refinement", 1, 1)
        return c

    def joint_refit(self, pick: _Pick, c: _LawCandidate) -> _LawCandidate:
        """2c. The nominal's declared parameters refitted jointly with the law (and its spill
        into the other state equations), against the parameters refitted alone
        (:func:`_joint_refit`); kept in ``joint`` and ``alone`` when it wins."""
        P = self.P
        if not (self.S.refit_parameters and free_parameters(self.base)):
            return c
        ch, law = c.channel, c.law
        P.tick("joint refit of the nominal's parameters", 0, 1)
        joint = _joint_refit(pick.start, P.disc, law, ch, P.y, P.u, self.x0_of[ch.name], P.C,
                             P.D, c.se,
                             int(c.evidence.nfree) if c.evidence is not None else law.npar,
                             self.decisions, self.declared, self.alone,
                             jr=pick.refit if law is pick.candidate.law else None)
        if joint is not None:
            self.alone, self.joint, jr = joint.alone, joint, joint.refit
            _, _, sel_j, hinges_j = law_coordinates(jr.law)
            law = _with_intervals(jr.law, sel_j, hinges_j, jr.law_halfwidths, ch, self.base)
            c = replace(c, se=jr.se, model=jr.model, trace=replace(c.trace, static=law))
            self.x0_of[ch.name] = jr.x_start
        P.tick("joint refit of the nominal's parameters", 1, 1)
        return c

    # ------------------------------------------------------------------ 3. gate
    def _evidence(self, r: _Residual, c: _LawCandidate) -> _Evidence:
        """The law's evidence (module stage 3), its kind recorded in the gate: the likelihood
        ratio against the parameters refitted alone (a joint refit), or on the output error
        (a delayed channel or terms chosen by output error: d^ is mostly estimation noise
        and the coefficients were estimated on y), or on d^ (the BIC gain plus penalty)."""
        P, law, gate = self.P, c.law, self.gate
        N, p = P.y.shape[1], P.base.noutputs
        Nd = N - 1 - SKIP
        if self.joint is not None:
            jr, alone = self.joint.refit, self.joint.alone
            Ny = p * (N - SKIP)
            gain, penalty, colour = _refit_evidence(jr.residual, alone.se, jr.se, jr.nlaw)
            n_eff = Ny / colour
            gate.update({"oe_colour": colour, "se_estimation_parameters_only": alone.se})
            gate["evidence"] = ("output error: likelihood ratio of the law (nominal parameters "
                                "refitted with it) against the nominal parameters refitted "
                                f"alone, divided by the residual's colour ({colour:.3g}); "
                                f"{jr.nlaw} free law parameter(s), {Ny} residuals "
                                f"({n_eff:.0f} independent)")
        elif (c.trace.relative_degree > 1 or c.oe_terms) and c.evidence is not None:
            nfree = c.evidence.nfree
            Ny = p * (N - SKIP)
            gain, colour = _oe_likelihood_ratio(P.disc(c.model), self.x0_of[c.channel.name],
                                                P.y, P.u, P.C, P.D, r.se_nom, c.se)
            # BIC's log n with n the independent samples, Ny / colour
            n_eff = Ny / colour if np.isfinite(colour) else Ny
            penalty = float(nfree * np.log(max(n_eff, 2.0)))
            gate.update({"oe_wald": float(c.evidence.wald), "oe_colour": colour})
            gate["evidence"] = ("output error: likelihood ratio of the law against the nominal "
                                "on the estimation outputs' simulation, divided by the "
                                f"residual's colour ({colour:.3g}); {nfree} free parameter(s), "
                                f"{Ny} residuals ({n_eff:.0f} independent)")
        else:
            gain = float(law.bic_gain + law.npar * np.log(Nd))
            penalty = float(c.npar * np.log(Nd))
            gate["evidence"] = ("d^: likelihood ratio of the law against d = 0 (BIC gain + "
                                "penalty)")
        return _Evidence(gain=float(gain), penalty=penalty)

    def judge(self, r: _Residual, c: _LawCandidate) -> _Verdict:
        """3. The gate: update only if the law's evidence exceeds ``bic_factor`` times its BIC
        penalty and the estimation SE drops below ``min_se_drop`` times the nominal's."""
        P = self.P
        ev = self._evidence(r, c)
        # the updated model's simulation error against what the noise model alone allows
        # (a diagnostic, not a criterion: real data rarely reach their noise model)
        floor_ratio = _floor_ratio(P.disc(c.model), c.se, P.y, r.x_op, P.u_mean, P.C, P.Q, P.R)
        self.gate["oe_floor_ratio"] = floor_ratio
        passed = _gate(self.gate, self.S, ev.gain, ev.penalty, c.se, r.se_nom)
        return _Verdict(candidate=c, passed=passed, floor_ratio=floor_ratio)

    def refused(self, r: _Residual, v: _Verdict) -> LoopReport:
        """3. The gate refused the best law: the declared parameters refitted alone, under
        their own gate, or the model unchanged (a refused joint refit kept for inspection)."""
        ch, tr = v.candidate.channel, v.candidate.trace
        failed = _failed(self.gate)
        if self.alone is not None:  # the declared parameters refitted alone, under their gate
            rep = self.parameters_only(r, dict(self.gate),
                                       why=f"the best law ({ch.name}, static) failed the gate "
                                           f"against them: {', '.join(failed)}",
                                       law_gate=self.gate, tr=tr)
            if rep is not None:
                return rep
            self.note("gate", "", "the declared parameters refitted alone failed their gate too "
                                  f"(estimation SE {r.se_nom:.3g} % -> {self.alone.se:.3g} %)")
        nl = self._nominal_update(r, refused=self.joint.refit) if self.joint is not None \
            else None
        return self._report(r, f"model error detected (UKF innovations not white), but the "
                               f"best candidate ({ch.name}, static) failed the gate: "
                               f"{', '.join(failed)}; model unchanged", True, tr=tr, nl=nl)

    def diverged(self, r: _Residual, v: _Verdict, err: Exception) -> LoopReport:
        """4. The law passed the gate, but the updated model's UKF diverges on the validation
        record (a law fitted where the state stayed small, extrapolated): not handed over."""
        ch, tr = v.candidate.channel, v.candidate.trace
        passed = dict(self.gate.get("passed", {}))
        passed["validation"] = False
        self.gate["passed"] = passed
        self.note("validate", ch.name, f"the updated model's predictor diverged on the validation "
                                       f"record: {err}")
        return self._report(r, f"model error detected (UKF innovations not white), and the "
                               f"best candidate ({ch.name}, static) passed the gate, but the "
                               f"updated model diverges on the validation record; model "
                               f"unchanged", True, tr=tr)

    def caveats(self, v: _Verdict) -> None:
        """Notes on a law that passed the gate: far above the noise floor, or weak terms."""
        ch, law = v.candidate.channel, v.candidate.law
        if v.floor_ratio > FLOOR_NOTE ** 2:
            self.note("gate", ch.name,
                      f"the updated model's simulation error on the "
                      f"estimation data is {np.sqrt(v.floor_ratio):.1f}x (RMS) what the "
                      f"noise model (Q, R) allows: the law explains part of the error; "
                      f"it may be incomplete, or a proxy for another law (e.g. a term "
                      f"of the right one missing)")
        weak = _weak_terms(law)
        if weak:
            self.note("gate", ch.name,
                      f"{len(weak)} of the law's {law.npar} terms "
                      f"({', '.join(weak)}) have 95 % intervals containing 0: d^ is "
                      f"mostly estimation noise in this channel (e.g. a velocity "
                      f"equation seen through positions only) and the law may be "
                      f"spurious; measure the state the suspected equation drives, or "
                      f"name the channel (channels=...)")

    # ------------------------------------------------------------------ 4. validate
    def _updated(self, r: _Residual, model, **changes) -> _BeforeAfter:
        """The updated model's validation row beside the nominal's, and its NonlinearUpdate:
        its linearization at the mean of its UKF's states on the estimation record.

        ``changes``: the NonlinearUpdate's ``parameters`` and ``spill``.
        """
        P, S = self.P, self.S
        upd_d = P.disc(model)
        x0_val = _prior(P.C, P.D, P.y_val, P.u_val)[0]

        def row_from(P0):
            return validation(NonlinearPlant(upd_d, P0, order=P.base.nstates, x0=x0_val),
                              P.y_val, P.u_val, Q=P.Q, R=P.R, name="updated", lags=S.lags,
                              alpha=S.alpha, skip=SKIP)
        P0 = P.P0
        try:
            row = row_from(P0)
        except ModelError:  # the prior's sigma points where the law is stiff: a settled prior
            P0 = _settled_prior(upd_d, x0_val, P.u_mean, P.Q, P.R)
            if P0 is None:
                raise
            row = row_from(P0)  # a ModelError again: the model diverges (not handed over)
            self.note("validate", "updated",
                      "the updated model's predictor diverged from the prior P0 = I (its "
                      "sigma points reach states where the law is stiff for the "
                      "integration); validated and filtered from the steady-state "
                      "covariance of its linearization at the first sample instead")
        kf_u = ukf(upd_d, P.y, P.u, Q=P.Q, R=P.R, x0=_prior(P.C, P.D, P.y, P.u)[0], P0=P0)
        x_op_u = kf_u.x_filt[:, SKIP:].mean(axis=1)
        nl = NonlinearUpdate(model=model, discrete=upd_d,
                             linearization=linearize_at(upd_d, x_op_u, P.u_mean), x_op=x_op_u,
                             u_op=P.u_mean, operating_point=_OP_TEXT.format(what="updated UKF's"),
                             substeps=P.nsub, **changes)
        return _BeforeAfter(table={"nominal": r.val_nom, "updated": row}, update=nl)

    def validate(self, r: _Residual, v: _Verdict) -> _BeforeAfter:
        """4. Before/after on the validation record, both models simulated with the same RK4."""
        P = self.P
        jr = self.joint.refit if self.joint is not None else None
        P.tick("validation", 0, 1)
        ba = self._updated(r, v.candidate.model,
                           parameters=jr.parameters if jr is not None else (),
                           spill=jr.spill if jr is not None else ())
        P.tick("validation", 1, 1)
        nl = ba.update
        self.note("validate", "",
                  f"the 'nominal' and 'updated' rows simulate the nonlinear models"
                  f"{' (RK4)' if P.cont else ''}; report.model.sys (updated_model.json) "
                  f"is the updated model's linearization at x_op = "
                  f"{np.array2string(nl.x_op, precision=4)}, u_op = "
                  f"{np.array2string(P.u_mean, precision=4)} ({nl.operating_point}), "
                  f"not a row of the table")
        self.note("baseline", "", "the parallel delta baseline (linear) is not computed for a "
                                  "nonlinear nominal model")
        for name, row in ba.table.items():
            if not row.se_defined:
                self.note("validate", name, f"SE n/a: {row.se_reason}")
        return ba

    # ------------------------------------------------------------------ 5. report
    def report(self, r: _Residual, v: _Verdict, ba: _BeforeAfter) -> LoopReport:
        """5. The report of an update: where, what (and the parameters refitted with it),
        before/after."""
        P, c = self.P, v.candidate
        ch, law = c.channel, c.law
        jr = self.joint.refit if self.joint is not None else None
        spill = jr.spill if jr is not None else ()
        effect = Effect(kind="static", order=0, formula=law.formula, channel=ch.name,
                        equations=tuple(ch.equations) + tuple(s for s, _, _ in spill),
                        nonlinear=law.nonlinear, linearized=False, law=law,
                        parameter_notes=_refit_notes(jr) if jr is not None else ())
        where = ", ".join(f"eq({s})" for s in ch.equations) or ch.name
        if ch.kind == "input":
            where = f"input {ch.input} (it enters {where})"
        if spill:
            where += " (and " + ", ".join(f"eq({s}) at {g:.2g}x" for s, g, _ in spill) + ")"
        refit = ""
        if jr is not None:
            changed = _changed(jr.parameters)
            refit = ("; nominal parameters refitted with it: " + (
                ", ".join(changed) if changed else "none changed beyond its 95 % interval"))
        msg = (f"model error found in {where}: static effect{refit}; "
               f"{describe_before_after(ba.table)}")
        return self._report(r, msg, True, updated=True, effect=effect, ch=ch, tr=c.trace,
                            table=ba.table, nl=ba.update,
                            model=UpdatedModel(sys=ba.update.linearization, Q=P.Q, R=P.R,
                                               order=P.base.nstates, kind="static"))


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
    channel; ``law.hold`` integrates a continuous law over each sample); this
    adds it as a ``NonlinearIOSystem`` (``rep.nonlinear``)
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
        model = add_law(res.sys, res.G, eff.law.evaluate, name=f"{rep.nominal.name}_updated",
                        hold=eff.law.hold)
    k0 = res.settled(SKIP)
    # the samples whose filtered state is finite (a channel's filter may diverge part-way:
    # zoo coulomb 20261210 #0, one output of a 3-mass chain, NaN from sample 152 on)
    finite = np.all(np.isfinite(res.x_filt), axis=0)
    diverged = not finite[k0:].all()
    ok = slice(k0, None)  # a slice where all is finite: the same sums to the last bit as ever
    if diverged:
        ok = np.flatnonzero(finite)
        ok = ok[ok >= k0] if np.any(ok >= k0) else ok
    u = np.asarray(res.u, dtype=float)
    if not diverged or ok.size:
        x_op = res.x_filt[:, ok].mean(axis=1)
        u_op = u[:, ok].mean(axis=1) if u.shape[0] else np.zeros(0)
        where = "unknown-input filter's"
    else:
        x_op, u_op = np.zeros(model.nstates), np.zeros(u.shape[0])
        where = None
    lin = linearize_at(model, x_op, u_op)
    nl = NonlinearUpdate(model=model, discrete=model, linearization=lin, x_op=x_op, u_op=u_op,
                         operating_point=_OP_TEXT.format(what=where) if where else
                         "the origin (the unknown-input filter's states are not finite)")
    note = ("which row is which: 'updated' simulates the full nonlinear law "
            "(report.nonlinear.model, a NonlinearIOSystem: " +
            (("A x + B u + G law(x, u)" if eff.law.hold is None else
              "A x + B u, the continuous law integrated over each sample (ETDRK4)")
             if eff.law.output is None else
             f"A x + B u, output {rep.nominal.output_labels[eff.law.output]} + law(x, u)") +
            " in discrete time); 'updated (linearized)' is report.model.sys, the StateSpace "
            "holding the law's best linear least-squares surrogate (a fit over the record, not "
            "a local linearization); report.nonlinear.linearization is the local linearization at "
            "the mean filtered state and input" +
            (" (a sign(x) term, smoothed as tanh(x/eps), has slope 1/eps there when x is "
             "near 0: use greybox.linearize_at at your own operating point)"
             if any(term_kind(s[1]).smoothed and np.any(eff.law.coef[:, j])
                    for j, s in enumerate(eff.law.spec)) else ""))
    out = replace(rep, nonlinear=nl).with_decision("validate", "", note)
    if diverged:  # say so: the law was traced on a filter that diverged
        k_bad = k0 + int(np.argmin(finite[k0:]))
        out = out.with_decision("validate", "", (
            f"the traced channel's unknown-input filter diverged: its states are not finite "
            f"from sample {k_bad} of {finite.size} on; the law was chosen by the output error "
            f"of the updated model, but its d^ and the operating point rest on the "
            f"{ok.size} samples before"))
    return out
