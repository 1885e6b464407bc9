"""One hidden subsystem of order 2 or 3 shared by several state equations.

A hidden chain of two or three lumped parts behind the bodies whose equations
it enters (thermal masses in series, a flexible part with its own mode) is
one subsystem of order q = 2 or 3 whose output drives md >= 2 equations along
no fixed direction. In the observer canonical form (unique for an observable
law: the poles and the zeros are read off it), for q = 2

.. math::

    \\dot z_1 = -\\alpha_1 z_1 + z_2 + \\sum_i \\beta_{1,i} w_i, \\qquad
    \\dot z_2 = -\\alpha_0 z_1 + \\sum_i \\beta_{0,i} w_i,

    d_c = k_c z_1 + \\sum_{i \\in S_c} e_{c,i} w_i, \\qquad k_r = 1,
    \\qquad w = [x; u],

so ``z_1 = sum_i (beta_1i s + beta_0i) / (s^2 + alpha_1 s + alpha_0) w_i``; for
q = 3 one more state, ``z_2' = -alpha_1 z_1 + z_3 + ...``, ``z_3' = -alpha_0 z_1 +
...`` (denominator ``s^3 + alpha_2 s^2 + alpha_1 s + alpha_0``).
:func:`fit_shared_order2` starts from a first-order shared law
(:class:`~greybox.trace.dynamic.SharedLaw`) with its drivers, gains and
feedthrough (and, from 0, the states of the channel's own equations as drivers
and feedthrough), and a second pole five times slower or faster (an exact
pole-zero cancellation: the start is the first-order law), refines every
coefficient by output error on y with the augmented model discretized exactly
(ZOH), and drops the term whose 95 % interval contains 0 by the widest margin
until none is left. A second start is the template of a hidden part touching
the bodies (driven by their states, each equation with its own state's
feedthrough); of the fits within 1 % of the lowest output error the one with
the fewest terms is kept (the hidden part is defined only up to
``z~ = z + c x_j``: two realizations of one law have different poles, and the
sparser is the physical one). Given a second-order law instead, it fits the
third-order one the same way: the start multiplies the law's denominator and
numerators by ``(s + p3)`` (an exact cancellation), a third pole five times
slower than the slowest, between the two, or five times faster than the
fastest. The workflow offers order 2 beside the first-order law, and order 3
beside order 2 where order 2 still leaves coloured innovations, and chooses
with the same criterion as between all candidates (the output-error criterion on
effective samples, :func:`greybox.metrics.criterion_scores`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from types import SimpleNamespace

import control as ct
import numpy as np
from numpy.typing import NDArray

from .._blas import single_thread_blas
from .._lti import lti_states
from ..update import UpdatedModel, free_state_names
from .channels import Channel
from .dynamic import SharedLaw, _augmented_models, _component_lines, _driver_name, \
    _gauss_newton_step, _pm, driver_weights, input_scale
from .oe import OutputError, lowest_start, zoh

__all__ = ["SharedLaw2", "fit_hidden_part2", "fit_input_lag2", "fit_shared_order2"]


@dataclass(frozen=True)
class SharedLaw2:
    """One subsystem of order 2 or 3 shared by the md components of a channel (module
    docstring). The name says "more than one state"; ``order`` says how many.

    Attributes
    ----------
    order : int
        q, 2 or 3.
    poles : ndarray, shape (q,)
        Poles of the subsystem [1/s] (complex pairs for an oscillating mode),
        real poles slowest first, then the complex pairs.
    pole_ci : ndarray, shape (q,)
        95 % half-widths of each real pole, and of (real part, imaginary
        part) of each complex pair, in the order of ``poles`` [1/s].
    taus : ndarray, shape (q,)
        Time constants -1/p [s] of real poles (NaN for a complex pair).
    alpha : ndarray, shape (q,)
        The denominator's coefficients, highest power first without the
        leading 1: (alpha_1, alpha_0) for ``s^2 + alpha_1 s + alpha_0``.
    states : tuple of str
        Names of the q law states (``z[0]``, ``z[1]``, ...); ``z[0]`` has the
        units of the reference component's d.
    drivers : tuple of str
        Names of the signals driving the subsystem.
    beta : ndarray, shape (q, len(drivers))
        Numerator gains per driver, highest power of s first ((beta_1,
        beta_0) for q = 2; 0 where dropped).
    k : ndarray, shape (md,)
        Gain of ``z[0]`` in each component (``k[reference] = 1``).
    reference : int
        The component whose gain is fixed to 1.
    feedthrough : tuple of (int, str, float)
        Feedthrough terms ``(component, driver name, e_{c,i})``.
    Bz : ndarray, shape (q, nstates + ninputs)
        The subsystem's input rows over ``[x; u]``.
    E : ndarray, shape (md, nstates + ninputs)
        Feedthrough over ``[x; u]``: ``d = k z_1 + E @ w``.
    ci : ndarray, shape (npar,)
        95 % half-widths of (alpha, beta terms, k without the reference, e)
        in that order.
    npar : int
        Number of coefficients.
    formula : str
        Readable law with intervals, poles and time constants.
    model : UpdatedModel
        The nominal model augmented with the q states, discretized exactly.
    se_estimation : float
        SE [%] of the augmented model on the output-error window.
    continuous : control.StateSpace
        The augmented model in continuous time (states ``[x; z]``).
    dt : float
        Sampling period [s] of the discrete model.
    """

    order: int
    poles: NDArray[np.complex128]
    pole_ci: NDArray[np.float64]
    taus: NDArray[np.float64]
    alpha: NDArray[np.float64]
    states: tuple[str, ...]
    drivers: tuple[str, ...]
    beta: NDArray[np.float64]
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
    def undetermined_pole(self) -> bool:
        """Whether a real pole's 95 % interval holds 0 (the formula's "not determined by
        the data"): an integrator, not a mode the data show."""
        nreal = int(np.sum(np.isreal(self.poles)))
        return any(not _determined(p, h) for p, h in
                   zip(self.poles[:nreal].real, self.pole_ci[:nreal]))

    def evaluate(self, x: NDArray, u: NDArray) -> NDArray[np.float64]:
        """The law's d, shape (md, K), on x (nstates, K) and u (ninputs, K).

        ``z`` starts at 0 and follows the ZOH-discretized subsystem.
        """
        w = np.vstack([x, u])
        q = self.alpha.size
        Phi, Gam = zoh(_companion(self.alpha), np.eye(q), self.dt)
        z = lti_states(Phi, Gam @ (self.Bz @ w), np.zeros(q))
        return self.k[:, None] * z[0][None, :] + self.E @ w


