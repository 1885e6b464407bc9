"""Static laws d = f(x, u): candidate terms, sparse fits, formulas, simulation, parameter notes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cached_property

import control as ct
import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm, logm, lstsq, solve_toeplitz
from scipy.signal import lfilter

from .._blas import single_thread_blas
from ..exceptions import IdentificationError, ModelError
from ..filters import FilterResult
from ..hold import LawHold, as_hold
from ..ident.regression import SparseLaw, forward_selection, forward_selection_gram
from ..terms import (BREAK_KINDS, BREAK_QUANTILES, LINEAR_KINDS, SAT_QUANTILES,
                     SENSOR_STATE_KINDS, SIBLING_KINDS, break_name, break_row, break_slope,
                     hinge_name, law_terms, linear_part, output_terms, shapes, siblings,
                     term_kind)
from ..terms import evaluate_terms as _eval_terms
from ..terms import evaluator
from ..update import Subsystem, psd_part
from .channels import Channel
from .intervals import hac_covariance



# --------------------------------------------------------------------------- static laws
# Terms, their kinds and the candidate libraries live in greybox.terms (one class per kind
# of term); the names below are re-exported for the modules and tests that import them here.


def sensor_states(law: StaticLaw | None) -> int:
    """Number of sensor states a sensor-error law adds to the updated model (0: a static law).

    A first-order sensor lag adds the reading (one state), a drift adds the
    offset and the drift rate (two states); the law's other terms are static.

    Parameters
    ----------
    law : StaticLaw or None
        A law from :func:`greybox.trace.trace_channel` (None: 0).

    Returns
    -------
    int
    """
    if law is None:
        return 0
    return sum(term_kind(sp[1]).sensor_states for j, sp in enumerate(law.spec)
               if np.any(law.coef[:, j]))


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
        Readable law in physical names, each coefficient with its 95 % interval
        (``-15 (-15.3, -14.7)*p2``) where ``ci`` is known.
    ci : ndarray, shape (md, nterms)
        95 % half-widths of the coefficients (NaN where unknown or not
        selected): from the output-error Jacobian with a covariance robust to
        the residual's autocorrelation (:func:`greybox.trace.intervals.hac_covariance`).
    time_base : str
        "continuous": ``dx/dt = A x + B u + G d`` with the nominal model's
        continuous G, d in the channel's physical units (the augmented model is
        discretized exactly); "discrete": ``d[j]`` acts through the
        ZOH-discretized G between samples j and j+1.
    hold : greybox.hold.LawHold or None
        A continuous-time law (``dx/dt = Ac x + Bc u + Gc law(x, u)``, the
        input held), as a law fitted on a delayed d^ or with first-order-hold
        weights is: :func:`simulate_with_law` and :func:`predict_with_law`
        integrate it over each sample (:meth:`greybox.hold.LawHold.step`,
        fourth order; a ``(Gamma0, Gamma1)`` pair is taken as a first-order
        hold integrated by the Heun step). None: d[k] is held over the sample
        and enters through G.
    output : int or None
        Index of the output a sensor-error law adds to (``y_i = C_i x + D_i u
        + d``; Ddx, Ddu are then its linear part in the output equation);
        None: the law enters the state equations. A first-order sensor lag
        (one term of kind "yhat_lag", coefficient tau [s]) and a drift (a
        term of kind "drift", coefficient the drift rate [output units/s],
        beside the offset "1" at the estimation record's first sample) are not
        static: the trace's updated model carries the reading, or the offset
        and the drift rate, as sensor states (:func:`sensor_states`), and
        :meth:`evaluate` raises ModelError for them. A saturation (kind
        "yhat_sat", ``clip(y_model, -L, L) - y_model``) has coefficient L.
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
    ci: NDArray[np.float64] | None = None
    time_base: str = "discrete"
    hold: LawHold | tuple | None = None
    output: int | None = None

    def __post_init__(self):
        # a law integrated over each sample steps as finely as its own rate needs (a
        # friction's sign smoothed over a narrow width): set wherever a law is built
        h = self.hold
        if isinstance(h, LawHold) and h.Gc is not None:
            object.__setattr__(self, "hold", h.with_substeps(h.substeps_for(self.rate())))

    def rate(self) -> float:
        """A bound [1/s] on how fast the law's smoothed terms change the states they read:
        ``sum |coef| * steepest slope * max |Gc column|`` over them (``hold.Gc``: how the
        law enters the continuous state equations); 0 without a continuous hold."""
        h = self.hold
        if not isinstance(h, LawHold) or h.Gc is None:
            return 0.0
        g = np.max(np.abs(h.Gc), axis=0) if h.Gc.size else np.zeros(0)
        out = 0.0
        for c, j in zip(*np.nonzero(self.coef)):
            _, kind, ix = self.spec[j]
            slope = term_kind(kind).steepest(ix, self.eps)
            if slope and c < g.size:
                out += abs(float(self.coef[c, j])) * slope * float(g[c])
        return out

    def evaluate(self, x: NDArray, u: NDArray) -> NDArray[np.float64]:
        """d = law(x, u) for x (nstates, ...) and u (ninputs, ...)."""
        coef, terms = self._selected_terms
        return coef @ terms(x, u)

    @cached_property
    def _selected(self) -> tuple[NDArray, tuple]:
        """(coefficients (md, nselected), spec) of the selected terms: only these are evaluated.

        A simulation evaluates the law once per sample (or per RK4 stage): over all
        ~30-100 candidate terms, 1.1 s per 2e4 samples; over the 1-3 selected ones, a
        few times less.
        """
        keep = np.flatnonzero(np.any(self.coef != 0, axis=0))
        return self.coef[:, keep], tuple(self.spec[j] for j in keep)

    @cached_property
    def _selected_terms(self):
        """(coefficients, evaluator) of the selected terms (:func:`greybox.terms.evaluator`)."""
        coef, spec = self._selected
        return coef, evaluator(spec, self.eps)

    @property
    def breakpoints(self) -> list[str]:
        """Names of the selected dead-zone and saturation terms (:data:`BREAK_KINDS`)."""
        return [sp[0] for j, sp in enumerate(self.spec)
                if sp[1] in BREAK_KINDS and np.any(self.coef[:, j])]

    def term_scale(self, x: NDArray, u: NDArray) -> NDArray[np.float64]:
        """RMS of every candidate term on (x (nstates, K), u (ninputs, K)), shape (nterms,)."""
        return np.sqrt(np.mean(_eval_terms(self.spec, self.eps, x, u) ** 2, axis=1))

    def direction(self, x: NDArray, u: NDArray) -> NDArray[np.float64] | None:
        """The one direction of an md > 1 law on (x, u) (see :func:`direction`), or None."""
        return direction(self.coef, self.term_scale(x, u))


def _fmt_sum(coefs, names, half=None) -> str:
    parts = []
    half = np.full(len(coefs), np.nan) if half is None else half
    for c, nm, h in zip(coefs, names, half):
        s = (f"({abs(c):.3g}, interval not determined)" if h == np.inf else
             f"{abs(c):.3g}" if not np.isfinite(h) else f"({abs(c):.3g} ± {h:.2g})")
        s = s if nm == "1" else f"{s}*{nm}"
        parts.append(("- " if c < 0 else "+ ") + s)
    if not parts:
        return "0"
    txt = " ".join(parts)
    return txt[2:] if txt.startswith("+ ") else "-" + txt[2:]


# A law term must remove at least this fraction of sum(d^2): d^ is a noisy,
# coloured output and the BIC alone keeps negligible terms.
_MIN_DROP = 1e-4


def _regression_halfwidths(J: NDArray, e: NDArray) -> NDArray[np.float64]:
    """95 % half-widths of a regression's coefficients on d^, robust to its autocorrelation.

    ``J`` (k, N): the regressors (with a breakpoint's derivative); ``e`` (N,): the
    residual. A term identically 0 on the record (a dead zone's breakpoint refitted past
    the input's range) has no interval: inf ("not determined"), not 0/0."""
    sx = np.sqrt(np.mean(J**2, axis=1))  # terms differ by decades (y^3, v^3)
    flat = ~(sx > 0)
    sx = np.where(flat, 1.0, sx)
    cov = hac_covariance((J / sx[:, None]).T, e, 1) / np.outer(sx, sx)
    return np.where(flat, np.inf, 1.96 * np.sqrt(np.clip(np.diag(cov), 0, None)))


def _select(terms: NDArray, d: NDArray, names: Sequence[str], exclusive=None) -> SparseLaw:
    """Forward selection (BIC) with backward pruning, as used for every static law;
    ``exclusive``: alternatives never selected together (:func:`greybox.terms.shapes`)."""
    return forward_selection(terms, d, names, min_drop=_MIN_DROP, prune=True,
                             exclusive=exclusive)


def _select_gram(gram: NDArray, cross: NDArray, d: NDArray, names: Sequence[str],
                 exclusive=None) -> SparseLaw:
    """:func:`_select` from the terms' products ``X X^T``, ``X d`` (d: the regressand)."""
    return forward_selection_gram(gram, cross, float(d @ d), d.size, names, min_drop=_MIN_DROP,
                                  prune=True, exclusive=exclusive)


# time samples per block of the filtered products (p x 8192 floats: 13 MB at p = 200)
_BLOCK = 8192


def _filtered_products(terms: NDArray, a: NDArray, dw: NDArray) -> tuple[NDArray, NDArray]:
    """``W W^T`` and ``W dw`` of the FIR-filtered terms W without forming W.

    ``W = lfilter(a, [1], terms, axis=1)[:, p:]`` (p = len(a) - 1, the
    filter's start-up dropped), accumulated over blocks of time: the whitened
    copy of the terms (as large as the terms, 130 MB for 160 terms at K = 1e5)
    is never held.
    """
    p = len(a) - 1
    K = terms.shape[1]
    gram = np.zeros((terms.shape[0], terms.shape[0]))
    cross = np.zeros(terms.shape[0])
    with single_thread_blas():  # thin products: threads only cost (and stall under load)
        for t0 in range(p, K, _BLOCK):
            t1 = min(t0 + _BLOCK, K)
            w = a[0] * terms[:, t0:t1]
            for i in range(1, p + 1):
                w += a[i] * terms[:, t0 - i:t1 - i]
            gram += w @ w.T
            cross += w @ dw[t0 - p:t1 - p]
    return gram, cross


def direction(coef: NDArray, tscale: NDArray) -> NDArray | None:
    """The one direction of an md > 1 law (largest component 1), or None if it has two."""
    if coef.shape[0] < 2 or not np.any(coef):
        return None
    U, sv, _ = np.linalg.svd(coef * tscale[None, :])
    if sv[1] >= 0.05 * sv[0]:
        return None
    return U[:, 0] / U[np.argmax(np.abs(U[:, 0])), 0]


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


def aligned(terms: NDArray, w: NDArray) -> NDArray[np.float64]:
    """``sum_i w[i] terms[:, j + i]`` for j = 0 .. K - r, the terms as a delayed d^ sees them.

    Parameters
    ----------
    terms : ndarray, shape (nterms, K)
    w : ndarray, shape (r,)
        Weights of ``d[j], ..., d[j + r - 1]`` in what ``d_est[:, j]`` estimates
        (:func:`greybox.filters.delayed.input_weights`).
    """
    r = len(w)
    K = terms.shape[1] - r + 1
    out = w[0] * terms[:, :K]
    # in place, a block of rows at a time: a sum of r weighted copies would hold three
    # arrays as large as the terms at once (the peak of a 32-state chain's trace)
    rows = max(1, _BLOCK * 16 // max(K, 1))
    for i in range(1, r):
        for j in range(0, out.shape[0], rows):
            out[j:j + rows] += w[i] * terms[j:j + rows, i:i + K]
    return out


# AR order of the prewhitening filter of a smoothed or delayed d^
_AR_ORDER = 4


def _ls_fit(terms: NDArray, d: NDArray) -> NDArray[np.float64]:
    """The least-squares fit of d (K,) on the rows of terms (p, K), by the normal equations.

    For the whitening filter's residual only: the Gram matrix of the
    RMS-scaled terms (one BLAS product, about 4x faster than an SVD of the
    K x p matrix at p ~ 200, K = 1e5) is solved by SVD, so collinear terms
    (x and x^3 of a small state) still give a minimum-norm fit. Raises
    IdentificationError when the products overflow (the channel's estimator
    diverged): the caller reports the channel as failed.
    """
    sc = np.sqrt(np.einsum("ij,ij->i", terms, terms))  # no K x p temporaries
    sc[sc == 0] = 1.0  # a term that is zero throughout (an input at rest over the window)
    with np.errstate(over="ignore", invalid="ignore"):
        gram = (terms @ terms.T) / np.outer(sc, sc)
        rhs = (terms @ d) / sc
    if not (np.all(np.isfinite(gram)) and np.all(np.isfinite(rhs))):
        raise IdentificationError("the law's terms overflow on this channel's estimates (its "
                                  "unknown-input filter or smoother diverged): no law fitted")
    th = lstsq(gram, rhs, cond=1e-12, lapack_driver="gelsd")[0]
    return (th / sc) @ terms


def _whitening(e: NDArray, p: int) -> NDArray[np.float64]:
    """``[1, -a_1, ..., -a_p]``: the Yule-Walker AR(p) whitening filter of the residual e."""
    e = e - e.mean()
    K = e.size
    acf = np.array([e[:K - lag] @ e[lag:] for lag in range(p + 1)]) / K
    if acf[0] <= 0:
        return np.r_[1.0, np.zeros(p)]
    return np.r_[1.0, -solve_toeplitz(acf[:p], acf[1:p + 1])]


def fit_static(d, x, u, sys, nonlinear, labels, units, align=None,
                relative=(), whiten=False, prebuilt=None, saturation=False,
                breaks=()) -> StaticLaw:
    """Sparse static law of every component of d^ on the terms of (x, u).

    ``align`` (md, r): d^[c, j] estimates ``sum_i align[c, i] d[c, j + i]``
    (a delayed or averaged estimate); x and u then carry r - 1 more columns
    than d, and each component is regressed on its own weighted terms.
    ``whiten``: d^'s estimation noise is coloured (a smoothed or delayed
    estimate; with only positions measured it is mostly high-frequency, a
    second difference of the sensor noise), so the white-noise BIC would
    badly understate what the low-frequency terms explain. The regression is
    then feasible generalized least squares: an AR(4) filter fitted
    (Yule-Walker) to the residual of all candidate terms whitens d^ and the
    terms alike before the selection and the intervals. ``saturation``: offer
    the hinge terms of :func:`law_terms`; ``breaks``: the inputs offered a
    dead zone and a saturation (:data:`BREAK_KINDS`), whose selected breakpoint
    is then refitted with the coefficients (:func:`_refine_break`; it counts as
    a parameter). ``prebuilt``:
    ``(terms, spec, eps)`` of other candidates (:func:`output_terms`).

    """
    if prebuilt is None:
        terms, spec, eps = law_terms(x, u, sys.state_labels, sys.input_labels,
                                     nonlinear=nonlinear, relative=relative,
                                     saturation=saturation, breaks=breaks)
    else:
        terms, spec, eps = prebuilt
    md = d.shape[0]
    n, m = x.shape[0], u.shape[0]
    coef = np.zeros((md, len(spec)))
    Ddx, Ddu = np.zeros((md, n)), np.zeros((md, m))
    rv = np.zeros(md)
    gain, npar, any_nl = 0.0, 0, False
    lines = []
    nlin = sum(1 for sp in spec if sp[1] in LINEAR_KINDS)  # the linear terms come first
    names = [s[0] for s in spec]
    alternatives = shapes(spec)  # one nonlinear odd shape per variable (see shapes)
    half = np.full((md, len(spec)), np.nan)
    tscale = None
    held = (None, None)  # (weights, aligned terms): components with equal weights share one
    for c in range(md):
        # one component's terms at a time (each aligned copy is as large as the terms)
        tcur = terms
        if align is not None:
            key = tuple(np.asarray(align[c], dtype=float))
            if held[0] != key:
                held = (None, None)
                held = (key, aligned(terms, align[c]))
            tcur = held[1]
            if c == md - 1:
                terms = None  # the unaligned terms are no longer needed here
        dc = d[c]
        # samples where d^ or a term is undefined (NaN: steps where the filter did not see
        # d) are left out, each component on its own
        ok = np.isfinite(dc) & np.all(np.isfinite(tcur), axis=0)
        if not np.all(ok):
            tcur, dc = tcur[:, ok], dc[ok]
        if tscale is None:  # the scale of the first component's terms, no squared copy
            tscale = np.sqrt(np.einsum("ij,ij->i", tcur, tcur) / tcur.shape[1])
        if whiten and tcur.shape[1] > 10 * (_AR_ORDER + len(spec)):
            aw = _whitening(dc - _ls_fit(tcur, dc), _AR_ORDER)
            dw = lfilter(aw, [1.0], dc)[_AR_ORDER:]
            gram, cross = _filtered_products(tcur, aw, dw)
            sel = _select_gram(gram, cross, dw, names, alternatives)
        else:
            aw, dw = None, dc
            sel = _select(tcur, dc, names, alternatives)
        idx, cf = list(sel.index), sel.coef
        brk = [q for q, j in enumerate(idx) if spec[j][1] in BREAK_KINDS]
        if len(brk) > 1:  # one breakpoint per input (the strongest; refitted below)
            top = max(brk, key=lambda q: abs(cf[q]) * tscale[idx[q]])
            idx = [j for q, j in enumerate(idx) if q not in brk or q == top]
            cf = np.zeros(len(idx))  # refitted with the breakpoint
            brk = [q for q, j in enumerate(idx) if spec[j][1] in BREAK_KINDS]
        if idx:  # 95 % half-widths of the regression on d^, robust to its autocorrelation
            X = tcur[idx] if aw is None else lfilter(aw, [1.0], tcur[idx], axis=1)[:, _AR_ORDER:]
            J = X
            if brk:  # a dead zone's or saturation's breakpoint, fitted with the coefficients
                def make(fn, level, white=True, sp=spec[idx[brk[0]]], c=c, ok=ok, aw=aw):
                    row = fn(u[sp[2][0]], sp[1], level)[None, :]
                    row = aligned(row, align[c]) if align is not None else row
                    row = row[:, ok]
                    return (row if aw is None or not white else
                            lfilter(aw, [1.0], row, axis=1)[:, _AR_ORDER:])[0]
                level, X, cf, J = _refine_break(X, dw, brk[0], make, u[spec[idx[brk[0]]][2][0]])
                tcur = tcur.copy()
                tcur[idx[brk[0]]] = make(break_row, level, white=False)
            hw = _regression_halfwidths(J, dw - cf @ X)
            half[c, idx] = hw[:len(idx)]
            if brk:
                j, sp = idx[brk[0]], spec[idx[brk[0]]]
                hl = float(hw[-1]) if np.all(np.isfinite(hw)) else np.inf
                spec[j] = term_kind(sp[1]).at_level(sp, level, hl)
                names[j] = spec[j][0]
        coef[c, idx] = cf
        rv[c] = (float(np.mean((dc - cf @ tcur[idx]) ** 2)) if idx else float(np.mean(dc**2)))
        gain += sel.bic_gain
        npar += len(idx) + len(brk)
        nl = any(j >= nlin for j in idx)
        any_nl |= nl
        if nl:  # best linear surrogate for the StateSpace
            lin = (_select(tcur[:nlin], dc, names[:nlin]) if aw is None else
                   _select_gram(gram[:nlin, :nlin], cross[:nlin], dw, names[:nlin]))
            lc = np.zeros(nlin)
            lc[list(lin.index)] = lin.coef
        else:
            lc = coef[c, :nlin]
        dx_, du_ = linear_part(spec[:nlin], lc[None, :], n, m)
        Ddx[c], Ddu[c] = dx_[0], du_[0]
        lines.append(law_line(labels[c], cf, [spec[j][0] for j in idx],
                               units[c] if c < len(units) else "", half[c, idx]))
        tcur = X = None
    held = None
    lines += _one_direction(coef, tscale, labels)
    return StaticLaw(spec=tuple(spec), eps=eps, coef=coef, Ddx=Ddx, Ddu=Ddu, nonlinear=any_nl,
                     residual_var=rv, bic_gain=gain, npar=npar, formula="; ".join(lines),
                     ci=half)


def _refine_break(X: NDArray, dw: NDArray, q: int, make, v: NDArray):
    """The breakpoint of row q of X refitted with the coefficients (variable projection).

    ``make(fn, level)`` gives a row as the regression sees it (aligned,
    masked, whitened) of ``fn(v, kind, level)`` with fn :func:`break_row` or
    :func:`break_slope`. The residual sum of squares is scanned over the
    2-98 % quantiles of ``|v|`` (49 levels) and minimized between the best
    level's neighbours (bounded Brent). Returns ``(level, X, coefficients,
    J)``: X with row q at that level, the least-squares coefficients and the
    Jacobian rows (X, then the breakpoint's derivative times its coefficient)
    for the intervals.
    """
    from scipy.optimize import minimize_scalar

    def fit(level):
        Xl = X.copy()
        Xl[q] = make(break_row, level)
        beta = lstsq(Xl.T, dw, lapack_driver="gelsy")[0]
        r = dw - beta @ Xl
        return float(r @ r), Xl, beta

    grid = np.nanquantile(np.abs(v), np.linspace(0.02, 0.98, 49))
    vals = [fit(g)[0] for g in grid]
    k = int(np.argmin(vals))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    level = float(grid[k])
    if hi > lo:
        res = minimize_scalar(lambda lv: fit(lv)[0], bounds=(lo, hi), method="bounded",
                              options={"xatol": 1e-6 * (hi - lo)})
        if res.fun < vals[k]:
            level = float(res.x)
    _, Xl, beta = fit(level)
    J = np.vstack([Xl, beta[q] * make(break_slope, level)[None, :]])
    return level, Xl, beta, J


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


def law_rows(law: StaticLaw, keep, labels, units) -> StaticLaw:
    """The law of the components ``keep`` of d alone (a channel narrowed to some of its
    equations: :func:`greybox.trace.channels.equation_subset`), its formula in their
    ``labels`` and ``units``; the rows of its coefficients, intervals, linear parts and
    residual variances, the same numbers.

    Parameters
    ----------
    law : StaticLaw
        A law of md components, not a sensor's (``law.output`` None), without a "one
        direction" line (it relates the rows); a continuous-time law's hold keeps its
        components' columns (:meth:`greybox.hold.LawHold.columns`).
    keep : sequence of int
        Components kept, in order.
    labels, units : sequence of str
        The kept components' names and units (those of the narrowed channel).
    """
    if law.output is not None or "one direction" in law.formula:
        raise ValueError("law_rows: a sensor's or a one-direction law keeps all its rows")
    keep = list(keep)
    hold = as_hold(law.hold)
    coef = law.coef[keep]
    ci = None if law.ci is None else law.ci[keep]
    lines = []
    for c, row in enumerate(coef):
        idx = list(np.flatnonzero(row))
        lines.append(law_line(labels[c], row[idx], [law.spec[j][0] for j in idx],
                              units[c] if c < len(units) else "",
                              None if ci is None else ci[c, idx]))
    return replace(law, coef=coef, ci=ci, Ddx=law.Ddx[keep], Ddu=law.Ddu[keep],
                   hold=None if hold is None else hold.columns(keep),
                   residual_var=np.asarray(law.residual_var)[keep], formula="; ".join(lines),
                   npar=int(law.npar) - int(np.count_nonzero(law.coef) - np.count_nonzero(coef)))


def one_term_law(law: StaticLaw, t: int, c: float, label: str, unit: str, n: int, m: int,
                 hold=None) -> StaticLaw:
    """The law ``d = c * term t`` of a one-component channel on the library of ``law`` (its
    terms and smoothing widths): a starting point for a refit (no interval yet).

    Parameters
    ----------
    law : StaticLaw
        The law whose library (``spec``, ``eps``, ``time_base``) the new one shares.
    t : int
        Index of the term in ``law.spec``.
    c : float
        Its coefficient.
    label, unit : str
        The channel's component name and unit (for the formula).
    n, m : int
        States and inputs of the model the library is of.
    hold : LawHold, optional
        A continuous-time law's hold for the new channel (:meth:`greybox.hold.LawHold.of`).
    """
    coef = np.zeros((1, law.coef.shape[1]))
    coef[0, t] = c
    Ddx, Ddu = linear_part(law.spec, coef, n, m)
    return replace(law, coef=coef, ci=None, Ddx=Ddx, Ddu=Ddu, nonlinear=False,
                   residual_var=np.full(1, np.nan), npar=1, hold=hold, output=None,
                   formula=law_line(label, [c], [law.spec[t][0]], unit))


def law_line(label: str, coefs, names, unit: str, half=None) -> str:
    """``"d_v2 = -(15 ± 0.3)*p2 [v2]/s"``: one component of a law, with its unit and intervals."""
    u = "" if not unit else f" {unit}" if unit.startswith("[") else f" [{unit}]"
    return f"{label} = {_fmt_sum(coefs, names, half)}{u}"



# --------------------------------------------------------------------------- nonlinear laws
def _step_cols(A, X, bu, G, law, uk):
    """:func:`_step` for the states in the columns of X (nstates, K); bu (nstates,)."""
    hold = as_hold(law.hold)
    if hold is None:
        return A @ X + bu[:, None] + G @ law.evaluate(X, uk)
    return hold.step(A, X, bu[:, None], lambda Z: law.evaluate(Z, uk))


def _step(A, xk, bu, G, law, uk):
    """``A x + B u + G d`` with d held (ZOH), or the law integrated over the sample
    (``law.hold``: :meth:`greybox.hold.LawHold.step`)."""
    return _step_cols(A, xk[:, None], bu, G, law, uk)[:, 0]


def step_matrix(A: NDArray, G: NDArray, law: StaticLaw) -> NDArray[np.float64]:
    """The state matrix of the model with the law replaced by its linear part ``Ddx``.

    A law held over the sample: ``A + G Ddx``. A law with ``law.hold`` (a
    continuous-time law, integrated over each sample): the continuous model with
    ``Gc Ddx`` added, discretized exactly, ``expm(L11 + L12 Ddx)`` with ``L`` the
    matrix logarithm of ``[[A, G0 + G1], [0, I]]`` (= ``[[Ac, Gc], [0, 0]] dt``);
    the first-order hold's Heun step linearized where that logarithm is not real.

    The linear model whose process noise the law's simulation carries (the noise
    model of its intervals). A stiffening law in a lightly damped plant, added
    one sample late (``A + G D``) or by the Heun step, can have a pole outside the
    unit circle where the continuous plant has none (zoo cubic_force: spectral
    radius 1.0047 held, 1.0017 Heun); a noise model on that unstable stand-in gave
    intervals 2600x the residual's.
    """
    A, D = np.asarray(A, dtype=float), np.asarray(law.Ddx, dtype=float)
    hold = as_hold(law.hold)
    if hold is None:
        return A + np.asarray(G, dtype=float) @ D
    G0, G1 = hold.G0, hold.G1
    n, md = A.shape[0], D.shape[0]
    M = np.block([[A, G0 + G1], [np.zeros((md, n)), np.eye(md)]])
    try:
        L = logm(M)
    except (ValueError, np.linalg.LinAlgError):
        L = None
    if L is None or not np.all(np.isfinite(L)) or \
            np.max(np.abs(np.imag(L)), initial=0.0) > 1e-8 * max(np.max(np.abs(L)), 1.0):
        return A + G0 @ D + G1 @ D @ (A + (G0 + G1) @ D)
    L = np.real(L)
    return expm(L[:n, :n] + L[:n, n:] @ D)


def simulate_with_law(model: ct.StateSpace, G: NDArray, law: StaticLaw, u: NDArray,
                      x0: NDArray) -> NDArray[np.float64]:
    """Simulated output of ``x[k+1] = A x + B u + G law(x, u)``, shape (noutputs, nsteps).

    With ``law.hold`` the law is integrated over each sample instead (see
    :class:`StaticLaw`); with ``law.output`` it adds to that output instead
    (G is then zero).
    """
    A, B, C, D = (np.asarray(a, dtype=float) for a in (model.A, model.B, model.C, model.D))
    N = u.shape[1]
    x = np.empty((A.shape[0], N))
    xk = np.asarray(x0, dtype=float).copy()
    Bu = B @ u
    with np.errstate(over="ignore", invalid="ignore"):  # a diverging law: inf, caught below
        for k in range(N):
            x[:, k] = xk
            xk = _step(A, xk, Bu[:, k], G, law, u[:, k:k + 1])
            if not xk @ xk < 1e200:  # |x| > 1e100, inf or nan (one dot product per sample)
                x[:, k + 1:] = np.nan
                break
    y = C @ x + D @ u
    if law.output is not None:  # a sensor-error law
        y[law.output] += law.evaluate(x, u)[0]
    return y


def predict_with_law(model: ct.StateSpace, G: NDArray, law: StaticLaw, y: NDArray,
                     u: NDArray, K: NDArray, x0: NDArray) -> NDArray[np.float64]:
    """One-step predictions ``C x^[k|k-1] + D u`` of a constant-gain filter on the nonlinear model.

    A gain designed on the law's linear stand-in can diverge (a |.| sensor);
    the validation table's PE uses :func:`ekf_predict_with_law`.
    """
    A, B, C, D = (np.asarray(a, dtype=float) for a in (model.A, model.B, model.C, model.D))
    N = u.shape[1]
    yp = np.empty((C.shape[0], N))
    xp = np.asarray(x0, dtype=float).copy()
    Bu, Du = B @ u, D @ u
    for k in range(N):
        yp[:, k] = C @ xp + Du[:, k]
        if law.output is not None:
            yp[law.output, k] += law.evaluate(xp[:, None], u[:, k:k + 1])[0, 0]
        xf = xp + K @ (y[:, k] - yp[:, k])
        with np.errstate(over="ignore", invalid="ignore"):  # a diverging law: inf, caught below
            xp = _step(A, xf, Bu[:, k], G, law, u[:, k:k + 1])
        if not np.all(np.isfinite(xp)) or np.max(np.abs(xp)) > 1e100:
            yp[:, k + 1:] = np.nan
            break
    return yp


def ekf_predict_with_law(model: ct.StateSpace, G: NDArray, law: StaticLaw, y: NDArray,
                         u: NDArray, x0: NDArray, *, Q: NDArray, R: NDArray,
                         P0: NDArray | None = None) -> NDArray[np.float64]:
    """One-step predictions of an extended Kalman filter on the model with a static law.

    The model is ``x[k+1] = A x + B u + G law(x, u)`` (a state-equation law,
    integrated as :func:`simulate_with_law` does) or ``y = C x + D u +
    law(x, u)`` on output ``law.output`` (a sensor law). The gain is
    recomputed at every sample from the law's local slope (forward
    differences of the step and of the output map at the current estimate):
    a constant gain designed on the law's linear stand-in is no predictor of
    a nonlinear law; e.g. the stand-in of a rectifying sensor ``|y|`` has
    the slope's sign wrong for half of the samples, and such a predictor
    diverges.

    Parameters
    ----------
    model : control.StateSpace
        Discrete nominal model (A, B, C, D).
    G : ndarray, shape (nstates, md)
        How the law enters the state equations (zero for a sensor law).
    law : StaticLaw
    y : ndarray, shape (noutputs, nsteps)
        Measured outputs.
    u : ndarray, shape (ninputs, nsteps)
        Known inputs.
    x0 : ndarray, shape (nstates,)
        Initial state estimate (prior mean at k = 0).
    Q : ndarray, shape (nstates, nstates)
        Process noise covariance of the discrete model.
    R : ndarray, shape (noutputs, noutputs)
        Measurement noise covariance.
    P0 : ndarray, shape (nstates, nstates), optional
        Prior covariance at k = 0 (default: identity, as :func:`greybox.kalman_filter`).

    Returns
    -------
    ndarray, shape (noutputs, nsteps)
        ``y^[k|k-1]``; NaN from the sample where the filter diverged (a
        non-finite or exploding estimate) on.
    """
    A, B, C, D = (np.asarray(a, dtype=float) for a in (model.A, model.B, model.C, model.D))
    Q, R = np.atleast_2d(np.asarray(Q, dtype=float)), np.atleast_2d(np.asarray(R, dtype=float))
    n, N = A.shape[0], u.shape[1]
    yp = np.full((C.shape[0], N), np.nan)
    xp = np.asarray(x0, dtype=float).copy()
    P = np.eye(n) if P0 is None else np.asarray(P0, dtype=float).copy()
    Bu, Du = B @ u, D @ u
    eye = np.eye(n)
    out = law.output
    with np.errstate(over="ignore", invalid="ignore"):  # a diverging filter: caught below
        for k in range(N):
            uk = u[:, k:k + 1]
            H = C
            yk = C @ xp + Du[:, k]
            if out is not None:  # the sensor law and its slope at x^[k|k-1]
                h = 1e-7 * (np.abs(xp) + np.sqrt(np.abs(np.diag(P)))) + 1e-12
                fv = law.evaluate(np.c_[xp, xp[:, None] + np.diag(h)], uk)[0]
                yk[out] += fv[0]
                H = C.copy()
                H[out] += (fv[1:] - fv[0]) / h
            yp[:, k] = yk
            PH = P @ H.T
            S = H @ PH + R
            try:
                Kk = np.linalg.solve(S, PH.T).T
            except np.linalg.LinAlgError:  # a singular innovation covariance: diverged
                yp[:, k] = np.nan
                break
            xf = xp + Kk @ (y[:, k] - yk)
            IKH = eye - Kk @ H
            P = IKH @ P @ IKH.T + Kk @ R @ Kk.T  # Joseph form: stays symmetric, PSD
            h = 1e-7 * (np.abs(xf) + np.sqrt(np.abs(np.diag(P)))) + 1e-12
            Xn = _step_cols(A, np.c_[xf, xf[:, None] + np.diag(h)], Bu[:, k], G, law, uk)
            xp = Xn[:, 0]
            F = (Xn[:, 1:] - xp[:, None]) / h
            P = F @ P @ F.T + Q
            P = 0.5 * (P + P.T)
            if not (np.all(np.isfinite(xp)) and np.all(np.isfinite(P))) \
                    or np.max(np.abs(xp)) > 1e100:
                break
    return yp


def _sensor_notes(channel: Channel, law: StaticLaw) -> tuple[str, ...]:
    """What a sensor-error law says about sensor ``channel.output``.

    Gain, offset, |.|, cube, saturation level, first-order lag, drift rate.
    """
    nm, out = channel.output, []
    drift = any(term_kind(sp[1]).carries_offset and law.coef[0, j]
                for j, sp in enumerate(law.spec))
    for j, (_, kind, _) in enumerate(law.spec):
        c = law.coef[0, j]
        if c == 0:
            continue
        h = law.ci[0, j] if law.ci is not None else np.nan
        pm = f" ± {h:.2g}" if np.isfinite(h) else ""
        note = term_kind(kind).sensor_note(nm, c, pm, drift)
        if note is not None:
            out.append(note)
    return tuple(out)


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
    zero there, the law is a term the model lacks. With 95 % intervals on the
    law (``law.ci``) each note carries its interval; a term whose interval
    contains 0 (the model's value) has already been dropped from the law, so
    a parameter the data do not contradict is never flagged.
    """
    if channel.kind == "output":
        return _sensor_notes(channel, law)
    A, B = np.asarray(sys.A, dtype=float), np.asarray(sys.B, dtype=float)
    out = []
    for k in range(channel.md):
        g = channel.G[:, k]
        S = np.flatnonzero(np.abs(g) > 0)
        rows = ", ".join(sys.state_labels[i] for i in S)
        for j, (name, kind, idx) in enumerate(law.spec):
            c, t = law.coef[k, j], term_kind(kind)
            if c != 0 and t.pair(idx) is not None:
                a, b = t.pair(idx)
                h = law.ci[k, j] if law.ci is not None else np.nan
                pm = f" ± {h:.2g}" if np.isfinite(h) else ""
                out.append(f"[{rows}] lacks a term in the relative coordinate {name}: the "
                           f"data want {c:.4g}{pm} (a force between "
                           f"{sys.state_labels[a]} and {sys.state_labels[b]})")
                continue
            if c == 0 or t.column(idx) is None:
                continue
            mat, i = t.column(idx)
            col = A[:, i] if mat == "A" else B[:, i]
            cs, gs = col[S], g[S]
            new = cs + c * gs
            h = law.ci[k, j] if law.ci is not None else np.nan
            pm = f" ± {_fmt_values(np.abs(h * gs), 2)}" if np.isfinite(h) else ""
            if np.all(cs == 0):
                out.append(f"{mat}[{rows}; {name}] is 0 in the model; the data want "
                           f"{_fmt_values(new, 3)}{pm} (a missing term)")
                continue
            cosv = abs(cs @ gs) / (np.linalg.norm(cs) * np.linalg.norm(gs))
            if cosv > 0.99:
                alpha = (cs @ gs) / (gs @ gs)
                pct = 100.0 * c / alpha
                ppm = f" ± {100.0 * h / abs(alpha):.2g}" if np.isfinite(h) else ""
                out.append(f"{mat}[{rows}; {name}] = {_fmt_values(cs, 4)} in the "
                           f"model; the data want {_fmt_values(new, 4)}{pm} ({pct:+.1f}{ppm}%)")
    return tuple(out)
