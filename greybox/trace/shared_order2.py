"""One second-order hidden subsystem shared by several state equations.

A hidden chain of two lumped parts behind the bodies whose equations it
enters (two thermal masses in series, a flexible part with its own mode) is
one second-order subsystem whose output drives md >= 2 equations along no
fixed direction. In the observer canonical form (unique for an observable
law: the two poles and the zeros are read off it)

.. math::

    \\dot z_1 = -\\alpha_1 z_1 + z_2 + \\sum_i \\beta_{1,i} w_i, \\qquad
    \\dot z_2 = -\\alpha_0 z_1 + \\sum_i \\beta_{0,i} w_i,

    d_c = k_c z_1 + \\sum_{i \\in S_c} e_{c,i} w_i, \\qquad k_r = 1,
    \\qquad w = [x; u],

so ``z_1 = sum_i (beta_1i s + beta_0i) / (s^2 + alpha_1 s + alpha_0) w_i``.
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
sparser is the physical one). The workflow offers it beside the first-order law and
chooses between them with the same rule as between all candidates (the fewest
parameters within the parsimony margin of the lowest estimation SE).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace

import control as ct
import numpy as np
from numpy.typing import NDArray

from .._blas import single_thread_blas
from .._lti import lti_states
from ..update import UpdatedModel, free_state_names
from .channels import Channel
from .dynamic import SharedLaw, _augmented_models, _component_lines, _driver_name, \
    _gauss_newton_step, _pm, driver_weights
from .oe import oe_window, robust_halfwidths, scaled_output_error, zoh

__all__ = ["SharedLaw2", "fit_shared_order2"]


@dataclass(frozen=True)
class SharedLaw2:
    """One second-order subsystem shared by the md components of a channel (module docstring).

    Attributes
    ----------
    order : int
        2.
    poles : ndarray, shape (2,)
        Poles of the subsystem [1/s] (complex for an oscillating mode).
    pole_ci : ndarray, shape (2,)
        95 % half-widths of the two real poles, or of (real part, imaginary
        part) of a complex pair [1/s].
    taus : ndarray, shape (2,)
        Time constants -1/p [s] of real poles (NaN for a complex pair).
    alpha : ndarray, shape (2,)
        (alpha_1, alpha_0): the denominator ``s^2 + alpha_1 s + alpha_0``.
    states : tuple of str
        Names of the two law states (``z[0]``, ``z[1]``); ``z[0]`` has the
        units of the reference component's d.
    drivers : tuple of str
        Names of the signals driving the subsystem.
    beta : ndarray, shape (2, len(drivers))
        Numerator gains (beta_1, beta_0) per driver (0 where dropped).
    k : ndarray, shape (md,)
        Gain of ``z[0]`` in each component (``k[reference] = 1``).
    reference : int
        The component whose gain is fixed to 1.
    feedthrough : tuple of (int, str, float)
        Feedthrough terms ``(component, driver name, e_{c,i})``.
    Bz : ndarray, shape (2, nstates + ninputs)
        The subsystem's input rows over ``[x; u]``.
    E : ndarray, shape (md, nstates + ninputs)
        Feedthrough over ``[x; u]``: ``d = k z_1 + E @ w``.
    ci : ndarray, shape (npar,)
        95 % half-widths of (alpha_1, alpha_0, beta terms, k without the
        reference, e) in that order.
    npar : int
        Number of coefficients.
    formula : str
        Readable law with intervals, poles and time constants.
    model : UpdatedModel
        The nominal model augmented with the two states, discretized exactly.
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
    states: tuple[str, str]
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

    def evaluate(self, x: NDArray, u: NDArray) -> NDArray[np.float64]:
        """The law's d, shape (md, K), on x (nstates, K) and u (ninputs, K).

        ``z`` starts at 0 and follows the ZOH-discretized subsystem.
        """
        w = np.vstack([x, u])
        Az = np.array([[-self.alpha[0], 1.0], [-self.alpha[1], 0.0]])
        Phi, Gam = zoh(Az, np.eye(2), self.dt)
        z = lti_states(Phi, Gam @ (self.Bz @ w), np.zeros(2))
        return self.k[:, None] * z[0][None, :] + self.E @ w


