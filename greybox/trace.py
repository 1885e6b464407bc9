"""Trace a model error to the state equation(s) it enters, and describe it.

For one candidate error channel (a matrix G: which state equations, with
which weights) the unknown-input filter :func:`greybox.uikf` estimates the
model error d^ on estimation data. d^ is then explained

* **statically** (order 0): ``d[j] = f(x[j], u[j])``, a sparse law chosen by
  forward selection with a BIC stopping rule over named linear terms (states
  and inputs) and, optionally, the nonlinear terms ``x^3``, ``sign(x)``
  (a smooth ``tanh(x/eps)``) and ``|x|`` of every state (PAPER_NOTES §9.4);
* **dynamically** (order 1..max_order): the subsystem (19)-(20) with
  feedthrough, by :func:`greybox.identify_subsystem` (closed-loop subspace
  identification, PAPER_NOTES §8.4).

Both are kept (PAPER_NOTES §9.2): the workflow chooses between them by the
simulation error of the augmented model. Laws stay in discrete time
(PAPER_NOTES §9.5): ``d[j]`` acts through the ZOH-discretized G between
samples j and j+1, so its units are those of the channel (e.g. [N] for a
force channel, [x_i units / s] for a bare continuous state equation).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import control as ct
import numpy as np
from numpy.typing import NDArray

from ._lti import lti_states
from ._validation import check_discrete, check_positive
from .exceptions import (DataError, DimensionError, GreyboxError, GreyboxWarning, ModelError,
                         RankConditionError)
from .filters import FilterResult, check_rank_condition, uikf
from .metrics import autocorrelation
from .ident.regression import SparseLaw, forward_selection
from .system import discretize, named_ss
from .update import Subsystem, UpdatedModel, augment_model, identify_subsystem, psd_part
from .validate import unstable_reason

__all__ = [
    "Channel",
    "default_channels",
    "resolve_channel_spec",
    "channel_model",
    "StaticLaw",
    "ChannelTrace",
    "trace_channel",
    "law_terms",
    "simulate_with_law",
    "predict_with_law",
    "parameter_notes",
]


# --------------------------------------------------------------------------- channels
@dataclass(frozen=True, eq=False)
class Channel:
    """A candidate error channel: the model error enters as ``G d``.

    Attributes
    ----------
    name : str
        Readable name, e.g. ``"eq(v1)"`` or ``"eq(v1)+eq(v2)"`` or a user name.
    G : ndarray, shape (nstates, md)
        Input matrix of d in the nominal model's own time base (continuous
        if the nominal model is continuous; it is then ZOH-discretized
        together with B).
    labels : tuple of str
        Names of the md components of d.
    units : tuple of str
        Units of the components of d ("" if unknown).
    equations : tuple of str
        Names of the states whose equations the channel enters.
    """

    name: str
    G: NDArray[np.float64]
    labels: tuple[str, ...]
    units: tuple[str, ...] = ()
    equations: tuple[str, ...] = ()

    @property
    def md(self) -> int:
        """Number of unknown-input components."""
        return self.G.shape[1]

    def _key(self):
        G = np.asarray(self.G, dtype=float)
        return (self.name, G.shape, G.tobytes(), tuple(self.labels), tuple(self.units),
                tuple(self.equations))

    def __eq__(self, other):  # G is an array: the generated __eq__ would be ambiguous
        if not isinstance(other, Channel):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self):
        return hash(self._key())


def _eq_channel(sys: ct.StateSpace, idx: Sequence[int]) -> Channel:
    n = sys.nstates
    G = np.zeros((n, len(idx)))
    for c, i in enumerate(idx):
        G[i, c] = 1.0
    names = [sys.state_labels[i] for i in idx]
    cont = not ct.isdtime(sys, strict=True)
    return Channel(name="+".join(f"eq({s})" for s in names), G=G,
                   labels=tuple(f"d_{s}" for s in names),
                   units=tuple((f"[{s}]/s" if cont else f"[{s}]/sample") for s in names),
                   equations=tuple(names))


def default_channels(sys: ct.StateSpace, *, pairs: bool | str = "auto") -> tuple[Channel, ...]:
    """Every single state equation, and pairs of equations where p allows.

    Parameters
    ----------
    sys : control.StateSpace
        Nominal model (continuous or discrete).
    pairs : bool or "auto"
        Also try pairs of equations (md = 2, PAPER_NOTES §9.6: an internal
        force between two bodies enters two equations). "auto": only when
        ``noutputs >= 2`` and ``nstates <= 4`` (the number of pairs grows as
        n^2; name channels explicitly for larger models).
    """
    if not (isinstance(pairs, (bool, np.bool_)) or pairs == "auto"):
        raise DataError(f"pairs must be True, False or 'auto'; found {pairs!r}")
    n = sys.nstates
    out = [_eq_channel(sys, [i]) for i in range(n)]
    use_pairs = (sys.noutputs >= 2 and n <= 4) if pairs == "auto" else bool(pairs)
    if use_pairs and sys.noutputs >= 2:
        out += [_eq_channel(sys, [i, j]) for i in range(n) for j in range(i + 1, n)]
    return tuple(out)


def resolve_channel_spec(sys: ct.StateSpace, spec) -> tuple[Channel, ...]:
    """Turn a user's channel specification into :class:`Channel` records.

    ``spec`` may be None (:func:`default_channels`), a sequence whose items
    are Channel records, state names, or tuples of state names (equations
    entered together), or a mapping ``{name: G}`` with G of shape
    (nstates,) or (nstates, md) in the nominal model's time base.
    """
    if spec is None:
        return default_channels(sys)
    if isinstance(spec, str):  # one state name, not a sequence of one-letter names
        spec = [spec]
    n = sys.nstates
    labels = list(sys.state_labels)
    out = []
    items = spec.items() if isinstance(spec, Mapping) else [(None, s) for s in spec]
    for key, s in items:
        if isinstance(s, Channel):
            out.append(s)
            continue
        if isinstance(s, str) or (isinstance(s, (tuple, list)) and s and
                                  all(isinstance(t, str) for t in s)):
            names = [s] if isinstance(s, str) else list(s)
            bad = [t for t in names if t not in labels]
            if bad:
                raise DimensionError(f"channels: no state named {bad}; states are {labels}")
            ch = _eq_channel(sys, [labels.index(t) for t in names])
            out.append(ch if key is None else Channel(key, ch.G, ch.labels, ch.units,
                                                       ch.equations))
            continue
        try:
            G = np.array(s, dtype=float)
        except (TypeError, ValueError) as e:
            raise DimensionError(f"channels[{key!r}] must be a G matrix or state names; "
                                 f"found {s!r}") from e
        if G.ndim == 1:
            G = G.reshape(-1, 1)
        if G.ndim != 2 or G.shape[0] != n or G.shape[1] < 1:
            raise DimensionError(f"channels[{key!r}] has shape {G.shape}; expected "
                                 f"({n},) or ({n}, md)")
        if not np.all(np.isfinite(G)):
            raise DimensionError(f"channels[{key!r}] contains NaN or inf")
        name = str(key) if key is not None else f"G{len(out)}"
        md = G.shape[1]
        eqs = tuple(labels[i] for i in range(n) if np.any(G[i] != 0))
        out.append(Channel(name=name, G=G,
                           labels=(name,) if md == 1 else tuple(f"{name}[{j}]" for j in range(md)),
                           units=("",) * md, equations=eqs))
    if not out:
        raise DimensionError("channels: give at least one candidate channel")
    return tuple(out)


def channel_model(sys: ct.StateSpace, channel: Channel, dt: float | None = None) -> ct.StateSpace:
    """Discrete model with inputs ``[u, d]`` for one channel (ZOH once, PAPER_NOTES §1).

    Parameters
    ----------
    sys : control.StateSpace
        Nominal model, continuous or discrete.
    channel : Channel
    dt : float, optional
        Sampling period [s]; needed if ``sys`` is continuous, and must agree
        with ``sys.dt`` if it is discrete.

    Raises
    ------
    ModelError
        If ``sys`` is continuous and ``dt`` is missing, or ``dt`` disagrees
        with a discrete ``sys``.
    DimensionError
        If ``channel.G`` does not have ``sys.nstates`` rows.
    """
    disc = ct.isdtime(sys, strict=True)
    if not disc and dt is None:
        raise ModelError("sys is continuous-time; give the sampling period dt [s] so that "
                         "it can be discretized (ZOH)")
    if disc and dt is not None and abs(float(dt) - float(sys.dt)) > 1e-9 * float(sys.dt):
        raise ModelError(f"dt = {dt} disagrees with the discrete model's dt = {sys.dt}")
    if channel.G.shape[0] != sys.nstates:
        raise DimensionError(f"channel {channel.name!r} has G of shape {channel.G.shape}; "
                             f"expected ({sys.nstates}, md)")
    A, B, C, D = (np.asarray(a, dtype=float) for a in (sys.A, sys.B, sys.C, sys.D))
    p, md = C.shape[0], channel.md
    inputs = list(sys.input_labels) + list(channel.labels)
    full = named_ss(A, np.hstack([B, channel.G]), C, np.hstack([D, np.zeros((p, md))]),
                    sys.dt if ct.isdtime(sys, strict=True) else 0,
                    states=sys.state_labels, inputs=inputs, outputs=sys.output_labels,
                    name=sys.name)
    if ct.isdtime(sys, strict=True):
        return full
    return discretize(full, dt)


# --------------------------------------------------------------------------- static laws
def law_terms(x: NDArray, u: NDArray, state_labels: Sequence[str],
              input_labels: Sequence[str], *, nonlinear: bool = True,
              eps: NDArray | None = None) -> tuple[NDArray, list[tuple[str, str, int]], NDArray]:
    """Candidate terms of a static law, evaluated on (x, u).

    Returns ``(terms, spec, eps)``: terms of shape (nterms, nsteps), a spec
    list of ``(display name, kind, index)`` with kind in
    {"x", "u", "x^3", "sign", "abs"}, and the eps of each state's
    ``tanh(x/eps)`` (5 % of the state's RMS unless given).
    """
    n, m = x.shape[0], u.shape[0]
    if eps is None:
        eps = 0.05 * np.sqrt(np.mean(x**2, axis=1)) + 1e-300
    rows, spec = [], []
    for i in range(n):
        rows.append(x[i])
        spec.append((state_labels[i], "x", i))
    for j in range(m):
        rows.append(u[j])
        spec.append((input_labels[j], "u", j))
    if nonlinear:
        for i in range(n):
            s = state_labels[i]
            rows.append(x[i] ** 3)
            spec.append((f"{s}^3", "x^3", i))
            rows.append(np.tanh(x[i] / eps[i]))
            spec.append((f"sign({s})", "sign", i))
            rows.append(np.abs(x[i]))
            spec.append((f"|{s}|", "abs", i))
    N = x.shape[1]
    return (np.array(rows) if rows else np.zeros((0, N))), spec, eps


def _eval_terms(spec, eps, x, u):
    out = np.empty((len(spec),) + x.shape[1:])
    for r, (_, kind, i) in enumerate(spec):
        v = x[i] if kind != "u" else u[i]
        out[r] = (v if kind in ("x", "u") else v**3 if kind == "x^3" else
                  np.tanh(v / eps[i]) if kind == "sign" else np.abs(v))
    return out


@dataclass(frozen=True)
class StaticLaw:
    """Sparse static law ``d[j] = coef @ terms(x[j], u[j])`` for each component of d.

    Attributes
    ----------
    spec : tuple of (name, kind, index)
        All candidate terms (see :func:`law_terms`).
    eps : ndarray, shape (nstates,)
        Smoothing widths of ``sign(x) ~ tanh(x/eps)``.
    coef : ndarray, shape (md, nterms)
        Coefficients (zero for terms not selected).
    Ddx : ndarray, shape (md, nstates)
        Linear part in the states (the best linear law when ``nonlinear``).
    Ddu : ndarray, shape (md, ninputs)
        Linear part in the inputs.
    nonlinear : bool
        True if a nonlinear term was selected.
    residual_var : ndarray, shape (md,)
        Variance of d^ minus the law.
    bic_gain : float
        BIC of "d = 0" minus BIC of the law (summed over components), on d^.
    npar : int
        Number of selected terms.
    formula : str
        Readable law in physical names.
    """

    spec: tuple
    eps: NDArray[np.float64]
    coef: NDArray[np.float64]
    Ddx: NDArray[np.float64]
    Ddu: NDArray[np.float64]
    nonlinear: bool
    residual_var: NDArray[np.float64]
    bic_gain: float
    npar: int
    formula: str

    def evaluate(self, x: NDArray, u: NDArray) -> NDArray[np.float64]:
        """d = law(x, u) for x (nstates, ...) and u (ninputs, ...)."""
        return self.coef @ _eval_terms(self.spec, self.eps, x, u)


def _fmt_sum(coefs, names) -> str:
    parts = []
    for c, nm in zip(coefs, names):
        s = f"{abs(c):.3g}*{nm}"
        parts.append(("- " if c < 0 else "+ ") + s)
    if not parts:
        return "0"
    txt = " ".join(parts)
    return txt[2:] if txt.startswith("+ ") else "-" + txt[2:]


# A law term must remove at least this fraction of sum(d^2): d^ is a noisy,
# coloured output and the BIC alone keeps negligible terms.
_MIN_DROP = 1e-4
# Below this excess of var(d^) over the filter's Pd, d^ is treated as mostly
# estimation noise and the static law is chosen by output error on y instead.
_LOW_SNR = 0.1
# Below this lag-1 autocorrelation d^ is taken to alternate sign (see trace_channel).
_ALTERNATING = -0.5
# Output-error refinements of static laws run on at most this many samples
# (their cost is then independent of the record length).
_OE_WINDOW = 10_000


def _select(terms: NDArray, d: NDArray, names: Sequence[str]) -> SparseLaw:
    """Forward selection (BIC) with backward pruning, as used for every static law."""
    return forward_selection(terms, d, names, min_drop=_MIN_DROP, prune=True)


def _one_direction(coef: NDArray, tscale: NDArray, labels) -> list[str]:
    """A line if the md > 1 law acts along one direction of d (PAPER_NOTES §9.6)."""
    if coef.shape[0] < 2 or not np.any(coef):
        return []
    sc = np.linalg.svd(coef * tscale[None, :], compute_uv=True)
    if sc[1][1] >= 0.05 * sc[1][0]:
        return []
    g = sc[0][:, 0] / sc[0][np.argmax(np.abs(sc[0][:, 0])), 0]
    return [f"one direction: [{', '.join(labels)}] ~ {np.array2string(g, precision=3)} "
            f"x (one force)"]


def _fit_static(d, x, u, sys, nonlinear, labels, units, pair_mean=False) -> StaticLaw:
    terms, spec, eps = law_terms(x, u, sys.state_labels, sys.input_labels, nonlinear=nonlinear)
    if pair_mean:  # regress (d[j] + d[j+1]) / 2 on (terms[j] + terms[j+1]) / 2
        terms = 0.5 * (terms[:, 1:] + terms[:, :-1])
        d = 0.5 * (d[:, 1:] + d[:, :-1])
    md = d.shape[0]
    n, m = x.shape[0], u.shape[0]
    coef = np.zeros((md, len(spec)))
    Ddx, Ddu = np.zeros((md, n)), np.zeros((md, m))
    rv = np.zeros(md)
    gain, npar, any_nl = 0.0, 0, False
    lines = []
    nlin = n + m
    names = [s[0] for s in spec]
    for c in range(md):
        sel = _select(terms, d[c], names)
        idx, cf = list(sel.index), sel.coef
        coef[c, idx] = cf
        rv[c] = sel.residual_var
        gain += sel.bic_gain
        npar += len(idx)
        nl = any(j >= nlin for j in idx)
        any_nl |= nl
        if nl:  # best linear surrogate for the StateSpace
            lin = _select(terms[:nlin], d[c], names[:nlin])
            lc = np.zeros(nlin)
            lc[list(lin.index)] = lin.coef
        else:
            lc = coef[c, :nlin]
        Ddx[c], Ddu[c] = lc[:n], lc[n:nlin]
        lines.append(_law_line(labels[c], cf, [spec[j][0] for j in idx],
                               units[c] if c < len(units) else ""))
    tscale = np.sqrt(np.mean(terms**2, axis=1))
    lines += _one_direction(coef, tscale, labels)
    return StaticLaw(spec=tuple(spec), eps=eps, coef=coef, Ddx=Ddx, Ddu=Ddu, nonlinear=any_nl,
                     residual_var=rv, bic_gain=gain, npar=npar, formula="; ".join(lines))


def _static_subsystem(law: StaticLaw, res: FilterResult, d: NDArray, x, u) -> Subsystem:
    md, n, m = law.Ddx.shape[0], law.Ddx.shape[1], law.Ddu.shape[1]
    e = d - law.Ddx @ x - law.Ddu @ u
    Re = np.atleast_2d(np.cov(e, bias=True))
    Rn = psd_part(Re - np.atleast_2d(res.d_cov))  # as identify_subsystem's noise_cov
    return Subsystem(order=0, Ad=np.zeros((0, 0)), Bdu=np.zeros((0, m)), Bdx=np.zeros((0, n)),
                     Cd=np.zeros((md, 0)), Ddu=law.Ddu, Ddx=law.Ddx, K=np.zeros((0, md)),
                     innovation_cov=Re, noise_cov=Rn, criterion={0: np.nan},
                     method="forward selection", feedthrough=True,
                     d_sim=law.Ddx @ x + law.Ddu @ u,
                     input_labels=tuple(res.sys.input_labels),
                     state_labels=tuple(res.sys.state_labels),
                     unknown_labels=tuple(res.unknown_labels))


def _law_line(label: str, coefs, names, unit: str) -> str:
    """``"d_v2 = -15*p2 [v2]/s"``: one component of a law, with its unit."""
    u = "" if not unit else f" {unit}" if unit.startswith("[") else f" [{unit}]"
    return f"{label} = {_fmt_sum(coefs, names)}{u}"


class _OutputErrorLaw:
    """Simulation error on y of the model augmented with a linear static law.

    The law's selected terms ``sel`` (pairs (component of d, term index))
    with coefficients ``theta`` are folded into A and B; the residual is the
    output error over at most ``_OE_WINDOW`` samples after ``k0``, scaled per
    output by its RMS (PAPER_NOTES §9.3: output-error fits are unbiased on a
    noisy d^).
    """

    def __init__(self, law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray,
                 u: NDArray, x0: NDArray, k0: int):
        self.law, self.md, self.k0, self.x0 = law, md, k0, x0
        self.y, self.u = y[:, :k0 + _OE_WINDOW], u[:, :k0 + _OE_WINDOW]
        m = model.ninputs - md
        Bf = np.asarray(model.B, dtype=float)
        self.A = np.asarray(model.A, dtype=float)
        self.B, self.G = Bf[:, :m], Bf[:, m:]
        self.C = np.asarray(model.C, dtype=float)
        self.D = np.asarray(model.D, dtype=float)[:, :m]
        self.scale = np.sqrt(np.mean(self.y[:, k0:] ** 2, axis=1)) + 1e-300

    def matrices(self, sel, theta):
        """(A + G Ddx, B + G Ddu, Ddx, Ddu) for the terms ``sel`` at ``theta``."""
        Ddx = np.zeros((self.md, self.A.shape[0]))
        Ddu = np.zeros((self.md, self.B.shape[1]))
        for (c, j), t in zip(sel, theta):
            _, kind, i = self.law.spec[j]
            (Ddx if kind == "x" else Ddu)[c, i] = t
        return self.A + self.G @ Ddx, self.B + self.G @ Ddu, Ddx, Ddu

    def resid(self, theta, sel):
        """Scaled output error, flattened; a diverged simulation counts as 1e6."""
        Aa, Ba, _, _ = self.matrices(sel, theta)
        with np.errstate(all="ignore"):
            x = lti_states(Aa, Ba @ self.u, self.x0)
            r = ((self.y - self.C @ x - self.D @ self.u)[:, self.k0:]
                 / self.scale[:, None]).ravel()
        return np.clip(np.where(np.isfinite(r), r, 1e6), -1e6, 1e6)

    def se(self, theta, sel) -> float:
        """Simulation error of eq. (42) [%] on the window."""
        r = self.resid(theta, sel).reshape(self.y.shape[0], -1)
        return float(100 * np.mean(np.sqrt(np.mean(r**2, axis=1))))  # |r| <= 1e6

    def fit(self, sel, start, max_nfev=60):
        """Levenberg-Marquardt from ``start``; returns the optimizer result."""
        from scipy.optimize import least_squares

        return least_squares(self.resid, start, args=(sel,), method="lm", x_scale="jac",
                             max_nfev=max_nfev)

    def law_with(self, sel, theta, labels, units, tscale=None, **changes) -> StaticLaw:
        """The law with the terms ``sel`` at ``theta`` (all others zero)."""
        law = self.law
        _, _, Ddx, Ddu = self.matrices(sel, theta)
        coef = np.zeros_like(law.coef)
        for (c, j), t in zip(sel, theta):
            coef[c, j] = t
        lines = []
        for c in range(self.md):
            idx = [j for (cc, j) in sel if cc == c]
            lines.append(_law_line(labels[c], coef[c, idx], [law.spec[j][0] for j in idx],
                                   units[c] if c < len(units) else ""))
        if tscale is not None:
            lines += _one_direction(coef, tscale, labels)
        return replace(law, coef=coef, Ddx=Ddx, Ddu=Ddu, formula="; ".join(lines), **changes)


def _refine_static_oe(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray,
                      u: NDArray, x0: NDArray, k0: int, labels, units, tscale=None):
    """Refine a linear static law by output error on y (PAPER_NOTES §9.3).

    The law's coefficients fitted on d^ are consistent but, when C G is small
    (e.g. only positions measured), d^ is so noisy that the law can make the
    augmented model unstable. Here the selected coefficients are re-fitted to
    minimize the simulation error of the augmented model on the outputs,
    starting from the d^ fit (shrunk towards zero until the model is stable).
    Returns ``(law, se_before, se_after)``; the law is unchanged when the
    refinement does not lower the simulation error.
    """
    sel = [(c, j) for c in range(md) for j in range(len(law.spec)) if law.coef[c, j] != 0]
    if not sel:
        return law, np.nan, np.nan
    prob = _OutputErrorLaw(law, model, md, y, u, x0, k0)
    theta0 = np.array([law.coef[c, j] for c, j in sel])
    se0 = prob.se(theta0, sel)
    start = theta0.copy()
    for _ in range(30):  # shrink towards the (stable) nominal model
        if np.max(np.abs(np.linalg.eigvals(prob.matrices(sel, start)[0]))) <= 1 + 1e-9:
            break
        start *= 0.5
    sol = prob.fit(sel, start)
    se1 = prob.se(sol.x, sel)
    if not se1 < se0:
        return law, se0, se0
    return prob.law_with(sel, sol.x, labels, units, tscale), se0, se1


def _select_static_oe(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray,
                      u: NDArray, x0: NDArray, k0: int, labels, units, max_terms: int = 4):
    """Choose a linear static law by output error on y (forward selection, BIC).

    Used when d^ is mostly estimation noise (its variance barely exceeds the
    filter's Pd, e.g. when only positions are measured and C G ~ dt^2/2):
    regressions on d^ then select terms at random. Each candidate support is
    fitted by Levenberg-Marquardt on the simulation error of the augmented
    model; terms are added while the BIC of the output error drops.
    """
    prob = _OutputErrorLaw(law, model, md, y, u, x0, k0)
    lin = [j for j, (_, kind, _) in enumerate(law.spec) if kind in ("x", "u")]
    cands = [(c, j) for c in range(md) for j in lin]
    Ny = prob.y[:, k0:].size

    def bic(rss, k):
        return Ny * np.log(max(rss / Ny, 1e-300)) + k * np.log(Ny)

    sel, theta = [], np.zeros(0)
    best_bic = bic(float(np.sum(prob.resid(theta, sel) ** 2)), 0)
    while len(sel) < max_terms:
        trial = None
        for cj in cands:
            if cj in sel:
                continue
            sol = prob.fit(sel + [cj], np.r_[theta, 0.0], max_nfev=100)
            b = bic(float(np.sum(sol.fun ** 2)), len(sel) + 1)
            if trial is None or b < trial[0]:
                trial = (b, cj, sol.x)
        if trial is None or trial[0] >= best_bic:
            break
        best_bic, sel, theta = trial[0], sel + [trial[1]], trial[2]
    return prob.law_with(sel, theta, labels, units, nonlinear=False, npar=len(sel))


# --------------------------------------------------------------------------- one channel
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
    law = _fit_static(d, x, uu, res.sys, nonlinear, labels, channel.units, pair_mean)
    if pair_mean:
        notes.append(f"d^ alternates sign (lag-1 autocorrelation {r1:.2f}): the static law "
                     f"is fitted on the mean of consecutive samples")
    # d^ barely above its own estimation noise: choose the law by output error
    excess = float(np.trace(np.atleast_2d(np.cov(d, bias=True)))) / \
        max(float(np.trace(np.atleast_2d(res.d_cov))), 1e-300) - 1.0
    # output error needs a simulation that stays bounded over the record
    oe_ok = not unstable_reason(model, y.shape[1])
    if not oe_ok:
        notes.append("the nominal model is unstable: the static law is the least-squares fit "
                     "on d^ (no output-error refinement)")
    if excess < _LOW_SNR and not pair_mean and oe_ok:
        law = _select_static_oe(law, model, channel.md, y, u, res.x_filt[:, 0], k0, labels,
                                channel.units)
        notes.append(f"d^ is mostly estimation noise (variance only {100 * excess:.2g}% above "
                     f"Pd): static law chosen by output error on y")
    elif not law.nonlinear and law.npar and oe_ok:
        tscale = np.sqrt(np.mean(_eval_terms(law.spec, law.eps, x, uu) ** 2, axis=1))
        law, se_d, se_y = _refine_static_oe(law, model, channel.md, y, u, res.x_filt[:, 0],
                                            k0, labels, channel.units, tscale)
        if se_y < se_d:
            notes.append(f"static law refined by output error on y: estimation SE "
                         f"{se_d:.3g}% -> {se_y:.3g}%")
    sub0 = _static_subsystem(law, res, d, x, uu)
    static_model = augment_model(model, sub0, unknown=labels, Q=Q, R=R)
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


# --------------------------------------------------------------------------- nonlinear laws
def simulate_with_law(model: ct.StateSpace, G: NDArray, law: StaticLaw, u: NDArray,
                      x0: NDArray) -> NDArray[np.float64]:
    """Simulated output of ``x[k+1] = A x + B u + G law(x, u)``, shape (noutputs, nsteps)."""
    A, B, C, D = (np.asarray(a, dtype=float) for a in (model.A, model.B, model.C, model.D))
    N = u.shape[1]
    x = np.empty((A.shape[0], N))
    xk = np.asarray(x0, dtype=float).copy()
    Bu = B @ u
    for k in range(N):
        x[:, k] = xk
        xk = A @ xk + Bu[:, k] + G @ law.evaluate(xk[:, None], u[:, k:k + 1])[:, 0]
        if not np.all(np.isfinite(xk)) or np.max(np.abs(xk)) > 1e100:
            x[:, k + 1:] = np.nan
            break
    return C @ x + D @ u


def predict_with_law(model: ct.StateSpace, G: NDArray, law: StaticLaw, y: NDArray,
                     u: NDArray, K: NDArray, x0: NDArray) -> NDArray[np.float64]:
    """One-step predictions ``C x^[k|k-1] + D u`` of a constant-gain filter on the nonlinear model."""
    A, B, C, D = (np.asarray(a, dtype=float) for a in (model.A, model.B, model.C, model.D))
    N = u.shape[1]
    yp = np.empty((C.shape[0], N))
    xp = np.asarray(x0, dtype=float).copy()
    Bu, Du = B @ u, D @ u
    for k in range(N):
        yp[:, k] = C @ xp + Du[:, k]
        xf = xp + K @ (y[:, k] - yp[:, k])
        xp = A @ xf + Bu[:, k] + G @ law.evaluate(xf[:, None], u[:, k:k + 1])[:, 0]
        if not np.all(np.isfinite(xp)) or np.max(np.abs(xp)) > 1e100:
            yp[:, k + 1:] = np.nan
            break
    return yp



def _fmt_values(v: NDArray, digits: int) -> str:
    """A scalar as a number, several values as a bracketed list."""
    v = np.atleast_1d(v)
    if v.size == 1:
        return f"{v[0]:.{digits}g}"
    return "[" + ", ".join(f"{a:.{digits}g}" for a in v) + "]"


def parameter_notes(sys: ct.StateSpace, channel: Channel, law: StaticLaw) -> tuple[str, ...]:
    """Where the law mirrors a term the model already has: which parameter is off, by how much.

    A linear term ``c * s`` of component k of d adds ``c * G[:, k]`` to the
    column of A (state s) or B (input s) of the nominal model ``sys`` (in its
    own time base). If that column, restricted to the rows G[:, k] enters,
    is parallel to G[:, k], the law re-scales an existing parameter; if it is
    zero there, the law is a term the model lacks.
    """
    A, B = np.asarray(sys.A, dtype=float), np.asarray(sys.B, dtype=float)
    out = []
    for k in range(channel.md):
        g = channel.G[:, k]
        S = np.flatnonzero(np.abs(g) > 0)
        rows = ", ".join(sys.state_labels[i] for i in S)
        for j, (name, kind, idx) in enumerate(law.spec):
            c = law.coef[k, j]
            if c == 0 or kind not in ("x", "u"):
                continue
            col = A[:, idx] if kind == "x" else B[:, idx]
            mat = "A" if kind == "x" else "B"
            cs, gs = col[S], g[S]
            new = cs + c * gs
            if np.all(cs == 0):
                out.append(f"{mat}[{rows}; {name}] is 0 in the model; the data want "
                           f"{_fmt_values(new, 3)} (a missing term)")
                continue
            cosv = abs(cs @ gs) / (np.linalg.norm(cs) * np.linalg.norm(gs))
            if cosv > 0.99:
                alpha = (cs @ gs) / (gs @ gs)
                pct = 100.0 * c / alpha
                out.append(f"{mat}[{rows}; {name}] = {_fmt_values(cs, 4)} in the "
                           f"model; the data want {_fmt_values(new, 4)} ({pct:+.1f}%)")
    return tuple(out)
