"""Regressions for static laws: scaled least squares and sparse forward selection.

Used for order-0 (static) model errors ``d = Dx x + Du u`` and for sparse
nonlinear laws over named candidate terms. Signals have time as the last axis.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validation import check_same_length, check_signal
from ..exceptions import DataError

__all__ = ["StaticFit", "static_least_squares", "SparseLaw", "forward_selection"]


@dataclass(frozen=True)
class StaticFit:
    """Least-squares static map ``d = coef @ w + e``.

    Attributes
    ----------
    coef : ndarray, shape (nout, nin)
        Coefficients, in the units of d per unit of w.
    residual_cov : ndarray, shape (nout, nout)
        Covariance of the residual e.
    residuals : ndarray, shape (nout, nsteps)
    rank : int
        Numerical rank of the (scaled) regressor matrix.
    """

    coef: NDArray[np.float64]
    residual_cov: NDArray[np.float64]
    residuals: NDArray[np.float64]
    rank: int


def static_least_squares(w: ArrayLike, d: ArrayLike, *, rtol: float = 1e-10) -> StaticFit:
    """Fit ``d[k] = coef @ w[k]`` by least squares with scaled regressors.

    Each regressor is scaled to unit RMS before the solve (PAPER_NOTES §8.7)
    and directions with singular values below ``rtol`` times the largest are
    dropped (minimum-norm solution).

    Parameters
    ----------
    w : array_like, shape (nin, nsteps)
        Regressors.
    d : array_like, shape (nout, nsteps)
        Regressand.
    rtol : float
        Relative singular-value threshold for the rank decision.

    Returns
    -------
    StaticFit
    """
    w = np.atleast_2d(np.asarray(w, dtype=float))
    d = np.atleast_2d(np.asarray(d, dtype=float))
    w = check_signal(w, w.shape[0], "w")
    d = check_signal(d, d.shape[0], "d")
    N = check_same_length(("w", w), ("d", d))
    if N < w.shape[0] + 1:
        raise DataError(f"{N} samples cannot fit {w.shape[0]} coefficients; give more data")
    s = np.sqrt(np.mean(w**2, axis=1))
    s[s == 0] = 1.0
    ws = w / s[:, None]
    coef_s, _, rank, _ = np.linalg.lstsq(ws.T, d.T, rcond=rtol)
    coef = (coef_s.T) / s[None, :]
    e = d - coef @ w
    return StaticFit(coef=coef, residual_cov=np.atleast_2d(np.cov(e, bias=True)),
                     residuals=e, rank=int(rank))


@dataclass(frozen=True)
class SparseLaw:
    """Sparse linear-in-parameters law ``d = sum_j coef_j * term_j``.

    Attributes
    ----------
    names : tuple of str
        Names of the selected terms, in order of selection.
    index : tuple of int
        Their indices among the candidate terms.
    coef : ndarray, shape (nselected,)
        Coefficients of the selected terms.
    residual_var : float
        Variance of the residual.
    bic_path : ndarray, shape (nselected + 1,)
        BIC after 0, 1, ... selected terms.
    """

    names: tuple[str, ...]
    index: tuple[int, ...]
    coef: NDArray[np.float64]
    residual_var: float
    bic_path: NDArray[np.float64]


def _bic(rss: float, N: int, k: int) -> float:
    return N * np.log(max(rss / N, np.finfo(float).tiny)) + k * np.log(N)


def forward_selection(terms: ArrayLike, d: ArrayLike, names: Sequence[str], *,
                      max_terms: int | None = None, min_gain: float = 0.0) -> SparseLaw:
    """Greedy forward selection of terms with a BIC stopping rule.

    At each step the term that most reduces the residual sum of squares is
    added; selection stops when the BIC (``N log(RSS/N) + k log N``) no
    longer drops by more than ``min_gain`` (PAPER_NOTES §9.4: this finds the
    true terms where thresholded least squares keeps too many).

    Parameters
    ----------
    terms : array_like, shape (nterms, nsteps)
        Candidate terms evaluated on the data.
    d : array_like, shape (nsteps,) or (1, nsteps)
        Regressand (one channel).
    names : sequence of str, length nterms
    max_terms : int, optional
    min_gain : float
        Required BIC decrease per added term (0: plain BIC).

    Returns
    -------
    SparseLaw
    """
    X = np.atleast_2d(np.asarray(terms, dtype=float))
    X = check_signal(X, X.shape[0], "terms")
    d = check_signal(np.asarray(d, dtype=float).reshape(1, -1), 1, "d")[0]
    N = check_same_length(("terms", X), ("d", d[None, :]))
    if len(names) != X.shape[0]:
        raise DataError(f"{len(names)} names for {X.shape[0]} terms")
    s = np.sqrt(np.mean(X**2, axis=1))
    usable = s > 0
    Xs = np.where(usable[:, None], X / np.where(usable, s, 1.0)[:, None], 0.0)
    max_terms = X.shape[0] if max_terms is None else min(max_terms, X.shape[0])
    sel: list[int] = []
    rss = float(d @ d)
    path = [_bic(rss, N, 0)]
    coef_s = np.zeros(0)
    while len(sel) < max_terms:
        best = None
        for j in range(X.shape[0]):
            if j in sel or not usable[j]:
                continue
            cols = Xs[sel + [j]].T
            c, *_ = np.linalg.lstsq(cols, d, rcond=1e-12)
            r = d - cols @ c
            rj = float(r @ r)
            if best is None or rj < best[1]:
                best = (j, rj, c)
        if best is None:
            break
        b = _bic(best[1], N, len(sel) + 1)
        if b > path[-1] - min_gain:
            break
        sel.append(best[0])
        rss, coef_s = best[1], best[2]
        path.append(b)
    coef = coef_s / s[sel] if sel else np.zeros(0)
    return SparseLaw(names=tuple(names[j] for j in sel), index=tuple(sel), coef=coef,
                     residual_var=rss / N, bic_path=np.array(path))
