"""Trace one candidate channel: unknown-input filter, static and dynamic laws."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import control as ct
import numpy as np
from numpy.typing import NDArray

from .._validation import check_discrete, check_positive
from ..exceptions import DataError, GreyboxError, GreyboxWarning, RankConditionError
from ..filters import FilterResult, check_rank_condition, uikf
from ..metrics import autocorrelation
from ..system import named_ss
from ..update import Subsystem, UpdatedModel, augment_model, identify_subsystem
from ..validate import unstable_reason
from .channels import Channel, channel_model
from .laws import LINEAR_KINDS, StaticLaw, _eval_terms, _fit_static, _static_subsystem
from .oe import _refine_static_oe, _select_static_oe, zoh

# Below this excess of var(d^) over the filter's Pd, d^ is treated as mostly
# estimation noise and the static law is chosen by output error on y instead.
_LOW_SNR = 0.1
# Below this lag-1 autocorrelation d^ is taken to alternate sign (see trace_channel).
_ALTERNATING = -0.5
# Terms offered to an output-error selection of a force law (ranked by correlation with d^).
_OE_CANDIDATES = 6


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
        The unknown-input filter on the estimation data.
    static : StaticLaw or None
    static_model : UpdatedModel or None
        Nominal model with the (linear part of the) static law folded into A, B.
    dynamic : Subsystem or None
    dynamic_model : UpdatedModel or None
    notes : tuple of str
        Warnings met on the way (e.g. a failed dynamic identification).
    """

    channel: Channel
    status: str
    reason: str = ""
    model: ct.StateSpace | None = field(default=None, repr=False)
    filter_result: FilterResult | None = field(default=None, repr=False)
    static: StaticLaw | None = None
    static_model: UpdatedModel | None = field(default=None, repr=False)
    dynamic: Subsystem | None = field(default=None, repr=False)
    dynamic_model: UpdatedModel | None = field(default=None, repr=False)
    notes: tuple[str, ...] = ()


