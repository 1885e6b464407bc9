"""A discrete model with a static law, simulated for K coefficient vectors at once, compiled.

Output-error fits of a nonlinear law simulate ``x[k+1] = A x + B u + G law(x, u)``
(or the law integrated over each sample by its hold, :class:`greybox.hold.LawHold`)
hundreds of times, each a loop over the samples that cannot be vectorized in time.
In numpy each sample costs some 40 small calls (25 us for a two-state model whatever
the number of columns); :func:`simulate_columns` runs the same recursion compiled by
numba when it is installed (the ``fast`` extra), about 50x faster. Without numba, or
for a law holding a kind this module has no code for, it returns None and the caller
runs its numpy loop: the same recursion, the same divergence rules, equal to rounding
(``tests/test_lawsim.py``).

A kind is compiled when :data:`CODES` names it: its code and how its spec index reads
as ``(state or input, second state or input, level or eps)``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ._jit import HAVE_NUMBA as _HAVE
from ._jit import compile_once
from .hold import as_hold

#: numba is installed (the ``fast`` extra; :mod:`greybox._jit`). Imported on the first
#: compiled simulation only (80 ms: a command that never simulates a law does not pay it).
HAVE_NUMBA = _HAVE

#: kind -> (code, reader of the spec index into (i, j, level or eps index)). Pairs read
#: (a, b, e) as x_b - x_a; a smoothed sign's eps is looked up by index.
CODES = {
    "x": (0, lambda ix: (ix, 0, -1)),
    "u": (1, lambda ix: (ix, 0, -1)),
    "x^3": (2, lambda ix: (ix, 0, -1)),
    "sign": (3, lambda ix: (ix, 0, ix)),
    "abs": (4, lambda ix: (ix, 0, -1)),
    "x|x|": (5, lambda ix: (ix, 0, -1)),
    "rel": (6, lambda ix: (ix[0], ix[1], -1)),
    "rel^3": (7, lambda ix: (ix[0], ix[1], -1)),
    "rel_sign": (8, lambda ix: (ix[0], ix[1], ix[2])),
    "rel_abs": (9, lambda ix: (ix[0], ix[1], -1)),
    "x*u": (10, lambda ix: (ix[0], ix[1], -1)),
    "x_hi": (11, lambda ix: (ix[0], 0, ix[1])),
    "x_lo": (12, lambda ix: (ix[0], 0, ix[1])),
    "const": (13, lambda ix: (0, 0, -1)),
    "u_dz": (14, lambda ix: (ix[0], 0, ix[1])),
    "u_sat": (15, lambda ix: (ix[0], 0, ix[1])),
}
_LEVEL_CODES = (11, 12, 14, 15)  # the third entry is a level, not an eps index


def compiled_terms(spec, eps: NDArray):
    """``(codes, i, j, w)`` arrays of a law's terms for the kernel; None when numba is
    absent or a kind has no code. ``w``: a smoothed sign's eps, a hinge's or a
    breakpoint's level (0 otherwise)."""
    if not HAVE_NUMBA:
        return None
    out = []
    for _, kind, ix in spec:
        if kind not in CODES:
            return None
        code, read = CODES[kind]
        i, j, w = read(ix)
        if code in _LEVEL_CODES:
            w = float(w)
        else:
            w = float(eps[w]) if w != -1 else 0.0
        out.append((code, int(i), int(j), w))
    codes, i, j, w = (np.array(c) for c in zip(*out)) if out else ([],) * 4
    return (np.asarray(codes, dtype=np.int64), np.asarray(i, dtype=np.int64),
            np.asarray(j, dtype=np.int64), np.asarray(w, dtype=float))


