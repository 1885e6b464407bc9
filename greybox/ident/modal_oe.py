"""Output-error refinement of a stable state-space model in modal form.

A strictly proper model ``x[k+1] = A x[k] + B u[k], y[k] = C x[k]`` is
refined so that its *simulated* output matches the data in least squares. ``A`` is kept in real
modal form: a pole per real eigenvalue, a rotation block per complex pair,
each parametrized so that it stays strictly inside the unit circle
(``lambda = rmax tanh(theta)``; ``r = rmax / (1 + exp(-s))``;
``rmax = 1 - 1e-7``). The output matrix
enters linearly and is eliminated by least squares (variable projection,
Golub & Pereyra 1973); the poles and the input matrix are optimized by
:func:`scipy.optimize.least_squares`. Every state is a scalar (or complex)
first-order recursion run by :func:`scipy.signal.lfilter`, so one cost
evaluation, Jacobian included, is O(n (ninputs + noutputs) N).

Used by :func:`greybox.update.delta_update` to refine the poles of its best
N4SID candidate (eqs. 21-24) on the simulated output error (the refined
poles are kept only if they predict a held-out tail better).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.signal import lfilter

from .._validation import check_positive, check_same_length, check_signal
from ..exceptions import IdentificationError

__all__ = ["ModalOEResult", "refine_output_error"]

#: Largest condition number of the eigenvector matrix accepted for the modal form.
_MAX_COND = 1e8
#: Largest pole modulus reachable by the parametrization (``tanh`` and the
#: logistic function round to exactly 1 for large arguments).
_RMAX = 1.0 - 1e-7


@dataclass(frozen=True)
class ModalOEResult:
    """A state-space model refined by output error, in real modal form.

    Attributes
    ----------
    A : ndarray, shape (order, order)
        Real modal form: 1x1 blocks (real poles), 2x2 blocks (complex pairs);
        spectral radius < 1.
    B : ndarray, shape (order, ninputs)
    C : ndarray, shape (noutputs, order)
    T : ndarray, shape (order, order)
        Similarity of the starting model: ``x_start = T x`` (so a gain ``K``
        of the starting model becomes ``T^-1 K``).
    cost_start, cost : float
        Sum of squared simulation errors before and after the refinement
        [output units squared].
    nfev : int
        Cost evaluations used.
    """

    A: NDArray[np.float64]
    B: NDArray[np.float64]
    C: NDArray[np.float64]
    T: NDArray[np.float64]
    cost_start: float
    cost: float
    nfev: int


def _real_modal(A: NDArray):
    """Real modal similarity ``T`` (``A = T M T^-1``) and the mode list, or None."""
    lam, V = np.linalg.eig(A)
    n = A.shape[0]
    cols, modes, used = [], [], np.zeros(n, dtype=bool)
    scale = max(1.0, float(np.max(np.abs(lam)))) if n else 1.0
    for i in np.argsort(-np.abs(lam)):
        if used[i]:
            continue
        used[i] = True
        if abs(lam[i].imag) <= 1e-10 * scale:
            cols.append(np.real(V[:, i]))
            modes.append("real")
        else:
            # its conjugate twin
            j = int(np.argmin(np.where(used, np.inf, np.abs(lam - np.conj(lam[i])))))
            used[j] = True
            v = V[:, i] if lam[i].imag < 0 else V[:, j]
            cols += [np.real(v), np.imag(v)]
            modes.append("pair")
    T = np.array(cols).T if cols else np.zeros((0, 0))
    if n and np.linalg.cond(T) > _MAX_COND:
        return None
    return T, modes


def _pack(M: NDArray, B: NDArray, modes) -> NDArray:
    """Parameters from a real modal form (poles inside the unit circle)."""
    theta, i = [], 0
    for kind in modes:
        if kind == "real":
            lam = float(np.clip(M[i, i] / _RMAX, -1 + 1e-12, 1 - 1e-12))
            theta += [np.arctanh(lam), *B[i]]
            i += 1
        else:
            mu = M[i, i] - 1j * M[i, i + 1]
            r = float(np.clip(abs(mu) / _RMAX, 1e-12, 1 - 1e-12))
            theta += [np.log(r / (1 - r)), np.angle(mu), *B[i], *B[i + 1]]
            i += 2
    return np.array(theta, dtype=float)


def _unpack(theta: NDArray, modes, m: int):
    """Poles (complex; real ones with zero imaginary part), input rows and d pole / d theta."""
    poles, rows, dpole, j = [], [], [], 0
    for kind in modes:
        if kind == "real":
            lam = _RMAX * np.tanh(theta[j])
            poles.append(complex(lam))
            rows.append(theta[j + 1:j + 1 + m].astype(complex))
            dpole.append((_RMAX * (1.0 - np.tanh(theta[j]) ** 2),))
            j += 1 + m
        else:
            s = 1.0 / (1.0 + np.exp(-np.clip(theta[j], -700, 700)))
            mu = _RMAX * s * np.exp(1j * theta[j + 1])
            poles.append(mu)
            rows.append(theta[j + 2:j + 2 + m] + 1j * theta[j + 2 + m:j + 2 + 2 * m])
            dpole.append(((1.0 - s) * mu, 1j * mu))
            j += 2 + 2 * m
    return poles, rows, dpole


def _filtered(poles, modes, u: NDArray):
    """``F_i(u) = q^-1 / (1 - pole_i q^-1) u`` for every mode, shape (nmodes, m, N)."""
    out = []
    for kind, mu in zip(modes, poles):
        if kind == "real":
            out.append(lfilter([0.0, 1.0], [1.0, -mu.real], u, axis=1))
        else:
            out.append(lfilter([0.0, 1.0], [1.0, -mu], u.astype(complex), axis=1))
    return out


def _states(theta: NDArray, modes, u: NDArray, with_jac: bool = False):
    """States of the modal model, its (A, B), and (optionally) d states / d theta.

    The derivative list has one entry per parameter: ``(state rows, values)``
    with values of shape (len(rows), N).
    """
    m, N = u.shape
    poles, rows, dpole = _unpack(theta, modes, m)
    F = _filtered(poles, modes, u)
    n = sum(1 if k == "real" else 2 for k in modes)
    X = np.empty((n, N))
    A = np.zeros((n, n))
    B = np.zeros((n, m))
    dX = []
    i = 0
    for kind, mu, b, Fi, dp in zip(modes, poles, rows, F, dpole):
        if kind == "real":
            X[i] = b.real @ Fi
            A[i, i], B[i] = mu.real, b.real
            if with_jac:
                dX.append(([i], dp[0] * lfilter([0.0, 1.0], [1.0, -mu.real], X[i])[None]))
                dX += [([i], Fi[j][None]) for j in range(m)]
            i += 1
        else:
            z = b @ Fi
            X[i], X[i + 1] = z.real, z.imag
            A[i:i + 2, i:i + 2] = [[mu.real, -mu.imag], [mu.imag, mu.real]]
            B[i], B[i + 1] = b.real, b.imag
            if with_jac:
                Fz = lfilter([0.0, 1.0], [1.0, -mu], z)
                for d in dp:
                    v = d * Fz
                    dX.append(([i, i + 1], np.vstack([v.real, v.imag])))
                for c in (1.0, 1j):
                    for j in range(m):
                        v = c * Fi[j]
                        dX.append(([i, i + 1], np.vstack([v.real, v.imag])))
            i += 2
    return X, A, B, dX


def _output_fit(X: NDArray, y: NDArray):
    """Least-squares ``C`` of ``y = C X``; returns (C, residual, Gram inverse)."""
    n = X.shape[0]
    G = X @ X.T
    G += max(1e-12 * np.trace(G) / max(n, 1), 1e-300) * np.eye(n)
    Gi = np.linalg.inv(G)
    C = (y @ X.T) @ Gi
    return C, y - C @ X, Gi


def refine_output_error(A: ArrayLike, B: ArrayLike, C: ArrayLike, u: ArrayLike,
                        y: ArrayLike, *, max_iter: int = 50) -> ModalOEResult:
    """Refine a stable model ``(A, B, C)`` by output error in real modal form.

    Parameters
    ----------
    A : array_like, shape (order, order)
        Starting state matrix, spectral radius < 1 and diagonalizable.
    B : array_like, shape (order, ninputs)
        Starting input matrix.
    C : array_like, shape (noutputs, order)
        Starting output matrix (only its shape is used: C is re-estimated by
        least squares at every step).
    u : array_like, shape (ninputs, nsteps)
        Input; the model starts from x = 0.
    y : array_like, shape (noutputs, nsteps)
        Output to match. Scale the channels beforehand: the cost is the plain
        sum of squares over all outputs.
    max_iter : int
        Limit on the trust-region iterations (each costs one simulation and
        one analytic Jacobian).

    Returns
    -------
    ModalOEResult
        Never worse than the start on the data: if the search does not lower
        the cost, the starting model (in modal form) is returned.

    Raises
    ------
    IdentificationError
        If ``A`` is unstable or its eigenvector matrix is too ill-conditioned
        (cond > 1e8) for a modal form.

    Notes
    -----
    The unknowns are the poles and ``B`` (``order * (1 + ninputs)`` numbers);
    ``C`` follows from them by linear least squares (variable projection,
    with the exact Jacobian of the projected residual). Poles are
    restricted to the unit disc by their parametrization, so the refined
    model is stable by construction; real poles stay real and complex pairs
    stay pairs (the structure of the start).

    References
    ----------
    G. H. Golub and V. Pereyra, "The differentiation of pseudo-inverses and
    nonlinear least squares problems whose variables separate", SIAM J.
    Numer. Anal. 10 (1973).
    """
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    C = np.asarray(C, dtype=float)
    u = check_signal(u, B.shape[1], "u")
    y = check_signal(y, C.shape[0], "y")
    check_same_length(("u", u), ("y", y))
    max_iter = check_positive(max_iter, "max_iter", integer=True)
    n = A.shape[0]
    if n == 0 or np.max(np.abs(np.linalg.eigvals(A))) >= 1.0:
        raise IdentificationError("refine_output_error needs a stable starting model of "
                                  "order >= 1 (spectral radius < 1)")
    modal = _real_modal(A)
    if modal is None:
        raise IdentificationError("the starting model's eigenvectors are too ill-conditioned "
                                  "for a modal form; refine another realization")
    T, modes = modal
    M = np.linalg.solve(T, A @ T)
    Bm = np.linalg.solve(T, B)
    theta0 = _pack(M, Bm, modes)
    cache = {}

    def evaluate(theta):
        key = theta.tobytes()
        if key not in cache:
            cache.clear()
            X, _, _, dX = _states(theta, modes, u, with_jac=True)
            Cx, r, Gi = _output_fit(X, y)
            cache[key] = (X, Cx, r, Gi, dX)
        return cache[key]

    def resid(theta):
        return evaluate(theta)[2].reshape(-1)

    def jac(theta):
        X, Cx, r, Gi, dX = evaluate(theta)
        J = np.empty((y.size, len(dX)))
        for c, (rows, dv) in enumerate(dX):
            # d r = -(C dX) P_perp - r dX^T G^-1 X  (Golub & Pereyra)
            d = Cx[:, rows] @ dv
            d -= ((d @ X.T) @ Gi) @ X
            d += ((r @ dv.T) @ Gi[rows]) @ X
            J[:, c] = -d.reshape(-1)
        return J

    r0 = resid(theta0)
    cost0 = float(r0 @ r0)
    best = theta0
    nfev = 1
    if np.isfinite(cost0):
        with np.errstate(over="ignore", invalid="ignore"):
            sol = least_squares(resid, theta0, jac=jac, method="trf", x_scale="jac",
                                max_nfev=max_iter, xtol=1e-10, ftol=1e-10)
        nfev += int(sol.nfev)
        if np.isfinite(sol.cost) and 2 * sol.cost < cost0:
            best = sol.x
    X, Am, Bm, _ = _states(best, modes, u)
    Cm, r, _ = _output_fit(X, y)
    return ModalOEResult(A=Am, B=Bm, C=Cm, T=T, cost_start=cost0, cost=float(np.sum(r**2)),
                         nfev=nfev)