def trace_channel(sys: ct.StateSpace, channel: Channel, y: NDArray, u: NDArray, *,
                  Q: NDArray, R: NDArray, dt: float | None = None, nonlinear: bool = True,
                  max_order: int = 2, min_order: int = 1, skip: int | None = None,
                  cond_tol: float = 1e-6) -> ChannelTrace:
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

    Returns
    -------
    ChannelTrace
        With status "skipped" and a reason when (17) fails.
    """
    if skip is not None:
        skip = check_positive(skip, "skip", integer=True, allow_zero=True)
    model = channel_model(sys, channel, dt)
    check_discrete(model)
    n, m = model.nstates, model.ninputs - channel.md
    Gd = np.asarray(model.B, dtype=float)[:, m:]
    C = np.asarray(model.C, dtype=float)
    try:
        check_rank_condition(C, Gd, channel.labels)
    except RankConditionError as e:
        return ChannelTrace(channel=channel, status="skipped", reason=str(e), model=model)
    sv = np.linalg.svd(C @ Gd, compute_uv=False)
    if sv.min() < cond_tol * np.linalg.norm(C, 2) * np.linalg.norm(Gd, 2):
        return ChannelTrace(channel=channel, status="skipped", model=model,
                            reason=f"C G is nearly singular (sigma_min/sigma_max = "
                                   f"{sv.min() / max(sv.max(), 1e-300):.2g}); the error "
                                   f"would be practically unobservable")
    labels = list(channel.labels)
    res = uikf(model, y, u, unknown=labels, Q=Q, R=R)
    N = y.shape[1] - 1
    k0 = skip if skip is not None else max(20, res.period_converged or 20)
    nterms = (4 * n if nonlinear else n) + m
    if N - k0 <= nterms:
        raise DataError(f"{N - k0} samples left after skipping {k0} cannot fit a law of "
                        f"{nterms} candidate terms; give more data or a smaller skip")
    d = res.d_est[:, k0:N]
    x = res.x_filt[:, k0:N]
    uu = u[:, k0:N]
    notes = []
    # d^ alternating sign: the channel reaches the outputs through a ZOH zero
    # near z = -1 (e.g. a velocity equation seen through positions only, C G ~
    # dt^2/2) and the filter's inversion leaves an oscillation at the Nyquist
    # frequency; the mean of two consecutive samples cancels it.
    r1 = float(np.min(autocorrelation(d, 1)[:, 1])) if d.shape[1] > 2 else 0.0
    pair_mean = r1 < _ALTERNATING
    law = _fit_static(d, x, uu, res.sys, nonlinear, labels, channel.units, pair_mean,
                      channel.relative)
    if pair_mean:
        notes.append(f"d^ alternates sign (lag-1 autocorrelation {r1:.2f}): the static law "
                     f"is fitted on the mean of consecutive samples")
    # d^ barely above its own estimation noise: choose the law by output error
    excess = float(np.trace(np.atleast_2d(np.cov(d, bias=True)))) / \
        max(float(np.trace(np.atleast_2d(res.d_cov))), 1e-300) - 1.0
    # a continuous nominal model: linear laws are parametrized in continuous time
    cont = None if ct.isdtime(sys, strict=True) else (
        np.asarray(sys.A, dtype=float), np.asarray(sys.B, dtype=float),
        np.asarray(channel.G, dtype=float), float(model.dt))
    # output error needs a simulation that stays bounded over the record
    oe_ok = not unstable_reason(model, y.shape[1])
    if not oe_ok:
        notes.append("the nominal model is unstable: the static law is the least-squares fit "
                     "on d^ (no output-error refinement)")
    if excess < _LOW_SNR and not pair_mean and oe_ok:
        law = _select_static_oe(law, model, channel.md, y, u, res.x_filt[:, 0], k0, labels,
                                channel.units, cont=cont, noise=(Q, R))
        notes.append(f"d^ is mostly estimation noise (variance only {100 * excess:.2g}% above "
                     f"Pd): static law chosen by output error on y")
    elif channel.relative and oe_ok and (pair_mean or law.npar > 2 * channel.md):
        # a force between bodies whose d^ fit is not sparse (d^ alternating or
        # noise-dominated, e.g. positions only): choose the law by output error among the
        # linear terms d^'s pair means correlate with most (per component of d)
        terms = _eval_terms(law.spec, law.eps, x, uu)
        lin = [j for j, sp in enumerate(law.spec) if sp[1] in LINEAR_KINDS]
        tm = 0.5 * (terms[lin, 1:] + terms[lin, :-1])
        tm = tm - tm.mean(axis=1, keepdims=True)
        only = set()
        for c in range(channel.md):
            dm = 0.5 * (d[c, 1:] + d[c, :-1])
            dm = dm - dm.mean()
            corr = np.abs(tm @ dm) / (np.linalg.norm(tm, axis=1) * np.linalg.norm(dm) + 1e-300)
            only |= {lin[q] for q in np.argsort(-corr)[:_OE_CANDIDATES]}
        law = _select_static_oe(law, model, channel.md, y, u, res.x_filt[:, 0], k0, labels,
                                channel.units, cont=cont, noise=(Q, R), only=sorted(only))
        notes.append("a force seen through alternating d^: static law chosen by output "
                     "error on y among the terms d^ correlates with most")
    elif not law.nonlinear and law.npar and oe_ok:
        tscale = law.term_scale(x, uu)
        law, se_d, se_y = _refine_static_oe(law, model, channel.md, y, u, res.x_filt[:, 0],
                                            k0, labels, channel.units, tscale, cont, (Q, R))
        if se_y < se_d:
            notes.append(f"static law refined by output error on y: estimation SE "
                         f"{se_d:.3g}% -> {se_y:.3g}%")
    sub0 = _static_subsystem(law, res, d, x, uu)
    static_model = augment_model(model, sub0, unknown=labels, Q=Q, R=R)
    if law.time_base == "continuous":  # fold the law in continuous time, discretize exactly
        Ac, Bc, Gc, h = cont
        Ad, Bd = zoh(Ac + Gc @ law.Ddx, Bc + Gc @ law.Ddu, h)
        s0 = static_model.sys
        static_model = replace(static_model, sys=named_ss(
            Ad, Bd, s0.C, s0.D, s0.dt, states=s0.state_labels, inputs=s0.input_labels,
            outputs=s0.output_labels, name=s0.name))
    dyn, dyn_model = None, None
    if max_order >= max(min_order, 1):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", GreyboxWarning)
                dyn = identify_subsystem(res, min_order=max(min_order, 1),
                                         max_order=max_order, skip=k0)
            if dyn.Ad.shape[0] != dyn.order:  # md > 1: pbsid may return md*order states
                dyn = replace(dyn, order=dyn.Ad.shape[0])
            dyn_model = augment_model(model, dyn, unknown=labels, Q=Q, R=R)
        except (GreyboxError, np.linalg.LinAlgError) as e:
            notes.append(f"dynamic fit failed: {e}")
    return ChannelTrace(channel=channel, status="ok", model=model, filter_result=res,
                        static=law, static_model=static_model, dynamic=dyn,
                        dynamic_model=dyn_model, notes=tuple(notes))