def simulate_columns(A: NDArray, G: NDArray, hold, Bu: NDArray, u: NDArray, x0: NDArray,
                     TH: NDArray, terms, comp: NDArray, isolate: bool) -> NDArray | None:
    """States (N, nstates, K) of the model with the law for the coefficient columns TH.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    G : ndarray, shape (n, md)
        How the law enters (no hold).
    hold : LawHold, (Gamma0, Gamma1) or None
    Bu : ndarray, shape (n, N)
        The known inputs' effect ``B u[k]``.
    u : ndarray, shape (m, N)
    x0 : ndarray, shape (n,)
    TH : ndarray, shape (nterms, K)
        The coefficients of each column.
    terms : tuple
        :func:`compiled_terms` of the law's spec (None: not compiled, returns None).
    comp : ndarray of int, shape (nterms,)
        The component of d each term feeds.
    isolate : bool
        A diverging column is NaN from the sample it diverged and the others go on
        (False: the first diverging column stops every column).

    Returns
    -------
    ndarray, shape (N, n, K), or None (numba absent or a kind without a code)
    """
    if terms is None or not HAVE_NUMBA:
        return None
    h = as_hold(hold)
    n, md = A.shape[0], G.shape[1]
    z, zn = np.zeros((n, md)), np.zeros((n, n))
    if h is None:  # M1..M4: (n, md) weights of the law's values; E2, W: (n, n)
        mode, mats = 0, (G, z, z, z, zn, zn)
    elif h.E2 is None:
        mode, mats = 1, (h.G0, h.G1, z, z, zn, zn)
    else:
        mode, mats = 2, (h.P2, h.F1, h.F23, h.F4, h.E2, h.W)
        if h.substeps > 1:  # the law stepped over sub-steps, the input held
            A, Bu = h.Ah, h.Ws @ np.asarray(Bu, dtype=float)
    mats = tuple(np.ascontiguousarray(np.asarray(M, dtype=float).reshape(s))
                 for M, s in zip(mats, [(n, md)] * 4 + [(n, n)] * 2))
    reps = h.substeps if mode == 2 else 1
    return _kernel()(np.ascontiguousarray(A, dtype=float), *mats, mode, int(reps),
                     np.ascontiguousarray(Bu, dtype=float), np.ascontiguousarray(u, dtype=float),
                     np.ascontiguousarray(x0, dtype=float),
                     np.ascontiguousarray(np.asarray(TH, dtype=float).T), *terms,
                     np.ascontiguousarray(comp, dtype=np.int64), md, bool(isolate))


def _build(numba):
    """The compiled :func:`_run`, its helpers compiled first (numba caches the machine
    code on disk: a later process loads it in ~0.1 s instead of compiling for ~4 s)."""
    global _term, _law, _mv  # noqa: PLW0603 - replaced by their compiled versions once
    jit = numba.njit(cache=True)
    _term, _law, _mv = jit(_term), jit(_law), jit(_mv)
    return jit(_run)


_kernel = compile_once(_build)


def _term(code, i, j, w, x, u):
    if code == 0:
        return x[i]
    if code == 1:
        return u[i]
    if code == 2:
        return x[i] * x[i] * x[i]
    if code == 3:
        return np.tanh(x[i] / w)
    if code == 4:
        return abs(x[i])
    if code == 5:
        return x[i] * abs(x[i])
    if code >= 6 and code <= 9:
        v = x[j] - x[i]
        if code == 6:
            return v
        if code == 7:
            return v * v * v
        if code == 8:
            return np.tanh(v / w)
        return abs(v)
    if code == 10:
        return x[i] * u[j]
    if code == 11:
        return max(x[i] - w, 0.0)
    if code == 12:
        return min(x[i] - w, 0.0)
    if code == 13:
        return 1.0
    cl = min(max(u[i], -w), w)
    return cl if code == 14 else u[i] - cl

def _law(x, u, th, codes, ti, tj, tw, comp, out):
    out[:] = 0.0
    for q in range(codes.shape[0]):
        if th[q] != 0.0:
            out[comp[q]] += th[q] * _term(codes[q], ti[q], tj[q], tw[q], x, u)

def _mv(M, v, out):  # out = M @ v
    for r in range(M.shape[0]):
        s = 0.0
        for c in range(M.shape[1]):
            s += M[r, c] * v[c]
        out[r] = s

