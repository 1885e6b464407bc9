"""How a continuous-time law is integrated over one sample of a discrete model.

A static law ``f(x, u)`` found on a continuous model enters as
``dx/dt = Ac x + Bc u + Gc f(x, u)`` with the input held over the sample (ZOH
data). The discrete model's ``A = expm(Ac dt)`` and ``B`` carry the linear part
exactly; only the law's integral over the sample is approximated.
:class:`LawHold` does it with the fourth-order exponential Runge-Kutta scheme
of Cox & Matthews (ETDRK4; J. Comput. Phys. 176, 2002, eq. 26) in the
phi-function form of Hochbruck & Ostermann (Acta Numerica 19, 2010), four law
evaluations per sample. The first-order hold of the law with a Heun step
(two evaluations, second order), which greybox used before, left a simulation
error of 0.86-1.84 % on three zoo draws sampled at 0.17-0.24 of the fastest
mode's period over 2 pi (the measurement noise there: 0.12-0.52 %); the same
laws by ETDRK4: 0.002-0.04 % (``bench/RESULTS_zoo.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import expm

__all__ = ["LawHold", "as_hold", "first_order_hold"]


def _phi_blocks(Ac: NDArray, Gc: NDArray, h: float) -> tuple[NDArray, ...]:
    """``(expm(Ac h), h phi1 Gc, h phi2 Gc, h phi3 Gc)`` with ``phi_k(Ac h)`` (one expm)."""
    n, md = Gc.shape
    M = np.zeros((n + 3 * md, n + 3 * md))
    M[:n, :n], M[:n, n:n + md] = Ac * h, Gc * h
    M[n:n + md, n + md:n + 2 * md] = np.eye(md)
    M[n + md:n + 2 * md, n + 2 * md:] = np.eye(md)
    E = expm(M)
    return E[:n, :n], E[:n, n:n + md], E[:n, n + md:n + 2 * md], E[:n, n + 2 * md:]


def first_order_hold(Ac: ArrayLike, Gc: ArrayLike, dt: float
                     ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(Gamma0, Gamma1)`` of ``x[k+1] = A x + Gamma0 d[k] + Gamma1 d[k+1]`` (first-order hold).

    Parameters
    ----------
    Ac : array_like, shape (nstates, nstates)
        Continuous-time state matrix.
    Gc : array_like, shape (nstates, md)
        Continuous-time input matrix of d.
    dt : float
        Sampling period [s].

    Returns
    -------
    Gamma0, Gamma1 : ndarray, shape (nstates, md)
        Weights of d[k] and d[k+1] when d(t) is linear between the samples.
    """
    Ac = np.asarray(Ac, dtype=float)
    _, p1, p2, _ = _phi_blocks(Ac, np.asarray(Gc, dtype=float).reshape(Ac.shape[0], -1), dt)
    return p1 - p2, p2


