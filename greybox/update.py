"""Model updating: the unknown subsystem from a filter result, the augmented model
(30)-(31), and the parallel delta-augmentation baseline (21)-(24).

The subsystem (19)-(20), generalized with feedthrough::

    z[k+1] = Ad z[k] + Bdu u[k] + Bdx x[k] + K e[k]
    d[k]   = Cd z[k] + Ddu u[k] + Ddx x[k] + e[k]

is identified from the filter's data: inputs ``(u[j], x^[j|j])`` and output
``d^[j]`` (the estimate of d[j], made from y[j+1]). These data are
closed-loop (PAPER_NOTES §8.4), so the dynamic candidates are identified with
output-error separable least squares (regressors are filtered inputs only),
and the static candidate (order 0) by least squares; see
:func:`identify_subsystem` for the order choice.

The parallel delta-augmentation baseline, :func:`delta_update`: ``dy = y -
y_initial`` modelled from ``u`` as a sum of first-order modes with poles from
N4SID and residues fitted by prediction error. The procedure, in order:

1. **Poles.** N4SID (:func:`greybox.ident.n4sid`, one block-Hankel factor
   shared by all orders) of every order ``1..max_order`` on the whole
   record, at horizons 10 and 40 (short horizons suit fast dynamics, long
   ones slow dynamics on oversampled data), in two variants: "plain"
   (``u -> W^-1 dy``) and "marginal" (``u -> [P(q) U1^T W^-1 dy; U2^T
   W^-1 dy]``, the initial model's unit-circle modes differenced out)
   when ``sys`` has such modes that the outputs see. A candidate with a
   pole on or outside the unit circle is rejected (not mirrored): it
   would diverge in simulation (PAPER_NOTES §8.6). Order 0 (no pole) is
   a candidate too when there are held integrators.
2. **Held integrators.** When the initial model's eigenvalue 1 is
   semisimple (integrators, as in the tape drive) and observed, every
   candidate also gets the term ``U1 R_0 sum u`` with the pole held
   *exactly* at 1 and its output directions ``U1 = orth(C V)`` (``A V =
   V``): ``dy`` carries the drift of the initial model's integrators
   that the truth does not have, which no pole inside the unit circle
   can follow. ``R_0`` is fitted (zero if the data do not need it), so
   this nests the structure without them.
3. **Residues by prediction error.** With the poles fixed the model is
   linear in the residues, which are fitted by least squares on the
   one-step prediction errors of the *combined* model under the initial
   model's noise model: ``e = S^-1/2 L(q) (dy - dy_hat)`` with ``L(q)``
   the innovation filter of ``sys``'s steady-state Kalman predictor for
   ``(Q, R)`` and ``S`` its innovation covariance (a prediction-error
   method with a fixed noise model; consistent whatever that model, and
   efficient when it is right). This matters on estimation data with
   process noise: there ``dy`` carries random walks and slow noise that a
   plain simulation-error fit mistakes for signal. With several inputs
   the residues are then made rank one, ``R_i = c_i v_i^T`` (one state
   per pole, as in an order-k state-space model): ``v_i`` is the first
   right singular vector of the full fit's ``R_i`` and ``c_i`` is
   refitted the same way. A candidate whose single modes are 1000 times
   larger than ``dy`` (near-equal poles cancelling) is rejected.
4. **Order, variant, horizon** by BIC: ``N_eff log det cov(e) + npar log
   N_eff``, ``npar`` = real coefficients of the poles, the ``c_i``, the
   ``v_i`` (up to scale) and ``R_0``; ``N_eff = N (1 - r1) / (1 + r1)``
   with ``r1`` the mean lag-1 autocorrelation of the initial model's
   whitened errors (an AR(1) correction for oversampled data whose errors
   the noise model does not whiten; on the tape drive ``N_eff / N`` is
   a few per cent, without it BIC picks models that fit the noise).
5. **Pole refinement.** For the ``nrefine`` best candidates the poles
   are refined by output error on the first ``1 -
   holdout`` of the variant's own data
   (:func:`greybox.ident.modal_oe.refine_output_error`, poles kept inside
   the unit circle) and kept as a further candidate only if, with
   residues fitted on that part too, they predict the held-out tail
   better (``log det`` of the whitened errors) than the N4SID poles.
6. **No improvement**, judged on the estimation record only. The
   candidates below the initial model's BIC (``dy_hat = 0``) are taken
   in BIC order (at most five) until one lowers the plain SE (eq. 42) on
   the record's selection coordinates (the "marginal" differencing when
   it applies) and, with its residues refitted on the head, does not
   raise it on the held-out tail (the last ``holdout`` of the record)
   by more than 1 % (relative; noise: with process noise in the data a
   random walk dominates every candidate's tail SE, e.g. 63.0-63.6 %
   against the initial model's 63.2 % on the tape drive, seed 2010): a
   model that fits the head's noise, or a delta the tail does not have,
   fails there. If none passes, the initial model is returned with
   ``improved=False``, order 0 and ``message`` starting "parallel model:
   no improvement found". The returned model never diverges in
   simulation.

The one-step prediction errors of the fits, scores and ``r1`` start
after the predictor's start-up transient (its decay to 1e-8, at most
``N / 20`` samples): with an initial-state mismatch (``x0`` estimated
elsewhere, as in :func:`greybox.close_the_loop`) the first whitened
errors are many standard deviations large and used to decide the order
(EMPS inside ``close_the_loop``, before this: ``r1`` -0.32 instead of
0.76, ``N_eff`` 8000 instead of 1075, order 6 instead of 3).

**Realization.** A real pole with a rank-r residue adds r states, a
complex pair with a rank-r complex residue 2 r states (the rank from the
residue's SVD, relative cut 1e-9; r = 1 with several inputs):
``DeltaModel.order`` is their sum, the N4SID order k.
The held integrator term is not duplicated in the combined model: it
drives the initial model's own integrators (``B + V M R_0`` with ``C V M
= U1``), the same input-output behaviour without an unobservable second
set of integrators (which a Kalman filter or LQ design could not use).
``DeltaModel.delta`` holds the delta model alone, the held integrators
as ``nfixed`` states at exactly 1.

Noise of the combined model: ``Q = blockdiag(Q, 0)`` (the delta states
are deterministic functions of u) and ``R``, the noise model under which
the residues were fitted.
"""

from __future__ import annotations

import functools
import time
import warnings
from dataclasses import dataclass, field

import control as ct
import numpy as np
from numpy.typing import ArrayLike, NDArray
import scipy.linalg as sla
from scipy.signal import lfilter

from ._lti import lti_states, spectral_radius
from ._validation import (
    check_covariance,
    check_discrete,
    check_positive,
    check_same_length,
    check_signal,
    check_vector,
)
from .exceptions import (
    DataError,
    DimensionError,
    GreyboxError,
    GreyboxWarning,
    IdentificationError,
)
from .filters import FilterResult, steady_state_filter
from .metrics import relative_error
from .ident import n4sid, pbsid
from .ident.modal_oe import refine_output_error
from .ident.oe import output_error
from .ident.regression import static_least_squares
from .system import named_ss, split_inputs

__all__ = [
    "Subsystem",
    "identify_subsystem",
    "UpdatedModel",
    "augment_model",
    "DeltaModel",
    "delta_update",
]


def psd_part(S: NDArray) -> NDArray:
    """Positive semidefinite part of a symmetric matrix (negative eigenvalues set to 0)."""
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    P = (V * np.clip(w, 0, None)) @ V.T
    return 0.5 * (P + P.T)  # exactly symmetric (python-control's dare checks it)


@dataclass(frozen=True)
class Subsystem:
    """Identified unknown subsystem (19)-(20) with feedthrough.

    Attributes
    ----------
    order : int
        Number of subsystem states n_d (0: static law ``d = Ddu u + Ddx x``); with
        md > 1 unknown inputs an output-error fit of order k per channel has
        n_d = md * k.
    Ad : ndarray, shape (order, order)
    Bdu : ndarray, shape (order, ninputs)
    Bdx : ndarray, shape (order, nstates)
    Cd : ndarray, shape (md, order)
    Ddu : ndarray, shape (md, ninputs)
    Ddx : ndarray, shape (md, nstates)
    K : ndarray, shape (order, md)
        Kalman gain of the subsystem's innovation form.
    innovation_cov : ndarray, shape (md, md)
        Covariance of the residual of d^ (includes the filter's own error Pd).
    noise_cov : ndarray, shape (md, md)
        ``innovation_cov - Pd`` (its PSD part): the part of the residual that
        is model error, not estimation error. Used as R_nu in the update.
    criterion : dict
        BIC of the simulated d^ for every order tried (recorded; the order
        is chosen by the variance-floor rule of :func:`identify_subsystem`).
    method : str
        "least squares" (order 0), "output-error", "n4sid" or "pbsid".
    feedthrough : bool
    d_sim : ndarray, shape (md, nsteps)
        The subsystem's simulated output on the identification data.
    input_labels, state_labels, unknown_labels : tuple of str
        Names of u, x and d.
    """

    order: int
    Ad: NDArray[np.float64]
    Bdu: NDArray[np.float64]
    Bdx: NDArray[np.float64]
    Cd: NDArray[np.float64]
    Ddu: NDArray[np.float64]
    Ddx: NDArray[np.float64]
    K: NDArray[np.float64]
    innovation_cov: NDArray[np.float64]
    noise_cov: NDArray[np.float64]
    criterion: dict
    method: str
    feedthrough: bool
    d_sim: NDArray[np.float64] = field(repr=False)
    input_labels: tuple[str, ...] = ()
    state_labels: tuple[str, ...] = ()
    unknown_labels: tuple[str, ...] = ()

    @property
    def is_static(self) -> bool:
        """True for an order-0 law."""
        return self.order == 0

    @property
    def npar(self) -> int:
        """Parameters the one criterion counts: ``Ad``, ``B`` and ``C`` of the hidden part and
        the feedthrough ``D`` from every state and input, ``q^2 + q nw + md q + md nw``
        (``nw`` = states + inputs), as the candidate was scored."""
        q, md = self.order, self.Cd.shape[0]
        nw = self.Bdu.shape[1] + self.Bdx.shape[1]
        return q * q + q * nw + md * q + md * nw


