"""Output-error identification by separable least squares (variable projection).

The model has one common denominator for all inputs of an output::

    d_i[k] = D_i w[k] + sum_j B_ij(q) / A_i(q) w_j[k] + e_i[k]

For a fixed denominator A(q) = 1 + a_1 q^-1 + ... + a_n q^-n the model is
linear in the numerators and D, solved by least squares on the inputs
filtered by 1/A(q); the denominator is then optimized (Nelder-Mead over its
poles, from several stable starting sets). The regressors are filtered
inputs only, so the estimates stay consistent when the output noise is
coloured or correlated with *future* inputs, as it is for the unknown-input
filter's data (PAPER_NOTES §8.4, §9.3: ARX / equation-error fits on d^ are
biased; output-error fits are not, but need several starting poles).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize, minimize_scalar
from scipy.signal import lfilter

from .._blas import single_thread_blas
from .._validation import check_positive, check_same_length, check_signal
from ..exceptions import DataError
from ..system import named_ss

__all__ = ["OEResult", "output_error"]


@dataclass(frozen=True)
class OEResult:
    """Output-error model in state-space form.

    Attributes
    ----------
    A : ndarray, shape (nout * order, nout * order)
    B : ndarray, shape (nout * order, nin)
    C : ndarray, shape (nout, nout * order)
    D : ndarray, shape (nout, nin)
    residual_cov : ndarray, shape (nout, nout)
        Covariance of the output error.
    order : int
        Denominator order per output.
    poles : ndarray
        Poles of every output's denominator.
    y_sim : ndarray, shape (nout, nsteps)
        Simulated output on the data.
    """

    A: NDArray[np.float64]
    B: NDArray[np.float64]
    C: NDArray[np.float64]
    D: NDArray[np.float64]
    residual_cov: NDArray[np.float64]
    order: int
    poles: NDArray[np.complex128]
    y_sim: NDArray[np.float64]

    def to_statespace(self, dt: float, *, inputs=None, outputs=None, state_prefix="z"):
        """As a python-control StateSpace."""
        nin, nout = self.B.shape[1], self.C.shape[0]
        return named_ss(self.A, self.B, self.C, self.D, dt,
                        states=[f"{state_prefix}[{i}]" for i in range(self.A.shape[0])],
                        inputs=inputs or [f"w[{j}]" for j in range(nin)],
                        outputs=outputs or [f"d[{i}]" for i in range(nout)])


def _poly_from_params(theta: NDArray, n: int) -> NDArray:
    """Denominator from parameters: for n >= 2 a complex pair (tanh r, angle) then reals."""
    if n >= 2:
        r, ang = np.tanh(theta[0]), theta[1]
        poles = [r * np.exp(1j * ang), r * np.exp(-1j * ang)] + list(np.tanh(theta[2:]))
    else:
        poles = list(np.tanh(theta))
    return np.real(np.poly(poles))


def _poly_real(theta: NDArray) -> NDArray:
    """Denominator with real poles tanh(theta)."""
    return np.real(np.poly(np.tanh(theta)))


def _fit_fixed_den(a: NDArray, ws: NDArray, d: NDArray, feedthrough: bool):
    """Least squares of the numerators (and D) for denominator a; returns (coef, resid)."""
    n = len(a) - 1
    nin, N = ws.shape
    filt = lfilter([1.0], a, ws, axis=1)
    off = nin if feedthrough else 0
    X = np.zeros((off + n * nin, N))
    if feedthrough:
        X[:nin] = ws
    for i in range(1, n + 1):
        X[off + (i - 1) * nin: off + i * nin, i:] = filt[:, :N - i]
    G = X @ X.T
    # ridge: collinear (or all-zero) regressors
    G += max(1e-10 * np.trace(G) / G.shape[0], 1e-300) * np.eye(G.shape[0])
    coef = np.linalg.solve(G, X @ d.T)
    resid = d - coef.T @ X
    return coef, resid


def _search_denominator(order, ws, di, feedthrough, taus, starts, maxiter):
    """Denominator A(q^-1) minimizing the output error (grid, then local refinement)."""

    def cost_a(a):
        if np.max(np.abs(np.roots(a))) >= 0.9999:
            return np.inf
        _, r = _fit_fixed_den(a, ws, di, feedthrough)
        return float(np.mean(r**2))

    lams = np.exp(-1.0 / taus)
    if order == 1:
        c = [cost_a(np.array([1.0, -lam])) for lam in lams]
        j = int(np.argmin(c))
        lo = lams[j - 1] if j > 0 else 0.0
        hi = lams[j + 1] if j + 1 < len(lams) else 0.9998
        res = minimize_scalar(lambda lam: cost_a(np.array([1.0, -lam])), bounds=(lo, hi),
                              method="bounded", options={"xatol": 1e-8})
        best_lam = res.x if res.fun <= c[j] else lams[j]
        return np.array([1.0, -best_lam])
    coarse = np.arctanh(lams[::3])
    cands = []
    for ti in range(len(coarse)):
        for tj in range(ti, len(coarse)):
            th = np.r_[coarse[ti], coarse[tj], np.full(order - 2, coarse[tj])]
            cands.append((_poly_real, th))
        for k in (0.5, 1.0, 2.0, 4.0):
            tau = taus[::3][ti]
            cands.append((_poly_from_params,
                          np.r_[coarse[ti], k / tau, np.full(order - 2, coarse[ti])]))

    def cost(theta, make):
        a = make(theta) if make is _poly_real else make(theta, order)
        v = cost_a(a)
        return 1e6 if not np.isfinite(v) else v

    scored = sorted(((cost(th, mk), mk, th) for mk, th in cands), key=lambda t: t[0])
    best = None
    opts = {"maxiter": maxiter, "xatol": 1e-6, "fatol": 1e-12}
    for _, mk, th in scored[:max(1, starts)]:
        res = minimize(cost, th, args=(mk,), method="Nelder-Mead", options=opts)
        if best is None or res.fun < best[0]:
            best = (res.fun, mk, res.x)
    _, mk, th = best
    return mk(th) if mk is _poly_real else mk(th, order)


def output_error(d: ArrayLike, w: ArrayLike, order: int, *, feedthrough: bool = True,
                 starts: int = 2, maxiter: int = 200, search_samples: int = 20_000
                 ) -> OEResult:
    """Fit an output-error model of the given denominator order.

    Parameters
    ----------
    d : array_like, shape (nout, nsteps)
        Output (e.g. the unknown-input estimates d^).
    w : array_like, shape (nin, nsteps)
        Inputs (e.g. [u; x^]).
    order : int
        Denominator order n >= 1 (per output).
    feedthrough : bool
        Estimate the direct term D.
    starts : int
        Order >= 2: number of best grid points refined by Nelder-Mead.
    maxiter : int
        Nelder-Mead iteration limit per start.
    search_samples : int
        The pole search runs on the first ``search_samples`` samples (its cost
        is then independent of N); the numerators and D are fitted on all data.

    Notes
    -----
    Order 1: the pole is scanned on a grid of 24 time constants from 1.5 to
    ``search_samples / 5`` samples, then refined by bounded Brent search.
    Order >= 2: a grid of real-pole sets and complex pairs is scanned and the
    ``starts`` best points are refined by Nelder-Mead.

    Returns
    -------
    OEResult
    """
    d = check_signal(d, None, "d")
    w = check_signal(w, None, "w")
    N = check_same_length(("d", d), ("w", w))
    order = check_positive(order, "order", integer=True)
    nin, nout = w.shape[0], d.shape[0]
    if N < 10 * (order + 1) * (nin + 1):
        raise DataError(f"{N} samples are too few for an output-error model of order {order} "
                        f"with {nin} inputs; give at least {10 * (order + 1) * (nin + 1)}")
    sw = np.sqrt(np.mean(w**2, axis=1))
    sw[sw == 0] = 1.0
    ws = w / sw[:, None]
    sd = np.sqrt(np.mean(d**2, axis=1))
    sd[sd == 0] = 1.0
    ds = d / sd[:, None]
    ns = min(N, int(search_samples))
    taus = np.geomspace(1.5, max(ns / 5.0, 10.0), 24)
    blocksA, blocksB, blocksC, Ds, sims, allpoles = [], [], [], [], [], []
    # small Gram products called hundreds of times: one BLAS thread (see greybox._blas)
    with single_thread_blas():
        for i in range(nout):
            di = ds[i:i + 1]
            a = _search_denominator(order, ws[:, :ns], di[:, :ns], feedthrough, taus, starts,
                                    maxiter)
            coef, r = _fit_fixed_den(a, ws, di, feedthrough)
            # unscale: d_i = sd_i * (Dn ws + sum_k bk filt(ws) delayed)
            off = nin if feedthrough else 0
            Dn = coef[:off, 0] * sd[i] / sw if feedthrough else np.zeros(nin)
            bks = [coef[off + k * nin: off + (k + 1) * nin, 0] * sd[i] / sw
                   for k in range(order)]
            # observer canonical form of sum_k b_k q^-k / A(q^-1)
            Ai = np.zeros((order, order))
            Ai[:, 0] = -a[1:]
            Ai[:-1, 1:] = np.eye(order - 1)
            Bi = np.vstack(bks)
            Ci = np.zeros((1, order))
            Ci[0, 0] = 1.0
            blocksA.append(Ai)
            blocksB.append(Bi)
            blocksC.append(Ci)
            Ds.append(Dn)
            sims.append((di - r)[0] * sd[i])
            allpoles.append(np.roots(a))
    from scipy.linalg import block_diag

    A = block_diag(*blocksA)
    B = np.vstack(blocksB)
    C = block_diag(*blocksC)
    D = np.vstack(Ds)
    y_sim = np.vstack(sims)
    e = d - y_sim
    return OEResult(A=A, B=B, C=C, D=D, residual_cov=np.atleast_2d(np.cov(e, bias=True)),
                    order=order, poles=np.concatenate(allpoles), y_sim=y_sim)