@dataclass(frozen=True, eq=False)
class LawHold:
    """A continuous-time law integrated over each sample of a discrete model.

    Attributes
    ----------
    G0, G1 : ndarray, shape (nstates, md)
        First-order-hold weights over one sample: ``x[k+1] = A x + B u +
        G0 f[k] + G1 f[k+1]`` when f is linear in time between the samples
        (the law's linear stand-in and its noise model use these).
    E2 : ndarray, shape (nstates, nstates), or None
        ``expm(Ac dt/2)``; None for a hold given by ``(G0, G1)`` only, which
        is then integrated by the Heun step (second order).
    P2 : ndarray, shape (nstates, md), or None
        ``(dt/2) phi1(Ac dt/2) Gc``: the law's weight over half a sample.
    W : ndarray, shape (nstates, nstates), or None
        ``(E2 + I)^-1``: maps the input's effect over a sample ``B u`` to its
        effect over half of it (``dt phi1(Ac dt) = (E2 + I) (dt/2) phi1(Ac dt/2)``).
    F1, F23, F4 : ndarray, shape (nstates, md), or None
        ETDRK4's weights of the four stages' law values over a sample.
    substeps : int
        ETDRK4 steps per sample (the input held): a law faster than a sample (a
        friction's sign smoothed over a narrow width) is integrated over
        ``dt / substeps``; ``E2, P2, W, F1, F23, F4`` are then those of one sub-step
        (``G0, G1`` stay the whole sample's first-order hold).
    Ah : ndarray, shape (nstates, nstates), or None
        ``expm(Ac dt / substeps)`` (substeps > 1).
    Ws : ndarray, shape (nstates, nstates), or None
        Maps the input's effect over a sample ``B u`` to its effect over one sub-step
        (``B u = (I + Ah + ... + Ah^(s-1)) Ws B u``; substeps > 1).
    Ac, Gc, dt
        What the hold was built from (None for a hold given by ``(G0, G1)``): another
        sub-step count is built from them (:meth:`with_substeps`).
    """

    G0: NDArray[np.float64]
    G1: NDArray[np.float64]
    E2: NDArray[np.float64] | None = None
    P2: NDArray[np.float64] | None = None
    W: NDArray[np.float64] | None = None
    F1: NDArray[np.float64] | None = None
    F23: NDArray[np.float64] | None = None
    F4: NDArray[np.float64] | None = None
    substeps: int = 1
    Ah: NDArray[np.float64] | None = None
    Ws: NDArray[np.float64] | None = None
    Ac: NDArray[np.float64] | None = None
    Gc: NDArray[np.float64] | None = None
    dt: float = 0.0

    @classmethod
    def of(cls, Ac: ArrayLike, Gc: ArrayLike, dt: float, substeps: int = 1) -> LawHold:
        """The hold of a law entering ``dx/dt = Ac x + ... + Gc f`` sampled every ``dt`` [s].

        Parameters
        ----------
        Ac : array_like, shape (nstates, nstates)
            Continuous-time state matrix.
        Gc : array_like, shape (nstates, md)
            How the law enters the continuous state equations.
        dt : float
            Sampling period [s].
        substeps : int
            ETDRK4 steps per sample (1: one step over the sample).

        Returns
        -------
        LawHold
            With the ETDRK4 matrices; only ``G0, G1`` (the Heun step) where ``expm(Ac
            h/2) + I`` is singular (an undamped mode at an odd multiple of pi/h, h the
            step).
        """
        Ac = np.asarray(Ac, dtype=float)
        Gc = np.asarray(Gc, dtype=float).reshape(Ac.shape[0], -1)
        s = max(1, int(substeps))
        h = dt / s
        E2, P2, _, _ = _phi_blocks(Ac, Gc, h / 2)
        _, p1, p2, p3 = _phi_blocks(Ac, Gc, dt)  # the whole sample's first-order hold
        g0, g1, built = p1 - p2, p2, {"Ac": Ac, "Gc": Gc, "dt": float(dt)}
        if s > 1:  # ETDRK4's weights over one sub-step, and its state step
            Ah, p1, p2, p3 = _phi_blocks(Ac, Gc, h)
        I = np.eye(Ac.shape[0])
        if np.linalg.cond(E2 + I) > 1e12:  # a mode at an odd multiple of pi/h: aliased
            return cls(G0=g0, G1=g1)  # the Heun step of the first-order hold
        W = np.linalg.solve(E2 + I, I)
        sub = {}
        if s > 1:
            S = I.copy()
            P = I.copy()
            for _ in range(s - 1):
                P = P @ Ah
                S += P
            sub = {"substeps": s, "Ah": Ah, "Ws": np.linalg.solve(S, I)}
        return cls(G0=g0, G1=g1, E2=E2, P2=P2, W=W, F1=p1 - 3 * p2 + 4 * p3,
                   F23=2 * p2 - 4 * p3, F4=4 * p3 - p2, **sub, **built)

    def with_substeps(self, substeps: int) -> LawHold:
        """The same hold integrated in ``substeps`` ETDRK4 steps per sample (itself where
        that is its count already, or where it cannot be rebuilt: a ``(G0, G1)`` hold)."""
        s = max(1, int(substeps))
        if s == self.substeps or self.Ac is None or self.E2 is None:
            return self
        return LawHold.of(self.Ac, self.Gc, self.dt, s)

    def substeps_for(self, rate: float) -> int:
        """Sub-steps that keep ``rate * dt / substeps`` at most :data:`STEP_RATE` (at most
        :data:`MAX_SUBSTEPS`): ``rate`` [1/s] bounds the law's own speed (how fast its
        terms change the states they read, :meth:`greybox.trace.laws.StaticLaw.rate`)."""
        if not (self.dt > 0 and np.isfinite(rate) and rate > 0):
            return 1
        return int(min(MAX_SUBSTEPS, max(1, np.ceil(rate * self.dt / STEP_RATE))))

    def columns(self, keep) -> LawHold:
        """The hold of the law's components ``keep`` alone: the columns of its (nstates,
        md) weights (each is its component's column of Gc mapped by the same matrix
        function of Ac), ``E2`` and ``W`` unchanged."""
        keep = list(keep)

        def pick(M):
            return None if M is None else np.asarray(M)[:, keep]

        return replace(self, G0=pick(self.G0), G1=pick(self.G1), P2=pick(self.P2),
                       F1=pick(self.F1), F23=pick(self.F23), F4=pick(self.F4),
                       Gc=pick(self.Gc))

    def step(self, A: NDArray, X: NDArray, bu: NDArray,
             f: Callable[[NDArray], NDArray]) -> NDArray[np.float64]:
        """The states one sample on, for the states in the columns of X.

        Parameters
        ----------
        A : ndarray, shape (nstates, nstates)
            The discrete model's state matrix (``expm(Ac dt)``).
        X : ndarray, shape (nstates, K)
            States at sample k (K trajectories at once).
        bu : ndarray, shape (nstates, 1) or (nstates, K)
            The known inputs' effect over the sample, ``B u[k]``.
        f : callable
            ``f(X) -> (md, K)``: the law at states X and the held input u[k].

        Returns
        -------
        ndarray, shape (nstates, K)
        """
        X = np.asarray(X, dtype=float)
        if X.ndim != 2:
            raise ValueError(f"X must be (nstates, K); found shape {X.shape}")
        bu = np.asarray(bu, dtype=float).reshape(X.shape[0], -1)
        if self.substeps > 1:  # the input held: its effect over a sub-step is Ws B u
            bh = self.Ws @ bu
            for _ in range(self.substeps):
                X = self._step(self.Ah, X, bh, f)
            return X
        return self._step(A, X, bu, f)

    def _step(self, A, X, bu, f):
        """One step of :meth:`step` (over a sub-step, A and bu being the sub-step's)."""
        fx = f(X)
        if self.E2 is None:  # (G0, G1) only: Heun, the predictor holds f over the sample
            base = A @ X + bu
            return base + self.G0 @ fx + self.G1 @ f(base + (self.G0 + self.G1) @ fx)
        bh = self.W @ bu
        half = self.E2 @ X + bh
        a = half + self.P2 @ fx
        fa = f(a)
        fb = f(half + self.P2 @ fa)
        fc = f(self.E2 @ a + bh + self.P2 @ (2 * fb - fx))
        return A @ X + bu + self.F1 @ fx + self.F23 @ (fa + fb) + self.F4 @ fc


#: A law integrated over each sample is stepped so that its own rate times the step is
#: at most this (ETDRK4 treats the law explicitly: its stability on a decaying mode ends
#: near 2.8, and its local error at 0.5 is ~(0.5)^5 / 120, 3e-4 of the step's change)
STEP_RATE = 0.5
#: At most this many sub-steps per sample (each costs four evaluations of the law)
MAX_SUBSTEPS = 32


def as_hold(hold) -> LawHold | None:
    """A :class:`LawHold` (or None) from a LawHold, None or a ``(Gamma0, Gamma1)`` pair."""
    if hold is None or isinstance(hold, LawHold):
        return hold
    G0, G1 = (np.asarray(g, dtype=float) for g in hold)
    return LawHold(G0=G0.reshape(G0.shape[0], -1), G1=G1.reshape(G1.shape[0], -1))