def _companion(alpha):
    """The subsystem's A in observer canonical form: first column -alpha, ones above."""
    q = alpha.size
    Az = np.eye(q, k=1)
    Az[:, 0] = -np.asarray(alpha, dtype=float)
    return Az


class _Problem:
    """Output error on y of ``[x; z_1 .. z_q]`` with the law folded in continuous time.

    ``theta = (alpha (q), beta over bterms, k without the reference, e over
    eterms)``; ``bterms`` are pairs (row r, driver), row r of ``Bz`` the
    numerator coefficient of ``s^(q-1-r)``; ``eterms`` pairs (component, driver).
    """

    def __init__(self, sys, channel, y, u, dt, x0, k0, bterms, eterms, ref, order=2):
        self.q = int(order)
        self.Ac, self.Bc = np.asarray(sys.A, dtype=float), np.asarray(sys.B, dtype=float)
        self.C, self.D = np.asarray(sys.C, dtype=float), np.asarray(sys.D, dtype=float)
        self.G = np.asarray(channel.G, dtype=float)
        self.n, self.m, self.md, self.dt, self.ref = self.Ac.shape[0], self.Bc.shape[1], \
            self.G.shape[1], dt, ref
        self.k0 = k0
        self.x0 = np.r_[x0, np.zeros(self.q)]
        self.bterms, self.eterms = list(bterms), list(eterms)
        self.Wb = driver_weights([dv for _, dv in self.bterms], self.n, self.m)
        self.We = driver_weights([dv for _, dv in self.eterms], self.n, self.m)
        self.Ca = np.hstack([self.C, np.zeros((self.C.shape[0], self.q))])
        self.engine = OutputError(lambda theta: self.cont(theta), self.Ca, self.D, y, u,
                                  self.x0, k0, dt=dt)
        self.y, self.u, self.scale = self.engine.y, self.engine.u, self.engine.scale

    def split(self, theta):
        """(alpha (q,), beta values, k with the reference's 1, e values)."""
        nb, md, q = len(self.bterms), self.md, self.q
        k = np.insert(theta[q + nb:q - 1 + nb + md], self.ref, 1.0)
        return theta[:q], theta[q:q + nb], k, theta[q - 1 + nb + md:]

    def rows(self, theta):
        """(Bz (q, n + m), E (md, n + m)) at ``theta``."""
        _, beta, _, e = self.split(theta)
        Bz = np.zeros((self.q, self.n + self.m))
        for (r, _), bv, wq in zip(self.bterms, beta, self.Wb):
            Bz[r] += bv * wq
        E = np.zeros((self.md, self.n + self.m))
        for (c, _), ev, wq in zip(self.eterms, e, self.We):
            E[c] += ev * wq
        return Bz, E

    def cont(self, theta):
        n, q = self.n, self.q
        alpha, _, k, _ = self.split(theta)
        Bz, E = self.rows(theta)
        A = np.zeros((n + q, n + q))
        A[:n, :n] = self.Ac + self.G @ E[:, :n]
        A[:n, n] = self.G @ k
        A[n:, :n] = Bz[:, :n]
        A[n:, n:] = _companion(alpha)
        B = np.vstack([self.Bc + self.G @ E[:, n:], Bz[:, n:]])
        return A, B

    def resid(self, theta):
        return self.engine.resid(theta)

    def fit(self, theta0):
        return self.engine.fit(theta0, max_nfev=60)

    def halfwidths(self, sol, Q, R, jac=None):
        n = self.n
        Qa = np.zeros((n + self.q, n + self.q))
        Qa[:n, :n] = Q
        s = sol if jac is None else SimpleNamespace(jac=jac, fun=sol.fun, x=sol.x)
        return self.engine.halfwidths(s, Qa, R)


