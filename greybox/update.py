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
from .ident import n4sid, pbsid
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


def _psd_part(S: NDArray) -> NDArray:
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    return (V * np.clip(w, 0, None)) @ V.T


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
        BIC of the simulated d^ for every order tried.
    method : str
        "least squares" (order 0), "output-error" or "pbsid".
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
        Subsystem order; None chooses it in ``0..max_order`` by the BIC of the
        simulated d^ (``N log det(cov(d^ - d_sim)) + npar log N``). Order 0 is
        a static law and needs ``feedthrough=True``.
    max_order : int
        Largest order tried when ``order`` is None. The order is the lowest
        whose residual variance is within 5 % of max(the best candidate's,
        the filter's Pd), see Notes.
    min_order : int
        Smallest order tried when ``order`` is None (1 forces dynamics).
    feedthrough : bool
        Allow the direct terms Ddu, Ddx (our generalization). False forces the
        paper's structure (30)-(31): d is then a delayed function of x and u.
    method : {"output-error", "pbsid"}
        Identification of the dynamic candidates: output-error separable
        least squares (:func:`greybox.ident.oe.output_error`, default; its
        regressors are filtered inputs only, consistent on the filter's
        closed-loop data) or the predictor-based subspace method. PBSID's
        past-output regressors are exactly collinear with the inputs here
        (d^[k-1] is a linear function of x^[k], x^[k-1], u[k-1]), so it
        returns poorly determined models on C = I data.
    starts : int
        Starting pole sets of the output-error search.
    horizon : int, optional
        Past horizon of :func:`greybox.ident.pbsid`; default ``order + 1``.
        Short horizons suit the filter's data: the regressors (u, x^) are
        strongly oversampled and, through the filter's own algebra, nearly
        collinear over long windows (PAPER_NOTES §8.4, §8.7).
    skip : int, optional
        Leading samples left out (filter transient); default: the sample where
        the filter's gains converged, at least 10.

    Returns
    -------
    Subsystem

    Notes
    -----
    Alignment: ``d^[j]`` (the estimate of ``d[j]``, made from ``y[j+1]``) is
    paired with ``(u[j], x^[j|j])``; both inputs depend on measurements up to
    ``j`` only, so the direct terms are identifiable (PAPER_NOTES §8.4).
    """
    if not isinstance(result, FilterResult) or result.d_est.shape[0] == 0:
        raise DataError("identify_subsystem needs the FilterResult of greybox.uikf "
                        "(with at least one unknown input)")
    if method not in ("output-error", "pbsid"):
        raise DataError(f"method must be 'output-error' or 'pbsid'; found {method!r}")
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
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", GreyboxWarning)
                    ident = pbsid(d, w, order=nd, horizon=horizon or nd + 1,
                                  feedthrough=feedthrough, dt=float(result.sys.dt))
                s_ = ident.sys
                Ad, Bw, Cd, Dw = (np.asarray(a, dtype=float) for a in (s_.A, s_.B, s_.C, s_.D))
                K, Re = ident.K, ident.innovation_cov
                how = "pbsid"
        except IdentificationError:
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
    # whose residual is within 5 % of max(best residual, Pd); BIC breaks ties.
    var = {k: float(np.trace(np.atleast_2d(np.cov(d - v[8], bias=True)))) for k, v in cands.items()}
    floor = 1.05 * max(min(var.values()), float(np.trace(Pd)))
    ok = [k for k in sorted(cands) if var[k] <= floor]
    best = ok[0] if ok else min(cands, key=lambda k: cands[k][0])
    _, Ad, Bw, Cd, Dw, K, Re, method, dsim = cands[best]
    labels_u = tuple(result.sys.input_labels)
    labels_x = tuple(result.sys.state_labels)
    return Subsystem(
        order=Ad.shape[0], Ad=Ad, Bdu=Bw[:, :m], Bdx=Bw[:, m:], Cd=Cd, Ddu=Dw[:, :m], Ddx=Dw[:, m:],
        K=K, innovation_cov=np.atleast_2d(Re), noise_cov=_psd_part(np.atleast_2d(Re) - Pd),
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
                  R: ArrayLike, state_prefix: str = "z") -> UpdatedModel:
    """Augment a model with its identified subsystem, eqs. (30)-(31) with feedthrough.

    .. math::

        \\begin{bmatrix} x \\\\ z \\end{bmatrix}_{k+1} =
        \\begin{bmatrix} A + G D_{dx} & G C_d \\\\ B_{dx} & A_d \\end{bmatrix}
        \\begin{bmatrix} x \\\\ z \\end{bmatrix}_k +
        \\begin{bmatrix} B + G D_{du} \\\\ B_{du} \\end{bmatrix} u_k

    A static law (order 0) is folded into A and B. Noise: with the
    subsystem's innovation e (covariance R_nu = ``subsystem.noise_cov``),
    ``Q_aug = [[Q + G R_nu G^T, G R_nu K^T], [K R_nu G^T, K R_nu K^T]]``.

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
    out = named_ss(Aa, Ba, Ca, D, base.dt, states=states, inputs=base.input_labels,
                   outputs=base.output_labels, name=f"{base.name or 'model'}_updated")
    return UpdatedModel(sys=out, Q=0.5 * (Qa + Qa.T), R=R, order=n + nd,
                        kind="static" if nd == 0 else "dynamic")


@dataclass(frozen=True)
class DeltaModel:
    """Parallel delta-augmentation baseline (21)-(24).

    Attributes
    ----------
    updated : UpdatedModel
        The combined model of order n + n_delta.
    delta : control.StateSpace
        The delta model from u to the output error.
    order : int
        n_delta.
    stabilized : bool
        True if the chosen delta model was unstable as identified and its
        poles were mirrored into the unit circle.
    """

    updated: UpdatedModel
    delta: ct.StateSpace
    order: int
    stabilized: bool


def delta_update(sys: ct.StateSpace, y: ArrayLike, u: ArrayLike, *, Q: ArrayLike,
                 R: ArrayLike, order: int | None = None, max_order: int = 8,
                 horizon: int | None = None, x0: ArrayLike | None = None,
                 state_prefix: str = "delta") -> DeltaModel:
    """Parallel delta augmentation: a model from u to the output error, run beside ``sys``.

    ``dy = y - y_initial`` (the initial model's simulated output) is identified
    from ``u`` with :func:`greybox.ident.n4sid` (open-loop data: u does not
    depend on the noise). Every order in ``1..max_order`` (or the given
    ``order``) is identified; an unstable candidate (PAPER_NOTES §8.6) has its
    unstable poles mirrored into the unit circle and B, D refitted by least
    squares; the order is chosen by the BIC of the simulated output error.

    Noise of the combined model: ``Q = blockdiag(Q, K_d Re K_d^T)`` and, as
    its output noise, ``R = Re``, the delta model's innovation covariance
    (it contains the measurement noise); the cross-covariance is neglected.

    Parameters
    ----------
    sys : control.StateSpace
        Discrete initial model from the known inputs (no unknown-input channels).
    y : array_like, shape (noutputs, nsteps)
    u : array_like, shape (ninputs, nsteps)
    Q : array_like, shape (nstates, nstates)
    R : array_like, shape (noutputs, noutputs)
    order : int, optional
    max_order : int
    horizon : int, optional
    x0 : array_like, shape (nstates,), optional
        Initial state of the initial model's simulation.
    state_prefix : str

    Returns
    -------
    DeltaModel
    """
    check_discrete(sys)
    y = check_signal(y, sys.noutputs, "y", min_steps=20)
    u = check_signal(u, sys.ninputs, "u")
    check_same_length(("y", y), ("u", u))
    n = sys.nstates
    Q = check_covariance(Q, n, "Q", definite=False)
    R = check_covariance(R, sys.noutputs, "R", definite=True)
    A, B, C, D = (np.asarray(a, dtype=float) for a in (sys.A, sys.B, sys.C, sys.D))
    x = lti_states(A, B @ u, np.zeros(n) if x0 is None else check_vector(x0, n, "x0"))
    dy = y - (C @ x + D @ u)
    orders = [order] if order is not None else list(range(1, max_order + 1))
    best = None
    for k in orders:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", GreyboxWarning)
                cand = n4sid(dy, u, order=k, horizon=horizon or max(5, k + 1),
                             dt=float(sys.dt))
        except IdentificationError:
            continue
        cA, cB, cC, cD = (np.asarray(a, dtype=float) for a in
                          (cand.sys.A, cand.sys.B, cand.sys.C, cand.sys.D))
        mirrored = _unstable(cA)
        if mirrored:
            cA, cB, cD = _mirror_and_refit(cA, cC, dy, u)
        xs = lti_states(cA, cB @ u, np.zeros(cA.shape[0]))
        resid = dy - cC @ xs - cD @ u
        if not np.all(np.isfinite(resid)):
            continue
        npar = k * k + k * u.shape[0] + dy.shape[0] * k
        score = _bic(resid, npar)
        if best is None or score < best[0]:
            best = (score, cA, cB, cC, cD, cand, mirrored)
    if best is None:
        raise IdentificationError(f"no delta model could be identified for orders {orders}")
    _, dA, dB, dC, dD, ident, stabilized = best
    nD = dA.shape[0]
    Aa = np.block([[A, np.zeros((n, nD))], [np.zeros((nD, n)), dA]])
    Ba = np.vstack([B, dB])
    Ca = np.hstack([C, dC])
    Da = D + dD
    Kd = ident.K if ident.K.shape[0] == nD else np.zeros((nD, sys.noutputs))
    Re = ident.innovation_cov
    Qa = np.block([[Q, np.zeros((n, nD))], [np.zeros((nD, n)), Kd @ Re @ Kd.T]])
    states = list(sys.state_labels) + [f"{state_prefix}[{i}]" for i in range(nD)]
    combined = named_ss(Aa, Ba, Ca, Da, sys.dt, states=states, inputs=sys.input_labels,
                        outputs=sys.output_labels, name=f"{sys.name or 'model'}_delta")
    # output noise: the delta innovation covariance, kept positive definite
    Rc = _psd_part(Re) + 1e-12 * max(np.trace(R), 1e-300) * np.eye(sys.noutputs)
    delta = named_ss(dA, dB, dC, dD, sys.dt, states=states[n:], inputs=sys.input_labels,
                     outputs=[f"d{s}" for s in sys.output_labels], name="delta")
    return DeltaModel(updated=UpdatedModel(sys=combined, Q=0.5 * (Qa + Qa.T),
                                           R=Rc,
                                           order=n + nD, kind="delta"),
                      delta=delta, order=nD, stabilized=stabilized)


def _unstable(A: NDArray, tol: float = 1e-6) -> bool:
    return A.size > 0 and bool(np.max(np.abs(np.linalg.eigvals(A))) > 1 + tol)


def _mirror_and_refit(A, C, dy, u):
    """Mirror unstable poles into the unit circle (modal form), refit B and D by LS."""
    lam, V = np.linalg.eig(A)
    lam = np.where(np.abs(lam) > 1, 1 / np.conj(lam), lam)
    A2 = np.real(V @ np.diag(lam) @ np.linalg.inv(V))
    n, m = A2.shape[0], u.shape[0]
    # output of unit-B columns: regressors for B (n*m) and D (p*m)
    p, N = dy.shape
    cols = []
    for i in range(n):
        for j in range(m):
            Bij = np.zeros((n, m))
            Bij[i, j] = 1.0
            xs = lti_states(A2, Bij @ u, np.zeros(n))
            cols.append((C @ xs).reshape(-1))
    for i in range(p):
        for j in range(m):
            Dij = np.zeros((p, m))
            Dij[i, j] = 1.0
            cols.append((Dij @ u).reshape(-1))
    theta, *_ = np.linalg.lstsq(np.array(cols).T, dy.reshape(-1), rcond=1e-10)
    return A2, theta[:n * m].reshape(n, m), theta[n * m:].reshape(p, m)