class _Problem:
    """Output error on y of ``[x; z1; z2]`` with the law folded in continuous time.

    ``theta = (alpha_1, alpha_0, beta over bterms, k without the reference, e over
    eterms)``; ``bterms`` are pairs (row 0 for beta_1 or 1 for beta_0, driver),
    ``eterms`` pairs (component, driver).
    """

    def __init__(self, sys, channel, y, u, dt, x0, k0, bterms, eterms, ref):
        self.Ac, self.Bc = np.asarray(sys.A, dtype=float), np.asarray(sys.B, dtype=float)
        self.C, self.D = np.asarray(sys.C, dtype=float), np.asarray(sys.D, dtype=float)
        self.G = np.asarray(channel.G, dtype=float)
        self.n, self.m, self.md, self.dt, self.ref = self.Ac.shape[0], self.Bc.shape[1], \
            self.G.shape[1], dt, ref
        win = oe_window(y.shape[0])
        self.y, self.u, self.k0 = y[:, :k0 + win], u[:, :k0 + win], k0
        self.x0 = np.r_[x0, 0.0, 0.0]
        self.scale = np.sqrt(np.mean(self.y[:, k0:] ** 2, axis=1)) + 1e-300
        self.bterms, self.eterms = list(bterms), list(eterms)
        self.Wb = driver_weights([dv for _, dv in self.bterms], self.n, self.m)
        self.We = driver_weights([dv for _, dv in self.eterms], self.n, self.m)
        self.Ca = np.hstack([self.C, np.zeros((self.C.shape[0], 2))])

    def split(self, theta):
        """(alpha (2,), beta values, k with the reference's 1, e values)."""
        nb, md = len(self.bterms), self.md
        k = np.insert(theta[2 + nb:1 + nb + md], self.ref, 1.0)
        return theta[:2], theta[2:2 + nb], k, theta[1 + nb + md:]

    def rows(self, theta):
        """(Bz (2, n + m), E (md, n + m)) at ``theta``."""
        _, beta, _, e = self.split(theta)
        Bz = np.zeros((2, self.n + self.m))
        for (r, _), bv, wq in zip(self.bterms, beta, self.Wb):
            Bz[r] += bv * wq
        E = np.zeros((self.md, self.n + self.m))
        for (c, _), ev, wq in zip(self.eterms, e, self.We):
            E[c] += ev * wq
        return Bz, E

    def cont(self, theta):
        n = self.n
        alpha, _, k, _ = self.split(theta)
        Bz, E = self.rows(theta)
        A = np.zeros((n + 2, n + 2))
        A[:n, :n] = self.Ac + self.G @ E[:, :n]
        A[:n, n] = self.G @ k
        A[n:, :n] = Bz[:, :n]
        A[n, n], A[n, n + 1], A[n + 1, n] = -alpha[0], 1.0, -alpha[1]
        B = np.vstack([self.Bc + self.G @ E[:, n:], Bz[:, n:]])
        return A, B

    def resid(self, theta):
        Ad, Bd = zoh(*self.cont(theta), self.dt)
        return scaled_output_error(Ad, Bd, self.Ca, self.D, self.y, self.u, self.x0, self.k0,
                                   self.scale)

    def fit(self, theta0):
        from scipy.optimize import least_squares

        return least_squares(self.resid, theta0, method="lm", x_scale="jac", max_nfev=150)

    def halfwidths(self, sol, Q, R, jac=None):
        n = self.n
        Qa = np.zeros((n + 2, n + 2))
        Qa[:n, :n] = Q
        s = sol if jac is None else SimpleNamespace(jac=jac, fun=sol.fun, x=sol.x)
        Ad = zoh(*self.cont(sol.x), self.dt)[0]
        return robust_halfwidths(s, self.y.shape[0], Ad, self.Ca, self.scale, self.k0, Qa, R)