def fit_shared_order2(sys: ct.StateSpace, channel: Channel, law: SharedLaw | SharedLaw2,
                      y: NDArray, u: NDArray, *, Q: NDArray, R: NDArray, dt: float,
                      x0: NDArray, k0: int) -> SharedLaw2 | None:
    """Fit one subsystem one order above ``law`` shared by an md >= 2 channel.

    Order 2 from a first-order shared law, order 3 from a second-order one
    (module docstring).

    Parameters
    ----------
    sys : control.StateSpace
        Continuous nominal model.
    channel : Channel
        The channel of ``law`` (md >= 2).
    law : SharedLaw or SharedLaw2
        The channel's shared law one order below (drivers, gains, feedthrough
        and poles of the start); a SharedLaw2 of order 3 gives None.
    y, u : ndarray, shapes (noutputs, nsteps), (ninputs, nsteps)
        The whole estimation record.
    Q, R : ndarray
        Noise covariances of the discrete nominal model (for the intervals).
    dt : float
        Sampling period [s].
    x0 : ndarray, shape (nstates,)
        Initial state for the output-error simulation.
    k0 : int
        First sample of the output-error window.

    Returns
    -------
    SharedLaw2 or None
        None when no stable law with determined gains is found.
    """
    if channel.md < 2 or law.k.size != channel.md:
        return None
    if isinstance(law, SharedLaw2):
        return _order3(sys, channel, law, y, u, Q, R, dt, x0, k0) if law.order == 2 else None
    drv = _driver_ref(sys)
    # the first-order law's drivers and feedthrough, and the states of the channel's own
    # equations (a hidden part exchanging with the bodies it touches: the first-order law
    # can have kept a proxy, e.g. an input's lag for a state's), the latter from 0
    own = [drv(e) for e in channel.equations if e in sys.state_labels]
    bdrv = [drv(nm) for nm in law.drivers]
    b1 = list(law.b) + [0.0] * sum(dv not in bdrv for dv in own)
    bdrv += [dv for dv in own if dv not in bdrv]
    b1 = np.asarray(b1)
    bterms = [(0, dv) for dv in bdrv] + [(1, dv) for dv in bdrv]
    eterms = [(c, drv(nm)) for c, nm, _ in law.feedthrough]
    ee = [v for _, _, v in law.feedthrough]
    for c, dv in enumerate(own if len(own) == channel.md else []):
        if (c, dv) not in eterms:
            eterms.append((c, dv))
            ee.append(0.0)
    kk = np.delete(law.k, law.reference)
    a = law.pole
    fits = []
    args = (sys, channel, y, u, Q, R, dt, x0, k0)
    with single_thread_blas():
        for p2 in (0.2 * a, 5.0 * a):  # the second pole slower or faster than the first
            theta0 = np.r_[-(a + p2), a * p2, b1, -p2 * b1, kk, ee]
            fits.append(_drop_weak(*args, bterms, eterms, law.reference, theta0))
            if len(own) == channel.md:
                fits.append(_template(args, own, np.r_[-(a + p2), a * p2], kk, law.reference))
    return _sparsest(sys, channel, fits, Q, R)