def _sim_subsystem(Ad, Bw, Cd, Dw, w, z0=None):
    nd = Ad.shape[0]
    if nd == 0:
        return Dw @ w
    z = lti_states(Ad, Bw @ w, np.zeros(nd) if z0 is None else z0)
    return Cd @ z + Dw @ w


def _bic(resid: NDArray, npar: int) -> float:
    N = resid.shape[1]
    S = np.atleast_2d(np.cov(resid, bias=True))
    sign, logdet = np.linalg.slogdet(S)
    if sign <= 0:
        return -np.inf
    return float(N * logdet + npar * np.log(N))


def identify_subsystem(result: FilterResult, *, order: int | None = None,
                       max_order: int = 2, min_order: int = 0, feedthrough: bool = True,
                       horizon: int | None = None, method: str = "output-error",
                       starts: int = 2, skip: int | None = None) -> Subsystem:
    """Identify the unknown subsystem from an unknown-input filter's result.

    Parameters
    ----------
    result : FilterResult
        Record of :func:`greybox.uikf` on the estimation data.
    order : int, optional
        Subsystem order; None chooses it in ``min_order..max_order`` by the
        rule in Notes. Order 0 is a static law and needs ``feedthrough=True``.
    max_order : int
        Largest order tried when ``order`` is None.
    min_order : int
        Smallest order tried when ``order`` is None (1 forces dynamics).
    feedthrough : bool
        Allow the direct terms Ddu, Ddx (our generalization). False forces the
        paper's structure (30)-(31): d is then a delayed function of x and u.
    horizon : int, optional
        Past horizon of the subspace methods ("pbsid", "n4sid"); default
        ``order + 1``. Short horizons suit the filter's data: the regressors
        (u, x^) are strongly oversampled and, through the filter's own
        algebra, nearly collinear over long windows (PAPER_NOTES §8.4, §8.7).
    method : {"output-error", "pbsid", "n4sid"}
        Identification of the dynamic candidates (order >= 1; order 0 is
        always static least squares):

        * "output-error" (default): separable least squares
          (:func:`greybox.ident.oe.output_error`); its regressors are filtered
          inputs only, consistent on the filter's closed-loop data.
        * "n4sid": the paper's own step (28)-(29), N4SID on the aligned data
          ``[u; x^] -> d^`` (:func:`greybox.ident.n4sid`), with the
          subsystem's Kalman gain and innovation covariance (Q_omega =
          K Re K^T, R_nu) carried into :func:`augment_model`. With feedthrough
          and the short default horizon it is usable; see the README section
          "Reproduction: Table III" for a measured comparison.
        * "pbsid": the predictor-based subspace method. Its past-output
          regressors are exactly collinear with the inputs here (d^[k-1] is a
          linear function of x^[k], x^[k-1], u[k-1]), so it returns poorly
          determined models on C = I data.
    starts : int
        Starting pole sets of the output-error search.
    skip : int, optional
        Leading samples left out (filter transient); default: the sample where
        the filter's gains converged, at least 10.

    Returns
    -------
    Subsystem

    Raises
    ------
    DataError
        Not a result of :func:`greybox.uikf`, unknown ``method``, order 0
        without feedthrough, fewer than 50 usable samples.
    IdentificationError
        No stable candidate.

    Notes
    -----
    Alignment: ``d^[j]`` (the estimate of ``d[j]``, made from ``y[j+1]``) is
    paired with ``(u[j], x^[j|j])``; both inputs depend on measurements up to
    ``j`` only, so the direct terms are identifiable (PAPER_NOTES §8.4).

    Order selection (``order=None``): every order in ``min_order..max_order``
    is fitted; unstable fits are dropped. With ``v_k`` the residual variance
    ``trace(cov(d^ - d_sim))`` of the order-k candidate's simulated output
    and ``Pd`` the filter's variance of d^, the chosen order is the *lowest*
    k with ``v_k <= 1.05 * max(min_j v_j, trace(Pd))``: a residual cannot
    honestly drop below the filter's own estimation variance, and a fit that
    does is explaining the filter's algebra (§8.4). The
    BIC ``N log det(cov(d^ - d_sim)) + npar log N`` of every candidate is
    recorded in ``Subsystem.criterion`` for reference, not used for the choice.
    """
    prob = _subsystem_problem(result, order, max_order, min_order, feedthrough, method, skip)
    cands = {}
    for nd in prob.orders:
        cand = _fit_candidate(prob, nd, method, feedthrough, starts, horizon, result.sys.dt)
        if cand is not None:
            cands[nd] = cand
    if not cands:
        raise IdentificationError("no stable subsystem could be identified for orders "
                                  f"{prob.orders}; check the filter result and the data length")
    Pd = np.atleast_2d(result.d_cov)
    best = cands[_parsimonious_order(cands, prob.d, Pd)]
    m = prob.u.shape[0]
    Bw, Dw, Re = best.Bw, best.Dw, np.atleast_2d(best.Re)
    labels_u = tuple(result.sys.input_labels)
    labels_x = tuple(result.sys.state_labels)
    return Subsystem(
        order=best.Ad.shape[0], Ad=best.Ad, Bdu=Bw[:, :m], Bdx=Bw[:, m:], Cd=best.Cd,
        Ddu=Dw[:, :m], Ddx=Dw[:, m:], K=best.K, innovation_cov=Re, noise_cov=psd_part(Re - Pd),
        criterion={k: v.bic for k, v in cands.items()}, method=best.method,
        feedthrough=feedthrough, d_sim=best.d_sim, input_labels=labels_u, state_labels=labels_x,
        unknown_labels=tuple(result.unknown_labels),
    )


@dataclass(frozen=True)
class _SubsystemProblem:
    """The orders :func:`identify_subsystem` tries and its data after the filter transient:
    inputs ``w = [u; x^]`` and output ``d^``."""

    orders: list
    u: NDArray[np.float64]
    x: NDArray[np.float64]
    d: NDArray[np.float64]
    w: NDArray[np.float64]


def _subsystem_problem(result, order, max_order, min_order, feedthrough, method,
                       skip) -> _SubsystemProblem:
    """The checked options of :func:`identify_subsystem` and its aligned data."""
    if not isinstance(result, FilterResult) or result.d_est.shape[0] == 0:
        raise DataError("identify_subsystem needs the FilterResult of greybox.uikf "
                        "(with at least one unknown input)")
    if method not in ("output-error", "pbsid", "n4sid"):
        raise DataError(f"method must be 'output-error', 'pbsid' or 'n4sid'; found {method!r}")
    if order is not None:
        order = check_positive(order, "order", integer=True, allow_zero=True)
    max_order = check_positive(max_order, "max_order", integer=True, allow_zero=True)
    if not feedthrough and order == 0:
        raise DataError("order 0 without feedthrough is no model at all; set feedthrough=True "
                        "or order >= 1")
    N = result.d_est.shape[1] - 1
    if skip is not None:
        skip = check_positive(skip, "skip", integer=True, allow_zero=True)
    k0 = skip if skip is not None else result.settled(10)
    if N - k0 < 50:
        raise DataError(f"only {N - k0} usable samples after the filter transient; "
                        f"at least 50 are needed")
    u = result.u[:, k0:N]
    x = result.x_filt[:, k0:N]
    d = result.d_est[:, k0:N]
    lo = max(min_order, 0 if feedthrough else 1)
    orders = [order] if order is not None else list(range(lo, max_order + 1))
    return _SubsystemProblem(orders=orders, u=u, x=x, d=d, w=np.vstack([u, x]))


@dataclass(frozen=True)
class _Candidate:
    """One fitted order of :func:`identify_subsystem`: ``(Ad, Bw, Cd, Dw)`` from ``w = [u; x^]``,
    the innovation form's K and Re, the BIC and the simulated d^."""

    bic: float
    Ad: NDArray[np.float64]
    Bw: NDArray[np.float64]
    Cd: NDArray[np.float64]
    Dw: NDArray[np.float64]
    K: NDArray[np.float64]
    Re: NDArray[np.float64]
    method: str
    d_sim: NDArray[np.float64]


