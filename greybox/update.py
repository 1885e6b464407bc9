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
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import control as ct
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._lti import lti_states
from ._validation import (
    check_covariance,
    check_discrete,
    check_positive,
    check_same_length,
    check_signal,
    check_vector,
)
from .exceptions import DataError, DimensionError, GreyboxWarning, IdentificationError
from .filters import FilterResult
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
    k0 = skip if skip is not None else max(10, result.period_converged or 10)
    if N - k0 < 50:
        raise DataError(f"only {N - k0} usable samples after the filter transient; "
                        f"at least 50 are needed")
    u = result.u[:, k0:N]
    x = result.x_filt[:, k0:N]
    d = result.d_est[:, k0:N]
    w = np.vstack([u, x])
    m, n, md = u.shape[0], x.shape[0], d.shape[0]
    nw = m + n
    lo = max(min_order, 0 if feedthrough else 1)
    orders = [order] if order is not None else list(range(lo, max_order + 1))
    cands = {}
    for nd in orders:
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
                                     feedthrough=feedthrough, dt=float(result.sys.dt))
                s_ = ident.sys
                Ad, Bw, Cd, Dw = (np.asarray(a, dtype=float) for a in (s_.A, s_.B, s_.C, s_.D))
                K, Re = ident.K, ident.innovation_cov
                how = method
        except (IdentificationError, np.linalg.LinAlgError):
            continue
        if not all(np.all(np.isfinite(M)) for M in (Ad, Bw, Cd, Dw)):
            continue
        if nd and np.max(np.abs(np.linalg.eigvals(Ad))) >= 1.0:
            continue  # unstable subsystem: not a physical candidate (§8.6)
        dsim = _sim_subsystem(Ad, Bw, Cd, Dw, w)
        npar = nd * nd + nd * nw + md * nd + (md * nw if feedthrough else 0)
        cands[nd] = (_bic(d - dsim, npar), Ad, Bw, Cd, Dw, K, Re, how, dsim)
    if not cands:
        raise IdentificationError("no stable subsystem could be identified for orders "
                                  f"{orders}; check the filter result and the data length")
    Pd = np.atleast_2d(result.d_cov)
    # Parsimony with the noise floor in mind: the residual of d^ cannot honestly
    # drop below the filter's own estimation variance Pd; a fit that does is
    # explaining the filter's algebra (PAPER_NOTES §8.4). Take the lowest order
    # whose residual is within 5 % of max(best residual, Pd).
    var = {k: float(np.trace(np.atleast_2d(np.cov(d - v[8], bias=True)))) for k, v in cands.items()}
    floor = 1.05 * max(min(var.values()), float(np.trace(Pd)))
    ok = [k for k in sorted(cands) if var[k] <= floor]
    best = ok[0]  # never empty: the best candidate is within the bound
    _, Ad, Bw, Cd, Dw, K, Re, method, dsim = cands[best]
    labels_u = tuple(result.sys.input_labels)
    labels_x = tuple(result.sys.state_labels)
    return Subsystem(
        order=Ad.shape[0], Ad=Ad, Bdu=Bw[:, :m], Bdx=Bw[:, m:], Cd=Cd, Ddu=Dw[:, :m], Ddx=Dw[:, m:],
        K=K, innovation_cov=np.atleast_2d(Re), noise_cov=psd_part(np.atleast_2d(Re) - Pd),
        criterion={k: v[0] for k, v in cands.items()}, method=method,
        feedthrough=feedthrough, d_sim=dsim, input_labels=labels_u, state_labels=labels_x,
        unknown_labels=tuple(result.unknown_labels),
    )


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
        "dynamic", "static" or "delta".
    """

    sys: ct.StateSpace
    Q: NDArray[np.float64]
    R: NDArray[np.float64]
    order: int
    kind: str


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
    states = list(base.state_labels) + [f"{state_prefix}[{i}]" for i in range(nd)]
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
        improvement was found); ``updated.order = n + order``. The fixed
        unit-circle states are not among them when they could be merged
        into the initial model's own integrators (see :func:`delta_update`).
    improved : bool
        False if no stable candidate lowered both the held-out SE and the
        estimation-record SE of the initial model: "parallel model: no
        improvement found".
    marginal : bool
        True if the initial model's unit-circle modes were factored out
        (chosen by the held-out SE, see :func:`delta_update`).
    nfixed : int
        Fixed states of ``delta`` (the initial model's unit-circle modes in
        series).
    refined : bool
        True if the output-error refinement was kept.
    se : dict of str to float
        Errors (eq. 42, relative RMS) [%]: ``"initial_holdout"`` and
        ``"delta_holdout"`` (held-out score in the selection coordinates of
        :func:`delta_update`), ``"initial_estimation"`` and ``"delta_estimation"`` (plain SE on the
        whole estimation record); keys are missing for steps not reached.
    criterion : dict of (str, int) to float
        Held-out score [%] of every candidate ``(variant, order)``, variant
        "plain", "marginal", or with "+oe" the refined winner; NaN for
        rejected (unstable) candidates.
    message : str
        One line for reports, e.g. "parallel model: no improvement found".
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


def _n4sid_fits(data: NDArray, u: NDArray, orders, dt: float, horizon: int | None):
    """N4SID models of several orders sharing one block-Hankel factor; {order: result}."""
    from .ident._hankel import hankel_r, small_blas
    from .ident.n4sid import (
        DEFAULT_RTOL,
        _choose_horizon,
        _common_setup,
        _n4sid_from_factor,
    )

    (ys, us, l, m, dt, il, ol, fed, _, _, rtol, sy, su) = _common_setup(
        data, u, dt, None, None, False, None, max(orders), DEFAULT_RTOL)
    i = _choose_horizon(horizon, None, [ys[0].shape[1]], m, l, max(orders), lambda k: 2 * k)
    h = hankel_r(ys, us, sy, su, 2 * i, chunk_size=None)
    out = {}
    with small_blas(), warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore", GreyboxWarning)
        for k in orders:
            if k > (i - 1) * l:
                continue
            try:
                out[k] = _n4sid_from_factor(h, i, ys, us, l, m, dt, il, ol, fed, k, None,
                                            rtol, sy, su, "N4SID", "bic", "z")
            except (IdentificationError, np.linalg.LinAlgError):
                continue
    return out


def _spectral_radius(A: NDArray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(A)))) if A.size else 0.0


def delta_update(sys: ct.StateSpace, y: ArrayLike, u: ArrayLike, *, Q: ArrayLike,
                 R: ArrayLike, order: int | None = None, max_order: int | None = None,
                 horizon: int | None = None, x0: ArrayLike | None = None,
                 marginal: bool | None = None, holdout: float = 0.25, refine: bool = True,
                 refine_iter: int = 20, refine_window: int | None = None,
                 state_prefix: str = "delta") -> DeltaModel:
    """Parallel delta augmentation: a model from u to the output error, run beside ``sys``.

    ``dy = y - y_initial`` (the initial model's simulated output) is modelled
    from ``u`` (open-loop data: u does not depend on the noise), eqs. (21)-(24).
    The procedure, in order:

    1. **Candidates.** Every order ``1..max_order`` is identified with N4SID
       (:func:`greybox.ident.n4sid`, one block-Hankel factor shared by all
       orders) on the first ``1 - holdout`` of the record, in two variants:
       "plain" (``u -> dy``) and "marginal" (the initial model's unit-circle
       modes factored out, below), when ``sys`` has such modes that the
       outputs see.
    2. **Stability.** A candidate whose identified part has a pole on or
       outside the unit circle is rejected (not mirrored): it would diverge
       in simulation (PAPER_NOTES §8.6).
    3. **Selection.** Each stable candidate is simulated over the whole
       record from rest and scored on the held-out tail by eq. (42)
       (relative RMS) of ``y - y_initial - dy_hat`` against ``y``, both taken
       in the *selection coordinates*: ``[P(q) U1^T W .; U2^T W .]`` when the
       initial model has observed unit-circle modes (below), else ``W .``.
       Differencing the channels that see those modes removes the random
       walk that process noise drives through them, which otherwise swamps
       any simulation error on estimation data (PAPER_NOTES §8.6). The
       candidate with the lowest score wins: this one rule chooses the order
       *and* the variant. (A second condition, a lower plain SE on the tail
       with both models restarted from a least-squares state, was tried and
       made the choice worse on every test plant: that state is poorly
       determined from a short window.)
    4. **Refinement.** The winner is refined by output error on its own
       identification data (``dy``, or its differenced form)
       (:func:`greybox.ident.modal_oe.refine_output_error`: poles kept
       inside the unit circle by construction, C by least squares) on the
       first part of the record, and kept if that lowers the held-out score.
       An unrefined winner is refitted by N4SID on the whole record (kept if
       stable).
    5. **No improvement.** If there is no stable candidate, or the winner's
       held-out score is not below the initial model's, or the final model
       does not lower the initial model's score over the whole estimation
       record (same coordinates) *and* its plain SE there, the
       initial model is returned with ``improved=False``, order 0 and
       ``message`` starting "parallel model: no improvement found". The
       returned model therefore never diverges in simulation.

    **Marginal modes of the initial model.** ``dy = (G_true - G_initial) u``
    has the initial model's unit-circle poles (e.g. integrators) unless the
    truth has them too with the same residues; a delta model with a pole
    *near* 1 cannot cancel such a drift. With ``P(q) = prod (1 - lambda
    q^-1)`` over the *minimal* polynomial of those eigenvalues (a semisimple
    double integrator counts once) and ``U1`` an orthonormal basis of the
    output directions in which they are observed (``range(W C V)``, ``V``
    their invariant subspace, ``W`` the output scaling below; ``U2`` its
    complement), the "marginal" candidates are identified from ``u`` to
    ``[P(q) U1^T W dy; U2^T W dy]`` and ``1/P(q)`` is placed in series on the
    ``U1`` channels as ``deg P * rank(C V)`` fixed states (``nfixed``), with
    exactly the initial model's unit-circle eigenvalues (marginally stable
    like the initial model itself, never unstable). ``DeltaModel.delta``
    holds that series form. In the combined model, when ``P(q) = 1 - q^-1``
    and the eigenvalue 1 of ``A`` is semisimple (integrators, as in the tape
    drive), the fixed states are not duplicated: the identified part's
    differenced output drives the initial model's own integrators through
    ``V M`` (``A V = V``, ``C V M = W^-1 U1``). The input-output behaviour
    is the same; a second set of integrators observed through the same
    outputs would be an unobservable mode on the unit circle, and the
    combined model could not be used for a Kalman filter or an LQ design.

    Scaling: every output is divided by its RMS (``W``) before
    identification, so the least-squares costs weigh the channels as eq. (42)
    does.

    Noise of the combined model: ``Q = blockdiag(Q, K_d Re K_d^T)`` and, as
    its output noise, ``R = Re``, the delta model's N4SID innovation
    covariance (it contains the measurement noise); the cross-covariance is
    neglected. With factored marginal modes the innovations of the ``U1``
    channels also drive the fixed states.

    Parameters
    ----------
    sys : control.StateSpace
        Discrete initial model from the known inputs (no unknown-input channels).
    y : array_like, shape (noutputs, nsteps)
    u : array_like, shape (ninputs, nsteps)
    Q : array_like, shape (nstates, nstates)
    R : array_like, shape (noutputs, noutputs)
    order : int, optional
        Order of the identified part of the delta model (skips the order
        selection; the variant is still chosen on the held-out tail).
    max_order : int, optional
        Highest order tried; default ``n + 6`` (the exact delta
        ``G_true - G_initial`` has order up to ``n_true + n``; the paper's
        parallel model had order 12 for n = 6).
    horizon : int, optional
        N4SID horizon; default ``max(10, ceil(max_order / noutputs) + 1)``.
    x0 : array_like, shape (nstates,), optional
        Initial state of the initial model's simulation.
    marginal : bool, optional
        None (default): try both variants and let the held-out SE choose.
        True / False: only the "marginal" / "plain" variant.
    holdout : float
        Fraction of the record (its tail) held out for the selection,
        in (0, 0.5].
    refine : bool
        Refine the chosen model by output error (step 4).
    refine_iter : int
        Iteration limit of the output-error refinement.
    refine_window : int, optional
        Refine on at most this many samples (the first of the estimation
        part); default all of them. Its cost grows with the samples (a dense
        Jacobian of ``noutputs * samples`` rows), the model it returns hardly
        does beyond ~1e5; the held-out check still uses the whole tail.
    state_prefix : str

    Returns
    -------
    DeltaModel

    Raises
    ------
    DataError
        Bad ``holdout``, or fewer than 200 samples.

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
    >>> dm = delta_update(sys, y, u, Q=[[1e-6]], R=[[1e-6]])
    >>> dm.improved, dm.order, dm.message[:36]
    (False, 0, 'parallel model: no improvement found')
    """
    check_discrete(sys)
    y = check_signal(y, sys.noutputs, "y", min_steps=200)
    u = check_signal(u, sys.ninputs, "u")
    N = check_same_length(("y", y), ("u", u))
    holdout = float(holdout)
    if not 0.0 < holdout <= 0.5:
        raise DataError(f"holdout must be in (0, 0.5]; found {holdout}")
    n = sys.nstates
    Q = check_covariance(Q, n, "Q", definite=False)
    R = check_covariance(R, sys.noutputs, "R", definite=True)
    if order is not None:
        order = check_positive(order, "order", integer=True)
    if max_order is not None:
        max_order = check_positive(max_order, "max_order", integer=True)
    if refine_window is not None:
        refine_window = check_positive(refine_window, "refine_window", integer=True)
    A, B, C, D = (np.asarray(a, dtype=float) for a in (sys.A, sys.B, sys.C, sys.D))
    x = lti_states(A, B @ u, np.zeros(n) if x0 is None else check_vector(x0, n, "x0"))
    y0 = C @ x + D @ u
    dy = y - y0
    p, m = dy.shape[0], u.shape[0]
    Ne = N - int(round(holdout * N))
    tail = slice(Ne, N)
    w = np.sqrt(np.mean(y**2, axis=1))
    w[w == 0] = 1.0
    dys = dy / w[:, None]

    variants = {}
    factor = _marginal_factor(A, C / w[:, None]) if marginal is not False else None
    if marginal is not True or factor is None:
        variants["plain"] = (dys, None)
    if factor is not None:
        variants["marginal"] = (_difference(dys, factor), factor)
    # selection coordinates: the initial model's unit-circle modes differenced out
    ys_sel = _difference(y / w[:, None], factor)
    max_order = max_order if max_order is not None else n + 6
    orders = [order] if order is not None else list(range(1, max_order + 1))
    head, tail = slice(0, Ne), slice(Ne, N)

    def model_of(fit):
        """(A, B, C, K, Re) of an N4SID fit (scaled outputs), or None if unstable."""
        s_ = fit.sys
        fA, fB, fC = (np.asarray(v, dtype=float) for v in (s_.A, s_.B, s_.C))
        if _spectral_radius(fA) >= 1.0:
            return None
        K = fit.K if fit.K.shape == (fA.shape[0], p) else np.zeros((fA.shape[0], p))
        return (fA, fB, fC, K, fit.innovation_cov)

    def refined(part, data, sl):
        """Output-error refinement of a delta model on the samples ``sl``, or None."""
        fA, fB, fC, K, Re = part
        try:
            ref = refine_output_error(fA, fB, fC, u[:, sl], data[:, sl], max_iter=refine_iter)
        except IdentificationError:
            return None
        if _spectral_radius(ref.A) > 1.0 - 1e-6:
            return None  # driven to the parametrization's bound: not a real pole
        return (ref.A, ref.B, ref.C, np.linalg.solve(ref.T, K), Re)

    def tail_error(part, fac):
        """Held-out criterion [%]: eq. (42) on the tail, in the selection coordinates."""
        if part is None:
            return float("nan")
        dA, dB, dC, _, _ = _assemble(*part, fac)
        with np.errstate(over="ignore", invalid="ignore"):
            e = _difference(dys - _simulate(dA, dB, dC, u), factor)
        if not np.all(np.isfinite(e)):
            return float("nan")
        return relative_error(ys_sel[:, tail], ys_sel[:, tail] - e[:, tail]).value

    crit, cands = {}, []
    for name, (data, fac) in variants.items():
        fits = _n4sid_fits(data[:, head], u[:, head], orders, float(sys.dt), horizon)
        for k in orders:
            part = model_of(fits[k]) if k in fits else None
            crit[(name, k)] = tail_error(part, fac)
            if np.isfinite(crit[(name, k)]):
                cands.append((crit[(name, k)], name, k, False, part))
    se = {"initial_holdout": relative_error(
        ys_sel[:, tail], _difference(y0 / w[:, None], factor)[:, tail]).value,
        "initial_estimation": relative_error(y, y0).value}

    def no_improvement(why):
        delta = named_ss(np.zeros((0, 0)), np.zeros((0, m)), np.zeros((p, 0)),
                         np.zeros((p, m)), sys.dt, states=[], inputs=sys.input_labels,
                         outputs=[f"d{s}" for s in sys.output_labels], name="delta")
        upd = UpdatedModel(sys=sys, Q=Q, R=R, order=n, kind="delta")
        return DeltaModel(updated=upd, delta=delta, order=0, improved=False, marginal=False,
                          nfixed=0, refined=False, se=se, criterion=crit,
                          message=f"parallel model: no improvement found ({why})")

    if not cands:
        return no_improvement("no stable candidate")
    best = min(cands, key=lambda c: (c[0], c[2]))
    se_best, name, k, _, part = best
    data, fac = variants[name]
    rsl = head if refine_window is None else slice(0, min(Ne, refine_window))
    rpart = refined(part, data, rsl) if refine else None
    se_ref = tail_error(rpart, fac)
    crit[(name + "+oe", k)] = se_ref
    use_refine = bool(np.isfinite(se_ref) and se_ref < se_best)
    if use_refine:
        se_best, part = se_ref, rpart
    se["delta_holdout"] = se_best
    if not se_best < se["initial_holdout"]:
        return no_improvement(f"best held-out error {se_best:.3g} % >= initial "
                              f"{se['initial_holdout']:.3g} %")
    if not use_refine:
        # N4SID on the whole record; the estimation-part model if that is unstable
        full = _n4sid_fits(data, u, [k], float(sys.dt), horizon)
        fpart = model_of(full[k]) if k in full else None
        part = fpart if fpart is not None else part
    part = _balance(*part)
    model = _assemble(*part, fac)
    yh = y0 + _simulate(*model[:3], u) * w[:, None]
    se["delta_estimation"] = relative_error(y, yh).value
    e_est = relative_error(ys_sel, _difference(yh / w[:, None], factor)).value
    e0_est = relative_error(ys_sel, _difference(y0 / w[:, None], factor)).value
    if not e_est < e0_est:
        return no_improvement(f"estimation error {e_est:.3g} % >= initial {e0_est:.3g} %")
    if not se["delta_estimation"] < se["initial_estimation"]:
        return no_improvement(f"estimation SE {se['delta_estimation']:.3g} % >= initial "
                              f"{se['initial_estimation']:.3g} %")
    dA, dB, dC, Kd, Re = model
    # unscale the outputs: dy = W dys
    dC = dC * w[:, None]
    Kd = Kd / w[None, :]
    Re = Re * np.outer(w, w)
    nD = dA.shape[0]
    dD = np.zeros((p, m))
    merge = _merge_drive(A, C / w[:, None], fac) if fac is not None else None
    if merge is None:
        Aa = np.block([[A, np.zeros((n, nD))], [np.zeros((nD, n)), dA]])
        Ba = np.vstack([B, dB])
        Ca = np.hstack([C, dC])
        Qa = np.block([[Q, np.zeros((n, nD))], [np.zeros((nD, n)), Kd @ Re @ Kd.T]])
        nc = nD
    else:
        # the fixed integrators accumulate in the initial model's own integrators
        fA, fB, fC, K, Re_r = part
        rho = fac[2]
        Aa = np.block([[A, merge @ fC[:rho]], [np.zeros((k, n)), fA]])
        Ba = np.vstack([B, fB])
        Ca = np.hstack([C, (fac[1] @ fC) * w[:, None]])
        Kaug = np.vstack([np.hstack([merge, np.zeros((n, p - rho))]), K])
        Qa = Kaug @ Re_r @ Kaug.T
        Qa[:n, :n] += Q
        nc = k
    states = list(sys.state_labels) + [f"{state_prefix}[{i}]" for i in range(nc)]
    combined = named_ss(Aa, Ba, Ca, D + dD, sys.dt, states=states, inputs=sys.input_labels,
                        outputs=sys.output_labels, name=f"{sys.name or 'model'}_delta")
    # output noise: the delta innovation covariance, kept positive definite
    Rc = psd_part(Re) + 1e-12 * max(np.trace(R), 1e-300) * np.eye(sys.noutputs)
    delta = named_ss(dA, dB, dC, dD, sys.dt,
                     states=[f"{state_prefix}[{i}]" for i in range(nD)],
                     inputs=sys.input_labels,
                     outputs=[f"d{s}" for s in sys.output_labels], name="delta")
    nfixed = nD - k
    fixed = ""
    if nfixed:
        fixed = (f", with {nfixed} fixed unit-circle states"
                 + (" merged into the initial model's integrators" if merge is not None else ""))
    msg = (f"parallel model: order {n + nc} (delta order {nD}{fixed}), estimation SE "
           f"{se['initial_estimation']:.3g} % -> {se['delta_estimation']:.3g} %")
    return DeltaModel(updated=UpdatedModel(sys=combined, Q=0.5 * (Qa + Qa.T), R=Rc,
                                           order=n + nc, kind="delta"),
                      delta=delta, order=nc, improved=True, marginal=fac is not None,
                      nfixed=nfixed, refined=use_refine, se=se, criterion=crit, message=msg)


def _balance(fA, fB, fC, K, Re):
    """Diagonal similarity giving every state equal input-row and output-column norms."""
    nb = np.linalg.norm(fB, axis=1)
    nc = np.linalg.norm(fC, axis=0)
    sc = np.sqrt(np.where((nb > 0) & (nc > 0), nb / np.where(nc > 0, nc, 1.0), 1.0))
    return fA * (sc[None, :] / sc[:, None]), fB / sc[:, None], fC * sc[None, :], \
        K / sc[:, None], Re


def _merge_drive(A: NDArray, Cs: NDArray, factor):
    """Input matrix ``V M`` that accumulates the differenced delta output in ``A``'s own
    integrators, or None if that realization does not apply.

    Applies when ``P(q) = 1 - q^-1`` and the eigenvalue 1 of ``A`` is semisimple
    (``A V = V`` for a basis ``V`` of its eigenspace); ``M`` solves
    ``Cs V M = U1`` (``U1`` lies in ``range(Cs V)`` by construction).
    """
    import scipy.linalg as sla

    a, T, rho = factor
    if a.shape != (1,) or abs(a[0] + 1.0) > 1e-12:
        return None
    V = sla.null_space(A - np.eye(A.shape[0]), rcond=1e-9)
    lam = np.linalg.eigvals(A)
    if V.shape[1] != int(np.sum(np.abs(lam - 1.0) <= 1e-6)):
        return None  # a Jordan block at 1: keep the fixed states
    CV = Cs @ V
    M = np.linalg.lstsq(CV, T[:, :rho], rcond=1e-10)[0]
    if np.linalg.norm(CV @ M - T[:, :rho]) > 1e-8 * max(1.0, np.linalg.norm(CV)):
        return None
    return V @ M


def _assemble(fA, fB, fC, K, Re, factor):
    """The delta model in scaled output coordinates, with the fixed factor if any."""
    p = fC.shape[0]
    if factor is None:
        return fA, fB, fC, K, Re
    Aa, Ba, Ca, _, Ka, Rea = _series_marginal(fA, fB, fC, np.zeros((p, fB.shape[1])), K, Re,
                                              *factor)
    return Aa, Ba, Ca, Ka, Rea


def _simulate(A: NDArray, B: NDArray, C: NDArray, u: NDArray) -> NDArray:
    """Output of ``(A, B, C)`` from rest."""
    return C @ lti_states(A, B @ u, np.zeros(A.shape[0]))


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


def _series_marginal(fA, fB, fC, fD, K, Re, a, T, rho):
    """Realize ``T [1/P(q) I_rho, 0; 0, I] G_f`` (G_f in innovation form).

    The fixed states hold the last ``r = deg P`` values of the first ``rho``
    outputs ``w = v / P(q)``: ``w[k] = v[k] - sum a_i w[k-i]``.
    """
    nf, r, p = fA.shape[0], len(a), fC.shape[0]
    C1, C2, D1 = fC[:rho], fC[rho:], fD[:rho]
    Arow = np.kron(a[None, :], np.eye(rho))            # rho x rho*r: sum a_i w[k-i]
    As = np.zeros((rho * r, rho * r))
    As[rho:, :-rho] = np.eye(rho * (r - 1))
    As[:rho] -= Arow
    E1 = np.vstack([np.eye(rho), np.zeros((rho * (r - 1), rho))])   # writes w[k] into s
    Aa = np.block([[fA, np.zeros((nf, rho * r))], [E1 @ C1, As]])
    Ba = np.vstack([fB, E1 @ D1])
    Ce = np.vstack([np.hstack([C1, -Arow]), np.hstack([C2, np.zeros((p - rho, rho * r))])])
    Ca = T @ Ce
    Da = T @ fD
    Ia = np.hstack([np.eye(rho), np.zeros((rho, p - rho))])
    Ka = np.vstack([K, E1 @ Ia])
    # innovations in dy coordinates: e_dy = T e, so K_dy = Ka T^T, Re_dy = T Re T^T
    return Aa, Ba, Ca, Da, Ka @ T.T, T @ Re @ T.T