def fit_input_lag2(sys: ct.StateSpace, channel: Channel, j: int, y: NDArray, u: NDArray, *,
                   Q: NDArray, R: NDArray, dt: float, x0: NDArray, k0: int,
                   tau: float | None = None) -> SharedLaw2 | None:
    """Input ``j`` reaching the plant through a second-order filter: its actuator's own
    mode (a servo, a valve with its own dynamics).

    The law of a one-component channel that carries input j's whole effect
    (``B[:, j] = c G``, :func:`greybox.trace.dynamic.input_scale`) with u_j its only
    driver, ``d = e u_j + (beta_1 s + beta_0)/(s^2 + alpha_1 s + alpha_0) u_j``: a
    lag ``w^2/(s^2 + 2 zeta w s + w^2)`` at ``e = -c``, ``beta_1 = 0``,
    ``beta_0 = c w^2``; terms whose interval contains 0 are dropped
    (:func:`_drop_weak`: a pure lag keeps 4 parameters). Fitted by output error on y
    alone from the pure lag whose output error is lowest among w in (1, 1.6, 2.5)/tau and
    9 frequencies from 1 % of the Nyquist frequency to it, zeta in (0.3, 0.5, 0.8), tau
    the first-order lag's time constant (default: the geometric middle of 2 .. 500
    samples): a first-order fit can put its lag far from the second-order one's mode
    (zoo actuator_lag2, 10.7 rad/s at zeta 0.36: tau = 1/95 s, and the fit from there
    ended at a lightly damped 86 rad/s at 3.5x the true model's error).

    Parameters
    ----------
    sys : control.StateSpace
        Continuous nominal model.
    channel : Channel
        md = 1, along ``B[:, j]``.
    j : int
        The input.
    y, u : ndarray, shapes (noutputs, nsteps), (ninputs, nsteps)
        The estimation record.
    Q, R : ndarray
        Noise covariances of the discrete nominal model (for the intervals).
    dt : float
        Sampling period [s].
    x0 : ndarray, shape (nstates,)
        Initial state of the output-error simulation.
    k0 : int
        First sample of the output-error window.
    tau : float, optional
        Time constant [s] of the input's first-order lag (the start's scale).

    Returns
    -------
    SharedLaw2 or None
        None when the channel does not carry input j's whole effect or no stable
        law with determined terms is found.
    """
    c = input_scale(sys, channel, j)
    if c is None:
        return None
    tau = float(tau) if tau is not None and tau > 0 else float(np.sqrt(2.0 * 500.0)) * dt
    dv = ("u", j)
    bterms, eterms = [(0, dv), (1, dv)], [(0, dv)]
    args = (sys, channel, y, u, Q, R, dt, x0, k0)
    with single_thread_blas():
        prob = _Problem(sys, channel, y, u, dt, x0, k0, bterms, eterms, 0, order=2)
        ws = np.r_[np.array([1.0, 1.6, 2.5]) / tau, np.geomspace(0.01, 1.0, 9) * np.pi / dt]
        theta0 = lowest_start(prob.resid, [np.array([2 * z * w, w * w, 0.0, c * w * w, -c])
                                           for w in ws for z in (0.3, 0.5, 0.8)])
        fit = None if theta0 is None else _drop_weak(*args, bterms, eterms, 0, theta0)
    if fit is None:
        return None
    law = _law_from(sys, channel, *fit, Q, R)
    return replace(law, formula=law.formula + _reach2(sys, law, j, c))