def fit_shared_order2(sys: ct.StateSpace, channel: Channel, law: SharedLaw, y: NDArray,
                      u: NDArray, *, Q: NDArray, R: NDArray, dt: float, x0: NDArray,
                      k0: int) -> SharedLaw2 | None:
    """Fit one second-order subsystem shared by an md >= 2 channel, from its first-order law.

    Parameters
    ----------
    sys : control.StateSpace
        Continuous nominal model.
    channel : Channel
        The channel of ``law`` (md >= 2).
    law : SharedLaw
        The first-order shared law of the channel (drivers, gains, feedthrough
        and pole of the start).
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
        None when no stable second-order law with determined gains is found.
    """
    if channel.md < 2 or law.k.size != channel.md:
        return None
    states, inputs = list(sys.state_labels), list(sys.input_labels)

    def drv(name):
        return ("x", states.index(name)) if name in states else ("u", inputs.index(name))

    # the first-order law's drivers and feedthrough, and the states of the channel's own
    # equations (a hidden part exchanging with the bodies it touches: the first-order law
    # can have kept a proxy, e.g. an input's lag for a state's), the latter from 0
    own = [drv(e) for e in channel.equations if e in states]
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
            if len(own) != channel.md:
                continue
            # the template of a hidden part touching the bodies: driven by their states,
            # each component with its own state's feedthrough; numerators and feedthrough
            # from one Gauss-Newton step at the start poles
            ob = [(0, dv) for dv in own] + [(1, dv) for dv in own]
            oe = list(enumerate(own))
            th = np.r_[-(a + p2), a * p2, np.zeros(len(ob)), kk, np.zeros(len(oe))]
            prob = _Problem(sys, channel, y, u, dt, x0, k0, ob, oe, law.reference)
            idx = list(range(2, 2 + len(ob))) + list(range(th.size - len(oe), th.size))
            step = _gauss_newton_step(prob, th, idx)
            if step is not None:
                fits.append(_drop_weak(*args, ob, oe, law.reference, step[1]))
        fits = [f for f in fits if f is not None]
        if not fits:
            return None
        # the fewest terms among the fits within 1 % of the lowest output error: the
        # hidden part is defined up to z~ = z + c x_j (x_j's equation is known), and two
        # starts can end in two realizations of one law, with different poles; the
        # sparser is the physical one (the rule of the first-order shared law)
        rss = [float(np.sum(f[1].fun ** 2)) for f in fits]
        lo = min(rss)
        prob, sol, hw = min((f for f, r in zip(fits, rss) if r <= 1.01**2 * lo),
                            key=lambda f: (f[1].x.size, float(np.sum(f[1].fun ** 2))))
        return _law_from(sys, channel, prob, sol, hw, Q, R)


def _drop_weak(sys, channel, y, u, Q, R, dt, x0, k0, bterms, eterms, ref, theta0):
    """Fit; drop the term whose interval contains 0 by the widest margin; repeat.

    ``(problem, solution, half-widths)``, or None when the law is unstable,
    its intervals undefined, or a component's gain k_c is not told from 0.
    """
    md = channel.G.shape[1]
    while True:
        prob = _Problem(sys, channel, y, u, dt, x0, k0, bterms, eterms, ref)
        sol = prob.fit(theta0)
        if not (sol.x[0] > 0 and sol.x[1] > 0):  # both poles in the left half-plane
            return None
        hw = prob.halfwidths(sol, Q, R)
        if not np.all(np.isfinite(hw)):
            return None
        nb = len(bterms)
        # beta terms (while the subsystem keeps one) and feedthrough terms; k stays
        idx = ([2 + q for q in range(nb)] if nb > 1 else []) + \
            list(range(1 + nb + md, sol.x.size))
        weak = [i for i in idx if abs(sol.x[i]) < hw[i]]
        if not weak:
            break
        i = min(weak, key=lambda i: abs(sol.x[i]) / hw[i])
        if i < 2 + nb:
            bterms = bterms[:i - 2] + bterms[i - 1:]
        else:
            q = i - (1 + nb + md)
            eterms = eterms[:q] + eterms[q + 1:]
        theta0 = np.delete(sol.x, i)
    # unstable through the loop x -> z -> x: no law (as for the first-order shared law)
    lam0 = float(np.max(np.linalg.eigvals(prob.Ac).real, initial=0.0))
    if np.max(np.linalg.eigvals(prob.cont(sol.x)[0]).real) > lam0 + 1e-9 * (1 + abs(lam0)):
        return None
    nb = len(prob.bterms)
    k, hk = prob.split(sol.x)[2], np.insert(hw[2 + nb:1 + nb + md], ref, 0.0)
    if np.any(np.abs(k) < hk):
        return None
    return prob, sol, hw


def _pole_halfwidths(prob, sol, Q, R):
    """(poles, 95 % half-widths of the real poles or of (re, im) of a complex pair).

    The Jacobian in (alpha_1, alpha_0) is carried to the poles by the chain
    rule: ``alpha_1 = -(p1 + p2), alpha_0 = p1 p2`` (real) or ``alpha_1 = -2 s,
    alpha_0 = s^2 + w^2`` for ``p = s +- j w``.
    """
    a1, a0 = sol.x[:2]
    disc = a1 * a1 - 4.0 * a0
    if disc > 0:
        r = np.sqrt(disc)
        p = np.array([(-a1 + r) / 2, (-a1 - r) / 2])  # slow pole first
        M = np.array([[-1.0, -1.0], [p[1], p[0]]])
    else:
        s, w = -a1 / 2, np.sqrt(max(-disc, 0.0)) / 2
        p = np.array([s + 1j * w, s - 1j * w])
        M = np.array([[-2.0, 0.0], [2 * s, 2 * w]])
    jac = np.array(sol.jac, dtype=float, copy=True)
    jac[:, :2] = jac[:, :2] @ M
    hp = prob.halfwidths(sol, Q, R, jac=jac)[:2]
    return p, hp


