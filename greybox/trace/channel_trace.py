"""Trace one candidate channel: unknown-input filter, static and dynamic laws."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import control as ct
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize_scalar
from scipy.signal import lfilter

from .._lti import lti_states
from .._validation import check_discrete, check_positive
from ..exceptions import DataError, GreyboxError, GreyboxWarning, RankConditionError
from ..filters import (
    FilterResult,
    check_rank_condition,
    delayed_uikf,
    detect_relative_degree,
    feedthrough_uikf,
    input_weights,
    smooth_uikf,
    uikf,
)
from ..hold import LawHold
from ..filters.smoother import smooth_feedthrough_of
from ..metrics import autocorrelation
from ..system import named_ss
from ..terms import own_state_terms, term_kind
from ..update import Subsystem, UpdatedModel, augment_model, identify_subsystem
from ..validate import has_marginal_pole, unstable_reason
from .channels import Channel, channel_model
from .laws import (
    LINEAR_KINDS,
    StaticLaw,
    _eval_terms,
    fit_static,
    law_line,
    _static_subsystem,
    aligned,
    linear_part,
    output_terms,
)
from .intervals import hac_covariance
from .oe import (
    _refine_nonlinear_oe,
    _refine_static_oe,
    _refine_static_pe,
    _select_static_oe,
    exchange_siblings,
    fit_smoothing,
    checked_intervals,
    offer_terms,
    simulates_better,
    prune_by_criterion,
    noise_covariance,
    oe_window,
    refine_force_direction,
    zoh,
)

# Below this excess of var(d^) over the filter's Pd, d^ is treated as mostly
# estimation noise and the static law is chosen by output error on y instead.
_LOW_SNR = 0.1
# Below this lag-1 autocorrelation d^ is taken to alternate sign (see trace_channel).
_ALTERNATING = -0.5
# Covariance iterations before an r = 1 filter counts as not converging (relative degree)
_DETECT_ITER = 1000
# Terms offered to an output-error selection of a force law (ranked by correlation with d^).
_OE_CANDIDATES = 6
# A linear d^ law of more terms per component of d is not a sparse physical law (noise
# proxies): its law is chosen by output error among its best-correlated terms instead of
# refined term by term (the same bound as trace.oe's for nonlinear laws).
_DENSE_LAW = 8


@dataclass(frozen=True)
class ChannelTrace:
    """What one candidate channel explains.

    Attributes
    ----------
    channel : Channel
    status : str
        "ok" or "skipped".
    reason : str
        Why a channel was skipped ("" otherwise).
    model : control.StateSpace or None
        Discrete model with inputs ``[u, d]``.
    filter_result : FilterResult or None
        The (r = 1) unknown-input filter on the estimation data; the dynamic
        fit uses it.
    law_estimate : FilterResult or None
        The estimate the static law was fitted on: smoothed and/or delayed
        (``relative_degree``, ``smoothed``), else ``filter_result`` itself.
    relative_degree : int
        Relative degree of ``law_estimate`` (1 when C G is used directly).
    static : StaticLaw or None
    static_model : UpdatedModel or None
        Nominal model with the (linear part of the) static law folded into A, B.
    dynamic : Subsystem or None
    dynamic_model : UpdatedModel or None
    notes : tuple of str
        Warnings met on the way (e.g. a failed dynamic identification).
    refined_G : ndarray, shape (nstates, 1), or None
        A force channel's G along the direction its law refitted by output
        error (:func:`greybox.trace.oe.refine_force_direction`) when the data
        contradict the given one (None otherwise); trace the channel again
        along it to have a law, filter and model consistent with it.
    """

    channel: Channel
    status: str
    reason: str = ""
    model: ct.StateSpace | None = field(default=None, repr=False)
    filter_result: FilterResult | None = field(default=None, repr=False)
    law_estimate: FilterResult | None = field(default=None, repr=False)
    relative_degree: int = 1
    static: StaticLaw | None = None
    static_model: UpdatedModel | None = field(default=None, repr=False)
    dynamic: Subsystem | None = field(default=None, repr=False)
    dynamic_model: UpdatedModel | None = field(default=None, repr=False)
    notes: tuple[str, ...] = ()
    refined_G: NDArray | None = field(default=None, repr=False)


def _law_estimate(model, labels, y, u, Q, R, res, smooth, notes, continuous=None):
    """(estimate, r, align) the static law is fitted on.

    The relative degree r is detected from the model and the noise
    (:func:`greybox.detect_relative_degree`); with ``smooth`` the estimate is
    the fixed-interval smoother's (:func:`greybox.smooth_uikf`), else the
    (delayed) filter's. ``align[c]`` (md, r) are the weights of d[j..j+r-1] in
    what ``d_est[c, j]`` estimates (:func:`greybox.input_weights`; with
    ``continuous = (Ac, Gc)`` of a continuous nominal model, d is a
    continuous-time law between the samples: r + 1 weights for r >= 2).
    """
    md = len(labels)
    try:
        rd = detect_relative_degree(model, unknown=labels, Q=Q, R=R, maxiter=_DETECT_ITER)
        r = rd.r
    except GreyboxError as e:
        r = 1
        notes.append(f"relative degree not detected ({e}); the r = 1 filter is used")
    if r == 1 and smooth != True:  # noqa: E712 ("auto": smooth delayed estimates only)
        return res, 1, np.ones((md, 1))
    w, misfit = input_weights(model, unknown=labels, r=r,
                              continuous=continuous if r >= 2 else None)
    if r >= 2:
        notes.append(f"relative degree {r} ({rd.reason}): d^[j] estimates "
                     + ", ".join(f"{labels[c]}: " + " + ".join(
                         f"{w[i, c, c]:.3g}*d[j+{i}]" for i in range(len(w))) for c in range(md))
                     + (f" (Markov-parameter misfit {misfit:.2g})" if misfit > 1e-3 else ""))
    off = np.abs(w - np.einsum("icc->ic", w)[:, :, None] * np.eye(md)).max() if md > 1 else 0.0
    if off > 0.05 * np.abs(w).max():
        notes.append(f"the delayed d^ mixes components of d (weight {off:.2g}); each "
                     f"component's law is aligned with its own weights only")
    align = np.einsum("icc->ci", w)
    kw = dict(unknown=labels, Q=Q, R=R, relative_degree=r)
    try:
        with np.errstate(over="raise"):  # an overflowing backward pass is no estimate
            est = smooth_uikf(model, y, u, **kw) if smooth else \
                (res if r == 1 else delayed_uikf(model, y, u, **kw))
    except (GreyboxError, np.linalg.LinAlgError, FloatingPointError) as e:
        notes.append(f"smoother failed ({e}); the law is fitted on the filter's d^")
        est = res if r == 1 else delayed_uikf(model, y, u, **kw)
    return est, r, align


def _trace_output(sys, channel, model, y, u, Q, R, nonlinear, skip, smooth) -> ChannelTrace:
    """A sensor-error channel: the filter with direct feedthrough and a law on the model output.

    The law is static (gain, offset, |.|, cube: :func:`_refit_sensor_law`), a
    first-order sensor lag ``1/(tau s + 1)`` (:func:`_fit_sensor_lag`), a
    drift (offset and drift rate: :func:`_fit_sensor_drift`) or a saturation
    ``clip(y, -L, L)`` (:func:`_fit_sensor_saturation`), whichever has the
    lowest BIC of the output error of that output on the estimation data
    (its first ``oe_window(1)`` samples; never the validation data). A lag's
    updated model carries the reading as one more state, a drift's the
    offset and the drift rate as two.
    """
    labels = list(channel.labels)
    res = feedthrough_uikf(model, y, u, unknown=labels, Q=Q, R=R)
    notes = []
    est = res
    if smooth is not False:  # the whole record: smoothed x^ and d^ (no delay here)
        try:
            est = smooth_feedthrough_of(res, model, y, u, unknown=labels, Q=Q, R=R)
        except (GreyboxError, np.linalg.LinAlgError) as e:
            notes.append(f"smoother failed ({e}); the law is fitted on the filter's d^")
    N = y.shape[1]
    k0 = skip if skip is not None else res.settled(20)
    m = model.ninputs - 1
    nterms = 4 if nonlinear else 1
    if N - k0 <= 10 * nterms:
        raise DataError(f"{N - k0} samples left after skipping {k0} cannot fit a sensor law of "
                        f"{nterms} candidate terms; give more data or a smaller skip")
    i = list(model.output_labels).index(channel.output)
    A, B = np.asarray(model.A, dtype=float), np.asarray(model.B, dtype=float)[:, :m]
    C, D = np.asarray(model.C, dtype=float), np.asarray(model.D, dtype=float)[:, :m]
    x, uu, d = est.x_filt[:, k0:N], u[:, k0:N], est.d_est[:, k0:N]
    law = fit_static(d, x, uu, res.sys, nonlinear, labels, channel.units,
                      whiten=est.smoothed,
                      prebuilt=output_terms(x, uu, C[i], D[i], channel.output,
                                            nonlinear=nonlinear))
    law = replace(law, output=i)
    if not unstable_reason(model, N):
        ks = min(k0, 20)  # the simulation starts from the filter's state there
        law = _refit_sensor_law(law, A, B, C[i], D[i], y[i, ks:], u[:, ks:], res.x_filt[:, ks],
                                labels[0], channel.units[0] if channel.units else "", notes,
                                noise=(Q, np.asarray(R, dtype=float)[i, i]))
    Cn, Dn = C.copy(), D.copy()
    Cn[i] += law.Ddx[0]
    Dn[i] += law.Ddu[0]
    upd = named_ss(A, B, Cn, Dn, model.dt, states=model.state_labels,
                   inputs=list(model.input_labels)[:m], outputs=model.output_labels,
                   name=f"{sys.name or 'model'}_updated")
    static_model = UpdatedModel(sys=upd, Q=Q, R=R, order=model.nstates, kind="static")
    notes.append("a sensor-error channel: static law on the model's own output "
                 "(gain, offset, |.|, cube), a first-order sensor lag, a drift or a saturation")
    if not unstable_reason(model, N):  # the alternatives by output error, on an OE window
        ks = min(k0, 20)
        ke = ks + oe_window(1)
        yw, uw = y[i, ks:ke], u[:, ks:ke]
        xs = _nominal_states(A, B, res.x_filt[:, ks], uw)
        e_st = yw - C[i] @ xs - D[i] @ uw - law.evaluate(xs, uw)[0]
        Ne = e_st.size

        def bic(sse, npar):
            return Ne * np.log(max(sse, 1e-300) / Ne) + npar * np.log(Ne)

        best = bic(float(e_st @ e_st), law.npar)
        name = f"{sys.name or 'model'}_updated"
        unit = channel.units[0] if channel.units else ""
        alts = []  # (BIC, what, its parameters, law, updated model)
        lag = _fit_sensor_lag(sys, model, i, yw, uw, res.x_filt[:, ks], (d, x, uu), (Q, R))
        if lag is not None:
            alts.append((bic(lag.sse, 1), "sensor lag", f"tau = {lag.tau:.4g} +- "
                         f"{lag.half:.2g} s", *_lag_law_and_model(lag, law, model, Q, R, m,
                                                                 channel, name)))
        drift = _fit_sensor_drift(law, model, i, yw, uw, xs, ks, (Q, R), (d, x, uu, k0),
                                  labels[0], unit, channel.output, name)
        if drift is not None:
            alts.append((bic(drift[2], drift[0].npar), "sensor drift",
                         drift[0].formula, drift[0], drift[1]))
        sat = _fit_sensor_saturation(model, i, yw, uw, xs, (Q, R), (d, x, uu),
                                     channel.output, name)
        if sat is not None:
            alts.append((bic(sat[2], 1), "sensor saturation", sat[0].formula, sat[0], sat[1]))
        for b, what, txt, _, _ in alts:
            notes.append(f"{what} ({txt}) against the static sensor law, by output error on "
                         f"the estimation data: BIC {b:.6g} vs {best:.6g}")
        if alts and min(a[0] for a in alts) < best:
            _, _, _, law, static_model = min(alts, key=lambda a: a[0])
    law, static_model = _affine_sensor(law, static_model, model, i, Q, R, channel.output,
                                       f"{sys.name or 'model'}_updated")
    return ChannelTrace(channel=channel, status="ok", model=model, filter_result=res,
                        law_estimate=est, relative_degree=0, static=law,
                        static_model=static_model, notes=tuple(notes))


def _affine_sensor(law, static_model, model, i, Q, R, out, name):
    """A static sensor law that is affine (a gain and an offset, or an offset alone) as a
    linear model: ``(law, updated model)``; both unchanged for any other law.

    The offset is one more state, ``<out>_offset`` (constant: ``b[k+1] = b[k]``, process
    noise 1e-12 of the largest of Q, as a drift's), read by output ``i`` beside the
    model's own output times ``1 + gain``: the updated model is a linear StateSpace that
    holds the whole law (not a surrogate), so a later pass of the loop can start from it,
    and a record's offset is estimated with its initial state (a sensor keeps its offset
    between records; the law's coefficient is the estimation record's).
    """
    sel = np.flatnonzero(law.coef[0]) if law.output is not None else np.zeros(0, int)
    kinds = [term_kind(law.spec[j][1]) for j in sel]
    if not any(k.constant for k in kinds) or not all(k.affine for k in kinds) or \
            any(k.sensor_states for k in kinds):
        return law, static_model
    m = model.ninputs - 1
    A, B = np.asarray(model.A, dtype=float), np.asarray(model.B, dtype=float)[:, :m]
    C, D = np.asarray(model.C, dtype=float), np.asarray(model.D, dtype=float)[:, :m]
    n = A.shape[0]
    Ddx, Ddu = linear_part(law.spec, law.coef, n, m)
    Aa = np.eye(n + 1)
    Aa[:n, :n] = A
    Ca = np.hstack([C, np.zeros((C.shape[0], 1))])
    Ca[i, :n] += Ddx[0]
    Ca[i, n] = 1.0
    Da = D.copy()
    Da[i] += Ddu[0]
    upd = named_ss(Aa, np.vstack([B, np.zeros((1, m))]), Ca, Da, model.dt,
                   states=list(model.state_labels) + [f"{out}_offset"],
                   inputs=list(model.input_labels)[:m], outputs=model.output_labels, name=name)
    Qa = np.zeros((n + 1, n + 1))
    Qa[:n, :n] = Q
    Qa[n, n] = 1e-12 * max(float(np.max(np.diag(Q))), 1e-300)
    return (replace(law, nonlinear=False, Ddx=Ddx, Ddu=Ddu),
            UpdatedModel(sys=upd, Q=Qa, R=R, order=n + 1, kind="static"))


def _refit_sensor_law(law, A, B, c, dd, y, u, x0, label, unit, notes, noise=None):
    """The sensor law's coefficients by output error: least squares on the nominal simulation.

    A sensor-error law does not feed back into the states, so the output-error
    fit of its selected terms is linear least squares of ``y - c x_sim - dd u``
    on the terms evaluated along the nominal simulation from ``x0`` (y, u
    start where x0 is the filter's state). The d^ fit
    sees the filter's x^, which the measurements pull toward the data (a
    rectifier's |.| came out at half its size on real data). Kept only when the
    estimation error drops; intervals as :func:`refit_sensor_on_states` (``noise = (Q,
    r)``: the model's process-noise covariance and the output's measurement-noise variance).
    """
    if not np.flatnonzero(law.coef[0]).size:
        return law
    return refit_sensor_on_states(law, _nominal_states(A, B, x0, u), c, dd, y, u, label, unit,
                                  notes, noise=None if noise is None else (A, *noise))


def refit_sensor_on_states(law, x, c, dd, y, u, label, unit, notes,
                           simulation: str = "the nominal simulation", prune: bool = False,
                           noise=None):
    """A sensor law's selected coefficients by least squares of ``y - c x - dd u`` on its
    terms along the states ``x`` (n, N) of a simulation (the law does not feed back into
    them); intervals from the HAC covariance of the residual, or with ``noise = (A, Q, r)``
    (the discrete state matrix of the simulated model, its process-noise covariance, the
    output's measurement-noise variance; A and Q may hold more states than x, the first
    ones x's) the larger, per coefficient, of it and the sandwich under that noise model
    (process noise makes the simulation's error a coloured, slowly wandering signal that
    the residual's own autocorrelation understates; as :func:`_sandwich_halfwidths`).
    The law unchanged when the error does not drop or the simulation is not finite (see
    :func:`_refit_sensor_law`).
    ``c`` (n,), ``dd`` (m,): the output's row of the model the law reads; ``y`` (N,) the
    measured output, ``u`` (m, N) the inputs; ``notes`` receives one line naming
    ``simulation``. With ``prune``, a term whose 95 % interval holds 0 is dropped (the
    weakest first) while more than one is left: a gain selected beside an offset while
    a state equation's error was still in the residual."""
    sel = np.flatnonzero(law.coef[0])
    if not sel.size or not np.all(np.isfinite(x)):
        return law
    r = y - c @ x - dd @ u
    terms = _eval_terms(law.spec, law.eps, x, u)
    e_old = r - law.coef[0, sel] @ terms[sel]
    while True:
        X = terms[sel]
        th = np.linalg.lstsq(X.T, r, rcond=None)[0]
        e_new = r - th @ X
        hw = _sensor_halfwidths(X, e_new, c, noise)
        weak = np.abs(th) / np.maximum(hw, 1e-300)
        if not prune or sel.size < 2 or weak.min() >= 1.0:
            break
        sel = np.delete(sel, int(np.argmin(weak)))  # its interval holds 0: not supported
    yk = y
    if not e_new @ e_new < e_old @ e_old and sel.size == np.count_nonzero(law.coef[0]):
        return law
    coef = np.zeros_like(law.coef)
    ci = np.full_like(law.ci, np.nan)
    coef[0, sel] = th
    ci[0, sel] = hw
    lin = [j for j, sp in enumerate(law.spec) if sp[1] in LINEAR_KINDS]
    lc = np.zeros((1, len(law.spec)))
    if law.nonlinear and lin:  # best linear surrogate, on the same simulation
        lc[0, lin] = np.linalg.lstsq(terms[lin].T, r, rcond=None)[0]
    else:
        lc = coef
    Ddx, Ddu = linear_part(law.spec, lc, x.shape[0], u.shape[0])
    names = [law.spec[j][0] for j in sel]
    se = [100 * np.sqrt((e @ e) / max(yk @ yk, 1e-300)) for e in (e_old, e_new)]
    notes.append(f"sensor law refit by output error (least squares on {simulation}): "
                 f"estimation SE {se[0]:.3g}% -> {se[1]:.3g}%")
    dropped = np.count_nonzero(law.coef[0]) - sel.size
    if dropped:
        notes.append(f"{dropped} term(s) whose interval holds 0 dropped")
    return replace(law, coef=coef, ci=ci, Ddx=Ddx, Ddu=Ddu, npar=law.npar - dropped,
                   residual_var=np.array([float(np.mean(e_new**2))]),
                   formula=law_line(label, th, names, unit, ci[0, sel]))


def _sensor_halfwidths(X, e, c, noise):
    """95 % half-widths of a sensor law's least squares on a simulation (see
    :func:`refit_sensor_on_states`): HAC, or with ``noise = (A, Q, r)`` the larger of it
    and the noise model's sandwich (:func:`_sandwich_halfwidths`)."""
    if noise is None:
        sx = np.sqrt(np.mean(X**2, axis=1)) + 1e-300
        cov = hac_covariance((X / sx[:, None]).T, e, 1) / np.outer(sx, sx)
        return 1.96 * np.sqrt(np.clip(np.diag(cov), 0, None))
    A, Q, r = noise
    A = np.asarray(A, dtype=float)
    cf = np.zeros(A.shape[0])
    cf[:c.size] = c
    return _sandwich_halfwidths(X, e, A, cf, (Q, np.atleast_2d(r)), 0)


def _nominal_states(A, B, x0, u):
    """States (n, N) of the nominal ``x[k+1] = A x + B u`` from ``x0`` (vectorized)."""
    return lti_states(A, B @ u, np.asarray(x0, dtype=float))


@dataclass(frozen=True)
class _SensorLag:
    """A first-order sensor lag fitted by output error (see :func:`_fit_sensor_lag`).

    ``tau`` [s] and its 95 % half-width ``half``; ``sse`` of the output error
    on the fitted samples; ``Ad, Bd`` (n + 1) the discrete model with the
    sensor state last; ``bic_gain`` and ``residual_var`` on d^ (as a static law's).
    """

    tau: float
    half: float
    sse: float
    Ad: NDArray
    Bd: NDArray
    bic_gain: float
    residual_var: float


def _dhat_bic_gain(d: NDArray, r: NDArray, npar: int) -> float:
    """BIC of "d = 0" minus that of a sensor law of ``npar`` parameters leaving ``r`` of d^ (K,)."""
    K = d.size
    return float(K * np.log(max(float(d @ d), 1e-300) / max(float(r @ r), 1e-300)) -
                 npar * np.log(K))


def _lag_row(sys, model, i, tau):
    """``(a, cz (n,), dz (m,))``: the sensor state's row ``z[k+1] = a z + cz x + dz u``.

    With a continuous nominal ``sys`` the augmented model ``[dx/dt; dz/dt] =
    [A 0; c/tau -1/tau] [x; z] + [B; dd/tau] u`` is discretized exactly (ZOH:
    the lag sees c x between the samples); with a discrete one ``s = c x + dd
    u`` is taken linear between the samples (first-order hold: ``z[k+1] = a
    z + b0 s[k] + b1 s[k+1]``, ``s[k+1] = c (A x + B u) + dd u``, the input held).
    """
    n, m = sys.nstates, sys.ninputs
    h = float(model.dt)
    c, dd = np.asarray(sys.C, dtype=float)[i], np.asarray(sys.D, dtype=float)[i]
    if ct.isdtime(sys, strict=True):
        a = float(np.exp(-h / tau))
        b1 = 1.0 - tau / h * (1.0 - a)
        b0 = 1.0 - a - b1
        cA, cB = c @ np.asarray(sys.A, dtype=float), c @ np.asarray(sys.B, dtype=float)
        return a, b0 * c + b1 * cA, (b0 + b1) * dd + b1 * cB
    Aa = np.zeros((n + 1, n + 1))
    Aa[:n, :n] = np.asarray(sys.A, dtype=float)
    Aa[n, :n], Aa[n, n] = c / tau, -1.0 / tau
    Ba = np.vstack([np.asarray(sys.B, dtype=float), dd[None, :] / tau])
    Ad, Bd = zoh(Aa, Ba, h)
    return float(Ad[n, n]), Ad[n, :n], Bd[n, :m]


def _lag_output(row, x, u, y):
    """(z, e): the lagged output along (x, u) with the initial reading fitted, and ``y - z``.

    The reading's initial value enters as ``a^k z0``: linear, fitted by least squares.
    """
    a, cz, dz = row
    s = cz @ x + dz @ u
    z = lfilter([0.0, 1.0], [1.0, -a], s)
    ak = a ** np.arange(s.size)
    z0 = float(ak @ (y - z)) / max(float(ak @ ak), 1e-300)
    z = z + z0 * ak
    return z, y - z


def _fit_sensor_lag(sys, model, i, y, u, x0, dxu, noise=None) -> _SensorLag | None:
    """Output ``i`` read through ``1/(tau s + 1)``: tau by output error on the nominal simulation.

    The lag does not feed back into the states: the nominal simulation from
    ``x0`` (the filter's state where y, u start) is run once, and tau
    minimizes ``sum (y - z)^2`` over a log-spaced grid from dt/5 to 1/20 of
    the record, then a bounded scalar search around the best grid point. The
    95 % interval of tau comes from the output-error Jacobian (central
    difference): the larger of the HAC variance of the residual and, with
    ``noise = (Q, R)``, the sandwich under that noise model
    (:func:`greybox.trace.oe.noise_covariance`, as
    :func:`greybox.trace.oe.robust_halfwidths`). None when the best
    tau is at the grid's short end (no lag) or the simulation is not finite.
    ``dxu = (d^, x^, u)`` (the law's estimation samples) give ``bic_gain``
    as for a static law: BIC of "d = 0" minus that of the lag on d^.
    """
    m = model.ninputs - 1
    A = np.asarray(model.A, dtype=float)
    B = np.asarray(model.B, dtype=float)[:, :m]
    x = _nominal_states(A, B, x0, u)
    if not np.all(np.isfinite(x)):
        return None
    h, N = float(model.dt), y.size

    def sse(lt):
        return float(np.sum(_lag_output(_lag_row(sys, model, i, np.exp(lt)), x, u, y)[1] ** 2))

    grid = np.linspace(np.log(h / 5), np.log(max(N * h / 20, h)), 25)
    f = np.array([sse(g) for g in grid])
    j = int(np.argmin(f))
    if j == 0 or not np.isfinite(f[j]):
        return None
    opt = minimize_scalar(sse, bounds=(grid[j - 1], grid[min(j + 1, grid.size - 1)]),
                          method="bounded", options={"xatol": 1e-6})
    tau = float(np.exp(opt.x))
    z, e = _lag_output(_lag_row(sys, model, i, tau), x, u, y)
    step = 1e-4 * tau
    jac = (_lag_output(_lag_row(sys, model, i, tau + step), x, u, y)[0] -
           _lag_output(_lag_row(sys, model, i, tau - step), x, u, y)[0]) / (2 * step)
    sj = np.sqrt(np.mean(jac**2)) + 1e-300
    cov = hac_covariance(jac[:, None] / sj, e, 1)[0, 0] / sj**2
    row = _lag_row(sys, model, i, tau)
    n = A.shape[0]
    Ad = np.zeros((n + 1, n + 1))
    Ad[:n, :n], Ad[n, :n], Ad[n, n] = A, row[1], row[0]
    if noise is not None:  # the sandwich under (Q, R): process noise colours e through the plant
        Qa = np.zeros((n + 1, n + 1))
        Qa[:n, :n] = noise[0]
        ca = np.zeros((1, n + 1))
        ca[0, n] = 1.0
        jj = float(jac @ jac)
        vm = noise_covariance(Ad, ca, jac[:, None], np.ones(1), 0, Qa,
                              np.atleast_2d(noise[1][i, i]))[0, 0] / max(jj, 1e-300) ** 2
        cov = max(cov, vm)
    d, xh, uh = dxu
    dpred = _lag_output(row, xh, uh, d[0] + np.asarray(sys.C, dtype=float)[i] @ xh +
                        np.asarray(sys.D, dtype=float)[i] @ uh)[0] - \
        (np.asarray(sys.C, dtype=float)[i] @ xh + np.asarray(sys.D, dtype=float)[i] @ uh)
    r1 = d[0] - dpred
    gain = _dhat_bic_gain(d[0], r1, 1)
    Bd = np.vstack([B, row[2][None, :]])
    return _SensorLag(tau=tau, half=1.96 * float(np.sqrt(max(cov, 0.0))), sse=float(e @ e),
                      Ad=Ad, Bd=Bd, bic_gain=float(gain), residual_var=float(np.mean(r1**2)))


def _lag_law_and_model(lag, law, model, Q, R, m, channel, name):
    """(StaticLaw, UpdatedModel) of a sensor lag: the reading is one more state, output ``i``.

    The law's single term has kind "yhat_lag" and coefficient tau [s] (it is
    not a function of the current sample: only the updated model, with the
    sensor state ``<output>_sensor`` last, simulates it).
    """
    i, out = law.output, channel.output
    n = model.nstates
    C = np.hstack([np.asarray(model.C, dtype=float), np.zeros((model.noutputs, 1))])
    D = np.asarray(model.D, dtype=float)[:, :m].copy()
    C[i], D[i] = 0.0, 0.0
    C[i, n] = 1.0
    upd = named_ss(lag.Ad, lag.Bd, C, D, model.dt,
                   states=list(model.state_labels) + [f"{out}_sensor"],
                   inputs=list(model.input_labels)[:m], outputs=model.output_labels, name=name)
    Qa = np.zeros((n + 1, n + 1))
    Qa[:n, :n] = Q
    Qa[n, n] = 1e-12 * max(float(np.max(np.diag(Q))), 1e-300)  # the lag itself is deterministic
    spec = ((f"{out}_model lag", "yhat_lag", i),)
    lg = StaticLaw(spec=spec, eps=np.zeros(1), coef=np.array([[lag.tau]]),
                   Ddx=np.zeros((1, n)), Ddu=np.zeros((1, m)), nonlinear=False,
                   residual_var=np.array([lag.residual_var]), bic_gain=lag.bic_gain, npar=1,
                   formula=f"{out} = {out}_model / (tau s + 1), tau = ({lag.tau:.4g} ± "
                           f"{lag.half:.2g}) [s]", ci=np.array([[lag.half]]), output=i)
    return lg, UpdatedModel(sys=upd, Q=Qa, R=R, order=n + 1, kind="static")


def _sandwich_halfwidths(X, e, A, c, noise, i):
    """95 % half-widths of the least-squares fit ``e = r - th @ X`` on a nominal simulation.

    The larger, per coefficient, of the HAC variance of the residual and the
    sandwich under the noise model ``noise = (Q, R)`` (process noise colours the
    output error through the plant: :func:`greybox.trace.oe.noise_covariance`),
    as :func:`_fit_sensor_lag` does. ``X`` (k, T), ``c`` the output row, ``i`` its index.
    """
    sx = np.sqrt(np.mean(X**2, axis=1)) + 1e-300  # terms differ by decades (1, t, y)
    Xs = X / sx[:, None]
    cov = hac_covariance(Xs.T, e, 1) / np.outer(sx, sx)
    Ji = np.linalg.pinv(Xs @ Xs.T)
    Q, R = noise
    vm = Ji @ noise_covariance(A, c[None, :], Xs.T, np.ones(1), 0, Q,
                               np.atleast_2d(R[i, i])) @ Ji / np.outer(sx, sx)
    return 1.96 * np.sqrt(np.maximum(np.clip(np.diag(cov), 0, None),
                                     np.clip(np.diag(vm), 0, None)))


def _fit_sensor_drift(law, model, i, y, u, xs, ks, noise, dxu, label, unit, out, name):
    """A drifting sensor ``y_i = C_i x + D_i u + g y_model + b0 + r t``: (law, model, sse) or None.

    Output-error least squares on the nominal simulation ``xs`` (the sensor
    error does not feed back into the states) of the offset ``b0`` [output
    units] and the drift rate ``r`` [output units/s], with the static law's
    gain term ``g`` when it has one. ``t`` [s] is counted from the record's
    first sample (y, u, xs start at sample ``ks``), so ``b0`` is the offset
    there. 95 % intervals: :func:`_sandwich_halfwidths`. None unless the
    rate's z-statistic under that variance passes BIC's threshold for one
    parameter, ``z^2 > ln N`` (|z| > 2.9 at N = 4000).

    The updated model carries the drift as two sensor states, ``<out>_offset``
    (b) and ``<out>_drift`` (r), with ``db/dt = r``, ``dr/dt = 0`` (exact in
    discrete time: ``b[k+1] = b[k] + dt r[k]``) and ``y_i += b``: a linear
    StateSpace, so a Kalman filter tracks the sensor on line. A record that
    starts later (validation data) has its own offset and rate at its first
    sample: both are states, estimated with the initial state (a sensor keeps
    drifting between records; the reported b0 and r are the estimation
    record's). Their process noise is negligible (1e-12 of the largest of Q).
    ``dxu = (d^, x^, u, k0)`` give ``bic_gain`` and ``residual_var`` on d^.
    """
    m = model.ninputs - 1
    A = np.asarray(model.A, dtype=float)
    C, D = np.asarray(model.C, dtype=float), np.asarray(model.D, dtype=float)[:, :m]
    h, n = float(model.dt), A.shape[0]
    yh = C[i] @ xs + D[i] @ u
    r = y - yh
    t = (ks + np.arange(y.size)) * h
    gain = any(term_kind(sp[1]).linear and law.coef[0, j] for j, sp in enumerate(law.spec))
    X = np.vstack(([yh] if gain else []) + [np.ones_like(yh), t])
    th = np.linalg.lstsq(X.T, r, rcond=None)[0]
    e = r - th @ X
    half = _sandwich_halfwidths(X, e, A, C[i], noise, i)
    # the rate's z-statistic under that robust variance against BIC's threshold for one
    # parameter: the white-noise BIC of the output error overstates the evidence (the
    # residual is coloured by the plant's wander), and a 95 % test alone would keep a
    # drift on a right sensor in 1 record of 20
    if not (1.96 * th[-1] / half[-1]) ** 2 > np.log(y.size):
        return None
    yidx = (tuple(float(v) for v in C[i]), tuple(float(v) for v in D[i]))
    spec = ([(f"{out}_model", "yhat", yidx)] if gain else []) + \
        [("1", "const", 0), ("t", "drift", i)]
    g = th[0] if gain else 0.0
    Ddx, Ddu = g * C[i][None, :], g * D[i][None, :]
    d, xh, uh, k0 = dxu
    dpred = (g * (C[i] @ xh + D[i] @ uh) if gain else 0.0) + th[-2] + \
        th[-1] * (k0 + np.arange(d.shape[1])) * h
    r1 = d[0] - dpred
    bic_gain = _dhat_bic_gain(d[0], r1, len(th))
    formula = law_line(label, th, [sp[0] for sp in spec], unit, half) + \
        f"; t [s] from the record's first sample, the drift rate in {unit}/s"
    lg = StaticLaw(spec=tuple(spec), eps=np.zeros(1), coef=th[None, :], Ddx=Ddx, Ddu=Ddu,
                   nonlinear=False, residual_var=np.array([float(np.mean(r1**2))]),
                   bic_gain=float(bic_gain), npar=len(th), formula=formula, ci=half[None, :],
                   output=i)
    Q, R = noise
    B = np.asarray(model.B, dtype=float)[:, :m]
    Ad = np.zeros((n + 2, n + 2))
    Ad[:n, :n], Ad[n:, n:] = A, [[1.0, h], [0.0, 1.0]]
    Ca = np.hstack([C, np.zeros((C.shape[0], 2))])
    Dn = D.copy()
    Ca[i, :n] += Ddx[0]
    Dn[i] += Ddu[0]
    Ca[i, n] = 1.0
    upd = named_ss(Ad, np.vstack([B, np.zeros((2, m))]), Ca, Dn, model.dt,
                   states=list(model.state_labels) + [f"{out}_offset", f"{out}_drift"],
                   inputs=list(model.input_labels)[:m], outputs=model.output_labels, name=name)
    Qa = np.zeros((n + 2, n + 2))
    Qa[:n, :n] = Q
    Qa[n, n] = Qa[n + 1, n + 1] = 1e-12 * max(float(np.max(np.diag(Q))), 1e-300)
    return lg, UpdatedModel(sys=upd, Q=Qa, R=R, order=n + 2, kind="static"), float(e @ e)


def _fit_sensor_saturation(model, i, y, u, xs, noise, dxu, out, name):
    """A sensor clipping at +-L, ``y_i = clip(C_i x + D_i u, -L, L)``: (law, model, sse) or None.

    L minimizes the output error on the nominal simulation ``xs`` over a grid
    of quantiles of |y_model| (5 % .. 99.9 %), then a bounded scalar search
    around the best grid point; None when the best L is at the grid's top
    (nothing clipped). Its 95 % interval: the HAC variance
    (:func:`greybox.trace.intervals.hac_covariance`) with the output-error
    Jacobian ``sign(y_model) 1{|y_model| > L}`` and the residual on the
    clipped samples (there the right model's output error is the
    measurement noise alone; the plant's wander under process noise, which
    colours the residual elsewhere, is clipped away). L is identifiable
    only from samples the model drives beyond it. The law is nonlinear: the
    updated StateSpace holds its best linear surrogate (a gain on y_model, a
    least-squares fit on the simulation), the law itself the clip.
    """
    m = model.ninputs - 1
    A = np.asarray(model.A, dtype=float)
    C, D = np.asarray(model.C, dtype=float), np.asarray(model.D, dtype=float)[:, :m]
    yh = C[i] @ xs + D[i] @ u
    r, a = y - yh, np.abs(yh)

    def sse(L):
        return float(np.sum((r - np.clip(yh, -L, L) + yh) ** 2))

    grid = np.unique(np.quantile(a, np.linspace(0.05, 0.999, 40)))
    if grid.size < 3 or not grid[0] > 0:
        return None
    f = np.array([sse(L) for L in grid])
    j = int(np.argmin(f))
    if j == grid.size - 1:
        return None
    opt = minimize_scalar(sse, bounds=(grid[max(j - 1, 0)], grid[j + 1]), method="bounded",
                          options={"xatol": 1e-9 * grid[-1]})
    L = float(opt.x)
    clipped = np.clip(yh, -L, L) - yh
    e = r - clipped
    jac = np.sign(yh) * (a > L)
    if not np.any(jac):
        return None
    # the score jac * e lives on the clipped samples only, where the right model's output
    # error is the measurement noise alone (the clip removes the plant's wander, which
    # colours e elsewhere): the HAC variance of the masked residual
    cov = hac_covariance(jac[:, None], e * (jac != 0), 1)[0, 0]
    half = 1.96 * float(np.sqrt(max(cov, 0.0)))
    yidx = (tuple(float(v) for v in C[i]), tuple(float(v) for v in D[i]))
    spec = ((f"{out}_model", "yhat", yidx), (f"sat({out}_model)", "yhat_sat", yidx + (L,)))
    s = float(yh @ clipped) / max(float(yh @ yh), 1e-300)  # the best linear surrogate
    d, xh, uh = dxu
    yhh = C[i] @ xh + D[i] @ uh
    r1 = d[0] - (np.clip(yhh, -L, L) - yhh)
    bic_gain = _dhat_bic_gain(d[0], r1, 1)
    lg = StaticLaw(spec=spec, eps=np.zeros(1), coef=np.array([[0.0, L]]),
                   Ddx=s * C[i][None, :], Ddu=s * D[i][None, :], nonlinear=True,
                   residual_var=np.array([float(np.mean(r1**2))]), bic_gain=float(bic_gain),
                   npar=1, formula=f"{out} = clip({out}_model, -L, L), L = ({L:.4g} ± "
                                   f"{half:.2g}) [{out}]",
                   ci=np.array([[np.nan, half]]), output=i)
    B = np.asarray(model.B, dtype=float)[:, :m]
    Q, R = noise
    Cn, Dn = C.copy(), D.copy()
    Cn[i] += s * C[i]
    Dn[i] += s * D[i]
    upd = named_ss(A, B, Cn, Dn, model.dt, states=model.state_labels,
                   inputs=list(model.input_labels)[:m], outputs=model.output_labels, name=name)
    return lg, UpdatedModel(sys=upd, Q=Q, R=R, order=A.shape[0], kind="static"), float(e @ e)


def _aligned_rows(v, align, K):
    """``v`` (nrows, K + r - 1) weighted like the first component of d^: shape (nrows, K)."""
    return aligned(v, align[0])[:, :K]


def _free_direction(sys, channel, model, cont, law, y, u, x0, k0, Q, R, notes):
    """A force's G along its direction refitted with its law, or None (:func:`refine_force_direction`).

    The smaller of the two entries of G is freed (``G[b] (1 + r)``); None
    when the data do not contradict the given direction, or for any channel but a force
    of a continuous model with a linear law in continuous time. The name of the other
    body's equation when the refitted share of ``b`` is not distinguishable from 0 (its
    95 % interval holds 0): the force then acts on that body alone.
    """
    if channel.kind != "force" or cont is None or not law.npar or law.nonlinear or \
            law.time_base != "continuous":
        return None
    G = np.asarray(channel.G, dtype=float)[:, 0]
    rows = [list(sys.state_labels).index(e) for e in channel.equations]
    b = min(rows, key=lambda i: abs(G[i]))
    dG = np.zeros_like(G)
    dG[b] = G[b]
    new, r, hr, se0, se1 = refine_force_direction(law, model, y, u, x0, k0, channel.labels,
                                                  channel.units, cont, (Q, R), dG)
    if new is law:
        return None
    a = next(i for i in rows if i != b)
    old, now = G[b] / G[a], G[b] * (1 + r) / G[a]
    notes.append(f"force direction refitted by output error: {sys.state_labels[b]}/"
                 f"{sys.state_labels[a]} ratio {old:.4g} -> {now:.4g} "
                 f"(+-{abs(G[b] / G[a]) * hr:.2g}); estimation SE {se0:.3g}% -> {se1:.3g}%")
    if abs(1 + r) <= hr:
        return sys.state_labels[a]
    return (G + r * dG)[:, None]


def _one_body(channel: Channel, model, body: str, notes) -> ChannelTrace:
    """A force whose refitted direction acts on one body alone (:func:`_free_direction`):
    skipped, since it is that body's equation's own law (traced on its own where the
    screen ranks it) with one parameter more: zoo state_sensor 20261207 #1, a damping of
    m6 named as force(v6,v7) with a v7 share of -0.0007 +- 0.014."""
    return ChannelTrace(channel=channel, status="skipped", model=model,
                        reason=f"the refitted direction acts on {body} alone (the other "
                               f"body's share holds 0): eq({body})'s own law, not a force "
                               "between two bodies", notes=tuple(notes))


def _dynamic_part(res, min_order, max_order, k0, model, labels, Q, R, notes):
    """``(dyn, dyn_model)``: the unstructured subsystem of orders ``min_order..max_order``
    fitted on d^ and the model augmented with it, or ``(None, None)`` (none asked, or
    the fit failed: said in ``notes``)."""
    if max_order < max(min_order, 1):
        return None, None
    try:
        dyn = _dynamic_fit(res, min_order, max_order, k0)
        return dyn, augment_model(model, dyn, unknown=labels, Q=Q, R=R)
    except (GreyboxError, np.linalg.LinAlgError) as e:
        notes.append(f"dynamic fit failed: {e}")
        return None, None


def law_estimate_of(sys: ct.StateSpace, tr: ChannelTrace, y: NDArray, u: NDArray, Q, R,
                    smooth: bool | str = "auto"):
    """The estimate a trace's static law was fitted on (delayed and/or smoothed), on (y, u).

    As :func:`trace_channel` computes it (its relative degree detected again);
    for the figure of a law (:func:`greybox.plotting.plot_law`), which the
    light trace of a report no longer carries. Returns a FilterResult whose
    ``d_est[:, j]`` estimates d about ``tr.relative_degree - 1`` samples later.
    """
    cont = None if ct.isdtime(sys, strict=True) else (np.asarray(sys.A, dtype=float),
                                                      np.asarray(tr.channel.G, dtype=float))
    est, _, _ = _law_estimate(tr.model, list(tr.channel.labels), y, u, Q, R,
                              tr.filter_result, smooth, [], cont)
    return est


def whole_inputs(sys: ct.StateSpace, channel: Channel) -> tuple[int, ...]:
    """Indices of the inputs whose whole effect passes through a one-component channel.

    An input j with ``B[:, j]`` along the channel's G (its own input channel,
    or the one state equation it enters): its dead zone or saturation is a
    law of this channel, so the channel's law is offered breakpoint terms in
    u_j (:data:`greybox.trace.laws.BREAK_KINDS`).
    """
    if channel.md != 1 or channel.kind == "output":
        return ()
    g = np.asarray(channel.G, dtype=float)[:, 0]
    B = np.asarray(sys.B, dtype=float)
    out = []
    for j in range(B.shape[1]):
        b = B[:, j]
        nb = np.linalg.norm(b)
        if nb > 0 and np.linalg.norm(b - g * (g @ b) / (g @ g)) <= 1e-9 * nb:
            out.append(j)
    return tuple(out)

def _checked_skip(skip, smooth):
    """:func:`trace_channel`'s ``skip`` checked (None: the filter's transient) and its
    ``smooth`` option."""
    if skip is not None:
        skip = check_positive(skip, "skip", integer=True, allow_zero=True)
    if not (isinstance(smooth, (bool, np.bool_)) or smooth == "auto"):
        raise DataError(f"smooth must be True, False or 'auto'; found {smooth!r}")
    return skip


def _continuous_parts(sys, channel: Channel, model):
    """``(A, B, G, dt)`` of a continuous nominal and channel (the law may be fitted in
    continuous time); None for a discrete nominal."""
    if ct.isdtime(sys, strict=True):
        return None
    return (np.asarray(sys.A, dtype=float), np.asarray(sys.B, dtype=float),
            np.asarray(channel.G, dtype=float), float(model.dt))


def _check_enough(nleft: int, k0: int, nterms: int) -> None:
    """Refuse a record too short for the law's candidate terms (DataError)."""
    if nleft <= nterms:
        raise DataError(f"{nleft} samples left after skipping {k0} cannot fit a law of "
                        f"{nterms} candidate terms; give more data or a smaller skip")


def _law_on_dhat(est, u, nsteps: int, k0: int, nterms: int, align, r: int, channel: Channel,
                 notes: list, sys_f, nonlinear: bool, brk, foh):
    """``(law data, law)``: the static law fitted on d^ (:func:`_law_data`, :func:`fit_static`).

    With ``foh`` (an r = 1 estimate of a continuous model) the law is fitted on the states
    within each sample, the input held. Kept for a law of the states alone (a drag, a
    spring, a friction): a law that also reads an input would pair mid-sample states with
    the input of the sample's start, a half-sample shift wherever the plant's input is not
    held (a measured flow); such a law is fitted on the states at the sample's start.
    """
    def fit(ld):
        return fit_static(ld.d, ld.xw, ld.uw, sys_f, nonlinear, list(channel.labels),
                           channel.units, None if ld.align.shape[1] == 1 and
                           np.allclose(ld.align, 1.0) else ld.align, channel.relative,
                           whiten=est.smoothed or r >= 2, breaks=brk)

    ld = _law_data(est, u, nsteps, k0, nterms, align, r, channel.md, notes, foh)
    law = fit(ld)
    if ld.midpoint and any(term_kind(law.spec[j][1]).reads_input
                           for j in np.flatnonzero(np.any(law.coef != 0, axis=0))):
        ld = _law_data(est, u, nsteps, k0, nterms, align, r, channel.md, [], None)
        law = fit(ld)
    return ld, law


def _held(law: StaticLaw, cont, r: int, midpoint: bool) -> StaticLaw:
    """The law fitted with first-order-hold weights (a delayed d^, or the states within
    each sample for an r = 1 one) carries that hold, so it is simulated alike; a linear one
    is then a continuous-time law, folded into the continuous nominal and discretized
    exactly (:func:`_static_model`)."""
    if cont is None or not (r >= 2 or midpoint):
        return law
    law = replace(law, hold=LawHold.of(cont[0], cont[2], cont[3]))
    return law if law.nonlinear else replace(law, time_base="continuous")


def _foh_weights(model, labels, cont) -> NDArray | None:
    """(md, 2) weights of f(x[j]), f(x[j+1]) in what an r = 1 estimate of a continuous law
    f stands for (first-order hold between the samples); None for a discrete model."""
    if cont is None:
        return None
    try:
        w, _ = input_weights(model, unknown=labels, r=1, continuous=(cont[0], cont[2]))
    except (GreyboxError, np.linalg.LinAlgError):
        return None
    return np.einsum("icc->ci", w)


def _estimate_end(est, nsteps: int, nw: int, k0: int) -> int:
    """One past the last column of d^ that is finite with its ``nw`` aligned x^ columns
    (a delayed estimate ends in NaN), at least ``k0``."""
    okd = np.all(np.isfinite(est.d_est), axis=0)
    okx = np.all(np.isfinite(est.x_filt), axis=0)
    Ne = nsteps - nw
    while Ne > k0 and not (okd[Ne - 1] and okx[Ne + nw - 2]):
        Ne -= 1
    return Ne


def _excess_variance(d, dnoise) -> float:
    """The variance of d^ over its estimation variance ``dnoise`` (traces), minus 1."""
    return float(np.trace(np.atleast_2d(np.cov(d, bias=True)))) / \
        max(float(np.trace(dnoise)), 1e-300) - 1.0


def _unobservable(C, Gd, channel: Channel, cond_tol: float) -> str | None:
    """Why d is not observable in ``channel`` (the rank condition (17), or ``C G`` nearly
    singular: ``sigma_min(C G) < cond_tol * ||C|| ||G||``); None when it is."""
    try:
        check_rank_condition(C, Gd, channel.labels)
    except RankConditionError as e:
        return str(e)
    sv = np.linalg.svd(C @ Gd, compute_uv=False)
    if sv.min() < cond_tol * np.linalg.norm(C, 2) * np.linalg.norm(Gd, 2):
        return (f"C G is nearly singular (sigma_min/sigma_max = "
                f"{sv.min() / max(sv.max(), 1e-300):.2g}); the error "
                f"would be practically unobservable")
    return None


def _most_correlated_terms(law, d, xw, uw, align) -> list[int]:
    """Indices of the law's linear terms d^ correlates with most: the ``_OE_CANDIDATES``
    best per component of d (terms weighted by ``align`` as d^ sees them)."""
    lin = [j for j, sp in enumerate(law.spec) if sp[1] in LINEAR_KINDS]
    only = set()
    for c in range(d.shape[0]):
        tm = aligned(_eval_terms(law.spec, law.eps, xw, uw)[lin], align[c])
        tm = tm - tm.mean(axis=1, keepdims=True)
        dm = d[c] - d[c].mean()
        corr = np.abs(tm @ dm) / (np.linalg.norm(tm, axis=1) * np.linalg.norm(dm) + 1e-300)
        only |= {lin[q] for q in np.argsort(-corr)[:_OE_CANDIDATES]}
    return sorted(only)


def _static_model(model, sub0, law, labels, Q, R, cont) -> UpdatedModel:
    """The channel model augmented with the static law; a law in continuous time folded
    into the continuous nominal ``cont = (A, B, G, dt)`` and discretized exactly (ZOH)."""
    static_model = augment_model(model, sub0, unknown=labels, Q=Q, R=R)
    if law.time_base == "continuous":  # fold the law in continuous time, discretize exactly
        Ac, Bc, Gc, h = cont
        Ad, Bd = zoh(Ac + Gc @ law.Ddx, Bc + Gc @ law.Ddu, h)
        s0 = static_model.sys
        static_model = replace(static_model, sys=named_ss(
            Ad, Bd, s0.C, s0.D, s0.dt, states=s0.state_labels, inputs=s0.input_labels,
            outputs=s0.output_labels, name=s0.name))
    return static_model


def _dynamic_fit(res, min_order: int, max_order: int, k0: int) -> Subsystem:
    """The unstructured dynamic subsystem on the causal r = 1 filter's d^ (its warnings
    silenced); the order is the state count pbsid returns (md > 1: md * order)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GreyboxWarning)
        dyn = identify_subsystem(res, min_order=max(min_order, 1), max_order=max_order,
                                 skip=k0)
    if dyn.Ad.shape[0] != dyn.order:  # md > 1: pbsid may return md*order states
        dyn = replace(dyn, order=dyn.Ad.shape[0])
    return dyn


def _pruned(law, model, channel: Channel, y, u, x0, k0, cont, noise, prune: float,
            oe_ok: bool, at, notes):
    """The law's terms kept only where the one criterion supports them
    (:func:`greybox.trace.oe.prune_by_criterion`; by output error, so not for a model with
    an integrator, whose simulation drifts: EMPS lost its ``|v|`` term so); the law as it
    is without ``prune`` or with one term. Appends the decisions to ``notes``."""
    if not (prune and oe_ok and law.npar > 1 and not has_marginal_pole(model)):
        return law
    law, more = prune_by_criterion(law, model, channel.md, y, u, x0, k0, list(channel.labels),
                                   channel.units, law.term_scale(*at),
                                   cont if law.time_base == "continuous" else None, noise,
                                   factor=float(prune))
    notes += more
    return law


def lacked_own_terms(law, channel: Channel, states) -> list[int]:
    """The term indices of the forms of a one-equation channel's own state (v, v^3,
    sign(v), v|v|) when ``law`` holds none of them; empty for any other channel or law.
    ``states``: the model's state labels (the terms' indices)."""
    if channel.kind != "equation" or channel.md != 1 or len(channel.equations) != 1:
        return []
    own = own_state_terms(law.spec, list(states).index(channel.equations[0]))
    return [] if np.any(law.coef[:, own] != 0) else own


def _own_offers(law, model, channel: Channel, fit_data) -> tuple[list, list]:
    """The forms of an equation's own state (v, v^3, sign(v), v|v|: its damping, loss,
    friction, drag) a one-equation law lacks, as ``(offers, guesses)`` for
    :func:`greybox.trace.oe.offer_terms`; none when the law has a form of it already. Each
    guess is the least-squares coefficient of the term on what the law leaves of d^."""
    own = lacked_own_terms(law, channel, model.state_labels)
    if not own:
        return [], []
    d, xw, uw, align = fit_data
    sel = np.flatnonzero(law.coef[0])
    spec = [law.spec[j] for j in list(sel) + own]
    tm = aligned(_eval_terms(spec, law.eps, xw, uw), align[0])
    K = min(tm.shape[1], d.shape[1])
    rest = d[0, :K] - law.coef[0, sel] @ tm[:len(sel), :K]
    tt = tm[len(sel):, :K]
    guesses = (tt @ rest) / np.maximum(np.sum(tt * tt, axis=1), 1e-300)
    return [(0, j) for j in own], list(guesses)


def _refined_note(what: str, se_d: float, se_y: float) -> str:
    """The decision note of a law refined by output error (SE [%] before and after; a
    diverging simulation's SE is 1e8 %, :func:`greybox.trace.oe.scaled_output_error`)."""
    if se_d < 1e6:
        return f"{what} law refined by output error on y: estimation SE {se_d:.3g}% -> {se_y:.3g}%"
    return (f"{what} law refined by output error on y from the d^ law shrunk until it "
            f"simulates (the d^ law diverges): estimation SE {se_y:.3g}%")


def _refined_law(law, model, channel: Channel, y, u, x0, k0, cont, noise, whitened: bool,
                 averaged: bool, excess: float, oe_ok: bool, fit_data, at, notes,
                 prune: float = 0.0, own: bool = False):
    """The static law fitted on d^, refined by output error on y where that is defined:
    chosen by output error when d^ is mostly noise or the d^ law is not sparse, its
    coefficients refined (linear or nonlinear), then its terms kept only where the one
    criterion supports them (:func:`greybox.trace.oe.prune_by_criterion`); with ``own``
    (and ``prune``), an equation's own state offered first (:func:`_own_offers`,
    :func:`greybox.trace.oe.offer_terms`). ``fit_data``: ``(d, xw, uw, align)`` of the
    d^ fit; ``at``: the aligned ``(x, u)``."""
    d, xw, uw, align = fit_data
    x, uu = at
    labels = list(channel.labels)
    law_d = law  # the d^ fit (its intervals are the regression's, not output error's)
    # (a delayed or smoothed d^ is fitted by GLS, whose selection already weighs its coloured
    # noise: only an empty law sends it to output error; its raw variance is mostly
    # high-frequency noise that says nothing about the law, and Q may be overstated)
    low_snr = law.npar == 0 if whitened else excess < _LOW_SNR
    linear_by_oe = False  # chosen by output error among linear terms only: forms unweighed
    if low_snr and not averaged and oe_ok:
        law = _select_static_oe(law, model, channel.md, y, u, x0, k0, labels,
                                channel.units, cont=cont, noise=noise)
        linear_by_oe = True
        notes.append("no term explains the delayed d^: static law chosen by output error on y"
                     if whitened else f"d^ is mostly estimation noise (variance only "
                     f"{100 * excess:.2g}% above Pd): static law chosen by output error on y")
    elif oe_ok and ((channel.relative and (averaged or law.npar > 2 * channel.md)) or
                    (law.npar > _DENSE_LAW * channel.md and (not law.nonlinear or
                     not simulates_better(law, model, channel.md, y, u, x0, k0)))):
        # a force between bodies whose d^ fit is not sparse (noise-dominated, e.g.
        # positions only), or any linear d^ law of more than _DENSE_LAW terms per component
        # of d, or a nonlinear one that simulates no better than no law: choose the law by
        # output error among the linear terms d^ correlates with most (per component of
        # d). Refining a 31-term law term by term cost 72 s of a 200 s run (n = 32,
        # positions only) and ended with no term; a nonlinear one was left as fitted on
        # d^ (zoo actuator_gain, positions of a chain of 9: ten terms in p, v, sign(v) and
        # v*F for F's gain error, diverging).
        law0_npar = law.npar
        law = _select_static_oe(law, model, channel.md, y, u, x0, k0, labels,
                                channel.units, cont=cont, noise=noise,
                                only=_most_correlated_terms(law, d, xw, uw, align))
        linear_by_oe = True
        notes.append(f"{'a force whose ' if channel.relative else ''}d^ law is not sparse "
                     f"({law0_npar} terms): static law chosen by output error on y among "
                     f"the terms d^ correlates with most")
    elif not law.nonlinear and law.npar and oe_ok:
        tscale = law.term_scale(x, uu)
        law, se_d, se_y = _refine_static_oe(law, model, channel.md, y, u, x0,
                                            k0, labels, channel.units, tscale, cont, noise)
        if se_y < se_d:
            notes.append(_refined_note("static", se_d, se_y))
    elif not oe_ok and not law.nonlinear and law.npar and noise is not None:  # unstable
        law, pe_d, pe_y = _refine_static_pe(law, model, channel.md, y, u, x0, k0, labels,
                                            channel.units, law.term_scale(x, uu), cont, noise)
        if pe_y < pe_d:
            notes.append(f"static law refined by one-step prediction error on y (the model's "
                         f"steady-state Kalman predictor): RMS of the whitened innovations "
                         f"{pe_d / 100:.4g} -> {pe_y / 100:.4g} (1 for the right model)")
    elif law.nonlinear and oe_ok:  # the same for a nonlinear law (simulated, pruned)
        law, se_d, se_y = _refine_nonlinear_oe(law, model, channel.md, y, u, x0,
                                               k0, labels, channel.units, law.term_scale(x, uu),
                                               noise=noise)
        if se_y < se_d:
            notes.append(_refined_note("nonlinear static", se_d, se_y))
    if own and prune and oe_ok and law.npar and not has_marginal_pole(model):
        offers, guesses = _own_offers(law, model, channel, fit_data)
        if offers:
            law, more = offer_terms(law, model, channel.md, y, u, x0, k0, labels,
                                    channel.units, law.term_scale(x, uu), offers, guesses,
                                    cont if law.time_base == "continuous" else None, noise,
                                    factor=float(prune))
            notes += more
    # a friction's smoothing width, where the criterion pays for it, before its terms are
    # weighed (a width off by 2x leaves a shape error a spurious linear term makes up for)
    if prune and oe_ok and law.nonlinear and not has_marginal_pole(model):
        law, more = fit_smoothing(law, model, channel.md, y, u, x0, k0, labels, channel.units,
                                  law.term_scale(x, uu), noise, factor=float(prune))
        notes += more
    # the one criterion: terms only where the data support them (by output error: not for a
    # model with an integrator, whose simulation drifts; EMPS lost its |v| term so)
    law = _pruned(law, model, channel, y, u, x0, k0, cont, noise, prune, oe_ok, at, notes)
    # a delayed d^ cannot tell a variable's forms apart (v or sign(v)): output error does;
    # the same for the relative coordinates of a force chosen among the linear terms by
    # output error (a cubic spring between two bodies measured in part)
    weigh = whitened or (linear_by_oe and channel.relative)
    if weigh and law.npar and oe_ok and not has_marginal_pole(model):
        law, more = exchange_siblings(law, model, channel.md, y, u, x0, k0, labels,
                                      channel.units, law.term_scale(x, uu), noise,
                                      family=None if whitened else "relative")
        notes += more
        if more:  # a form that explains the law alone leaves the others' support to weigh
            law = _pruned(law, model, channel, y, u, x0, k0, cont, noise, prune, oe_ok, at,
                          notes)
    # a nonlinear law the criterion left linear is still held over each sample (a
    # discrete-time law): refitted in continuous time, it folds into the continuous model,
    # where the next pass and the joint refit work (zoo state_sensor 1984922569 #1: a
    # damping error so held left pass 2 a discrete model and no joint refit, 40x the true
    # model's error)
    if cont is not None and oe_ok and law.npar and not law.nonlinear and law.hold is None \
            and law.time_base != "continuous" and law.output is None:
        law, se_d, se_y = _refine_static_oe(law, model, channel.md, y, u, x0, k0, labels,
                                            channel.units, law.term_scale(x, uu), cont, noise)
        notes.append(f"linear once pruned: refitted in continuous time by output error on y "
                     f"(estimation SE {se_d:.3g}% -> {se_y:.3g}%)")
    # an output-error fit's intervals, checked against the law's own simulation
    if law is not law_d and law.nonlinear and oe_ok:
        law, more = checked_intervals(law, model, channel.md, y, u, x0, k0, labels,
                                      channel.units, law.term_scale(x, uu))
        notes += more
    return law


def trace_channel(sys: ct.StateSpace, channel: Channel, y: NDArray, u: NDArray, *,
                  Q: NDArray, R: NDArray, dt: float | None = None, nonlinear: bool = True,
                  max_order: int = 2, min_order: int = 1, skip: int | None = None,
                  cond_tol: float = 1e-6, smooth: bool | str = "auto",
                  breaks: bool = False, prune: float = 0.0, own: bool = False) -> ChannelTrace:
    """Run the unknown-input filter for one channel and fit static and dynamic laws.

    Parameters
    ----------
    sys : control.StateSpace
        Nominal model (continuous with ``dt`` given, or discrete).
    channel : Channel
    y : ndarray, shape (noutputs, nsteps)
    u : ndarray, shape (ninputs, nsteps)
    Q, R : ndarray
        Noise covariances of the (discrete) nominal model.
    dt : float, optional
        Sampling period [s] (needed if ``sys`` is continuous).
    nonlinear : bool
        Offer x^3, sign(x), |x| terms to the static law.
    max_order : int
        Largest dynamic order tried (0 skips the dynamic fit).
    min_order : int
        Smallest dynamic order tried.
    skip : int, optional
        Leading samples left out of the fits (default: filter transient, >= 20).
    cond_tol : float
        A channel with ``sigma_min(C G) < cond_tol * ||C|| ||G||`` is skipped
        as practically unobservable (beyond the exact rank test (17)).
    breaks : bool
        Also offer the static law a dead zone and a saturation of each input
        whose whole effect passes through this channel (:func:`whole_inputs`;
        :data:`greybox.trace.laws.BREAK_KINDS`). Close the loop traces such
        a channel twice, without and with them, and lets its criterion choose.
    prune : float
        Above 0: keep the static law's terms only where the one criterion
        supports them (:func:`greybox.trace.oe.prune_by_criterion`: each term
        refitted by output error and dropped while the output-error BIC on
        effective samples, each parameter priced at ``prune`` times its BIC
        penalty, falls; True is 1, the BIC). Close the loop asks it for the
        candidate it chose, at its ``bic_factor``: the price its choice between
        candidates pays (pruning every candidate cost 2-6x the trace).
    own : bool
        With ``prune``: a one-equation law without its own state offered its forms first
        (:func:`greybox.trace.oe.offer_terms`).
    smooth : bool or "auto"
        Fit the static law on the fixed-interval smoothed d^ and x^
        (:func:`greybox.smooth_uikf`, the whole record is available) rather
        than on the filter's. "auto": only for a delayed estimate (r >= 2),
        where the filter's x^ lags; at r = 1 the smoother barely lowers the
        variance of d^ (d is free at every sample, so only y[j+1] informs
        d[j]) and costs as much as the filter. Either way the estimate has the relative degree
        :func:`greybox.detect_relative_degree` chooses (a force entering an
        acceleration with only positions measured: r = 2, no alternating d^),
        and the law's terms are weighted as d^ sees them
        (:func:`greybox.input_weights`). The dynamic fit always uses the causal
        r = 1 filter (closed-loop identification, PAPER_NOTES §8.4).

    Returns
    -------
    ChannelTrace
        With status "skipped" and a reason when (17) fails.
    """
    skip = _checked_skip(skip, smooth)
    model = channel_model(sys, channel, dt)
    check_discrete(model)
    if channel.kind == "output":
        return _trace_output(sys, channel, model, y, u, Q, R, nonlinear, skip, smooth)
    n, m = model.nstates, model.ninputs - channel.md
    Gd = np.asarray(model.B, dtype=float)[:, m:]
    C = np.asarray(model.C, dtype=float)
    reason = _unobservable(C, Gd, channel, cond_tol)
    if reason is not None:
        return ChannelTrace(channel=channel, status="skipped", reason=reason, model=model)
    labels = list(channel.labels)
    res = uikf(model, y, u, unknown=labels, Q=Q, R=R)
    N = y.shape[1] - 1
    k0 = skip if skip is not None else res.settled(20)
    nterms = (4 * n + 1 if nonlinear else n) + m
    _check_enough(N - k0, k0, nterms)
    notes = []
    cont = _continuous_parts(sys, channel, model)
    est, r, align = _law_estimate(model, labels, y, u, Q, R, res, smooth, notes,
                                  None if cont is None else (cont[0], cont[2]))
    ld, law = _law_on_dhat(est, u, y.shape[1], k0, nterms, align, r, channel, notes, res.sys,
                           nonlinear, whole_inputs(sys, channel) if breaks and nonlinear else (),
                           _foh_weights(model, labels, cont) if r == 1 and not est.smoothed
                           else None)
    law = _held(law, cont, r, ld.midpoint)
    d, xw, uw, align, averaged, Ne = ld.d, ld.xw, ld.uw, ld.align, ld.averaged, ld.Ne
    K = d.shape[1]
    x = _aligned_rows(xw, align, K)
    uu = _aligned_rows(uw, align, K)
    # d^ barely above its own estimation noise: choose the law by output error (r = 1)
    dnoise = np.atleast_2d(est.d_cov) if averaged or not est.smoothed else \
        np.diag(np.mean(est.d_var[:, k0:Ne], axis=1))
    excess = _excess_variance(d, dnoise)
    # output error needs a simulation that stays bounded over the record
    oe_ok = not unstable_reason(model, y.shape[1])
    if not oe_ok:
        notes.append("the nominal model is unstable: the static law is the least-squares fit "
                     "on d^ (no output-error refinement: its simulation diverges)")
    law = _refined_law(law, model, channel, y, u, res.x_filt[:, 0], k0, cont, (Q, R),
                       est.smoothed or r >= 2, averaged, excess, oe_ok, (d, xw, uw, align),
                       (x, uu), notes, prune, own)
    refined_G = _free_direction(sys, channel, model, cont, law, y, u, res.x_filt[:, 0], k0,
                                Q, R, notes) if oe_ok else None
    if isinstance(refined_G, str):
        return _one_body(channel, model, refined_G, notes)
    sub0 = _static_subsystem(law, replace(res, d_cov=dnoise), d, x, uu)
    static_model = _static_model(model, sub0, law, labels, Q, R, cont)
    dyn, dyn_model = _dynamic_part(res, min_order, max_order, k0, model, labels, Q, R, notes)
    return ChannelTrace(channel=channel, status="ok", model=model, filter_result=res,
                        law_estimate=est, relative_degree=r, static=law, static_model=static_model, dynamic=dyn,
                        dynamic_model=dyn_model, notes=tuple(notes), refined_G=refined_G)


@dataclass(frozen=True)
class _LawData:
    """The samples of :func:`trace_channel`'s static law: d^ on ``k0:Ne`` (``averaged`` over
    consecutive samples when it alternates), the states ``xw`` and inputs ``uw`` its terms
    are formed from, and the weights ``align`` of d^ over ``d[j], d[j+1], ...``;
    ``midpoint``: ``xw`` holds the states within each sample where a continuous law's
    first-order hold weighs them (the law is then simulated with that hold)."""

    d: NDArray[np.float64]
    xw: NDArray[np.float64]
    uw: NDArray[np.float64]
    align: NDArray[np.float64]
    averaged: bool
    Ne: int
    midpoint: bool = False


def _law_data(est, u, nsteps: int, k0: int, nterms: int, align, r: int, md: int,
              notes: list, foh=None) -> _LawData:
    """The static law's window of the estimate ``est`` of ``nsteps`` samples (enough checked).

    ``foh`` (md, 2): the first-order-hold weights of a continuous law in what the r = 1
    estimate stands for (:func:`greybox.input_weights` with ``continuous``): the terms
    are then formed from the states at those weights within the sample and the held
    input, unless d^ alternates (then it is averaged over consecutive samples instead)."""
    # est.d_est[:, j] estimates sum_i align[:, i] d[j + i]: the law's terms are weighted alike,
    # so x and u carry nw - 1 more columns than d (the last r columns of a delayed d^ are NaN)
    nw = align.shape[1]
    Ne = _estimate_end(est, nsteps, nw, k0)
    _check_enough(Ne - k0, k0, nterms)
    d = est.d_est[:, k0:Ne]
    xw = est.x_filt[:, k0:Ne + nw - 1]
    uw = u[:, k0:Ne + nw - 1]
    averaged = False
    if r == 1 and not est.smoothed:
        # the r = 1 filter kept (the delayed one was not better): d^ may still alternate in
        # sign (a ZOH zero near z = -1); then it estimates about the mean of two samples
        r1 = float(np.min(autocorrelation(d, 1)[:, 1])) if d.shape[1] > 2 else 0.0
        if r1 < _ALTERNATING:
            align = np.full((md, 2), 0.5)
            d = 0.5 * (d[:, 1:] + d[:, :-1])
            averaged = True
            notes.append(f"d^ alternates sign (lag-1 autocorrelation {r1:.2f}): the static law "
                         f"is fitted on terms averaged over consecutive samples")
    midpoint = False
    if foh is not None and not averaged and Ne + 1 <= nsteps:
        # a continuous law f between the samples, the input held: d^[j] stands for
        # w0 f(x[j], u[j]) + w1 f(x[j+1], u[j]) ~ f(w0 x[j] + w1 x[j+1], u[j])
        xn = est.x_filt[:, k0 + 1:Ne + 1]
        if np.all(np.isfinite(xn)):
            w = np.mean(foh, axis=0)
            xw, midpoint = w[0] * xw + w[1] * xn, True
    return _LawData(d=d, xw=xw, uw=uw, align=align, averaged=averaged, Ne=Ne,
                    midpoint=midpoint)