def fit_hidden_part2(sys: ct.StateSpace, channel: Channel, y: NDArray, u: NDArray, *,
                     Q: NDArray, R: NDArray, dt: float, x0: NDArray, k0: int,
                     poles) -> SharedLaw2 | None:
    """A hidden second-order part attached to one body: a load behind a flexible shaft,
    a mass on a spring and damper, driven by the body's own state.

    The law of a one-component channel along one state equation x_j' with x_j (a
    velocity, a speed) its only driver, ``d = e x_j + (beta_1 s + beta_0)/(s^2 +
    alpha_1 s + alpha_0) x_j``: a hidden body coupled to x_j's body by a spring and
    a damper moves with the relative coordinate, whose rate is x_j minus its own
    speed, so x_j alone drives it. Fitted by output error on y from each pair of
    start ``poles`` (numerators and feedthrough from one Gauss-Newton step there,
    :func:`_template`); terms whose interval contains 0 are dropped; the sparsest
    fit within 1 % of the lowest output error is kept (:func:`_sparsest`).

    Parameters
    ----------
    sys : control.StateSpace
        Continuous nominal model.
    channel : Channel
        md = 1, kind "equation", one state's equation.
    y, u : ndarray, shapes (noutputs, nsteps), (ninputs, nsteps)
        The estimation record.
    Q, R : ndarray
        Noise covariances of the discrete nominal model (for the intervals).
    dt : float
        Sampling period [s].
    x0 : ndarray, shape (nstates,)
        Initial state of the output-error simulation.
    k0 : int
        First sample of the output-error window.
    poles : sequence of pairs of complex
        Continuous start poles [1/s] (a conjugate pair or two real poles each).

    Returns
    -------
    SharedLaw2 or None
        None for another channel, or when no stable law with determined terms is found.
    """
    eqs = [e for e in channel.equations if e in sys.state_labels]
    if channel.md != 1 or channel.kind != "equation" or len(eqs) != 1:
        return None
    own = [_driver_ref(sys)(eqs[0])]
    args = (sys, channel, y, u, Q, R, dt, x0, k0)
    fits = []
    with single_thread_blas():
        for p1, p2 in poles:
            alpha = np.real([-(p1 + p2), p1 * p2])
            if np.all(np.isfinite(alpha)) and np.all(alpha > 0):  # a stable start
                fits.append(_template(args, own, alpha, np.zeros(0), 0))
        fits.append(_mode_grid_fit(args, own, y.shape[1], dt))
    return _sparsest(sys, channel, fits, Q, R)


#: Natural frequencies of the mode grid: from ten periods over the record to 0.3 of
#: Nyquist, this many geometric steps (a lightly damped mode's output error has a
#: minimum per frequency; a start must lie within ~20 % of it, and the grid's step is
#: <= 1.4 over the range of a 4000-sample record), damping 0.1.
_GRID_POINTS, _GRID_ZETA = 16, 0.1


def _mode_grid_fit(args, own, nsamples, dt):
    """The template fitted from the lowest-output-error start of a grid of lightly damped
    modes, or None.

    The other starts (the unstructured law's poles, the first-order law's pole) miss
    a lightly damped hidden mode when its poles are not the unstructured law's: a
    flexible shaft's hidden load read through a law driven by V, i and om put its mode
    at 26.5 rad/s for a true 14.7 (zoo seed 5150, draw 1), and output error from there
    diverged. Each grid point costs one Gauss-Newton step (a few simulations)."""
    lo, hi = 20.0 * np.pi / (nsamples * dt), 0.3 * np.pi / dt
    if not hi > lo:
        return None
    starts = []
    for w in np.geomspace(lo, hi, _GRID_POINTS):
        s = _template_start(args, own, np.array([2.0 * _GRID_ZETA * w, w * w]), np.zeros(0),
                            0)
        if s is not None:
            starts.append(s)
    if not starts:
        return None
    best = lowest_start(lambda s: s[3].resid(s[2]), starts)
    if best is None:
        return None
    ob, oe, theta, _ = best
    return _drop_weak(*args, ob, oe, 0, theta, order=2)


def _reach2(sys, law: SharedLaw2, j: int, c: float) -> str:
    """"; F reaches the plant through ...": 1 + law / c of a second-order input law."""
    name = sys.input_labels[j]
    if list(law.drivers) != [name]:
        return ""
    a1, a0 = law.alpha
    b1, b0 = law.beta[:, 0]
    e = sum(v for _, nm, v in law.feedthrough if nm == name)
    k2, k1, k0 = 1 + e / c, a1 * (1 + e / c) + b1 / c, a0 * (1 + e / c) + b0 / c
    w = float(np.sqrt(a0)) if a0 > 0 else float("nan")
    def sgn(v):  # "+ 0.1" or "- 0.1", not "+ -0.1"
        return f"{'-' if v < 0 else '+'} {abs(v):.3g}"

    return (f"; {name} reaches the plant through ({k2:.3g} s^2 {sgn(k1)} s {sgn(k0)})/"
            f"(s^2 {sgn(a1)} s {sgn(a0)}): DC gain {k0 / a0:.3g}, natural frequency "
            f"{w:.3g} rad/s, damping {a1 / (2 * w):.3g}")