def _z_names(sys) -> tuple[str, str]:
    """Names of the two law states: the first two free ``z[k]``."""
    return tuple(free_state_names(sys.state_labels, 2))


def _law_from(sys, channel, prob, sol, hw, Q, R) -> SharedLaw2:
    """The SharedLaw2 record at the solution ``sol`` with half-widths ``hw``."""
    md, dt = prob.md, prob.dt
    theta = sol.x
    alpha, beta, k, e = prob.split(theta)
    nb = len(prob.bterms)
    hb = hw[2:2 + nb]
    hk = np.insert(hw[2 + nb:1 + nb + md], prob.ref, np.nan)
    he = hw[1 + nb + md:]
    poles, hp = _pole_halfwidths(prob, sol, Q, R)
    r = prob.resid(theta).reshape(prob.y.shape[0], -1)
    se = float(100 * np.mean(np.sqrt(np.mean(r**2, axis=1))))
    z0, z1 = _z_names(sys)
    lines, unit = _component_lines(sys, channel, prob.ref, z0, k, hk, prob.eterms, e, he)
    dnames, dlist = [], []
    for _, dv in prob.bterms:
        if dv not in dlist:
            dlist.append(dv)
            dnames.append(_driver_name(sys, dv))
    B2 = np.zeros((2, len(dlist)))
    H2 = np.full((2, len(dlist)), np.nan)
    for (row, dv), bv, hv in zip(prob.bterms, beta, hb):
        B2[row, dlist.index(dv)], H2[row, dlist.index(dv)] = bv, hv
    den = f"(s^2 + {alpha[0]:.3g} s + {alpha[1]:.3g})"
    zparts = []
    for q, nm in enumerate(dnames):
        num = [f"{_pm(B2[0, q], H2[0, q])} s" if B2[0, q] != 0 else "",
               _pm(B2[1, q], H2[1, q]) if B2[1, q] != 0 else ""]
        zparts.append(f"({' + '.join(s for s in num if s)})/{den}*{nm}")
    formula = "; ".join(lines) + f"; {z0} = " + " + ".join(zparts) + unit(prob.ref)
    taus = np.full(2, np.nan)
    if np.all(np.isreal(poles)):
        pr = poles.real
        taus = -1.0 / pr
        desc = []
        for p, h in zip(pr, hp):
            lo, hi = -p - h, -p + h
            span = (f" (95 %: {1 / hi:.3g} .. {1 / lo:.3g} s)" if np.isfinite(h) and lo > 0
                    else " (not determined by the data)")
            desc.append(f"{-1 / p:.3g} s{span}")
        formula += (f", poles {_pm(pr[0], hp[0])} and {_pm(pr[1], hp[1])} 1/s, time constants "
                    f"{desc[0]} and {desc[1]}")
    else:
        formula += (f", poles ({_pm(poles[0].real, hp[0])}) ± j({_pm(poles[0].imag, hp[1])}) "
                    f"1/s (natural frequency {abs(poles[0]):.3g} rad/s, damping "
                    f"{-poles[0].real / abs(poles[0]):.3g})")
    formula += f" (one second-order subsystem shared by {', '.join(channel.labels)})"
    model, cont = _augmented_models(sys, *prob.cont(theta), dt, Q, R, [z0, z1])
    Bz, E = prob.rows(theta)
    feed = tuple((int(c), _driver_name(sys, dv), float(ec)) for (c, dv), ec in zip(prob.eterms, e))
    return SharedLaw2(order=2, poles=poles, pole_ci=np.asarray(hp), taus=taus,
                      alpha=np.array(alpha), states=(z0, z1), drivers=tuple(dnames), beta=B2,
                      k=np.array(k), reference=prob.ref, feedthrough=feed, Bz=Bz, E=E,
                      ci=np.asarray(hw), npar=int(theta.size), formula=formula, model=model,
                      se_estimation=se, continuous=cont, dt=dt)