def _fit_candidate(prob: _SubsystemProblem, nd: int, method: str, feedthrough: bool,
                   starts: int, horizon: int | None, dt) -> _Candidate | None:
    """The order-``nd`` subsystem on ``prob``'s data; None if it fails or is unstable."""
    d, w = prob.d, prob.w
    md, nw = d.shape[0], w.shape[0]
    try:
        if nd == 0:
            fit = static_least_squares(w, d)
            Ad, Bw, Cd = np.zeros((0, 0)), np.zeros((0, nw)), np.zeros((md, 0))
            Dw, K = fit.coef, np.zeros((0, md))
            Re = fit.residual_cov
            how = "least squares"
        elif method == "output-error":
            oe = output_error(d, w, nd, feedthrough=feedthrough, starts=starts)
            Ad, Bw, Cd, Dw = oe.A, oe.B, oe.C, oe.D
            K, Re = np.zeros((Ad.shape[0], md)), oe.residual_cov
            how = "output-error"
        else:
            ident_fn = pbsid if method == "pbsid" else n4sid
            # an unstable predictor may overflow in the initial-state fit:
            # such a candidate fails (LinAlgError) and is skipped
            with warnings.catch_warnings(), np.errstate(all="ignore"):
                warnings.simplefilter("ignore", GreyboxWarning)
                ident = ident_fn(d, w, order=nd, horizon=horizon or nd + 1,
                                 feedthrough=feedthrough, dt=float(dt))
            s_ = ident.sys
            Ad, Bw, Cd, Dw = (np.asarray(a, dtype=float) for a in (s_.A, s_.B, s_.C, s_.D))
            K, Re = ident.K, ident.innovation_cov
            how = method
    except (IdentificationError, np.linalg.LinAlgError):
        return None
    if not all(np.all(np.isfinite(M)) for M in (Ad, Bw, Cd, Dw)):
        return None
    if nd and np.max(np.abs(np.linalg.eigvals(Ad))) >= 1.0:
        return None  # unstable subsystem: not a physical candidate (§8.6)
    dsim = _sim_subsystem(Ad, Bw, Cd, Dw, w)
    npar = nd * nd + nd * nw + md * nd + (md * nw if feedthrough else 0)
    return _Candidate(bic=_bic(d - dsim, npar), Ad=Ad, Bw=Bw, Cd=Cd, Dw=Dw, K=K, Re=Re,
                      method=how, d_sim=dsim)


def _parsimonious_order(cands: dict, d: NDArray, Pd: NDArray) -> int:
    """The lowest order whose residual variance is within 5 % of max(best residual, Pd).

    Parsimony with the noise floor in mind: the residual of d^ cannot honestly drop below
    the filter's own estimation variance Pd; a fit that does is explaining the filter's
    algebra (PAPER_NOTES §8.4).
    """
    var = {k: float(np.trace(np.atleast_2d(np.cov(d - v.d_sim, bias=True))))
           for k, v in cands.items()}
    floor = 1.05 * max(min(var.values()), float(np.trace(Pd)))
    ok = [k for k in sorted(cands) if var[k] <= floor]
    return ok[0]  # never empty: the best candidate is within the bound


@dataclass(frozen=True)
class UpdatedModel:
    """A model augmented with an identified effect, ready for control design.

    Attributes
    ----------
    sys : control.StateSpace
        Discrete model of order n + n_d; inputs: the known inputs only;
        physical states first with their names, then the new states.
    Q : ndarray, shape (n + n_d, n + n_d)
        Process-noise covariance of the augmented model.
    R : ndarray, shape (noutputs, noutputs)
        Measurement-noise covariance.
    order : int
        n + n_d.
    kind : str
        "dynamic", "static", "delta" (or "parameters": a nonlinear nominal
        with its declared parameters refitted, no law).
    """

    sys: ct.StateSpace
    Q: NDArray[np.float64]
    R: NDArray[np.float64]
    order: int
    kind: str


def free_state_names(labels, count: int, prefix: str = "z") -> list[str]:
    """The first ``count`` names ``prefix[k]`` (k = 0, 1, ...) not among ``labels``.

    Parameters
    ----------
    labels : sequence of str
        Names already taken (a model's state labels).
    count : int
        How many new names.
    prefix : str
        Stem of the names.

    Returns
    -------
    list of str
    """
    out, k = [], 0
    while len(out) < count:
        if f"{prefix}[{k}]" not in labels:
            out.append(f"{prefix}[{k}]")
        k += 1
    return out


def augment_model(sys: ct.StateSpace, subsystem: Subsystem, *, unknown, Q: ArrayLike,
                  R: ArrayLike, state_prefix: str = "z",
                  output_unknown: bool = False) -> UpdatedModel:
    """Augment a model with its identified subsystem, eqs. (30)-(31) with feedthrough.

    .. math::

        \\begin{bmatrix} x \\\\ z \\end{bmatrix}_{k+1} =
        \\begin{bmatrix} A + G D_{dx} & G C_d \\\\ B_{dx} & A_d \\end{bmatrix}
        \\begin{bmatrix} x \\\\ z \\end{bmatrix}_k +
        \\begin{bmatrix} B + G D_{du} \\\\ B_{du} \\end{bmatrix} u_k

    A static law (order 0) is folded into A and B. Noise: with the
    subsystem's innovation e (covariance R_nu = ``subsystem.noise_cov``),
    ``Q_aug = [[Q + G R_nu G^T, G R_nu K^T], [K R_nu G^T, K R_nu K^T]]``:
    the model's own Q, the subsystem's output noise seen through G, and the
    subsystem's own process noise ``Q_omega = K R_nu K^T`` (innovation form).
    R is unchanged.

    With ``output_unknown=True`` the output row of (31) is appended: ``d^ =
    [D_dx, C_d] [x; z] + D_du u + nu`` as extra outputs named after the
    unknown inputs, with measurement noise ``subsystem.innovation_cov`` (the
    residual of d^, filter error included); the correlation of that noise
    with the ``G nu`` part of the process noise is neglected.

    Parameters
    ----------
    sys : control.StateSpace
        The discrete model with inputs ``[u, d]`` given to :func:`greybox.uikf`.
    subsystem : Subsystem
    unknown : label(s) or index(es)
        The unknown-input channels of ``sys``.
    Q : array_like, shape (nstates, nstates)
    R : array_like, shape (noutputs, noutputs)
    state_prefix : str
        Names of the new states: ``z[0]``, ``z[1]``, ...
    output_unknown : bool
        Append d^ as extra outputs (the output row of eq. 31).

    Returns
    -------
    UpdatedModel
    """
    sp = split_inputs(sys, unknown)
    base, G = sp.sys, sp.G
    checks = (("unknown inputs", subsystem.unknown_labels, sp.unknown_labels),
              ("known inputs", subsystem.input_labels, tuple(base.input_labels)),
              ("states", subsystem.state_labels, tuple(base.state_labels)))
    for what, have, want in checks:
        if have and tuple(have) != tuple(want):
            raise DimensionError(
                f"the subsystem was identified with {what} {list(have)} but this model has "
                f"{list(want)}; pass the model and the unknown channels given to uikf")
    A, B, C, D = (np.asarray(a, dtype=float) for a in (base.A, base.B, base.C, base.D))
    n, nd = A.shape[0], subsystem.order
    if subsystem.Ddx.shape != (G.shape[1], n) or subsystem.Ddu.shape[1] != B.shape[1]:
        raise DataError("the subsystem does not fit this model (its x or u dimensions differ)")
    Q = check_covariance(Q, n, "Q", definite=False)
    R = check_covariance(R, C.shape[0], "R", definite=True)
    Aa = np.block([[A + G @ subsystem.Ddx, G @ subsystem.Cd],
                   [subsystem.Bdx, subsystem.Ad]])
    Ba = np.vstack([B + G @ subsystem.Ddu, subsystem.Bdu])
    Ca = np.hstack([C, np.zeros((C.shape[0], nd))])
    Rn = subsystem.noise_cov
    Kd = subsystem.K
    Qa = np.block([[Q + G @ Rn @ G.T, G @ Rn @ Kd.T], [Kd @ Rn @ G.T, Kd @ Rn @ Kd.T]])
    # the next free names: a base from an earlier pass may hold z[0]
    states = list(base.state_labels) + free_state_names(base.state_labels, nd, state_prefix)
    outputs = list(base.output_labels)
    Da = D
    if output_unknown:
        Ca = np.vstack([Ca, np.hstack([subsystem.Ddx, subsystem.Cd])])
        Da = np.vstack([D, subsystem.Ddu])
        Rd = np.atleast_2d(subsystem.innovation_cov)
        R = np.block([[R, np.zeros((R.shape[0], Rd.shape[0]))],
                      [np.zeros((Rd.shape[0], R.shape[0])), 0.5 * (Rd + Rd.T)]])
        outputs += [f"{lab}_hat" for lab in sp.unknown_labels]
    out = named_ss(Aa, Ba, Ca, Da, base.dt, states=states, inputs=base.input_labels,
                   outputs=outputs, name=f"{base.name or 'model'}_updated")
    return UpdatedModel(sys=out, Q=0.5 * (Qa + Qa.T), R=R, order=n + nd,
                        kind="static" if nd == 0 else "dynamic")