def _driver_ref(sys):
    """name -> ("x", state index) or ("u", input index) of ``sys``."""
    states, inputs = list(sys.state_labels), list(sys.input_labels)
    return lambda name: (("x", states.index(name)) if name in states else
                         ("u", inputs.index(name)))


def _template(args, own, alpha, kk, ref):
    """The template of a hidden part touching the bodies, fitted and pruned (or None).

    Driven by the bodies' states ``own`` in every numerator row, each component with
    its own state's feedthrough; numerators and feedthrough from one Gauss-Newton step
    at the start poles (the denominator ``alpha``), gains ``kk`` from the lower order.
    """
    start = _template_start(args, own, alpha, kk, ref)
    if start is None:
        return None
    ob, oe, theta, _ = start
    return _drop_weak(*args, ob, oe, ref, theta, order=alpha.size)


def _template_start(args, own, alpha, kk, ref):
    """``(bterms, eterms, theta, problem)`` of the template at the denominator ``alpha``:
    numerators and feedthrough from one Gauss-Newton step from 0; None when the step
    carries no signal."""
    sys, channel, y, u, _, _, dt, x0, k0 = args
    q = alpha.size
    ob = [(r, dv) for r in range(q) for dv in own]
    oe = list(enumerate(own))
    th = np.r_[alpha, np.zeros(len(ob)), kk, np.zeros(len(oe))]
    prob = _Problem(sys, channel, y, u, dt, x0, k0, ob, oe, ref, order=q)
    idx = list(range(q, q + len(ob))) + list(range(th.size - len(oe), th.size))
    step = _gauss_newton_step(prob, th, idx)
    if step is None:
        return None
    return ob, oe, step[1], prob


def _determined(p: float, h: float) -> bool:
    """Whether the real pole ``p`` [1/s] with 95 % half-width ``h`` is stable in its
    whole interval (a finite interval that does not reach 0)."""
    return bool(np.isfinite(h) and -p - h > 0)


def _sparsest(sys, channel, fits, Q, R):
    """The record of the fewest terms among the fits within 1 % of the lowest output error.

    The hidden part is defined up to z~ = z + c x_j (x_j's equation is known), and
    two starts can end in two realizations of one law, with different poles; the
    sparser is the physical one (the rule of the first-order shared law).
    """
    fits = [f for f in fits if f is not None]
    if not fits:
        return None
    rss = [float(np.sum(f[1].fun ** 2)) for f in fits]
    lo = min(rss)
    prob, sol, hw = min((f for f, r in zip(fits, rss) if r <= 1.01**2 * lo),
                        key=lambda f: (f[1].x.size, float(np.sum(f[1].fun ** 2))))
    return _law_from(sys, channel, prob, sol, hw, Q, R)


def _order3(sys, channel, law, y, u, Q, R, dt, x0, k0):
    """The third-order law from the second-order ``law``: its denominator and numerators
    times ``(s + p3)`` (an exact cancellation: the start is ``law``), p3 five times slower
    than the slowest pole, between the two (geometric mean) or five times faster than the
    fastest; every numerator row of every driver free from the start, then pruned. At
    each p3 also the template of a hidden chain touching the bodies (as for order 2):
    driven by the channel's own states, each component with its own state's feedthrough,
    numerators and feedthrough from one Gauss-Newton step at the start poles (the
    second-order law may have taken a proxy driver, an input for a state)."""
    drv = _driver_ref(sys)
    dl = [drv(nm) for nm in law.drivers]
    own = [drv(e) for e in channel.equations if e in sys.state_labels]
    eterms = [(c, drv(nm)) for c, nm, _ in law.feedthrough]
    ee = [v for _, _, v in law.feedthrough]
    kk = np.delete(law.k, law.reference)
    mag = np.abs(law.poles.real)
    bterms = [(r, dv) for r in range(3) for dv in dl]
    args = (sys, channel, y, u, Q, R, dt, x0, k0)
    fits = []
    with single_thread_blas():
        for p3 in (0.2 * mag.min(), float(np.sqrt(mag.min() * mag.max())), 5.0 * mag.max()):
            alpha = np.convolve(np.r_[1.0, law.alpha], [1.0, p3])[1:]
            num = np.array([np.convolve(law.beta[:, j], [1.0, p3]) for j in range(len(dl))])
            theta0 = np.r_[alpha, num.T.ravel(), kk, ee]
            fits.append(_drop_weak(*args, bterms, eterms, law.reference, theta0, order=3))
            if len(own) == channel.md and set(own) != set(dl):
                fits.append(_template(args, own, alpha, kk, law.reference))
    return _sparsest(sys, channel, fits, Q, R)


