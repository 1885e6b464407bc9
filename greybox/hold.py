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
    """

    G0: NDArray[np.float64]
    G1: NDArray[np.float64]
    E2: NDArray[np.float64] | None = None
    P2: NDArray[np.float64] | None = None
    W: NDArray[np.float64] | None = None
    F1: NDArray[np.float64] | None = None
    F23: NDArray[np.float64] | None = None
    F4: NDArray[np.float64] | None = None

    @classmethod
    def of(cls, Ac: ArrayLike, Gc: ArrayLike, dt: float) -> LawHold:
        """The hold of a law entering ``dx/dt = Ac x + ... + Gc f`` sampled every ``dt`` [s].

        Parameters
        ----------
        Ac : array_like, shape (nstates, nstates)
            Continuous-time state matrix.
        Gc : array_like, shape (nstates, md)
            How the law enters the continuous state equations.
        dt : float
            Sampling period [s].

        Returns
        -------
        LawHold
            With the ETDRK4 matrices; only ``G0, G1`` (the Heun step) where ``expm(Ac
            dt/2) + I`` is singular (an undamped mode at an odd multiple of pi/dt).
        """
        Ac = np.asarray(Ac, dtype=float)
        Gc = np.asarray(Gc, dtype=float).reshape(Ac.shape[0], -1)
        E2, P2, _, _ = _phi_blocks(Ac, Gc, dt / 2)
        _, p1, p2, p3 = _phi_blocks(Ac, Gc, dt)
        I = np.eye(Ac.shape[0])
        if np.linalg.cond(E2 + I) > 1e12:  # a mode at an odd multiple of pi/dt: aliased
            return cls(G0=p1 - p2, G1=p2)  # the Heun step of the first-order hold
        W = np.linalg.solve(E2 + I, I)
        return cls(G0=p1 - p2, G1=p2, E2=E2, P2=P2, W=W, F1=p1 - 3 * p2 + 4 * p3,
                   F23=2 * p2 - 4 * p3, F4=4 * p3 - p2)

    def columns(self, keep) -> LawHold:
        """The hold of the law's components ``keep`` alone: the columns of its (nstates,
        md) weights (each is its component's column of Gc mapped by the same matrix
        function of Ac), ``E2`` and ``W`` unchanged."""
        keep = list(keep)

        def pick(M):
            return None if M is None else np.asarray(M)[:, keep]

        return replace(self, G0=pick(self.G0), G1=pick(self.G1), P2=pick(self.P2),
                       F1=pick(self.F1), F23=pick(self.F23), F4=pick(self.F4))

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


def as_hold(hold) -> LawHold | None:
    """A :class:`LawHold` (or None) from a LawHold, None or a ``(Gamma0, Gamma1)`` pair."""
    if hold is None or isinstance(hold, LawHold):
        return hold
    G0, G1 = (np.asarray(g, dtype=float) for g in hold)
    return LawHold(G0=G0.reshape(G0.shape[0], -1), G1=G1.reshape(G1.shape[0], -1))