@dataclass(frozen=True)
class DeltaModel:
    """Parallel delta-augmentation baseline (21)-(24).

    Attributes
    ----------
    updated : UpdatedModel
        The combined model of order n + n_delta; the initial model itself
        (``kind="delta"``, order n) when ``improved`` is False.
    delta : control.StateSpace
        The delta model from u to the output error (order 0, zero gain, when
        ``improved`` is False).
    order : int
        States the delta model adds to the combined model (0 when no
        improvement was found); ``updated.order = n + order``. The held
        integrators are not among them: they drive the initial model's own
        integrators (see :func:`delta_update`).
    improved : bool
        False if no candidate lowered the initial model's BIC and its SE on
        the estimation record and on its held-out tail: "parallel model: no
        improvement found".
    marginal : bool
        True if the chosen candidate is of the "marginal" variant (poles from
        the differenced data, with held integrators when they apply).
    nfixed : int
        States of ``delta`` held exactly at 1 (the held integrators).
    refined : bool
        True if the residues were fitted by prediction error (always, when
        ``improved``).
    se : dict of str to float
        Errors (eq. 42, relative RMS) [%]: ``"initial_estimation"`` and
        ``"delta_estimation"`` (plain SE on the whole estimation record,
        which on data with process noise is dominated by the noise's
        random walk); ``"initial_tail"`` and ``"delta_tail"`` (SE in the
        selection coordinates on the held-out tail, the delta's residues
        fitted on the head: the no-improvement judgement of step 6); keys
        are missing for steps not reached.
    criterion : dict of (str, int) to float
        BIC of every candidate ``(variant, N4SID order)`` (variant "plain" or
        "marginal"; order 0: held integrators only) and of the initial model
        ``("initial", 0)``; NaN for rejected (unstable) candidates. The pole
        refinement of step 5 adds ``(variant + "+oe tail", k)`` (its held-out
        gain) and ``(variant + "+oe", k)`` (its BIC; NaN when the refinement
        failed or drove a pole to the unit circle).
    message : str
        One line for reports, e.g. "parallel model: no improvement found".
    bounded : str
        Empty when every candidate was fitted; else what the ``deadline`` of
        :func:`delta_update` cut (e.g. "stopped at its time budget after 12 of
        32 candidates; pole refinement skipped"), also ending ``message``.
    """

    updated: UpdatedModel
    delta: ct.StateSpace
    order: int
    improved: bool
    marginal: bool
    nfixed: int
    refined: bool
    se: dict
    criterion: dict
    message: str
    bounded: str = ""

    def initial_state(self, y: ArrayLike, u: ArrayLike) -> NDArray[np.float64]:
        """Initial state of the combined model for a record: the initial model's
        states by least squares from the first samples, the delta's at rest.

        The delta states are functions of past inputs that the record does not
        hold; estimated from a short window with the others, slow delta modes
        (poles near 1, time constants beyond the window) are ill-determined
        and their large, cancelling estimates swamp the simulation (EMPS
        validation SE 16-620 % from the window length alone). At rest, the
        combined model starts as it did on the estimation record.

        Parameters
        ----------
        y : array_like, shape (noutputs, nsteps)
            Measured outputs of the record.
        u : array_like, shape (ninputs, nsteps)
            Its inputs.

        Returns
        -------
        ndarray, shape (updated.order,)
        """
        from .validate import estimate_initial_state, simulate_output

        full = self.updated.sys
        y = check_signal(y, full.noutputs, "y", min_steps=1)
        u = check_signal(u, full.ninputs, "u")
        check_same_length(("y", y), ("u", u))
        nD = self.order
        n = full.nstates - nD
        A, B, C, D = (np.asarray(a, dtype=float) for a in (full.A, full.B, full.C, full.D))
        # the delta's response from rest, then the initial model's part (its B
        # includes the held integrators' drive) as for any model
        y_delta = simulate_output(full, u) - simulate_output(
            ct.ss(A[:n, :n], B[:n], C[:, :n], D, full.dt), u)
        x0 = estimate_initial_state(ct.ss(A[:n, :n], B[:n], C[:, :n], D, full.dt),
                                    y - y_delta, u)
        return np.concatenate([x0, np.zeros(nD)])


def _n4sid_fits(data: NDArray, u: NDArray, orders, dt: float, horizon: int | None,
                late=lambda: False):
    """N4SID models of several orders sharing one block-Hankel factor; {order: result}.

    ``late()`` True stops before the next order (the orders fitted so far are returned).
    """
    from .ident._hankel import hankel_r, small_blas
    from .ident.n4sid import (
        DEFAULT_RTOL,
        choose_horizon,
        common_setup,
        n4sid_from_factor,
    )

    (ys, us, l, m, dt, il, ol, fed, _, _, rtol, sy, su) = common_setup(
        data, u, dt, None, None, False, None, max(orders), DEFAULT_RTOL)
    i = choose_horizon(horizon, None, [ys[0].shape[1]], m, l, max(orders), lambda k: 2 * k)
    h = hankel_r(ys, us, sy, su, 2 * i, chunk_size=None)
    out = {}
    with small_blas(), warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore", GreyboxWarning)
        for k in orders:
            if k > (i - 1) * l:
                continue
            if late():
                break
            try:
                out[k] = n4sid_from_factor(h, i, ys, us, l, m, dt, il, ol, fed, k, None,
                                            rtol, sy, su, "N4SID", "bic", "z")
            except (IdentificationError, np.linalg.LinAlgError):
                continue
    return out


#: Largest condition number of the eigenvector matrix of the whitening filter's
#: modal split (:class:`_Whitener`).
_MODAL_COND = 1e8
#: N4SID horizons tried by :func:`delta_update` (poles from each are candidates):
#: short horizons suit fast dynamics, long ones oversampled slow dynamics.
_HORIZONS = (10, 40)
#: Largest block-Hankel factor (rows ``2 x horizon x (noutputs + ninputs)``) of the
#: default horizons: its QR costs rows^2 x samples (a 32-output model at horizon 40:
#: 2640 rows, minutes at 2e4 samples); a longer default horizon is shortened to fit.
#: Models with noutputs + ninputs <= 10 keep both default horizons.
_MAX_HANKEL_ROWS = 800