def _drop_weak(sys, channel, y, u, Q, R, dt, x0, k0, bterms, eterms, ref, theta0, order=2):
    """Fit; drop the term whose interval contains 0 by the widest margin; repeat.

    ``(problem, solution, half-widths)``, or None when the law is unstable,
    its intervals undefined, or a component's gain k_c is not told from 0.
    """
    md, q = channel.G.shape[1], order
    while True:
        prob = _Problem(sys, channel, y, u, dt, x0, k0, bterms, eterms, ref, order=q)
        sol = prob.fit(theta0)
        if not np.max(np.roots(np.r_[1.0, sol.x[:q]]).real) < 0:  # every pole stable
            return None
        hw = prob.halfwidths(sol, Q, R)
        if not np.all(np.isfinite(hw)):
            return None
        nb = len(bterms)
        # beta terms (while the subsystem keeps one) and feedthrough terms; k stays
        idx = ([q + j for j in range(nb)] if nb > 1 else []) + \
            list(range(q - 1 + nb + md, sol.x.size))
        weak = [i for i in idx if abs(sol.x[i]) < hw[i]]
        if not weak:
            break
        i = min(weak, key=lambda i: abs(sol.x[i]) / hw[i])
        if i < q + nb:
            bterms = bterms[:i - q] + bterms[i - q + 1:]
        else:
            j = i - (q - 1 + nb + md)
            eterms = eterms[:j] + eterms[j + 1:]
        theta0 = np.delete(sol.x, i)
    # unstable through the loop x -> z -> x: no law (as for the first-order shared law)
    lam0 = float(np.max(np.linalg.eigvals(prob.Ac).real, initial=0.0))
    if np.max(np.linalg.eigvals(prob.cont(sol.x)[0]).real) > lam0 + 1e-9 * (1 + abs(lam0)):
        return None
    nb = len(prob.bterms)
    k, hk = prob.split(sol.x)[2], np.insert(hw[q + nb:q - 1 + nb + md], ref, 0.0)
    if np.any(np.abs(k) < hk):
        return None
    return prob, sol, hw


def _pole_coords(alpha):
    """(poles, phi): real poles slowest first, then each complex pair (upper one first);
    phi the real coordinates: each real pole, then (real part, imaginary part) per pair."""
    p = np.roots(np.r_[1.0, np.asarray(alpha, dtype=float)])
    tol = 1e-9 * (1.0 + np.abs(p))
    real = np.sort(p[np.abs(p.imag) <= tol].real)[::-1]
    upper = sorted(p[p.imag > tol], key=lambda z: -z.real)
    poles = np.r_[real.astype(complex), [z for c in upper for z in (c, np.conj(c))]]
    phi = np.r_[real, [v for c in upper for v in (c.real, c.imag)]]
    return (poles.real if not upper else poles), phi, real.size


def _alpha_of(phi, nreal):
    """The denominator's coefficients (without the leading 1) of the pole coordinates."""
    pairs = [complex(a, b) for a, b in zip(phi[nreal::2], phi[nreal + 1::2])]
    roots = list(phi[:nreal]) + pairs + [np.conj(c) for c in pairs]
    return np.real(np.poly(roots))[1:]


def _pole_halfwidths(prob, sol, Q, R):
    """(poles, 95 % half-widths of each real pole and of (re, im) of each complex pair).

    The Jacobian in alpha is carried to the pole coordinates by the chain rule,
    d alpha / d phi by central differences of the polynomial's coefficients
    (for two real poles ``[[-1, -1], [p2, p1]]``).
    """
    q = prob.q
    poles, phi, nreal = _pole_coords(sol.x[:q])
    M = np.empty((q, q))
    for j in range(q):
        h = 1e-6 * max(1.0, abs(phi[j]))
        e = np.zeros(q)
        e[j] = h
        M[:, j] = (_alpha_of(phi + e, nreal) - _alpha_of(phi - e, nreal)) / (2 * h)
    jac = np.array(sol.jac, dtype=float, copy=True)
    jac[:, :q] = jac[:, :q] @ M
    hp = prob.halfwidths(sol, Q, R, jac=jac)[:q]
    return poles, hp


def _z_names(sys, q=2) -> tuple[str, ...]:
    """Names of the q law states: the first q free ``z[k]``."""
    return tuple(free_state_names(sys.state_labels, q))


