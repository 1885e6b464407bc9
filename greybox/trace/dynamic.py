"""Sparse first-order dynamic laws in continuous time.

A dynamic model error is often one lag driven by one or two signals: an
actuator lag (d = -tau s / (tau s + 1) F), a Maxwell element, a thermal
mass. A subsystem driven by every state and input explains such an error
with n + m drivers and reads as noise. Here the law is

.. math::

    \\dot z = a z + \\sum_{i \\in S} b_i w_i, \\qquad
    d = z + \\sum_{i \\in S} e_i w_i, \\qquad w = [x; u],

with a sparse driver set S chosen by forward selection (BIC) on d^ at the
pole of the unstructured fit, then (a, b_S, e_S) refined by output error on
y with the augmented continuous model discretized exactly (ZOH), and
drivers whose two coefficients' intervals both contain 0 dropped.

For a channel of md >= 2 equations driven by one hidden state along no
fixed direction (a thermal mass shared by two bodies), :func:`fit_shared_dynamic`
fits one shared state instead (:class:`SharedLaw`):

.. math::

    \\dot z = a z + \\sum_{i \\in S} b_i w_i, \\qquad
    d_c = k_c z + \\sum_{i \\in S_c} e_{c,i} w_i, \\qquad k_r = 1,

with the drivers S of z and the feedthrough terms S_c of each component
chosen sparsely, refined by output error the same way, and every term whose
interval contains 0 dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import control as ct
import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from .._blas import single_thread_blas
from ..ident.regression import forward_selection
from ..metrics import effective_samples, oe_criterion
from ..system import named_ss
from ..update import UpdatedModel, free_state_names
from .channels import Channel
from .channel_trace import _LOW_SNR
from .oe import TRIAL_TOL, OutputError, lowest_start, zoh

__all__ = ["DynamicLaw", "SharedLaw", "fit_input_lag", "fit_shared_dynamic",
           "fit_sparse_dynamic"]

# Samples (block means) on which the drivers of a sparse law are chosen.
_SELECT_SAMPLES = 4000


@dataclass(frozen=True)
class DynamicLaw:
    """First-order continuous-time law with sparse drivers (see module docstring).

    Attributes
    ----------
    pole : float
        a [1/s] (negative for a stable law).
    tau : float
        Time constant -1/a [s].
    drivers : tuple of str
        Names of the driving states/inputs S.
    b, e : ndarray, shape (len(drivers),)
        Filtered gains [d units * 1/s per driver unit] and feedthrough gains.
    ci : ndarray, shape (1 + 2 * len(drivers),)
        95 % half-widths of (a, b, e).
    npar : int
        1 + 2 len(drivers).
    formula : str
        Readable law, e.g. ``"d_F = -(1 ± 0.01)*F + (20 ± 1)/(s + 20 ± 1)*F"``.
    model : UpdatedModel
        The nominal model augmented with the law's state ``z[0]``, discretized
        exactly.
    se_estimation : float
        SE [%] of the augmented model on the output-error window.
    continuous : control.StateSpace
        The augmented model in continuous time (states ``[x; z[0]]``).
    rows : tuple of int
        Rows of the drivers in ``[x; u]`` (-1 for a relative coordinate).
    dt : float
        Sampling period [s] of the discrete model.
    weights : ndarray, shape (len(drivers), nstates + ninputs)
        Each driver as a combination of ``[x; u]``: a unit row for a state or
        an input, ``e_j - e_i`` for a relative coordinate ``x_j - x_i``.
    """

    pole: float
    tau: float
    drivers: tuple[str, ...]
    b: NDArray[np.float64]
    e: NDArray[np.float64]
    ci: NDArray[np.float64]
    npar: int
    formula: str
    model: UpdatedModel = field(repr=False)
    se_estimation: float
    continuous: ct.StateSpace = field(default=None, repr=False)
    rows: tuple[int, ...] = ()
    dt: float = float("nan")
    weights: NDArray[np.float64] = field(default=None, repr=False)

    def evaluate(self, x: NDArray, u: NDArray) -> NDArray[np.float64]:
        """The law's d, shape (1, K), on x (nstates, K) and u (ninputs, K).

        ``z`` starts at 0 and follows the ZOH-equivalent first-order filter.
        """
        w = self.weights @ np.vstack([x, u])
        phi = np.exp(self.pole * self.dt)
        out = np.zeros((1, w.shape[1]))
        for wq, b, e in zip(w, self.b, self.e):
            out[0] += e * wq + lfilter([0.0, b * (phi - 1.0) / self.pole], [1.0, -phi], wq)
        return out


class _DynProblem:
    """Output error on y of ``[x; z]`` with the law folded in continuous time."""

    def __init__(self, Ac, Bc, Gc, C, D, dt, y, u, x0, k0, drv):
        self.Ac, self.Bc, self.Gc, self.C, self.D, self.dt = Ac, Bc, Gc[:, 0], C, D, dt
        self.x0, self.k0, self.drv = np.r_[x0, 0.0], k0, drv
        self.n = Ac.shape[0]
        Ca = np.hstack([C, np.zeros((C.shape[0], 1))])
        self.engine = OutputError(lambda theta: self.cont(theta), Ca, D, y, u, self.x0, k0,
                                  dt=dt)
        self.y, self.u, self.scale = self.engine.y, self.engine.u, self.engine.scale

    def cont(self, theta):
        n, k = self.n, len(self.drv)
        a, b, e = theta[0], theta[1:1 + k], theta[1 + k:]
        W = driver_weights(self.drv, n, self.Bc.shape[1])
        bw, ew = b @ W, e @ W
        bx, bu, ex, eu = bw[:n], bw[n:], ew[:n], ew[n:]
        A = np.zeros((n + 1, n + 1))
        A[:n, :n] = self.Ac + np.outer(self.Gc, ex)
        A[:n, n] = self.Gc
        A[n, :n], A[n, n] = bx, a
        B = np.vstack([self.Bc + np.outer(self.Gc, eu), bu[None, :]])
        return A, B

    def disc(self, theta):
        return self.engine.model(theta)

    def resid(self, theta):
        return self.engine.resid(theta)

    def fit(self, theta0, trial: bool = False):
        """Levenberg-Marquardt from ``theta0``; ``trial``: a fit only compared by its
        residual (a driver selection's trial, :data:`greybox.trace.oe.TRIAL_TOL`), at most
        80 residual evaluations. A law's own fit may take ~30 iterations, each one
        evaluation per parameter for the Jacobian and one for the step: at a fixed 80 a
        shared state of 6 parameters stopped 11 iterations in, its pole 18 % off the
        optimum the same start reaches in 93 (zoo thermal_mass 270939893 #0: the true
        6-parameter law lost to an 8-parameter one)."""
        cap = 80 if trial else max(80, 30 * (len(theta0) + 1))
        return self.engine.fit(theta0, max_nfev=cap, tol=TRIAL_TOL if trial else 1e-8)

    def halfwidths(self, sol, Q, R):
        Qa = np.zeros((self.n + 1, self.n + 1))
        Qa[:self.n, :self.n] = Q
        return self.engine.halfwidths(sol, Qa, R)


def driver_weights(drv, n: int, m: int) -> NDArray[np.float64]:
    """Drivers ``("x", i)``, ``("u", i)``, ``("r", (i, j))`` (x_j - x_i) as rows over [x; u]."""
    W = np.zeros((len(drv), n + m))
    for q, (kind, i) in enumerate(drv):
        if kind == "x":
            W[q, i] = 1.0
        elif kind == "u":
            W[q, n + i] = 1.0
        else:
            W[q, i[1]], W[q, i[0]] = 1.0, -1.0
    return W


def _driver_name(sys, d) -> str:
    kind, i = d
    if kind == "x":
        return sys.state_labels[i]
    if kind == "u":
        return sys.input_labels[i]
    return f"({sys.state_labels[i[1]]}-{sys.state_labels[i[0]]})"


def _pm(v, h):
    return f"{v:.3g}" if not np.isfinite(h) else f"({v:.3g} ± {h:.2g})"


def fit_sparse_dynamic(sys: ct.StateSpace, channel: Channel, x: NDArray, d: NDArray,
                       y: NDArray, u: NDArray, *, Q: NDArray, R: NDArray, dt: float,
                       x0: NDArray, k0: int, pole: float | None = None,
                       max_drivers: int = 3, d_noise: float | None = None) -> DynamicLaw | None:
    """Fit a first-order law with sparse drivers for a one-component channel.

    Parameters
    ----------
    sys : control.StateSpace
        Continuous nominal model.
    channel : Channel
        md = 1.
    x : ndarray, shape (nstates, K)
        Filtered states aligned with ``d``.
    d : ndarray, shape (1, K)
        d^ on the same samples.
    y, u : ndarray, shapes (noutputs, nsteps), (ninputs, nsteps)
        The whole estimation record (the output-error fit starts at sample 0).
    Q, R : ndarray
        Noise covariances of the discrete nominal model (for the intervals).
    dt : float
        Sampling period [s].
    x0 : ndarray, shape (nstates,)
        Initial state for the output-error simulation.
    k0 : int
        First sample of the output-error window.
    pole : float, optional
        A discrete pole to try as a start (e.g. from an unstructured fit),
        beside a log grid of time constants from 2 to 500 samples; the two
        poles that explain d^ best are refined and the better fit is kept.
    max_drivers : int
        Largest number of drivers.
    d_noise : float, optional
        Variance of d^'s own estimation noise (the filter's Pd). When the
        variance of ``d`` exceeds it by less than ``_LOW_SNR`` (10 %), d^ is
        mostly noise and regressions on it pick drivers at random: drivers
        chosen by output error on y (:func:`_select_drivers_oe`) are then one
        more start.

    Returns
    -------
    DynamicLaw or None
        None when no stable law improves on the start.
    """
    if channel.md != 1:
        return None
    w = np.vstack([x, u[:, k0:k0 + x.shape[1]]])

    # the unstructured fit's pole may sit far from the law's (it also fits the noise):
    # screen a log grid of time constants from 2 to 500 samples on d^ as well
    grid = list(np.exp(-1.0 / np.geomspace(2.0, 500.0, 16)))
    if pole is not None and 0 < pole < 1:
        grid.append(float(pole))
    # d^ alone ranks slow poles too well (they fit its coloured estimation noise):
    # rank the grid by the output error of the augmented model at the least-squares start
    starts = [_start(sys, channel, w, d, y, u, dt, x0, k0, p0, max_drivers) for p0 in grid]
    starts = sorted((st for st in starts if st is not None), key=lambda st: st[0])[:2]
    # one input alone (an actuator or servo lag) as a start too: d^ also carries what an
    # earlier pass's law borrowed, and its forward selection can then prefer states
    for j in range(sys.ninputs):
        lone = [_start(sys, channel, w, d, y, u, dt, x0, k0, p0, max_drivers, [("u", j)])
                for p0 in grid]
        lone = [st for st in lone if st is not None]
        if lone:
            starts.append(min(lone, key=lambda st: st[0]))
    if d_noise is not None and float(np.var(d)) < (1.0 + _LOW_SNR) * float(d_noise):
        # d^ mostly noise: its regressions pick drivers at random; drivers chosen by output
        # error on y as one more start (the lowest output error among them all is kept:
        # d^'s drivers can also undo an earlier pass's borrowed terms, which the joint
        # refinement of the effects then drops)
        cand = [("x", i) for i in range(sys.nstates)] + \
            [("u", j) for j in range(sys.ninputs)] + [("r", tuple(ij)) for ij in channel.relative]
        sel = _select_drivers_oe(sys, channel, y, u, dt, x0, k0, cand, max_drivers,
                                 pole, _oe_candidates(sys, cand, w, d))
        if sel is not None:
            starts.append((np.nan, *sel))
    def restart(drv, a):  # the least-squares start of these drivers at the pole a [1/s]
        pole = float(np.exp(a * dt))
        if not 0 < pole < 1:
            return None
        return _drivers_and_start(sys, w, d, dt, pole, max_drivers, drv, channel.relative)[1]

    fits = [_fit_scored(sys, channel, y, u, Q, R, dt, x0, k0, drv, theta0, restart)
            for _, drv, theta0 in starts]
    return _by_criterion([f for f in fits if f is not None], y.shape[0])


def _by_criterion(fits, noutputs: int) -> DynamicLaw | None:
    """The law of ``fits`` ((law, flat scaled residual) from different starts) that the one
    criterion prefers (:func:`greybox.metrics.oe_criterion`, on the effective samples of
    the best-fitting one): the starts may end with different drivers, and the lowest
    error alone took a 7-parameter local minimum of the Maxwell element (pole 0.28 1/s,
    drivers p1, p2, v2) over its 3-parameter law at SE 0.46487 % against 0.46488 %."""
    if not fits:
        return None
    res = [r.reshape(noutputs, -1) for _, r in fits]
    best = min(range(len(fits)), key=lambda i: fits[i][0].se_estimation)
    neff = effective_samples(res[best])
    scores = [oe_criterion(r, law.npar, neff) for (law, _), r in zip(fits, res)]
    return fits[int(np.argmin(scores))][0]



def input_scale(sys: ct.StateSpace, channel: Channel, j: int) -> float | None:
    """c with ``B[:, j] = c G`` when the one-component channel carries input j's whole
    effect (the input's own channel: 1; the one state equation it enters: B's entry),
    else None."""
    if channel.md != 1 or channel.kind == "output":
        return None
    g = np.asarray(channel.G, dtype=float)[:, 0]
    b = np.asarray(sys.B, dtype=float)[:, j]
    c = float(g @ b / (g @ g)) if g @ g > 0 else 0.0
    if c == 0 or np.linalg.norm(b - c * g) > 1e-9 * np.linalg.norm(b):
        return None
    return c


def fit_input_lag(sys: ct.StateSpace, channel: Channel, j: int, y: NDArray, u: NDArray, *,
                  Q: NDArray, R: NDArray, dt: float, x0: NDArray, k0: int,
                  ntau: int = 12) -> DynamicLaw | None:
    """Input ``j`` reaching the plant through a first-order filter: its actuator lag.

    The law of a one-component channel that carries input j's whole effect
    (``B[:, j] = c G``: the input's own channel, or the one state equation it
    enters) with u_j its only driver, ``d = e u_j + b/(s - a) u_j``: u_j
    reaches the plant through ``(1 + e/c) + (b/c)/(s - a)``, a lag
    ``1/(tau s + 1)`` at ``e = -c``, ``b = c/tau``, ``a = -1/tau``; 3
    parameters (a gain error and a lag together). Fitted by output error on y
    alone (no d^: through a delayed channel d^ is mostly estimation noise),
    from the pure lag whose output error is lowest on a log grid of ``ntau``
    time constants from 2 to 500 samples.

    Parameters
    ----------
    sys : control.StateSpace
        Continuous nominal model.
    channel : Channel
        md = 1, along ``B[:, j]``.
    j : int
        The input.
    y, u : ndarray, shapes (noutputs, nsteps), (ninputs, nsteps)
        The estimation record (the output-error fit starts at sample 0).
    Q, R : ndarray
        Noise covariances of the discrete nominal model (for the intervals).
    dt : float
        Sampling period [s].
    x0 : ndarray, shape (nstates,)
        Initial state of the output-error simulation.
    k0 : int
        First sample of the output-error window.
    ntau : int
        Time constants on the start grid.

    Returns
    -------
    DynamicLaw or None
        None when the channel does not carry input j's whole effect or no
        stable law is found.
    """
    c = input_scale(sys, channel, j)
    if c is None:
        return None
    drv = [("u", j)]
    with single_thread_blas():
        prob = _problem(sys, channel, y, u, dt, x0, k0, drv)
        theta0 = lowest_start(prob.resid, [np.array([-1.0 / tau, c / tau, -c]) for tau in
                                           np.geomspace(2.0, 500.0, ntau) * dt])
    if theta0 is None:
        return None
    fit = _fit_scored(sys, channel, y, u, Q, R, dt, x0, k0, drv, theta0)
    return None if fit is None else fit[0]

# Output-error driver selection (noise-dominated d^): start poles (time constants in
# samples), candidates kept per step after the score test, and at most this many
# candidate drivers (those whose first-order lags d^ correlates with most).
_OE_TAUS = np.geomspace(2.0, 500.0, 7)
_OE_TOP = 3
_OE_MAX_CAND = 12


def _oe_candidates(sys, cand, w, d):
    """Indices of the ``_OE_MAX_CAND`` candidate drivers that d^ correlates with most.

    Every input is kept (an actuator or servo lag); states and relative
    coordinates are ranked by |corr(d^, lag(w))| over the lags of the pole grid.
    """
    if len(cand) <= _OE_MAX_CAND:
        return list(range(len(cand)))
    W = driver_weights(cand, sys.nstates, sys.ninputs) @ w
    dm = d[0] - d[0].mean()
    score = np.zeros(len(cand))
    for tau in _OE_TAUS:
        p = np.exp(-1.0 / tau)
        f = lfilter([0.0, 1.0 - p], [1.0, -p], W, axis=1)
        f = f - f.mean(axis=1, keepdims=True)
        score = np.maximum(score, np.abs(f @ dm) / (np.linalg.norm(f, axis=1) *
                                                     np.linalg.norm(dm) + 1e-300))
    keep = [q for q, c in enumerate(cand) if c[0] == "u"]
    rest = [q for q in np.argsort(-score) if cand[q][0] != "u"]
    return sorted(keep + [int(q) for q in rest[:max(0, _OE_MAX_CAND - len(keep))]])


def _select_drivers_oe(sys, channel, y, u, dt, x0, k0, cand, max_drivers, pole, allowed):
    """Drivers and start ``(drv, theta)`` by forward selection on the output error of y (BIC).

    For d^ that is mostly its own estimation noise. Each step scores every
    candidate driver c not yet chosen by the score test: the drop of the
    output-error RSS of one Gauss-Newton step in (b_c, e_c) from the current
    law (two extra simulations per candidate; at the first step at every
    pole of a log grid of time constants from 2 to 500 samples, and at
    ``pole``). The ``_OE_TOP`` best are refitted in full (pole, b, e) by
    Levenberg-Marquardt; the one with the lowest BIC of the output error is
    added while that BIC drops. None when no driver lowers it.
    """
    a_grid = [-1.0 / (t * dt) for t in _OE_TAUS]  # continuous poles [1/s]
    if pole is not None and 0 < pole < 1:
        a_grid.append(float(np.log(pole)) / dt)
    with single_thread_blas():
        prob0 = _problem(sys, channel, y, u, dt, x0, k0, [cand[allowed[0]]])
        r0 = prob0.resid(np.array([a_grid[0], 0.0, 0.0]))
        ny = r0.size

        def bic(rss, k):
            return ny * np.log(max(rss / ny, 1e-300)) + k * np.log(ny)

        best_bic, sel, theta = bic(float(r0 @ r0), 0), [], None
        while len(sel) < max_drivers:
            trials = []
            for q in allowed:
                c = cand[q]
                if c in sel:
                    continue
                drv = sel + [c]
                prob = _problem(sys, channel, y, u, dt, x0, k0, drv)
                k = len(sel)
                for a in (a_grid if theta is None else [theta[0]]):
                    th = np.r_[a, np.zeros(2)] if theta is None else \
                        np.r_[theta[0], theta[1:1 + k], 0.0, theta[1 + k:], 0.0]
                    step = _gauss_newton_step(prob, th, [1 + k, 2 + 2 * k])
                    if step is not None:
                        trials.append((step[0], drv, step[1]))
            trials.sort(key=lambda t: -t[0])
            fits, seen = [], set()
            for _, drv, th in trials:
                if drv[-1] in seen:
                    continue
                seen.add(drv[-1])
                sol = _problem(sys, channel, y, u, dt, x0, k0, drv).fit(th, trial=True)
                if sol.x[0] < 0:
                    fits.append((bic(float(np.sum(sol.fun ** 2)), 1 + 2 * len(drv)), drv, sol.x))
                if len(seen) >= _OE_TOP:
                    break
            if not fits:
                break
            b, drv, th = min(fits, key=lambda f: f[0])
            if not b < best_bic:
                break
            best_bic, sel, theta = b, drv, th
    return (sel, theta) if sel else None


def _gauss_newton_step(prob, theta, idx):
    """(RSS drop, theta after) of one Gauss-Newton step in the entries ``idx`` of theta.

    The Jacobian columns by forward differences (the output is affine in a
    feedthrough or filtered gain of an input, and nearly so for a state's at a
    small step); None when the columns carry no signal.
    """
    r0 = prob.resid(theta)
    J = np.empty((r0.size, len(idx)))
    for c, i in enumerate(idx):
        for h in (1e-4, 1e-2, 1.0):
            th = theta.copy()
            th[i] += h
            j = (prob.resid(th) - r0) / h
            if np.max(np.abs(j)) * h > 1e-9 * (np.max(np.abs(r0)) + 1e-300):
                break
        J[:, c] = j
    if not np.all(np.isfinite(J)):
        return None
    g, *_ = np.linalg.lstsq(J, -r0, rcond=None)
    drop = float(r0 @ r0 - np.sum((r0 + J @ g) ** 2))
    out = theta.copy()
    out[idx] += g
    return drop, out


def _drivers_and_start(sys, w, d, dt, pole, max_drivers, drivers=None, relative=()):
    """Drivers by forward selection on d^ at ``pole`` (or ``drivers``), least-squares (a, b, e)."""
    n, m = sys.nstates, sys.ninputs
    cand = [("x", i) for i in range(n)] + [("u", i) for i in range(m)] + \
        [("r", tuple(ij)) for ij in relative]
    w = driver_weights(cand, n, m) @ w
    names = [_driver_name(sys, c) for c in cand]
    f = lfilter([0.0, 1.0 - pole], [1.0, -pole], w, axis=1)
    if drivers is not None:
        idx = [cand.index(c) for c in drivers]
        cols = np.vstack([f[idx], w[idx]])
        coef = np.linalg.lstsq(cols.T, d[0], rcond=None)[0]
        a0 = np.log(pole) / dt
        return list(drivers), np.r_[a0, -a0 * coef[:len(idx)], coef[len(idx):]]
    terms = np.vstack([w, f])
    tnames = [f"{s}" for s in names] + [f"lag({s})" for s in names]
    # the driver choice on at most _SELECT_SAMPLES samples (block means of d^ and terms)
    b = max(1, terms.shape[1] // _SELECT_SAMPLES)
    nb = terms.shape[1] // b
    tb = terms[:, :nb * b].reshape(terms.shape[0], nb, b).mean(axis=2)
    dbm = d[0, :nb * b].reshape(nb, b).mean(axis=1)
    sel = forward_selection(tb, dbm, tnames, max_terms=2 * max_drivers, min_drop=1e-3,
                            prune=True)
    idx = sorted({j % len(cand) for j in sel.index})[:max_drivers]
    if not idx:
        return None, None
    drv = [cand[i] for i in idx]
    cols = np.vstack([f[idx], w[idx]])
    coef = np.linalg.lstsq(cols.T, d[0], rcond=None)[0]
    a0 = np.log(pole) / dt
    return drv, np.r_[a0, -a0 * coef[:len(idx)], coef[len(idx):]]


def _problem(sys, channel, y, u, dt, x0, k0, drv):
    return _DynProblem(np.asarray(sys.A, dtype=float), np.asarray(sys.B, dtype=float),
                       np.asarray(channel.G, dtype=float), np.asarray(sys.C, dtype=float),
                       np.asarray(sys.D, dtype=float), dt, y, u, x0, k0, drv)


def _start(sys, channel, w, d, y, u, dt, x0, k0, pole, max_drivers, drivers=None):
    """(output-error RSS at the least-squares start, drivers, start), or None."""
    drv, theta0 = _drivers_and_start(sys, w, d, dt, pole, max_drivers, drivers,
                                     channel.relative)
    if drv is None:
        return None
    with single_thread_blas():
        r = _problem(sys, channel, y, u, dt, x0, k0, drv).resid(theta0)
    return float(np.sum(r**2)), drv, theta0


def _fit_scored(sys, channel, y, u, Q, R, dt, x0, k0, drv, theta0, restart=None):
    """(law, its flat scaled output error) of the output-error fit from one start, or None.

    Output error on y from one start (drivers and least-squares values from _start).

    Drivers whose two coefficients' intervals both contain 0 are dropped one at a time,
    the weakest first, each drop refitted from the others' values. Where that refit
    no longer simulates (the law without the driver leaves a diverging model the fit
    cannot leave: a Maxwell element's p2 taken out beside p1 and v2, SE 1e8 %), it is
    refitted from ``restart(drivers, a)`` (the least-squares start of the remaining
    drivers on d^ at the fit's pole), and where that diverges too, the drop is not
    taken and the next weakest is tried. Without this, whether a drop diverged
    depended on the last bits of the fit (the BLAS kernels of the machine)."""
    prob = _problem(sys, channel, y, u, dt, x0, k0, drv)
    sol = prob.fit(theta0)
    hw = prob.halfwidths(sol, Q, R)
    while len(drv) > 1:
        k = len(drv)
        b, e = sol.x[1:1 + k], sol.x[1 + k:]
        hb, he = hw[1:1 + k], hw[1 + k:]
        weak = sorted((q for q in range(k) if abs(b[q]) < hb[q] and abs(e[q]) < he[q]),
                      key=lambda q: abs(b[q]) / hb[q] + abs(e[q]) / he[q])
        for q in weak:
            d2 = drv[:q] + drv[q + 1:]
            p2 = _problem(sys, channel, y, u, dt, x0, k0, d2)
            s2 = p2.fit(np.r_[sol.x[0], np.delete(b, q), np.delete(e, q)])
            if not _converged(s2) and restart is not None:
                t2 = restart(d2, float(sol.x[0]))
                s2 = p2.fit(t2) if t2 is not None else s2
            if _converged(s2):
                drv, prob, sol = d2, p2, s2
                hw = prob.halfwidths(sol, Q, R)
                break
        else:
            break
    if not float(sol.x[0]) < 0:
        return None
    return _law_from(sys, channel, prob, drv, sol.x, hw, Q, R), np.asarray(sol.fun)


#: A scaled output error this large (the residual's clip is 1e6 per sample) is a
#: simulation that diverged.
_DIVERGED = 1e5


def _converged(sol) -> bool:
    """A first-order fit with a stable pole whose simulation did not diverge."""
    return float(sol.x[0]) < 0 and float(np.max(np.abs(sol.fun))) < _DIVERGED


def _law_from(sys, channel, prob, drv, theta, hw, Q, R, reach: bool = True) -> DynamicLaw:
    """The DynamicLaw record of the drivers ``drv`` at ``theta = (a, b, e)``, half-widths ``hw``.
    ``reach``: an input channel's formula says how the input reaches the plant (not when
    part of the law, its feedthrough, is held by another effect: a joint refit's merge)."""
    n, k, dt = sys.nstates, len(drv), prob.dt
    a, b, e = float(theta[0]), theta[1:1 + k], theta[1 + k:]
    hb, he = hw[1:1 + k], hw[1 + k:]
    r = prob.resid(theta).reshape(prob.y.shape[0], -1)
    se = float(100 * np.mean(np.sqrt(np.mean(r**2, axis=1))))
    dn = [_driver_name(sys, dv) for dv in drv]
    unit = channel.units[0] if channel.units else ""
    unit = "" if not unit else f" {unit}" if unit.startswith("[") else f" [{unit}]"
    parts = []
    for nm, ei, hi, bi, hbi in zip(dn, e, he, b, hb):
        if ei != 0 and (abs(ei) >= hi or not np.isfinite(hi)):
            parts.append(f"{_pm(ei, hi)}*{nm}")
        if bi != 0:  # 0: dropped by a joint refinement (greybox.trace.joint)
            parts.append(f"{_pm(bi, hbi)}/(s + {_pm(-a, hw[0])})*{nm}")
    formula = f"{channel.labels[0]} = " + " + ".join(parts).replace("+ (-", "- (") + unit
    formula += f", time constant {1 / -a:.3g} s"
    if np.isfinite(hw[0]):
        lo, hi = -a - hw[0], -a + hw[0]
        formula += (f" (95 %: {1 / hi:.3g} .. {1 / lo:.3g} s)" if lo > 0
                    else " (not determined by the data)")
    carried = [(q, c) for q, (kind, j) in enumerate(drv) if kind == "u"
               for c in [input_scale(sys, channel, j)] if c is not None]
    if reach and len(drv) == 1 and carried:
        # u_j = c d-units along the channel: it reaches the plant through 1 + law / c
        (q, c), = carried
        k1, dc = 1.0 + e[q] / c, 1.0 + e[q] / c + b[q] / c / -a
        formula += (f"; {dn[q]} reaches the plant through "
                    f"({k1:.3g} s + {dc * -a:.3g})/(s + {-a:.3g}): DC gain {dc:.3g}, "
                    f"time constant {1 / -a:.3g} s")
    model, cont = _augmented_models(sys, *prob.cont(theta), dt, Q, R, [_lag_state(sys)])
    return DynamicLaw(pole=a, tau=1 / -a, drivers=tuple(dn), b=np.array(b), e=np.array(e),
                      ci=np.asarray(hw), npar=1 + 2 * k, formula=formula, model=model,
                      se_estimation=se, continuous=cont,
                      rows=tuple(i if kind == "x" else n + i if kind == "u" else -1
                                 for kind, i in drv), dt=dt,
                      weights=driver_weights(drv, n, sys.ninputs))


def _lag_state(sys) -> str:
    """Name of a new law state: z[0], or z[1] if the model already has z[0], ..."""
    return free_state_names(sys.state_labels, 1)[0]


@dataclass(frozen=True)
class SharedLaw:
    """One first-order state shared by the md components of a channel (see module docstring).

    Attributes
    ----------
    pole : float
        a [1/s] (negative for a stable law).
    tau : float
        Time constant -1/a [s].
    state : str
        Name of the shared state (``z[0]``); it has the units of the reference
        component's d.
    drivers : tuple of str
        Names of the signals driving the state, S.
    b : ndarray, shape (len(drivers),)
        Their gains [d_ref units * 1/s per driver unit].
    k : ndarray, shape (md,)
        Gain of the state in each component (``k[reference] = 1``).
    reference : int
        The component whose gain is fixed to 1 (the scale of z).
    feedthrough : tuple of (int, str, float)
        Feedthrough terms ``(component, driver name, e_{c,i})``.
    Bz : ndarray, shape (nstates + ninputs,)
        The state's input row over ``[x; u]``: ``dz/dt = a z + Bz @ w``.
    E : ndarray, shape (md, nstates + ninputs)
        Feedthrough over ``[x; u]``: ``d = k z + E @ w``.
    ci : ndarray, shape (npar,)
        95 % half-widths of (a, b, k without the reference, e) in that order.
    npar : int
        1 + len(drivers) + (md - 1) + len(feedthrough).
    formula : str
        Readable law, e.g. ``"d_T1 = z[0] - (1 ± 0.02)*T1; d_T2 = (0.4 ± 0.01)*z[0] - ..."``.
    model : UpdatedModel
        The nominal model augmented with ``z``, discretized exactly.
    se_estimation : float
        SE [%] of the augmented model on the output-error window.
    continuous : control.StateSpace
        The augmented model in continuous time (states ``[x; z]``).
    dt : float
        Sampling period [s] of the discrete model.
    """

    pole: float
    tau: float
    state: str
    drivers: tuple[str, ...]
    b: NDArray[np.float64]
    k: NDArray[np.float64]
    reference: int
    feedthrough: tuple[tuple[int, str, float], ...]
    Bz: NDArray[np.float64] = field(repr=False)
    E: NDArray[np.float64] = field(repr=False)
    ci: NDArray[np.float64] = field(repr=False)
    npar: int
    formula: str
    model: UpdatedModel = field(repr=False)
    se_estimation: float
    continuous: ct.StateSpace = field(repr=False)
    dt: float

    @property
    def one_direction(self) -> bool:
        """True if d stays along k: the feedthrough is ``k e^T`` (within 5 % of its largest term).

        Such a law is one force along k (an md = 1 law along ``G k``), not a
        state shared along no fixed direction.
        """
        dev = self.E - np.outer(self.k, self.E[self.reference])
        return bool(np.max(np.abs(dev), initial=0.0) <=
                    0.05 * np.max(np.abs(self.E), initial=0.0))

    def evaluate(self, x: NDArray, u: NDArray) -> NDArray[np.float64]:
        """The law's d, shape (md, K), on x (nstates, K) and u (ninputs, K).

        ``z`` starts at 0 and follows the ZOH-equivalent first-order filter.
        """
        w = np.vstack([x, u])
        phi = np.exp(self.pole * self.dt)
        z = lfilter([0.0, (phi - 1.0) / self.pole], [1.0, -phi], self.Bz @ w)
        return self.k[:, None] * z[None, :] + self.E @ w


class _SharedProblem(_DynProblem):
    """Output error on y of ``[x; z]`` with one state shared by the md components of d.

    ``theta = (a, b over bdrv, k without the reference, e over eterms)``;
    ``eterms`` are pairs (component, driver).
    """

    def __init__(self, Ac, Bc, Gc, C, D, dt, y, u, x0, k0, bdrv, eterms, ref):
        super().__init__(Ac, Bc, Gc, C, D, dt, y, u, x0, k0, list(bdrv))
        self.G = np.asarray(Gc, dtype=float)
        self.md, self.ref = self.G.shape[1], ref
        self.bdrv, self.eterms = list(bdrv), list(eterms)
        m = self.Bc.shape[1]
        self.Wb = driver_weights(self.bdrv, self.n, m)
        self.We = driver_weights([dv for _, dv in self.eterms], self.n, m)

    def split(self, theta):
        """(a, b, k with the reference's 1, e) of ``theta``."""
        nb, md = len(self.bdrv), self.md
        k = np.insert(theta[1 + nb:nb + md], self.ref, 1.0)
        return theta[0], theta[1:1 + nb], k, theta[nb + md:]

    def rows(self, theta):
        """(Bz over [x; u], E (md, n + m)) at ``theta``."""
        _, b, _, e = self.split(theta)
        E = np.zeros((self.md, self.Wb.shape[1]))
        for (c, _), ec, wq in zip(self.eterms, e, self.We):
            E[c] += ec * wq
        return b @ self.Wb, E

    def cont(self, theta):
        n = self.n
        a, _, k, _ = self.split(theta)
        bw, E = self.rows(theta)
        A = np.zeros((n + 1, n + 1))
        A[:n, :n] = self.Ac + self.G @ E[:, :n]
        A[:n, n] = self.G @ k
        A[n, :n], A[n, n] = bw[:n], a
        B = np.vstack([self.Bc + self.G @ E[:, n:], bw[n:][None, :]])
        return A, B


def fit_shared_dynamic(sys: ct.StateSpace, channel: Channel, x: NDArray, d: NDArray,
                       y: NDArray, u: NDArray, *, Q: NDArray, R: NDArray, dt: float,
                       x0: NDArray, k0: int, pole: float | None = None,
                       max_drivers: int = 3, own_only: bool = False) -> SharedLaw | None:
    """Fit one first-order state shared by the components of an md >= 2 channel.

    Parameters
    ----------
    sys : control.StateSpace
        Continuous nominal model.
    channel : Channel
        md >= 2 (e.g. a pair of equations).
    x : ndarray, shape (nstates, K)
        Filtered states aligned with ``d``.
    d : ndarray, shape (md, K)
        d^ on the same samples.
    y, u : ndarray, shapes (noutputs, nsteps), (ninputs, nsteps)
        The whole estimation record (the output-error fit starts at sample 0).
    Q, R : ndarray
        Noise covariances of the discrete nominal model (for the intervals).
    dt : float
        Sampling period [s].
    x0 : ndarray, shape (nstates,)
        Initial state for the output-error simulation.
    k0 : int
        First sample of the output-error window.
    pole : float, optional
        A discrete pole to try as a start (e.g. from an unstructured fit),
        beside a log grid of time constants from 2 to 500 samples; the two
        starts with the lowest output error are refined and the better fit kept.
    max_drivers : int
        Largest number of drivers of the state (and of feedthrough terms per
        component).
    own_only : bool
        Start only from the states of the channel's equations as drivers (the touching
        bodies' template below), not from a selection on d^.

    Returns
    -------
    SharedLaw or None
        None when no stable law is found.

    Notes
    -----
    At each start pole the drivers are chosen on d^ per component by forward
    selection (BIC) among ``[x; u]`` and their first-order lags, and, as a
    second start, taken as the states of the channel's equations (a hidden
    body exchanging with the bodies it touches: with collinear drivers, such
    as neighbouring temperatures, forward selection can keep a proxy); the lag
    coefficients of the components are made rank one (one shared state) by
    their leading singular pair. The starts are ranked by output error. The refinement is output error on y with
    the augmented model discretized exactly (ZOH); the term whose 95 %
    interval contains 0 by the widest margin is dropped and the rest refitted
    until none is left (the state keeps at least one driver).
    """
    md = channel.md
    if md < 2 or d.shape[0] != md:
        return None
    w = np.vstack([x, u[:, k0:k0 + x.shape[1]]])
    wrms = np.sqrt(np.mean(w**2, axis=1)) + 1e-300
    grid = list(np.exp(-1.0 / np.geomspace(2.0, 500.0, 16)))
    if pole is not None and 0 < pole < 1:
        grid.append(float(pole))
    starts = []
    kinds = (True,) if own_only else (False, True)
    for p0, own in ((p0, own) for p0 in grid for own in kinds):
        st = _shared_start(sys, channel, w, d, dt, p0, max_drivers, own)
        if st is None or any(s[1:4] == st[:3] and np.allclose(s[4], st[3]) for s in starts):
            continue
        bdrv, eterms, ref, theta0 = st
        with single_thread_blas():
            r = _shared_problem(sys, channel, y, u, dt, x0, k0, bdrv, eterms, ref).resid(theta0)
        starts.append((float(np.sum(r**2)), bdrv, eterms, ref, theta0, own))
    ranked = sorted(starts, key=lambda s: s[0])
    # the two best starts, and the best of the touching-bodies template (a second effect
    # elsewhere can spoil d^ and rank it low, while its refit is the sparse realization)
    extra = next((s for s in ranked[2:] if s[5]), None)
    chosen = [(s, 0) for s in ranked[:2]] + ([(extra, 1)] if extra is not None else [])
    laws = []  # (law, 1 for the extra template start)
    for (_, bdrv, eterms, ref, theta0, _), flag in chosen:
        law = _shared_fit_from(sys, channel, y, u, Q, R, dt, x0, k0, bdrv, eterms, ref, theta0,
                               wrms)
        if law is not None:
            laws.append((law, flag))
    if not laws:
        return None
    return _fewest_then_lowest(laws)


#: Two fits whose estimation SEs agree to this relative difference are one law (two
#: scalings of one shared state converge to the same output error, to the optimizer's
#: tolerance of 1e-8); beyond it, at one number of parameters, the lower SE is the
#: higher likelihood and wins.
_SAME_LAW_RTOL = 1e-5


def _fewest_then_lowest(laws):
    """The fewest terms among the fits within 1 % of the lowest output error (two starts
    can end in two realizations of one law, one with a spurious small term); among
    those, the lowest output error; the extra template start (flag 1) only where it is
    not the same law as a first-ranked start's (:data:`_SAME_LAW_RTOL`). Zoo
    thermal_mass 244465831 #0: the template start reached the true realization (pole
    -0.36, driven by T1 and T2; SE 0.30198 %) and lost at 6 parameters each to a
    local optimum (pole -0.54, driven by T1, a spurious T3; 0.30216 %) by its flag."""
    lo = min(lw.se_estimation for lw, _ in laws)
    near = [(lw, x) for lw, x in laws if lw.se_estimation <= 1.01 * lo]
    few = min(lw.npar for lw, _ in near)
    near = [(lw, x) for lw, x in near if lw.npar == few]
    best = min(lw.se_estimation for lw, _ in near)
    same = [(lw, x) for lw, x in near if lw.se_estimation <= best * (1 + _SAME_LAW_RTOL)]
    return min(same, key=lambda t: (t[1], t[0].se_estimation))[0]


def _shared_start(sys, channel, w, d, dt, pole, max_drivers, own=False):
    """Drivers of z and feedthrough terms on d^ at ``pole``; least-squares rank-one start.

    The drivers are chosen by forward selection (BIC) per component, or with
    ``own``, taken as the states of the channel's equations, each component
    carrying its own state: a hidden body exchanging with the bodies whose
    equations it enters. With collinear drivers (the temperatures of
    neighbouring bodies) forward selection can keep an early proxy term (an
    input's lag for a state's) in every component; the output-error
    refinement drops what the data do not support in either start.
    """
    n, m, md = sys.nstates, sys.ninputs, channel.md
    cand = [("x", i) for i in range(n)] + [("u", i) for i in range(m)]
    wc = driver_weights(cand, n, m) @ w
    f = lfilter([0.0, 1.0 - pole], [1.0, -pole], wc, axis=1)
    names = [_driver_name(sys, c) for c in cand]
    terms = np.vstack([wc, f])
    tnames = list(names) + [f"lag({s})" for s in names]
    b = max(1, terms.shape[1] // _SELECT_SAMPLES)
    nb = terms.shape[1] // b
    tb = terms[:, :nb * b].reshape(terms.shape[0], nb, b).mean(axis=2)
    dbm = d[:, :nb * b].reshape(md, nb, b).mean(axis=2)
    if own:
        labels = list(sys.state_labels)
        mine = [labels.index(e) for e in channel.equations if e in labels]
        if len(mine) != md:
            return None
        lag, feed = sorted(mine), [[j] for j in mine]
    else:
        lag, feed = set(), []
        for c in range(md):
            sel = forward_selection(tb, dbm[c], tnames, max_terms=2 * max_drivers,
                                    min_drop=1e-3, prune=True)
            lag |= {j - len(cand) for j in sel.index if j >= len(cand)}
            feed.append(sorted(j for j in sel.index if j < len(cand))[:max_drivers])
        lag = sorted(lag)[:max_drivers]
    if not lag:
        return None
    L = np.zeros((md, len(lag)))
    for c in range(md):
        cols = np.vstack([f[lag], wc[feed[c]]])
        L[c] = np.linalg.lstsq(cols.T, d[c], rcond=None)[0][:len(lag)]
    U, s, Vt = np.linalg.svd(L, full_matrices=False)
    ref = int(np.argmax(np.abs(U[:, 0])))
    k = U[:, 0] / U[ref, 0]
    beta = s[0] * U[ref, 0] * Vt[0]
    zf = beta @ f[lag]
    e = []
    for c in range(md):  # the feedthrough given the shared state
        if feed[c]:
            e.extend(np.linalg.lstsq(wc[feed[c]].T, d[c] - k[c] * zf, rcond=None)[0])
    a0 = np.log(pole) / dt
    eterms = [(c, cand[j]) for c in range(md) for j in feed[c]]
    return [cand[j] for j in lag], eterms, ref, np.r_[a0, -a0 * beta, np.delete(k, ref), e]


def _shared_problem(sys, channel, y, u, dt, x0, k0, bdrv, eterms, ref):
    return _SharedProblem(np.asarray(sys.A, dtype=float), np.asarray(sys.B, dtype=float),
                          np.asarray(channel.G, dtype=float), np.asarray(sys.C, dtype=float),
                          np.asarray(sys.D, dtype=float), dt, y, u, x0, k0, bdrv, eterms, ref)


def _shared_fit_from(sys, channel, y, u, Q, R, dt, x0, k0, bdrv, eterms, ref, theta0, wrms):
    """Output error from one start; weak terms dropped; the sparsest equivalent realization."""
    args = (sys, channel, y, u, Q, R, dt, x0, k0, ref)
    prob, sol, hw = _drop_weak(*args, bdrv, eterms, theta0)
    for _ in range(3):
        sp = _sparsest_realization(prob, sol.x, wrms)
        if sp is None:
            break
        alt = _drop_weak(*args, *sp)
        # the same law in other coordinates with fewer terms: kept within 1 % of the
        # output error (the rule that picks among starts in fit_shared_dynamic)
        if not (alt[1].x.size < sol.x.size and
                np.sum(alt[1].fun ** 2) <= 1.01**2 * np.sum(sol.fun ** 2)):
            break
        prob, sol, hw = alt
    if not float(sol.x[0]) < 0 or not np.all(np.isfinite(hw)):
        return None
    # unstable through the loop x -> z -> x (the output-error window is finite): no law
    lam0 = float(np.max(np.linalg.eigvals(prob.Ac).real, initial=0.0))
    if np.max(np.linalg.eigvals(prob.cont(sol.x)[0]).real) > lam0 + 1e-9 * (1 + abs(lam0)):
        return None
    # a component whose gain k_c is not told from 0: the law of the smaller channel (and,
    # with feedthrough, an independent static law beside it: two effects, which the
    # several-effects loop finds one by one), not a shared state
    nb, md = len(prob.bdrv), prob.md
    k, hk = prob.split(sol.x)[2], np.insert(hw[1 + nb:nb + md], prob.ref, 0.0)
    if np.any(np.abs(k) < hk):
        return None
    return _shared_law_from(sys, channel, prob, sol.x, hw, Q, R)


def _drop_weak(sys, channel, y, u, Q, R, dt, x0, k0, ref, bdrv, eterms, theta0):
    """Fit; drop the term whose interval contains 0 by the widest margin; repeat."""
    md = channel.md
    while True:
        prob = _shared_problem(sys, channel, y, u, dt, x0, k0, bdrv, eterms, ref)
        sol = prob.fit(theta0)
        hw = prob.halfwidths(sol, Q, R)
        nb = len(bdrv)
        # candidates to drop: b (while z keeps a driver) and e; k stays (the state's gains)
        idx = ([1 + q for q in range(nb)] if nb > 1 else []) + \
            list(range(nb + md, sol.x.size))
        weak = [i for i in idx if abs(sol.x[i]) < hw[i]]
        if not weak:
            return prob, sol, hw
        i = min(weak, key=lambda i: abs(sol.x[i]) / hw[i])
        if i <= nb:
            bdrv = bdrv[:i - 1] + bdrv[i:]
        else:
            q = i - nb - md
            eterms = eterms[:q] + eterms[q + 1:]
        theta0 = np.delete(sol.x, i)


def _sparsest_realization(prob, theta, wrms):
    """The same law in the coordinates with the smallest terms: ``(bdrv, eterms, theta)`` or None.

    The shared state is defined up to ``z~ = z + c x_j`` for any state x_j:
    x_j's equation is known, so ``dz~/dt`` is again first order in (z~, x, u),
    with pole ``a + c (G k)_j``, and ``d = k z~ + (E - c k e_j^T) w`` -- the
    same output for every c, but a different pole and different terms: the
    time constant is defined only by the sparse realization. Every entry of
    the new (Bz, E) is a polynomial of degree <= 2 in c; at its real roots
    (an entry vanishes) the terms are counted, leaving out those whose
    contribution to d (``|e| rms(w)`` for feedthrough, ``max|k| |b| / |a| rms(w)``
    for the state's drivers) is below 1 % of the largest; the realization
    with the fewest terms (then the smallest sum of contributions) is
    returned when it has fewer terms than now and a stable pole. The caller
    refits it and keeps it only if the refit keeps fewer terms at the same
    output error. ``wrms``: RMS of ``[x; u]``.
    """
    n, md, ref = prob.n, prob.md, prob.ref
    m = prob.Bc.shape[1]
    a, _, k, _ = prob.split(theta)
    Bz, E = prob.rows(theta)
    A, B = prob.cont(theta)
    AB = np.hstack([A[:n, :n], B[:n]])  # the states' known equations over [x; u]
    kmax = float(np.max(np.abs(k)))

    def terms(c, j):
        """(pole, Bz~, E~) of z~ = z + c x_j."""
        ej = np.zeros(n + m)
        ej[j] = 1.0
        ap = a + c * A[j, n]
        return ap, Bz + c * AB[j] - c * ap * ej, E - c * np.outer(k, ej)

    def contrib(ap, bz, ee):
        return np.r_[kmax * np.abs(bz) * wrms / abs(ap), (np.abs(ee) * wrms[None, :]).ravel()]

    cur = contrib(a, Bz, E)
    now = int(np.sum(cur > 0.01 * cur.max()))
    best = None
    for j in range(n):
        v = np.array([np.r_[terms(c, j)[1], terms(c, j)[2].ravel()] for c in (-1.0, 0.0, 1.0)])
        c2, c1, c0 = (v[0] + v[2]) / 2 - v[1], (v[2] - v[0]) / 2, v[1]
        roots = set()
        for q in range(v.shape[1]):
            if c0[q] == 0:
                continue
            rq = np.roots([c2[q], c1[q], c0[q]]) if abs(c2[q]) > 1e-12 * abs(c0[q]) else \
                (np.array([-c0[q] / c1[q]]) if c1[q] != 0 else np.zeros(0))
            roots |= {(float(r.real), q) for r in np.atleast_1d(rq)
                      if abs(r.imag) <= 1e-9 * max(1.0, abs(r)) and r.real != 0}
        for c, q in roots:
            ap, bz, ee = terms(c, j)
            if not ap < 0:
                continue
            vv = np.r_[bz, ee.ravel()]
            vv[q] = 0.0  # the entry this c removes (exactly 0 up to rounding)
            cv = contrib(ap, vv[:n + m], vv[n + m:].reshape(md, n + m))
            vv[cv <= 0.01 * cv.max()] = 0.0
            bz, ee = vv[:n + m], vv[n + m:].reshape(md, n + m)
            cnt = int(np.sum(vv != 0))
            key = (cnt, float(np.sum(cv)))
            if np.any(bz != 0) and cnt < now and (best is None or key < best[0]):
                best = (key, ap, bz, ee)
    if best is None:
        return None
    _, ap, bz, ee = best
    drv = [("x", i) if i < n else ("u", i - n) for i in range(n + m)]
    bdrv = [drv[i] for i in range(n + m) if bz[i] != 0]
    eterms = [(c, drv[i]) for c in range(md) for i in range(n + m) if ee[c, i] != 0]
    theta0 = np.r_[ap, bz[bz != 0], np.delete(k, ref), [ee[c, i] for c in range(md)
                                                     for i in range(n + m) if ee[c, i] != 0]]
    return bdrv, eterms, theta0


def _shared_law_from(sys, channel, prob, theta, hw, Q, R) -> SharedLaw:
    """The SharedLaw record of ``prob`` at ``theta``, half-widths ``hw``."""
    dt, md = prob.dt, prob.md
    a, b, k, e = prob.split(theta)
    a = float(a)
    nb = len(prob.bdrv)
    hb = hw[1:1 + nb]
    hk = np.insert(hw[1 + nb:nb + md], prob.ref, np.nan)
    he = hw[nb + md:]
    r = prob.resid(theta).reshape(prob.y.shape[0], -1)
    se = float(100 * np.mean(np.sqrt(np.mean(r**2, axis=1))))
    zname = _lag_state(sys)
    lines, unit = _component_lines(sys, channel, prob.ref, zname, k, hk, prob.eterms, e, he)
    dn = [_driver_name(sys, dv) for dv in prob.bdrv]
    zpart = " + ".join(f"{_pm(bi, hbi)}/(s + {_pm(-a, hw[0])})*{nm}"
                       for nm, bi, hbi in zip(dn, b, hb)).replace("+ (-", "- (")
    formula = "; ".join(lines) + f"; {zname} = {zpart}{unit(prob.ref)}"
    formula += f", time constant {1 / -a:.3g} s"
    if np.isfinite(hw[0]):
        lo, hi = -a - hw[0], -a + hw[0]
        formula += (f" (95 %: {1 / hi:.3g} .. {1 / lo:.3g} s)" if lo > 0
                    else " (not determined by the data)")
    formula += f" (one state shared by {', '.join(channel.labels)})"
    model, cont = _augmented_models(sys, *prob.cont(theta), dt, Q, R, [zname])
    Bz, E = prob.rows(theta)
    feed = tuple((int(c), _driver_name(sys, dv), float(ec)) for (c, dv), ec in zip(prob.eterms, e))
    return SharedLaw(pole=a, tau=1 / -a, state=zname, drivers=tuple(dn), b=np.array(b),
                     k=np.array(k), reference=prob.ref, feedthrough=feed, Bz=Bz, E=E,
                     ci=np.asarray(hw), npar=int(theta.size), formula=formula, model=model,
                     se_estimation=se, continuous=cont, dt=dt)


def _component_lines(sys, channel, ref, zname, k, hk, eterms, e, he):
    """The formula line of each component of a shared law, and the unit suffix per component.

    ``d_c = k_c*z + sum e*driver`` with intervals (``zname`` alone in the
    reference component ``ref``); ``eterms``: pairs (component, driver).
    """
    md = len(k)
    units = list(channel.units) if channel.units else [""] * md

    def unit(c):
        un = units[c] if c < len(units) else ""
        return "" if not un else f" {un}" if un.startswith("[") else f" [{un}]"

    lines = []
    for c in range(md):
        parts = [zname if c == ref else f"{_pm(k[c], hk[c])}*{zname}"]
        parts += [f"{_pm(ec, hc)}*{_driver_name(sys, dv)}"
                  for (cc, dv), ec, hc in zip(eterms, e, he) if cc == c]
        lines.append(f"{channel.labels[c]} = " + " + ".join(parts).replace("+ (-", "- (") +
                     unit(c))
    return lines, unit


def _augmented_models(sys, Ac, Bc, dt, Q, R, znames):
    """(UpdatedModel discretized exactly, continuous StateSpace) of ``sys`` with law states.

    ``Ac, Bc``: the augmented continuous matrices (states ``[x; z]``); the
    law states get a negligible process noise (1e-12 of the mean of Q's
    diagonal) and are not measured.
    """
    n, nz = sys.nstates, len(znames)
    C, D = np.asarray(sys.C, dtype=float), np.asarray(sys.D, dtype=float)
    Ca = np.hstack([C, np.zeros((C.shape[0], nz))])
    Qa = np.zeros((n + nz, n + nz))
    Qa[:n, :n] = Q
    Qa[n:, n:] = 1e-12 * max(float(np.trace(Q)) / n, 1e-300) * np.eye(nz)
    kw = dict(states=list(sys.state_labels) + list(znames), inputs=sys.input_labels,
              outputs=sys.output_labels, name=f"{sys.name or 'model'}_updated")
    out = named_ss(*zoh(Ac, Bc, dt), Ca, D, dt, **kw)
    cont = named_ss(Ac, Bc, Ca, D, 0, **kw)
    return UpdatedModel(sys=out, Q=Qa, R=R, order=n + nz, kind="dynamic"), cont