def _default_horizons(width: int) -> list[int]:
    """The default N4SID horizons ``_HORIZONS``, each at most ``_MAX_HANKEL_ROWS`` rows."""
    top = max(_MAX_HANKEL_ROWS // (2 * max(width, 1)), 2)
    return sorted({min(h, top) for h in _HORIZONS})


class _Cut:
    """The deadline of :func:`delta_update`: what it cut, for the report."""

    def __init__(self, deadline: float | None):
        self.deadline, self.cut = deadline, []

    def late(self, what: str) -> bool:
        """True (and ``what`` recorded) once the deadline has passed."""
        if self.deadline is None or time.monotonic() < self.deadline:
            return False
        if what not in self.cut:
            self.cut.append(what)
        return True

    def what(self) -> str:
        return ("" if not self.cut else
                "stopped at its time budget: skipped the remaining " + ", ".join(self.cut))

    def note(self) -> str:
        return "" if not self.cut else f"; {self.what()}"


#: Candidates (in BIC order) :func:`delta_update` checks on the held-out tail
#: before it reports "no improvement found".
_TAIL_TRIES = 5
#: Relative slack of that check: a candidate's tail SE may exceed the initial
#: model's by this fraction (noise: with process noise in the data every
#: candidate's tail SE is within +-0.5 % of the initial model's, its random
#: walk dominating; a delta the tail does not have costs far more).
_TAIL_SLACK = 0.01


def delta_update(sys: ct.StateSpace, y: ArrayLike, u: ArrayLike, *, Q: ArrayLike,
                 R: ArrayLike, order: int | None = None, max_order: int | None = None,
                 horizon: int | None = None, x0: ArrayLike | None = None,
                 marginal: bool | None = None, holdout: float = 0.25,
                 refine: bool = True, refine_iter: int = 20, nrefine: int = 1,
                 refine_window: int | None = None,
                 state_prefix: str = "delta", deadline: float | None = None) -> DeltaModel:
    """Parallel delta augmentation: a model from u to the output error, run beside ``sys``.

    ``dy = y - y_initial`` (the initial model's simulated output) is modelled
    from ``u`` (open-loop data: u does not depend on the noise), eqs. (21)-(24),
    as a sum of first-order modes::

        dy_hat[k] = sum_i R_i F_i(u)[k] (+ U1 R_0 sum_{j<k} u[j]),
        F_i = q^-1 / (1 - lambda_i q^-1)

    with poles ``lambda_i`` from N4SID and residue matrices ``R_i``
    (noutputs x ninputs, complex for complex poles) fitted by prediction
    error. The procedure (1. poles, 2. held integrators, 3. residues by
    prediction error, 4. order, variant and horizon by BIC, 5. pole
    refinement, 6. the no-improvement judgement), the realization of the
    delta and the noise of the combined model are written out in the module
    docstring (:mod:`greybox.update`); the steps below refer to it.

    Parameters
    ----------
    sys : control.StateSpace
        Discrete initial model from the known inputs (no unknown-input channels).
    y : array_like, shape (noutputs, nsteps)
    u : array_like, shape (ninputs, nsteps)
    Q : array_like, shape (nstates, nstates)
    R : array_like, shape (noutputs, noutputs)
    order : int, optional
        N4SID order of the poles (skips the order selection; the variant is
        still chosen by BIC).
    max_order : int, optional
        Highest N4SID order tried; default ``n + 6`` (the exact delta
        ``G_true - G_initial`` has order up to ``n_true + n``; the paper's
        parallel model had order 12 for n = 6).
    horizon : int, optional
        A single N4SID horizon instead of the default 10 and 40 (raised when
        ``max_order`` needs it).
    x0 : array_like, shape (nstates,), optional
        Initial state of the initial model's simulation.
    marginal : bool, optional
        None (default): try both variants and let BIC choose.
        True: only the "marginal" variant. False: only the "plain" variant,
        without held integrators.
    holdout : float
        Fraction of the record (its tail) held out to check a pole
        refinement (step 5), in (0, 0.5].
    refine : bool
        Refine poles by output error (step 5).
    refine_iter : int
        Iteration limit of that refinement.
    nrefine : int
        Number of best candidates whose poles are refined.
    refine_window : int, optional
        Refine on at most this many samples (the first of the estimation
        part); default all of them. Its cost grows with the samples (a dense
        Jacobian of ``noutputs * samples`` rows), the poles it returns hardly
        do beyond ~1e5; the held-out check still uses the whole tail.
    state_prefix : str
        Names of the delta states: ``delta[0]``, ``delta[1]``, ...
    deadline : float, optional
        A :func:`time.monotonic` time [s] after which no further N4SID order,
        candidate score or pole refinement is started: the choice is made
        among the candidates scored by then (``DeltaModel.bounded`` says what
        was cut). Default: none (every candidate). :func:`greybox.close_the_loop`
        sets it so that the baseline costs no more than the trace.

    Returns
    -------
    DeltaModel

    Raises
    ------
    DataError
        Fewer than 200 samples, or ``holdout`` outside (0, 0.5].

    Examples
    --------
    A correct model leaves only noise to explain:

    >>> import numpy as np, greybox as gb
    >>> from greybox.update import delta_update
    >>> sys = gb.named_ss([[0.9]], [[1.0]], [[1.0]], [[0.0]], 1.0, states=["x"],
    ...                   inputs=["u"], outputs=["y"])
    >>> rng = np.random.default_rng(0)
    >>> u = rng.standard_normal((1, 400))
    >>> y = gb.validate.simulate_output(sys, u) + 0.1 * rng.standard_normal((1, 400))
    >>> dm = delta_update(sys, y, u, Q=[[1e-6]], R=[[1e-2]])
    >>> dm.improved, dm.order, dm.message[:36]
    (False, 0, 'parallel model: no improvement found')
    """
    dd = _delta_data(sys, y, u, Q, R, order, max_order, x0, marginal, holdout, refine_iter,
                     nrefine, refine_window)
    sc = _scored_candidates(sys, dd, horizon, deadline)
    _refine_best(dd, sc, refine)
    return _chosen_delta(sys, dd, sc, state_prefix)


@dataclass(frozen=True)
class _DeltaData:
    """The checked record and options of :func:`delta_update`, the initial model's output
    ``y0`` and error ``dy``, and the variants' data ``{name: (data, held)}`` (step 1)."""

    y: NDArray[np.float64]
    u: NDArray[np.float64]
    Q: NDArray[np.float64]
    R: NDArray[np.float64]
    order: int | None
    orders: list
    y0: NDArray[np.float64]
    dy: NDArray[np.float64]
    w: NDArray[np.float64]
    factor: tuple | None
    variants: dict
    ys_sel: NDArray[np.float64]
    refine_iter: int
    nrefine: int
    refine_window: int | None
    N: int
    Ne: int


def _delta_data(sys, y, u, Q, R, order, max_order, x0, marginal, holdout, refine_iter,
                nrefine, refine_window) -> _DeltaData:
    """The checks of :func:`delta_update`, the initial model's simulation and the variants."""
    check_discrete(sys)
    y = check_signal(y, sys.noutputs, "y", min_steps=200)
    u = check_signal(u, sys.ninputs, "u")
    N = check_same_length(("y", y), ("u", u))
    n = sys.nstates
    Q = check_covariance(Q, n, "Q", definite=False)
    R = check_covariance(R, sys.noutputs, "R", definite=True)
    order = None if order is None else check_positive(order, "order", integer=True)
    max_order = None if max_order is None else check_positive(max_order, "max_order",
                                                              integer=True)
    A, B, C, D = (np.asarray(a, dtype=float) for a in (sys.A, sys.B, sys.C, sys.D))
    x = lti_states(A, B @ u, np.zeros(n) if x0 is None else check_vector(x0, n, "x0"))
    y0 = C @ x + D @ u
    dy = y - y0
    w = np.sqrt(np.mean(y**2, axis=1))
    w[w == 0] = 1.0
    dys = dy / w[:, None]

    factor = _marginal_factor(A, C / w[:, None]) if marginal is not False else None
    held = _held_integrators(A, C) if factor is not None else None
    # the held integrators nest the plain structure (their drive may be 0), so
    # every candidate gets them where they apply; the variants differ in the
    # data N4SID takes its poles from
    variants = {}
    if marginal is not True or factor is None:
        variants["plain"] = (dys, held)
    if factor is not None:
        variants["marginal"] = (_difference(dys, factor), held)
    ys_sel = _difference(y / w[:, None], factor)
    holdout = float(holdout)
    if not 0.0 < holdout <= 0.5:
        raise DataError(f"holdout must be in (0, 0.5]; found {holdout}")
    refine_iter = check_positive(refine_iter, "refine_iter", integer=True)
    nrefine = check_positive(nrefine, "nrefine", integer=True, allow_zero=True)
    if refine_window is not None:
        refine_window = check_positive(refine_window, "refine_window", integer=True)
    Ne = N - int(round(holdout * N))
    max_order = max_order if max_order is not None else n + 6
    orders = [order] if order is not None else list(range(1, max_order + 1))
    return _DeltaData(y=y, u=u, Q=Q, R=R, order=order, orders=orders, y0=y0, dy=dy, w=w,
                      factor=factor, variants=variants, ys_sel=ys_sel, refine_iter=refine_iter,
                      nrefine=nrefine, refine_window=refine_window, N=N, Ne=Ne)


@dataclass(frozen=True)
class _Scored:
    """The scored candidates of :func:`delta_update` (steps 1-4): the score, the samples it
    uses, the BIC of every key, the candidates ``(bic, k, variant, fit)`` and their origin;
    ``crit``, ``cands`` and ``origin`` grow with the pole refinement (step 5)."""

    score: _DeltaScore
    whole: slice
    head: slice
    tail: slice
    crit: dict
    cands: list
    origin: dict
    cut: _Cut


def _scored_candidates(sys, dd: _DeltaData, horizon, deadline) -> _Scored:
    """N4SID poles of every variant, order and horizon, each scored with its residues."""
    wh = _Whitener(sys, dd.Q, dd.R)
    wdy = wh.apply(dd.dy)
    # the predictor starts at rest: an initial-state mismatch of the simulation
    # (dy[0] != 0, e.g. with an estimated x0) is a transient of wdy many
    # standard deviations large; it would dominate the fits, the scores and r1
    N, Ne, u, variants = dd.N, dd.Ne, dd.u, dd.variants
    k0 = wh.settling(N)
    whole, head, tail = slice(k0, N), slice(k0, Ne), slice(Ne, N)
    ew = wdy[:, whole]  # the initial model's whitened errors
    Neff = _effective_samples(ew)
    score = _DeltaScore(wh=wh, u=u, wdy=wdy, dy=dd.dy, whole=whole, Neff=Neff)
    crit, cands, origin = {("initial", 0): Neff * _logdet(ew)}, [], {}
    p, m = dd.dy.shape[0], u.shape[0]
    horizons = [horizon] if horizon is not None else _default_horizons(p + m)
    cut = _Cut(deadline)
    for name, (data, hold) in variants.items():
        held_only = dd.order is None and hold is not None and name == list(variants)[-1]
        starts = _n4sid_starts(name, data, u, dd.orders, float(sys.dt), horizons, cut, crit,
                               held_only)
        for key, fABC in starts.items():
            if cut.late("candidate scores"):
                break
            poles = np.zeros(0, dtype=complex) if fABC is None else _upper_poles(fABC[0])
            crit[key], fit = score(poles, hold)
            if fit is not None:
                cands.append((crit[key], key[1], name, fit))
                origin[(name, key)] = (fABC, data, hold)
    return _Scored(score=score, whole=whole, head=head, tail=tail, crit=crit, cands=cands,
                   origin=origin, cut=cut)


def _refine_best(dd: _DeltaData, sc: _Scored, refine: bool) -> None:
    """Step 5: the best candidates' poles refined by output error (added to ``sc``).

    The poles of N4SID on oversampled, noisy data can be far off: they are refined in
    modal form (stable by construction) on the head of the variant's own data, and kept
    only if, with residues fitted on the head too, they predict the held-out tail better
    than N4SID's poles (noise fitting shows there).
    """
    crit = sc.crit
    ranked = sorted(((b_, k, name, key) for (name, key), (b_, k) in
                     ((nk, (crit[nk[1]], nk[1][1])) for nk in sc.origin) if k > 0),
                    key=lambda c: (c[0], c[1]))
    Ne, refine_window = dd.Ne, dd.refine_window
    rsl = slice(0, Ne if refine_window is None else min(Ne, refine_window))
    _refine_poles(ranked[:dd.nrefine if refine else 0], sc.origin, dd.u, rsl, dd.refine_iter,
                  sc.score, sc.head, sc.tail, crit, sc.cands, sc.cut)


def _chosen_delta(sys, dd: _DeltaData, sc: _Scored, state_prefix: str) -> DeltaModel:
    """Step 6: the first candidate in BIC order that lowers the SE without raising the
    held-out tail's, as a DeltaModel; else the initial model ("no improvement found")."""
    y, u, y0, Q, R, crit, cut = dd.y, dd.u, dd.y0, dd.Q, dd.R, sc.crit, sc.cut
    se = {"initial_estimation": relative_error(y, y0).value}
    if not sc.cands:
        return _no_delta(sys, Q, R, se, crit, cut, "no stable candidate")
    ranked = sorted(sc.cands, key=lambda c: (c[0], c[1]))
    if not ranked[0][0] < crit[("initial", 0)]:
        return _no_delta(sys, Q, R, se, crit, cut, f"BIC {ranked[0][0]:.6g} >= initial "
                                                    f"model's {crit[('initial', 0)]:.6g}")
    sel_error = functools.partial(_sel_error, dd.ys_sel, dd.w, dd.factor)
    # judged on the estimation record only: the candidates in BIC order (those
    # below the initial model's BIC, at most _TAIL_TRIES) until one lowers the
    # plain SE on the whole record and, with its residues fitted on the head,
    # on the held-out tail (a model that fits the head's noise or feedback
    # fails there; PAPER_NOTES §8.6)
    whole, tail = sc.whole, sc.tail
    e0_est, e0_tail = sel_error(y0, whole), sel_error(y0, tail)
    se["initial_tail"] = e0_tail
    failed = []
    for bic, k, name, fit in [c for c in ranked if c[0] < crit[("initial", 0)]][:_TAIL_TRIES]:
        yh = y0 + fit.predict(u)
        e_est = sel_error(yh, whole)
        _, fit_h = sc.score(fit.poles, fit.held, sc.head, tail)
        e_tail = np.inf if fit_h is None else sel_error(y0 + fit_h.predict(u), tail)
        if e_est < e0_est and e_tail <= (1.0 + _TAIL_SLACK) * e0_tail:
            break
        failed.append(f"order {k}: {e_est:.3g} %, tail {e_tail:.3g} %")
    else:
        return _no_delta(sys, Q, R, se, crit, cut,
                         f"no candidate lowers the SE ({e0_est:.3g} %) without raising "
                         f"the held-out tail's ({e0_tail:.3g} %): {'; '.join(failed)}")
    se["delta_tail"] = e_tail
    se["delta_estimation"] = relative_error(y, yh).value
    return _delta_model(sys, Q, R, fit, k, name == "marginal", se, crit, cut, state_prefix)


def _delta_model(sys, Q, R, fit, k: int, marginal: bool, se: dict, crit: dict, cut,
                 state_prefix: str) -> DeltaModel:
    """The improved DeltaModel: ``sys`` beside the delta ``fit`` (its realization and held
    integrators), the delta alone, and the message (``k`` N4SID poles)."""
    A, B, C, D = (np.asarray(a, dtype=float) for a in (sys.A, sys.B, sys.C, sys.D))
    n, (p, m) = A.shape[0], D.shape
    dA, dB, dC = fit.realize()
    nD = dA.shape[0]
    Bm = B.copy()
    hold = fit.held
    rho = 0 if hold is None else hold[0].shape[1]
    if rho:
        U1, VM = hold
        Bm = B + VM @ fit.R0
    Aa = np.block([[A, np.zeros((n, nD))], [np.zeros((nD, n)), dA]])
    Ba = np.vstack([Bm, dB])
    Ca = np.hstack([C, dC])
    Qa = np.zeros((n + nD, n + nD))
    Qa[:n, :n] = Q
    states = list(sys.state_labels) + [f"{state_prefix}[{i}]" for i in range(nD)]
    combined = named_ss(Aa, Ba, Ca, D, sys.dt, states=states, inputs=sys.input_labels,
                        outputs=sys.output_labels, name=f"{sys.name or 'model'}_delta")
    # the delta alone: identified modes, then the held integrators (exactly at 1)
    if rho:
        fA = np.block([[dA, np.zeros((nD, rho))], [np.zeros((rho, nD)), np.eye(rho)]])
        fB, fC = np.vstack([dB, fit.R0]), np.hstack([dC, U1])
    else:
        fA, fB, fC = dA, dB, dC
    delta = named_ss(fA, fB, fC, np.zeros((p, m)), sys.dt,
                     states=[f"{state_prefix}[{i}]" for i in range(nD + rho)],
                     inputs=sys.input_labels,
                     outputs=[f"d{s}" for s in sys.output_labels], name="delta")
    fixed = (f", with {rho} held integrators driving the initial model's own"
             if rho else "")
    msg = (f"parallel model: order {n + nD} (delta order {nD}, {k} N4SID poles{fixed}), "
           f"estimation SE {se['initial_estimation']:.3g} % -> {se['delta_estimation']:.3g} %")
    return DeltaModel(updated=UpdatedModel(sys=combined, Q=Qa, R=R, order=n + nD, kind="delta"),
                      delta=delta, order=nD, improved=True, marginal=marginal,
                      nfixed=rho, refined=True, se=se, criterion=crit,
                      message=msg + cut.note(), bounded=cut.what())


def _no_delta(sys, Q, R, se: dict, crit: dict, cut, why: str) -> DeltaModel:
    """The DeltaModel when no parallel model improves ``sys`` (``why``): sys unchanged."""
    p, m = sys.noutputs, sys.ninputs
    delta = named_ss(np.zeros((0, 0)), np.zeros((0, m)), np.zeros((p, 0)),
                     np.zeros((p, m)), sys.dt, states=[], inputs=sys.input_labels,
                     outputs=[f"d{s}" for s in sys.output_labels], name="delta")
    upd = UpdatedModel(sys=sys, Q=Q, R=R, order=sys.nstates, kind="delta")
    return DeltaModel(updated=upd, delta=delta, order=0, improved=False, marginal=False,
                      nfixed=0, refined=False, se=se, criterion=crit,
                      message=f"parallel model: no improvement found ({why})" + cut.note(),
                      bounded=cut.what())


def _effective_samples(ew) -> float:
    """Effective sample size of the whitened errors ``ew`` (noutputs, nsteps): those of an
    imperfect noise model stay correlated (oversampled data); AR(1) correction
    N (1 - r1) / (1 + r1), r1 the mean lag-1 autocorrelation (in [0, 0.999])."""
    r1 = float(np.mean(np.sum(ew[:, 1:] * ew[:, :-1], axis=1)
                       / np.maximum(np.sum(ew**2, axis=1), np.finfo(float).tiny)))
    r1 = min(max(r1, 0.0), 0.999)
    return max(ew.shape[1] * (1.0 - r1) / (1.0 + r1), 1.0)


def _sel_error(ys_sel, w, factor, yh, sl) -> float:
    """Plain SE (eq. 42) [%] of the outputs ``yh`` in the selection coordinates (scaled by
    ``w``, differenced by ``factor``) against ``ys_sel``, on the samples ``sl``."""
    return relative_error(ys_sel[:, sl], _difference(yh / w[:, None], factor)[:, sl]).value


def _logdet(e) -> float:
    """``log det`` of the covariance of the residuals ``e`` (nsignals, nsteps), floored at
    1e-12 of the mean variance: noise-free data give (near) singular covariances, whose
    -inf would tie every candidate."""
    S = np.atleast_2d(np.cov(e, bias=True))
    S = S + max(1e-12 * np.trace(S) / S.shape[0], np.finfo(float).tiny) * np.eye(S.shape[0])
    sign, ld = np.linalg.slogdet(S)
    return ld if sign > 0 else -np.inf


@dataclass(frozen=True)
class _DeltaScore:
    """The score of a delta candidate: fixed poles (and held integrators), residues fitted
    on the whitened output error ``wdy`` of ``dy`` (:func:`_fit_delta`).

    Called ``(poles, hold, fit_on=whole, score_on=None)``: ``(BIC, fit)`` with the
    effective sample size ``Neff``; with ``score_on`` the fit uses ``fit_on`` and the
    score is ``log det`` on ``score_on``; ``(nan, None)`` when the fit cancels the error.
    """

    wh: object
    u: NDArray = field(repr=False)
    wdy: NDArray = field(repr=False)
    dy: NDArray = field(repr=False)
    whole: slice
    Neff: float

    def __call__(self, poles, hold, fit_on=None, score_on=None):
        wh, u, wdy, dy, m = self.wh, self.u, self.wdy, self.dy, self.u.shape[0]
        fit_on = self.whole if fit_on is None else fit_on
        grams = {}
        fit = _fit_delta(wh, poles, hold, u, wdy, sl=fit_on, grams=grams)
        npar = fit.npar
        if m > 1 and poles.size:
            # one state per pole (rank-one residues, as in an order-k model):
            # input directions from the full-residue fit's SVD, then refit
            dirs = [np.linalg.svd(Rq)[2][:1].T for Rq in fit.residues]
            fit = _fit_delta(wh, poles, hold, u, wdy, dirs, sl=fit_on, grams=grams)
            npar = fit.npar + int(np.sum(np.where(poles.imag == 0.0, 1, 2))) * (m - 1)
        if fit.cancels(u, dy):
            return float("nan"), None
        e = wh.apply(dy - fit.predict(u))
        if score_on is not None:
            return _logdet(e[:, score_on]), fit
        return self.Neff * _logdet(e[:, self.whole]) + npar * np.log(self.Neff), fit


def _n4sid_starts(name: str, data, u, orders, dt: float, horizons, cut, crit: dict,
                  held_only: bool) -> dict:
    """The stable N4SID models ``(A, B, C)`` of one variant's ``data``, keyed ``(name
    [hH], order)`` per horizon and order; an unstable or non-finite one is recorded in
    ``crit`` as nan. ``held_only``: the held integrators alone start too, key
    ``(name, 0)`` (None)."""
    starts = {}
    if held_only:
        starts[(name, 0)] = None  # held integrators only
    for h in horizons:
        if cut.late("N4SID horizons"):
            break
        try:
            fits = _n4sid_fits(data, u, orders, dt, h, late=lambda: cut.late("N4SID orders"))
        except GreyboxError:
            continue  # horizon too long for these data
        for k in orders:
            key = (name if len(horizons) == 1 else f"{name} h{h}", k)
            s_ = fits[k].sys if k in fits else None
            fABC = None if s_ is None else tuple(np.asarray(v, dtype=float)
                                                 for v in (s_.A, s_.B, s_.C))
            if (fABC is None or not all(np.all(np.isfinite(v)) for v in fABC)
                    or spectral_radius(fABC[0]) >= 1.0):
                crit[key] = float("nan")
                continue
            starts[key] = fABC
    return starts


def _refine_poles(ranked, origin: dict, u, rsl: slice, refine_iter: int, score, head, tail,
                  crit: dict, cands: list, cut) -> None:
    """The ``ranked`` candidates' poles refined by output error on the samples ``rsl`` of
    their variant's data (modal form, stable by construction); a refit kept as a new
    candidate (appended to ``cands``) only if, with residues fitted on ``head``, it
    predicts the held-out ``tail`` better than N4SID's poles. Scores go into ``crit``."""
    for _, k, name, key in ranked:
        if cut.late("pole refinement"):
            break
        (fA, fB, fC), data, hold = origin[(name, key)]
        try:
            # output error simulates from rest: from the record's start, not k0
            ref = refine_output_error(fA, fB, fC, u[:, rsl], data[:, rsl],
                                      max_iter=refine_iter)
        except IdentificationError:
            crit[(key[0] + "+oe", k)] = float("nan")
            continue
        if spectral_radius(ref.A) > 1.0 - 1e-6:
            # driven to the parametrization's bound: not a real pole (with process
            # noise in the data a simulation-error fit follows its random walk)
            crit[(key[0] + "+oe", k)] = float("nan")
            continue
        new_poles = _upper_poles(ref.A)
        t_new, _ = score(new_poles, hold, head, tail)
        t_old, _ = score(_upper_poles(fA), hold, head, tail)
        crit[(key[0] + "+oe tail", k)] = t_new - t_old
        if not t_new < t_old:
            continue
        crit[(key[0] + "+oe", k)], fit = score(new_poles, hold)
        if fit is not None:
            cands.append((crit[(key[0] + "+oe", k)], k, name, fit))


def _upper_poles(A: NDArray) -> NDArray:
    """Eigenvalues of A, one of each complex-conjugate pair (complex dtype)."""
    lam = np.linalg.eigvals(A).astype(complex)
    return lam[lam.imag >= 0.0]


def _held_integrators(A: NDArray, C: NDArray):
    """``(U1, V M)`` for the initial model's observed, semisimple eigenvalue 1, or None.

    ``V`` spans ``null(A - I)`` (as many columns as eigenvalues at 1, else the
    eigenvalue is defective and None is returned), ``U1 = orth(C V)`` and
    ``C V M = U1``: a drive ``V M r`` accumulates in the integrators and
    shows as ``U1 r`` in the outputs.
    """
    import scipy.linalg as sla

    V = sla.null_space(A - np.eye(A.shape[0]), rcond=1e-9)
    lam = np.linalg.eigvals(A)
    if V.shape[1] == 0 or V.shape[1] != int(np.sum(np.abs(lam - 1.0) <= 1e-6)):
        return None
    CV = C @ V
    Uc, sv, _ = np.linalg.svd(CV, full_matrices=False)
    rho = int(np.sum(sv > 1e-9 * max(sv[0], np.finfo(float).tiny)))
    if rho == 0:
        return None
    U1 = Uc[:, :rho]
    M = np.linalg.lstsq(CV, U1, rcond=1e-10)[0]
    if np.linalg.norm(CV @ M - U1) > 1e-8:
        return None
    return U1, V @ M


class _Whitener:
    """Innovation filter of the initial model's steady-state Kalman predictor.

    ``e = S^-1/2 (eps - C xt)``, ``xt[k+1] = (A - Kp C) xt[k] + Kp eps[k]``:
    applied to ``eps = dy - dy_hat`` it gives the combined model's one-step
    prediction errors, whitened by the predictor's innovation covariance S.
    ``D`` lists the p x p matrices that weight the base signals of
    :meth:`base` (a signal and its responses through the filter's modes);
    without a well-conditioned modal form only the static part ``S^-1/2``
    is used (``D = [S^-1/2]``).
    """

    def __init__(self, sys, Q, R):
        A, C = (np.asarray(a, dtype=float) for a in (sys.A, sys.C))
        p = C.shape[0]
        Abar = None
        try:
            f = steady_state_filter(sys, Q=Q, R=R)
            Kp, S = A @ f.L, np.asarray(f.innovation_cov)
            Abar = A - Kp @ C
        except GreyboxError:
            Kp, S = np.zeros((A.shape[0], p)), np.asarray(R, dtype=float)
        self.Sih = np.linalg.inv(np.linalg.cholesky(0.5 * (S + S.T)))
        self.D, self.modes = [self.Sih], []
        self.Abar, self.Kp, self.C = None, None, C
        if Abar is None or not Abar.size:
            return
        lam, V = np.linalg.eig(Abar)
        if np.max(np.abs(lam)) >= 1.0 or np.linalg.cond(V) > _MODAL_COND:
            return
        self.Abar, self.Kp = Abar, Kp
        Wv = np.linalg.inv(V)
        for t in range(len(lam)):
            M = self.Sih @ C @ np.outer(V[:, t], Wv[t] @ Kp)
            if lam[t].imag == 0.0:
                self.modes.append(complex(lam[t].real))
                self.D.append(-M.real)
            elif lam[t].imag > 0:
                self.modes.append(complex(lam[t]))
                self.D += [-2.0 * M.real, 2.0 * M.imag]

    def settling(self, N: int, decay: float = 1e-8) -> int:
        """Samples for the predictor's start-up transient to decay by ``decay``
        (at most ``N // 20``; 0 for the static whitening ``S^-1/2``)."""
        if self.Abar is None:
            return 0
        rho = spectral_radius(self.Abar)
        k = 1 if rho <= 0.0 else int(np.ceil(np.log(decay) / np.log(rho)))
        return int(min(max(k, 1), max(N // 20, 1)))

    def apply(self, eps: NDArray) -> NDArray:
        """Whitened one-step prediction errors of the residual ``eps`` (p, N)."""
        if self.Abar is None:
            return self.Sih @ eps
        xt = lti_states(self.Abar, self.Kp @ eps, np.zeros(self.Abar.shape[0]))
        return self.Sih @ (eps - self.C @ xt)

    def base(self, F: NDArray) -> NDArray:
        """Base signals, shape (len(D), J, N): ``F`` and its mode responses."""
        out = [F]
        for mu in self.modes:
            if mu.imag == 0.0:
                out.append(lfilter([0.0, 1.0], [1.0, -mu.real], F, axis=1))
            else:
                h = lfilter([0.0, 1.0], [1.0, -mu], F.astype(complex), axis=1)
                out += [h.real, h.imag]
        return np.stack(out)


def _pole_signals(poles: NDArray, u: NDArray, directions=None):
    """``q^-1 / (1 - pole q^-1) v^T u`` per pole (one of each complex pair) and
    input direction ``v`` (the columns of ``directions[q]``, default: every input).

    Returns (signals (J, N), meta): a complex pole gives the real then the
    imaginary parts; ``meta[j] = (pole index, direction, part)``.
    """
    sig, meta = [], []
    for q, lam in enumerate(poles):
        Vq = np.eye(u.shape[0]) if directions is None else directions[q]
        v = Vq.T @ u
        r = Vq.shape[1]
        if lam.imag == 0.0:
            f = lfilter([0.0, 1.0], [1.0, -lam.real], v, axis=1)
            if np.iscomplexobj(f):
                raise AssertionError("real pole with a complex direction")
            sig.append(f)
            meta += [(q, j, 0) for j in range(r)]
        else:
            f = lfilter([0.0, 1.0], [1.0, -lam], v.astype(complex), axis=1)
            sig += [f.real, f.imag]
            meta += [(q, j, 0) for j in range(r)] + [(q, j, 1) for j in range(r)]
    return (np.vstack(sig) if sig else np.zeros((0, u.shape[1]))), meta


@dataclass(frozen=True)
class _DeltaFit:
    """Fixed-pole delta model: residues of every pole, and of the held integrators."""

    poles: NDArray
    residues: list   # per pole: (p, ninputs) real, or complex Rr - 1j Ri
    held: tuple | None   # (U1, V M) or None
    R0: NDArray      # (rho, ninputs) drive of the held integrators
    npar: int

    def predict(self, u: NDArray) -> NDArray:
        out = np.zeros((self.residues[0].shape[0] if self.residues else
                        self.held[0].shape[0], u.shape[1]))
        for lam, Rq in zip(self.poles, self.residues):
            if lam.imag == 0.0:
                out += Rq @ lfilter([0.0, 1.0], [1.0, -lam.real], u, axis=1)
            else:
                f = lfilter([0.0, 1.0], [1.0, -lam], u.astype(complex), axis=1)
                out += np.real(Rq @ f)
        if self.held is not None:
            out += self.held[0] @ (self.R0 @ lfilter([0.0, 1.0], [1.0, -1.0], u, axis=1))
        return out

    def cancels(self, u: NDArray, dy: NDArray, ratio: float = 1e3) -> bool:
        """True if some pole's contribution exceeds ``ratio`` times the RMS of
        ``dy``: nearly equal poles whose large residues cancel on these data
        (ill-conditioned, and not to be trusted on other inputs)."""
        lim = ratio * max(float(np.sqrt(np.mean(dy**2))), np.finfo(float).tiny)
        for lam, Rq in zip(self.poles, self.residues):
            f = lfilter([0.0, 1.0], [1.0, -lam], u.astype(complex), axis=1)
            if not float(np.sqrt(np.mean(np.real(Rq @ f) ** 2))) <= lim:
                return True
        return False

    def realize(self):
        """(A, B, C) of the identified modes, minimal per pole (residue rank)."""
        blocks = []
        for lam, Rq in zip(self.poles, self.residues):
            U, s, Vh = np.linalg.svd(Rq, full_matrices=False)
            r = int(np.sum(s > 1e-9 * max(s[0] if s.size else 0.0, np.finfo(float).tiny)))
            if r == 0:
                continue
            # balanced: input rows and output columns of equal norm
            Bc = np.sqrt(s[:r, None]) * Vh[:r]
            U = U * np.concatenate([np.sqrt(s[:r]), np.ones(U.shape[1] - r)])[None, :]
            if lam.imag == 0.0:
                blocks.append((lam.real * np.eye(r), np.real(Bc), np.real(U[:, :r])))
            else:
                a, b = lam.real, lam.imag
                Ab = np.block([[a * np.eye(r), -b * np.eye(r)], [b * np.eye(r), a * np.eye(r)]])
                blocks.append((Ab, np.vstack([Bc.real, Bc.imag]),
                               np.hstack([U[:, :r].real, -U[:, :r].imag])))
        p = self.held[0].shape[0] if self.held is not None else self.residues[0].shape[0]
        mi = self.R0.shape[1]
        if not blocks:
            return np.zeros((0, 0)), np.zeros((0, mi)), np.zeros((p, 0))
        import scipy.linalg as sla

        return (sla.block_diag(*[b[0] for b in blocks]), np.vstack([b[1] for b in blocks]),
                np.hstack([b[2] for b in blocks]))


def _direction_map(poles: NDArray, directions, metaf, mi: int):
    """Matrix P with ``F_dir = P^T F_full`` (signals of :func:`_pole_signals` with
    and without input ``directions``), and the meta of ``F_dir``."""
    index = {m_: j for j, m_ in enumerate(metaf)}
    cols, meta = [], []
    for q, (lam, Vq) in enumerate(zip(poles, directions)):
        r = Vq.shape[1]
        parts = (0,) if lam.imag == 0.0 else (0, 1)
        for part in parts:
            for i in range(r):
                col = np.zeros(len(metaf))
                for j in range(mi):
                    vr, vi = Vq[j, i].real, Vq[j, i].imag
                    if lam.imag == 0.0:
                        col[index[(q, j, 0)]] = vr
                    elif part == 0:   # Re(v^T f) = vr Re f - vi Im f
                        col[index[(q, j, 0)]] = vr
                        col[index[(q, j, 1)]] = -vi
                    else:             # Im(v^T f) = vr Im f + vi Re f
                        col[index[(q, j, 1)]] = vr
                        col[index[(q, j, 0)]] = vi
                cols.append(col)
                meta.append((q, i, part))
    return (np.array(cols).T if cols else np.zeros((len(metaf), 0))), meta


def _fit_delta(wh: _Whitener, poles: NDArray, held, u: NDArray, wdy: NDArray,
               directions=None, sl: slice = slice(None), grams: dict | None = None
               ) -> _DeltaFit:
    """Residues of the fixed poles (and held integrators) minimizing the whitened
    one-step prediction errors ``wh.apply(dy - dy_hat)`` (``wdy = wh.apply(dy)``).

    The regressors ``wh.apply(d F_j)`` (direction d, pole signal F_j) are never
    formed: their Gram matrix comes from the Gram matrix of the base signals
    (F and its responses through the whitening filter's modes). A fit with
    every input (``directions`` None) stores those Gram matrices in
    ``grams``; a fit with input ``directions`` on the same poles reuses them
    (its signals are real linear combinations of the full fit's).
    """
    p, mi = wdy.shape[0], u.shape[0]
    key = (sl.start, sl.stop)
    if directions is not None and grams is not None and key in grams:
        GSf, SLf, metaf, Jf = grams[key]
        P, meta = _direction_map(poles, directions, metaf, mi)
        J = P.shape[1]
        if held is not None:
            nh = GSf.shape[1] - Jf
            P = sla.block_diag(P, np.eye(nh))
        GS = np.einsum("ja,tjsk,kb->tasb", P, GSf, P, optimize=True)
        SL = np.einsum("ja,tjp->tap", P, SLf, optimize=True)
    else:
        F, meta = _pole_signals(poles, u, directions)
        J = F.shape[0]
        if held is not None:
            F = np.vstack([F, lfilter([0.0, 1.0], [1.0, -1.0], u, axis=1)])
        base = wh.base(F)
        T = base.shape[0]
        Bs = base[:, :, sl].reshape(T * F.shape[0], -1)
        GS = (Bs @ Bs.T).reshape(T, F.shape[0], T, F.shape[0])
        SL = (Bs @ wdy[:, sl].T).reshape(T, F.shape[0], p)
        if directions is None and grams is not None:
            grams[key] = (GS, SL, meta, J)
    T = GS.shape[0]
    dirs = [np.eye(p)] * J
    jr = [np.repeat(np.arange(J), p)]
    rho = 0
    if held is not None:
        U1 = held[0]
        rho = U1.shape[1]
        dirs += [U1.T] * mi
        jr.append(np.repeat(J + np.arange(mi), rho))
    dirs = np.vstack(dirs) if dirs else np.zeros((0, p))
    jr = np.concatenate(jr).astype(int)
    E = [Dt @ dirs.T for Dt in wh.D]
    nr = dirs.shape[0]
    G = np.zeros((nr, nr))
    b = np.zeros(nr)
    for t in range(T):
        b += np.einsum("pr,rp->r", E[t], SL[t, jr])
        for t2 in range(T):
            G += (E[t].T @ E[t2]) * GS[t][:, t2][np.ix_(jr, jr)]
    s = np.sqrt(np.clip(np.diag(G), np.finfo(float).tiny, None))
    ev, V = np.linalg.eigh(G / np.outer(s, s))
    keep = ev > 1e-10 * max(ev[-1], np.finfo(float).tiny)
    c = (V[:, keep] @ ((V[:, keep].T @ (b / s)) / ev[keep])) / s
    dirs_in = [np.eye(mi)] * len(poles) if directions is None else directions
    coef = [np.zeros((p, Vq.shape[1]), dtype=complex) for Vq in dirs_in]
    for j, (q, i, part) in enumerate(meta):
        # Re((Cr - 1j Ci) f) = Cr Re f + Ci Im f
        coef[q][:, i] += c[j * p:(j + 1) * p] * (1.0 if part == 0 else -1j)
    residues = [Cq @ Vq.T if lam.imag != 0.0 else np.real(Cq @ Vq.T)
                for lam, Cq, Vq in zip(poles, coef, dirs_in)]
    R0 = c[J * p:].reshape(mi, rho).T if rho else np.zeros((0, mi))
    npar = len(c) + int(np.sum(np.where(poles.imag == 0.0, 1, 2)))
    return _DeltaFit(poles=poles, residues=residues, held=held, R0=R0, npar=npar)


def _difference(v: NDArray, factor) -> NDArray:
    """``[P(q) U1^T v; U2^T v]`` for a marginal factor ``(a, T, rho)``; ``v`` if None."""
    if factor is None:
        return v
    a, T, rho = factor
    out = T.T @ v
    out[:rho] = _poly_filter(a, out[:rho])
    return out


def _marginal_factor(A: NDArray, C: NDArray, tol: float = 1e-6):
    """Minimal polynomial of A's unit-circle eigenvalues and the outputs that see them.

    Returns None if A has no eigenvalue within ``tol`` of the unit circle or
    none of those modes is observed in C. Otherwise ``(a, T, rho)``: ``P(q) =
    1 + a[0] q^-1 + ... + a[r-1] q^-r`` (real), ``T = [U1 U2]`` orthogonal with
    ``U1`` (first ``rho`` columns) spanning ``range(C V)``, ``V`` the invariant
    subspace of the unit-circle eigenvalues.
    """
    n = A.shape[0]
    if n == 0:
        return None
    import scipy.linalg as sla

    on = lambda re, im: abs(np.hypot(re, im) - 1) <= tol  # noqa: E731
    Ts, Z, r = sla.schur(A, output="real", sort=on)
    if r == 0:
        return None
    T11 = Ts[:r, :r]
    lam = np.linalg.eigvals(T11)
    scale = max(1.0, float(np.linalg.norm(T11)))
    roots, used = [], np.zeros(r, dtype=bool)
    for i in range(r):
        if used[i]:
            continue
        # cluster of (numerically) equal eigenvalues; multiplicity in the
        # minimal polynomial = Jordan index (rank test on (T11 - l I)^j)
        same = np.abs(lam - lam[i]) <= np.sqrt(tol)
        used |= same
        mu = int(same.sum())
        li = complex(np.mean(lam[same]))
        M = T11 - li * np.eye(r)
        Mj = np.eye(r, dtype=complex)
        index = mu
        for j in range(1, mu + 1):
            Mj = Mj @ M
            sv = np.linalg.svd(Mj, compute_uv=False)
            if int(np.sum(sv > np.sqrt(tol) * scale**j)) <= r - mu:
                index = j
                break
        roots += [li] * index
    a = np.real(np.poly(roots))[1:]
    O = C @ Z[:, :r]
    U, sv, _ = np.linalg.svd(O)
    rho = int(np.sum(sv > 1e-9 * max(1.0, sv[0] if sv.size else 0.0)))
    if rho == 0:
        return None
    return a, U, rho


def _poly_filter(a: NDArray, v: NDArray) -> NDArray:
    """``P(q) v`` with ``P(q) = 1 + sum a_i q^-i``, zero initial conditions."""
    out = v.copy()
    for i, ai in enumerate(a, start=1):
        out[:, i:] += ai * v[:, :-i]
    return out