def _and(items):
    """``a``, ``a and b``, ``a, b and c``."""
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def _law_from(sys, channel, prob, sol, hw, Q, R) -> SharedLaw2:
    """The SharedLaw2 record at the solution ``sol`` with half-widths ``hw``."""
    md, dt, q = prob.md, prob.dt, prob.q
    theta = sol.x
    alpha, beta, k, e = prob.split(theta)
    nb = len(prob.bterms)
    hb = hw[q:q + nb]
    hk = np.insert(hw[q + nb:q - 1 + nb + md], prob.ref, np.nan)
    he = hw[q - 1 + nb + md:]
    poles, hp = _pole_halfwidths(prob, sol, Q, R)
    r = prob.resid(theta).reshape(prob.y.shape[0], -1)
    se = float(100 * np.mean(np.sqrt(np.mean(r**2, axis=1))))
    zn = _z_names(sys, q)
    lines, unit = _component_lines(sys, channel, prob.ref, zn[0], k, hk, prob.eterms, e, he)
    dnames, dlist = [], []
    for _, dv in prob.bterms:
        if dv not in dlist:
            dlist.append(dv)
            dnames.append(_driver_name(sys, dv))
    Bq = np.zeros((q, len(dlist)))
    Hq = np.full((q, len(dlist)), np.nan)
    for (row, dv), bv, hv in zip(prob.bterms, beta, hb):
        Bq[row, dlist.index(dv)], Hq[row, dlist.index(dv)] = bv, hv

    def power(r):
        return {0: "", 1: " s"}.get(r, f" s^{r}")

    den = "(s^" + str(q) + "".join(f" + {alpha[r]:.3g}{power(q - 1 - r)}" for r in range(q)) + ")"
    zparts = []
    for j, nm in enumerate(dnames):
        num = [f"{_pm(Bq[r, j], Hq[r, j])}{power(q - 1 - r)}" for r in range(q) if Bq[r, j] != 0]
        one = len(num) == 1 and not num[0].endswith("s") and " s^" not in num[0]
        zparts.append(f"{num[0]}/{den}*{nm}" if one else f"({' + '.join(num)})/{den}*{nm}")
    formula = "; ".join(lines) + f"; {zn[0]} = " + " + ".join(zparts) + unit(prob.ref)
    taus = np.full(q, np.nan)
    nreal = int(np.sum(np.isreal(poles)))
    pr = poles[:nreal].real
    taus[:nreal] = -1.0 / pr
    desc = []
    for p, h in zip(pr, hp[:nreal]):
        lo, hi = -p - h, -p + h
        span = (f" (95 %: {1 / hi:.3g} .. {1 / lo:.3g} s)" if _determined(p, h)
                else " (not determined by the data)")
        desc.append(f"{-1 / p:.3g} s{span}")
    parts = []
    if nreal:
        parts.append(f"{_and([_pm(p, h) for p, h in zip(pr, hp[:nreal])])} 1/s, time "
                     f"constant{'s' if nreal > 1 else ''} {_and(desc)}")
    for c in range(nreal, q, 2):
        pc = poles[c]
        re_, im_ = (_pm(v, h) for v, h in ((pc.real, hp[c]), (pc.imag, hp[c + 1])))
        re_, im_ = (t if t.startswith("(") else f"({t})" for t in (re_, im_))  # once
        parts.append(f"{re_} ± j{im_} 1/s (natural "
                     f"frequency {abs(pc):.3g} rad/s, damping {-pc.real / abs(pc):.3g})")
    formula += ", poles " + " and ".join(parts)
    formula += (f" (one {'second' if q == 2 else 'third'}-order subsystem shared by "
                f"{', '.join(channel.labels)})" if md > 1 else "")
    model, cont = _augmented_models(sys, *prob.cont(theta), dt, Q, R, list(zn))
    Bz, E = prob.rows(theta)
    feed = tuple((int(c), _driver_name(sys, dv), float(ec)) for (c, dv), ec in zip(prob.eterms, e))
    return SharedLaw2(order=q, poles=poles, pole_ci=np.asarray(hp), taus=taus,
                      alpha=np.array(alpha), states=zn, drivers=tuple(dnames), beta=Bq,
                      k=np.array(k), reference=prob.ref, feedthrough=feed, Bz=Bz, E=E,
                      ci=np.asarray(hw), npar=int(theta.size), formula=formula, model=model,
                      se_estimation=se, continuous=cont, dt=dt)