def _run(A, M1, M2, M3, M4, E2, W, mode, reps, Bu, u, x0, THt, codes, ti, tj, tw, comp,
        md, isolate):
    """States (N, n, K): :func:`simulate_columns`' recursion, column by column.

    ``mode`` 0: ``x' = A x + Bu + M1 f(x)``; 1: Heun of the first-order hold (M1 = G0,
    M2 = G1); 2: ETDRK4 (:meth:`greybox.hold.LawHold.step`: M1 = P2, M2..M4 = F1, F23,
    F4, with E2 and W), ``reps`` times per sample (sub-steps: A, Bu, E2, W and the M's are
    then a sub-step's). ``THt`` (K, nterms): one row of coefficients per column."""
    n, N, K = A.shape[0], Bu.shape[1], THt.shape[0]
    xs = np.full((N, n, K), np.nan)
    dead = np.full(K, N)
    X = np.empty((K, n))  # one row per column: contiguous
    for c in range(K):
        X[c] = x0
    uT, BuT = np.ascontiguousarray(u.T), np.ascontiguousarray(Bu.T)
    fx, fa, fb, fc = np.empty(md), np.empty(md), np.empty(md), np.empty(md)
    t1, t2, t3, t4, bh = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    dd = np.empty(md)
    for k in range(N):
        for c in range(K):
            for r in range(n):
                xs[k, r, c] = X[c, r]
        uk, bu = uT[k], BuT[k]
        if mode == 2:
            _mv(W, bu, bh)
        stop = False
        for c in range(K):
            if dead[c] < N:
                continue
            x, th = X[c], THt[c]
            for _ in range(reps):  # sub-steps (the input held); 1 but for a stiff law
                _law(x, uk, th, codes, ti, tj, tw, comp, fx)
                _mv(A, x, t1)
                if mode == 0:  # x' = A x + B u + G f(x)
                    _mv(M1, fx, t2)
                    for r in range(n):
                        x[r] = t1[r] + bu[r] + t2[r]
                elif mode == 1:  # Heun of the first-order hold
                    for r in range(n):
                        t1[r] += bu[r]
                    for r in range(n):
                        s = 0.0
                        for q in range(md):
                            s += (M1[r, q] + M2[r, q]) * fx[q]
                        t3[r] = t1[r] + s
                    _law(t3, uk, th, codes, ti, tj, tw, comp, fa)
                    _mv(M1, fx, t2)
                    _mv(M2, fa, t4)
                    for r in range(n):
                        x[r] = t1[r] + t2[r] + t4[r]
                else:  # ETDRK4 (LawHold.step)
                    _mv(E2, x, t2)
                    for r in range(n):
                        t2[r] += bh[r]  # half
                    _mv(M1, fx, t3)
                    for r in range(n):
                        t3[r] += t2[r]  # a
                    _law(t3, uk, th, codes, ti, tj, tw, comp, fa)
                    _mv(M1, fa, t4)
                    for r in range(n):
                        t4[r] += t2[r]
                    _law(t4, uk, th, codes, ti, tj, tw, comp, fb)
                    _mv(E2, t3, t4)
                    for q in range(md):
                        dd[q] = 2.0 * fb[q] - fx[q]
                    _mv(M1, dd, t2)
                    for r in range(n):
                        t4[r] += bh[r] + t2[r]
                    _law(t4, uk, th, codes, ti, tj, tw, comp, fc)
                    for r in range(n):
                        s = t1[r] + bu[r]
                        for q in range(md):
                            s += M2[r, q] * fx[q] + M3[r, q] * (fa[q] + fb[q]) + M4[r, q] * fc[q]
                        x[r] = s  # x's old values are read above only (t1 = A x, t2 = E2 x)
            ok = True
            for r in range(n):
                if not abs(x[r]) <= 1e100:
                    ok = False
            if not ok:
                if not isolate:
                    stop = True
                    break
                dead[c] = k + 1
                x[:] = 0.0
        if stop:
            break
        alive = False
        for c in range(K):
            if dead[c] == N:
                alive = True
        if not alive:
            break
    for c in range(K):
        if dead[c] < N:
            xs[dead[c]:, :, c] = np.nan
    return xs

