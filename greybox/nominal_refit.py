"""The nominal model's own parameters refitted jointly with an added law (nonlinear models).

A law found by the trace is first fitted on a FIXED nominal model. When the
nominal's parameters were themselves fitted on the same record (the usual
case for a physical model of a real machine: orifice coefficients, a sensor's
offset), they absorbed part of the missing effect, and the law on the fixed
nominal sees only what is left: the cascaded tanks' overflow on a Torricelli
model fitted with the overflow periods in moves the estimation SE by 10 %
only (``bench/tanks_floors.py``, rows 13-14 against 12). Here the parameters
the model DECLARES (``control.nlsys(..., params={...})``, finite real
scalars, read by its update function) are refitted by output error together
with the law's coefficients (and saturation levels), the law's direction in
the other state equations (its "spill": the same flow leaving one store and
entering another, a force acting on two bodies; one ratio per other state)
and the initial state. The result names every parameter's change with its
95 % interval: which parameter was wrong and by how much.

Layer: workflow (7), beside :mod:`greybox.workflow_nonlinear`, which uses it (stages 1b and
2c); it reads the trace's law records (:mod:`greybox.trace.laws`), simulates
with :func:`greybox.simulate_nonlinear` and never filters.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import control as ct
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from .exceptions import GreyboxError, ModelError
from .metrics import relative_error
from .nonlinear import add_law, simulate_nonlinear
from .terms import HINGE_KINDS, term_kind
from .trace.intervals import hac_covariance

__all__ = ["ParameterChange", "JointRefit", "free_parameters", "with_parameters",
           "law_coordinates", "refit_jointly"]

_BIG = 1e3  # residual of a diverged simulation, per sample (scaled units)


@dataclass(frozen=True)
class ParameterChange:
    """One declared parameter of the nominal model, before and after the joint refit.

    Attributes
    ----------
    name : str
        Key in the model's ``params``.
    nominal : float
        The value the model declared (its units are the model's).
    refitted : float
        The value refitted with the law, by output error on the estimation record.
    halfwidth : float
        95 % half-width of ``refitted`` (autocorrelation-robust covariance of the
        output-error fit); NaN when the fit's Jacobian is degenerate.
    """

    name: str
    nominal: float
    refitted: float
    halfwidth: float

    @property
    def change(self) -> float:
        """Relative change ``refitted / nominal - 1`` (NaN for a zero nominal)."""
        return self.refitted / self.nominal - 1.0 if self.nominal != 0 else float("nan")

    def text(self) -> str:
        """``k1 0.0437 -> 0.0362 ± 0.002 (-17 %)``."""
        ch = f" ({100 * self.change:+.0f} %)" if np.isfinite(self.change) else ""
        hw = f" ± {self.halfwidth:.2g}" if np.isfinite(self.halfwidth) else ""
        return f"{self.name} {self.nominal:.4g} -> {self.refitted:.4g}{hw}{ch}"

    def as_dict(self) -> dict:
        return {"name": self.name, "nominal": self.nominal, "refitted": self.refitted,
                "halfwidth": self.halfwidth}


@dataclass(frozen=True)
class JointRefit:
    """A nominal model's declared parameters refitted jointly with a law.

    Attributes
    ----------
    model : control.NonlinearIOSystem
        The nominal with the refitted parameters, plus ``G law(x, u)`` when a law
        was refitted (the model's own time base).
    law : StaticLaw or None
        The refitted law (coefficients, levels, 95 % half-widths in ``ci``), or
        None for the parameters alone.
    G : ndarray, shape (nstates, md) or None
        The law's direction: the channel's G plus the fitted spill entries.
    parameters : tuple of ParameterChange
        Every declared parameter, nominal and refitted.
    spill : tuple of (state name, ratio, 95 % half-width)
        The law's entries in other state equations, relative to its own channel's
        (e.g. ``("x2", -0.98, 0.05)``: what leaves eq(x1) enters eq(x2) at 98 %).
    x_start : ndarray, shape (nstates,)
        The refitted state at the record's first compared sample.
    se : float
        Estimation SE [%] (eq. 42) of the refitted model's simulation.
    residual : ndarray, shape (noutputs, nsteps)
        Its output error on the compared samples.
    nfree : int
        Parameters fitted besides the initial state.
    nlaw : int
        Of those, the law's (coefficients, levels, spill ratios).
    law_halfwidths : ndarray
        95 % half-widths of the law's coordinates in :func:`law_coordinates`'
        order (coefficients, then hinge levels); empty without a law.
    unidentifiable : tuple of str
        Declared parameters that move together along a direction the output
        does not see (the scaled Jacobian's smallest singular value below
        ``IDENTIFIABLE`` times its largest, and the data not determining that
        combination to within its own size): only a combination of them is
        determined (e.g. k1, k2, k4 of tanks whose upper level is not
        measured: the level's scale is free). Their half-widths are NaN; fix
        one of them (do not declare it) to pin the scale.
    dropped : tuple of str
        The law's terms dropped because they moved with a declared parameter
        (the same blind direction: e.g. a linear term ``x`` beside a declared
        linear coefficient): the parameter carries them, the law keeps the rest.
    """

    model: ct.NonlinearIOSystem
    law: object | None
    G: NDArray[np.float64] | None
    parameters: tuple[ParameterChange, ...]
    spill: tuple[tuple[str, float, float], ...]
    x_start: NDArray[np.float64]
    se: float
    residual: NDArray[np.float64]
    nfree: int
    nlaw: int
    law_halfwidths: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    unidentifiable: tuple[str, ...] = ()
    dropped: tuple[str, ...] = ()

    def parameter_text(self) -> str:
        """``k1 0.0437 -> 0.0362 ± 0.002 (-17 %), ...`` (and the unidentifiable ones)."""
        out = ", ".join(p.text() for p in self.parameters)
        if self.dropped:
            out += (f"; law term(s) {', '.join(self.dropped)} dropped: they duplicate a "
                    f"declared parameter")
        if self.unidentifiable:
            out += (f"; not separately identifiable from the outputs: "
                    f"{', '.join(self.unidentifiable)} (only a combination is determined: "
                    f"do not declare one of them, to fix the scale)")
        return out

    def spill_text(self) -> str:
        """``eq(x2) at -0.98 ± 0.05 times the law`` for every spill entry ('' without)."""
        return ", ".join(f"eq({s}) at {g:.3g}" + (f" ± {h:.2g}" if np.isfinite(h) else "")
                         + " times the law" for s, g, h in self.spill)


def free_parameters(sys) -> dict[str, float]:
    """The parameters a nonlinear model declares that can be refitted: finite real scalars.

    ``sys.params`` of a ``control.NonlinearIOSystem`` (what its update function
    receives); entries that are not finite real numbers (arrays, flags,
    callables) are left out. Empty for a StateSpace.
    """
    par = getattr(sys, "params", None) or {}
    out = {}
    for k, v in par.items():
        if isinstance(v, (bool, np.bool_)):
            continue
        if isinstance(v, (int, float, np.integer, np.floating)) and np.isfinite(v):
            out[str(k)] = float(v)
    return out


def with_parameters(sys: ct.NonlinearIOSystem, values: dict) -> ct.NonlinearIOSystem:
    """A copy of ``sys`` whose declared ``params`` take ``values`` (the others kept).

    Raises
    ------
    ModelError
        A name that ``sys`` does not declare.
    """
    par = dict(getattr(sys, "params", None) or {})
    unknown = sorted(set(values) - set(par))
    if unknown:
        raise ModelError(f"{sys.name} declares no parameter(s) {unknown}; its params are "
                         f"{sorted(par)}")
    par.update({k: float(v) for k, v in values.items()})
    return ct.nlsys(sys.updfcn, sys.outfcn, states=list(sys.state_labels),
                    inputs=list(sys.input_labels), outputs=list(sys.output_labels),
                    dt=sys.dt, params=par, name=sys.name)


def law_coordinates(law) -> tuple[NDArray, Callable, list, list]:
    """The free coordinates of a static law: its selected coefficients, then its hinge levels.

    Returns ``(theta0, law_at, sel, hinges)``: ``law_at(theta)`` the law with
    those coordinates (the hinges renamed at their new levels), ``sel`` the
    (component, term) pairs of the coefficients, ``hinges`` the term indices
    of the selected saturation hinges whose levels follow the coefficients.
    """
    sel = [(c, int(j)) for c in range(law.coef.shape[0]) for j in np.flatnonzero(law.coef[c])]
    rows = np.array([s[0] for s in sel], dtype=int)
    cols = np.array([s[1] for s in sel], dtype=int)
    hinges = sorted({j for _, j in sel if law.spec[j][1] in HINGE_KINDS})
    nc = len(sel)

    def law_at(theta):
        coef = law.coef.copy()
        coef[rows, cols] = theta[:nc]
        spec = list(law.spec)
        for j, level in zip(hinges, theta[nc:]):
            spec[j] = term_kind(spec[j][1]).at_level(spec[j], level)
        return replace(law, coef=coef, spec=tuple(spec))

    theta0 = np.concatenate([law.coef[rows, cols], [law.spec[j][2][1] for j in hinges]])
    return theta0.astype(float), law_at, sel, hinges


@dataclass(frozen=True)
class _JointProblem:
    """The output-error problem of :func:`refit_jointly`: the coordinates ``theta`` are the
    declared parameters ``keys``, the law's coordinates, the spill ratios, the initial state."""

    base: ct.NonlinearIOSystem
    disc: Callable
    y: NDArray
    u: NDArray
    C: NDArray
    D: NDArray
    keys: list
    th0: NDArray
    law: object
    law_at: Callable | None
    G: NDArray | None
    max_nfev: int
    scale: NDArray
    big: NDArray

    def build(self, theta, sp):
        """The model, law and law direction at ``theta`` (spill into the states ``sp``)."""
        keys, th0, law, G, base = self.keys, self.th0, self.law, self.G, self.base
        kp, nl = len(keys), len(th0)
        model = with_parameters(base, dict(zip(keys, theta[:kp])))
        lw, Gt = None, None
        if law is not None:
            lw = self.law_at(theta[kp:kp + nl])
            Gt = G.copy()
            for q, j in enumerate(sp):
                Gt[j, 0] = theta[kp + nl + q] * G[np.flatnonzero(G[:, 0])[0], 0]
            model = add_law(model, Gt, lw.evaluate, name=f"{base.name}_updated")
        return model, lw, Gt

    def resid_of(self, theta, sp):
        """Scaled output errors (flat) and the simulation; ``big`` and None if it fails."""
        y, u, n, big = self.y, self.u, self.base.nstates, self.big
        model, _, _ = self.build(theta, sp)
        try:
            sim = simulate_nonlinear(self.disc(model), u, x0=theta[-n:])
        except (GreyboxError, FloatingPointError, ValueError):
            return big, None
        r = (y - self.C @ sim.x - self.D @ u) / self.scale
        if not np.all(np.isfinite(r)) or np.max(np.abs(r)) > _BIG:
            return big, None
        return r.ravel(), sim

    def fit(self, sp, start):
        """The least-squares fit from ``start`` (None if it fails)."""
        try:
            with np.errstate(all="ignore"):
                return least_squares(lambda t: self.resid_of(t, sp)[0], start, x_scale="jac",
                                     max_nfev=self.max_nfev, ftol=1e-6, xtol=1e-6)
        except (ValueError, np.linalg.LinAlgError):
            return None


def refit_jointly(base: ct.NonlinearIOSystem, disc: Callable, y: NDArray, u: NDArray,
                  x_start: NDArray, C: NDArray, D: NDArray, *, law=None,
                  G: NDArray | None = None, spill: bool = True, max_nfev: int = 60,
                  names: tuple[str, ...] | None = None) -> JointRefit | None:
    """Refit ``base``'s declared parameters (and a law) by output error on (y, u).

    Parameters
    ----------
    base : control.NonlinearIOSystem
        Nominal model in its own time base, with ``params``.
    disc : callable
        ``disc(model)`` -> the discrete model to simulate (identity for a discrete one).
    y, u : ndarray, shapes (noutputs, nsteps), (ninputs, nsteps)
        The compared samples (the caller drops its filter's start-up).
    x_start : ndarray, shape (nstates,)
        Start of the fit's initial state (refitted).
    C, D : ndarray
        The model's linear output map.
    law : StaticLaw, optional
        The law to refit with the parameters (coefficients and hinge levels).
    G : ndarray, shape (nstates,) or (nstates, 1)
        The law's channel.
    spill : bool
        For a one-equation channel (a unit column G), let the law also enter
        every other state equation at a fitted ratio; ratios within their own
        95 % interval of zero are dropped (one refit without them).
    max_nfev : int
        Function evaluations of each least-squares fit (each costs
        1 + nfree simulations for the Jacobian).
    names : tuple of str, optional
        The parameters to refit (default all of :func:`free_parameters`).

    Returns
    -------
    JointRefit or None
        None when the model declares no parameter or the fit fails.
    """
    p0 = free_parameters(base)
    if names is not None:
        p0 = {k: p0[k] for k in names if k in p0}
    if not p0:
        return None
    keys = list(p0)
    n = base.nstates
    if law is not None:
        th0, law_at, sel, _ = law_coordinates(law)
        G = np.asarray(G, dtype=float).reshape(n, -1)
    else:
        th0, law_at, sel = np.zeros(0), None, []
    unit = law is not None and G.shape[1] == 1 and np.count_nonzero(G[:, 0]) == 1
    others = [j for j in range(n) if unit and spill and G[j, 0] == 0]
    jp = _JointProblem(base=base, disc=disc, y=y, u=u, C=C, D=D, keys=keys, th0=th0,
                       law=law, law_at=law_at, G=G, max_nfev=max_nfev,
                       scale=np.maximum(np.std(y, axis=1), 1e-300)[:, None],
                       big=np.full(y.size, _BIG))
    start = np.concatenate([[p0[k] for k in keys], th0, np.zeros(len(others)),
                            np.asarray(x_start, dtype=float)])
    sol = jp.fit(others, start)
    if sol is None or not np.all(np.isfinite(sol.x)) or np.all(sol.fun == _BIG):
        return None
    kp, nl = len(keys), len(th0)
    half = _halfwidths(sol, y.shape[0])
    if others:  # a ratio within its own 95 % interval of zero is dropped
        keep = [q for q in range(len(others))
                if abs(sol.x[kp + nl + q]) > half[kp + nl + q]]
        if len(keep) < len(others):
            idx = list(range(kp + nl)) + [kp + nl + q for q in keep] + \
                list(range(len(sol.x) - n, len(sol.x)))
            others = [others[q] for q in keep]
            sol2 = jp.fit(others, sol.x[idx])
            if sol2 is None or not np.all(np.isfinite(sol2.x)):
                return None
            sol, half = sol2, _halfwidths(sol2, y.shape[0])
    flat = _flat_direction(sol)
    nc = len(sel)
    twins = [sel[i - kp] for i in flat if kp <= i < kp + nc]
    if law is not None and twins and any(i < kp for i in flat):
        # law terms that move with a declared parameter (e.g. a linear term beside the
        # parameter of the same linear term): the parameter carries them; drop and refit
        coef = law.coef.copy()
        for c, j in twins:
            coef[c, j] = 0.0
        if not np.any(coef):
            return None
        out = refit_jointly(base, disc, y, u, x_start, C, D, law=replace(law, coef=coef),
                            G=G, spill=spill, max_nfev=max_nfev, names=tuple(keys))
        return None if out is None else replace(
            out, dropped=out.dropped + tuple(law.spec[j][0] for _, j in twins))
    r, sim = jp.resid_of(sol.x, others)
    if sim is None:
        return None
    lost = tuple(keys[i] for i in flat if i < kp)
    if lost:  # only a combination of them is determined: no interval for each
        half[list(flat)] = np.nan
    model, lw, Gt = jp.build(sol.x, others)
    if lw is not None:  # the law's 95 % half-widths from the joint covariance
        ci = np.full_like(lw.coef, np.nan)
        for q, (c, j) in enumerate(sel):
            ci[c, j] = half[kp + q]
        lw = replace(lw, ci=ci)
    changes = tuple(ParameterChange(k, p0[k], float(sol.x[i]), float(half[i]))
                    for i, k in enumerate(keys))
    states = list(base.state_labels)
    sp = tuple((states[j], float(sol.x[kp + nl + q]), float(half[kp + nl + q]))
               for q, j in enumerate(others))
    res = y - C @ sim.x - D @ u
    return JointRefit(model=model, law=lw, G=Gt, parameters=changes, spill=sp,
                      x_start=np.asarray(sol.x[-n:], dtype=float),
                      se=float(relative_error(y, y - res).value),
                      residual=res, nfree=len(sol.x) - n, nlaw=nl + len(others),
                      law_halfwidths=np.asarray(half[kp:kp + nl], dtype=float),
                      unidentifiable=lost)


IDENTIFIABLE = 1e-5  # smallest over largest singular value of the relative Jacobian


def _flat_direction(sol) -> list[int]:
    """Indices of the coordinates in the output's blind direction ([] when none).

    The Jacobian's columns are scaled by the coordinates' magnitudes (relative
    sensitivities). A direction is blind when both (i) the smallest singular value is
    below ``IDENTIFIABLE`` times the largest (numerically degenerate) and (ii) the
    data do not determine the coordinates along it to within their own size: the 95 %
    half-width of that combination, ``1.96 s / sigma_min`` (s the residual's standard
    deviation, white-noise least squares), is at least 1. Then the coordinates
    carrying more than 20 % of that right singular vector move together unseen. The
    ratio alone is relative to the best-seen coordinate (an initial state), and moved
    by a factor 7 with the last-digit rounding of a law's terms on the cascaded tanks,
    where the spill along that direction is determined to +-35 % (measured).
    """
    jac = np.asarray(sol.jac, dtype=float)
    if not np.all(np.isfinite(jac)) or jac.shape[1] < 2:
        return []
    J = jac * np.maximum(np.abs(sol.x), 1e-8)[None, :]
    try:
        _, sv, vt = np.linalg.svd(J, full_matrices=False)
    except np.linalg.LinAlgError:
        return []
    if not sv[0] > 0 or sv[-1] >= IDENTIFIABLE * sv[0]:
        return []
    fun = np.asarray(sol.fun, dtype=float)
    s = np.sqrt(np.sum(fun ** 2) / max(fun.size - J.shape[1], 1))
    if 1.96 * s < sv[-1]:  # determined to within its size: not blind
        return []
    return [int(i) for i in np.flatnonzero(np.abs(vt[-1]) > 0.2)]


def _halfwidths(sol, p: int) -> NDArray[np.float64]:
    """95 % half-widths of a least-squares solution (autocorrelation-robust covariance)."""
    jac, fun = np.asarray(sol.jac, dtype=float), np.asarray(sol.fun, dtype=float)
    if not (np.all(np.isfinite(jac)) and np.max(np.abs(fun)) < _BIG):
        return np.full(sol.x.size, np.nan)
    try:
        cov = hac_covariance(jac, fun, p)
    except (np.linalg.LinAlgError, ValueError):
        return np.full(sol.x.size, np.nan)
    return 1.96 * np.sqrt(np.clip(np.diag(cov), 0, None))
