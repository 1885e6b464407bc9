"""Regressions for static laws: scaled least squares and sparse forward selection.

Used for order-0 (static) model errors ``d = Dx x + Du u`` and for sparse
nonlinear laws over named candidate terms. Signals have time as the last axis.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._blas import single_thread_blas
from .._validation import check_positive, check_same_length, check_signal
from ..exceptions import DataError, DimensionError

__all__ = ["StaticFit", "static_least_squares", "SparseLaw", "forward_selection",
           "forward_selection_gram"]


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
    w = check_signal(w, None, "w")
    d = check_signal(d, None, "d")
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
        Coefficients of the selected terms, in the units of d per unit of term.
    residual_var : float
        Variance (mean square) of the residual ``d - sum_j coef_j term_j``.
    bic_path : ndarray, shape (nselected + 1,)
        BIC after 0, 1, ... selected terms of the forward pass; the last entry
        is the BIC of the returned law (after pruning, if any).
    pruned : tuple of str
        Names of terms the backward pruning removed again (empty without it).
    """

    names: tuple[str, ...]
    index: tuple[int, ...]
    coef: NDArray[np.float64]
    residual_var: float
    bic_path: NDArray[np.float64]
    pruned: tuple[str, ...] = ()

    @property
    def bic_gain(self) -> float:
        """BIC of ``d = 0`` minus BIC of the law (> 0 when the law is kept)."""
        return float(self.bic_path[0] - self.bic_path[-1])


def _bic(rss: float, N: int, k: int) -> float:
    return N * np.log(max(rss / N, np.finfo(float).tiny)) + k * np.log(N)


# Gram matrices of unit-RMS-scaled terms with a larger condition number are
# treated as singular (the scaled regressor matrix then has cond > 1e6).
_GRAM_COND_MAX = 1e12


def _exclusive(exclusive, nterms: int):
    """The alternatives' labels, checked against the number of terms (None: no constraint)."""
    if exclusive is None:
        return None
    ex = list(exclusive)
    if len(ex) != nterms:
        raise DimensionError(f"exclusive has {len(ex)} labels for {nterms} terms; expected one "
                             f"label (or None) per term")
    return ex


def _swap_alternatives(Gm, b, dd, sel, coef_s, rss, exclusive, usable, floor):
    """Each selected term that has alternatives (the same ``exclusive`` label) swapped for
    the one that lowers the RSS most in its place, until no swap helps: a greedy pick of
    one shape (sign(v)) is revised once the other terms (v) are in."""
    improved = True
    while improved:
        improved = False
        for pos, i in enumerate(sel):
            if exclusive[i] is None:
                continue
            for j in range(len(exclusive)):
                if j in sel or not usable[j] or exclusive[j] != exclusive[i]:
                    continue
                idx = sel[:pos] + [j] + sel[pos + 1:]
                Gs = Gm[np.ix_(idx, idx)]
                try:
                    c = np.linalg.solve(Gs, b[idx])
                except np.linalg.LinAlgError:
                    continue
                r = dd - float(c @ b[idx])
                if np.linalg.cond(Gs) <= _GRAM_COND_MAX and r < rss - floor:
                    sel, coef_s, rss, improved = idx, c, max(r, floor), True
                    break
            if improved:
                break
    return sel, coef_s, rss


def _select_on_gram(gram, cross, dd, N, names, max_terms, min_gain, min_drop, prune,
                    exclusive=None):
    """The forward pass and pruning of :func:`forward_selection` on ``X X^T``, ``X d``, ``d^T d``.

    Returns the term scale s (nterms,), the selected indices, their coefficients
    on the unit-RMS terms, the RSS, the BIC path and the pruned names.
    """
    nterms = gram.shape[0]
    s = np.sqrt(np.clip(np.diag(gram), 0.0, None) / N)
    usable = s > 0
    sd = np.where(usable, s, 1.0)
    Gm = gram / np.outer(sd, sd)
    b = cross / sd
    floor = 1e-10 * dd

    sel: list[int] = []
    coef_s = np.zeros(0)
    rss = dd
    path = [_bic(dd, N, 0)]
    while len(sel) < max_terms:
        best = None
        taken = set() if exclusive is None else {exclusive[i] for i in sel} - {None}
        for j in range(nterms):
            if j in sel or not usable[j] or (exclusive is not None and exclusive[j] in taken):
                continue
            idx = sel + [j]
            Gs = Gm[np.ix_(idx, idx)]
            try:
                c = np.linalg.solve(Gs, b[idx])
            except np.linalg.LinAlgError:
                continue
            if np.linalg.cond(Gs) > _GRAM_COND_MAX:
                continue
            r = dd - float(c @ b[idx])
            if best is None or r < best[1]:
                best = (j, r, c)
        if best is None:
            break
        rj = max(best[1], floor)
        bb = _bic(rj, N, len(sel) + 1)
        if bb >= path[-1] - min_gain or rss - best[1] < min_drop * dd:
            break
        sel.append(best[0])
        rss, coef_s = rj, best[2]
        path.append(bb)
        if exclusive is not None:  # an alternative may now fit better in its place
            sel, coef_s, rss = _swap_alternatives(Gm, b, dd, sel, coef_s, rss, exclusive,
                                                  usable, floor)
            path[-1] = _bic(rss, N, len(sel))

    pruned: list[str] = []
    while prune and len(sel) > 1:
        for j in list(sel):
            idx = [i for i in sel if i != j]
            c = np.linalg.solve(Gm[np.ix_(idx, idx)], b[idx])
            r = dd - float(c @ b[idx])
            if r - rss < min_drop * dd:
                pruned.append(names[j])
                sel, coef_s, rss = idx, c, max(r, floor)
                path = path[:len(sel)] + [_bic(rss, N, len(sel))]
                break
        else:
            break

    return s, sel, coef_s, rss, path, pruned


def _selection_options(names, nterms, max_terms, min_gain, min_drop):
    """The checked names and options of a forward selection over nterms terms."""
    try:
        names = None if isinstance(names, str) else list(names)
    except TypeError:
        names = None
    if names is None or not all(isinstance(v, str) for v in names):
        raise DimensionError("names must be a sequence of term names (strings), one per row "
                             "of terms")
    if len(names) != nterms:
        raise DimensionError(f"names has {len(names)} entries; expected nterms = {nterms} "
                             f"(one name per row of terms)")
    if max_terms is not None:
        max_terms = check_positive(max_terms, "max_terms", integer=True, allow_zero=True)
    min_gain = check_positive(min_gain, "min_gain", allow_zero=True)
    min_drop = check_positive(min_drop, "min_drop", allow_zero=True)
    if min_drop >= 1:
        raise DataError(f"min_drop must be below 1 (a fraction of sum(d**2)); found {min_drop!r}")
    max_terms = nterms if max_terms is None else min(max_terms, nterms)
    return names, max_terms, min_gain, min_drop


def forward_selection(terms: ArrayLike, d: ArrayLike, names: Sequence[str], *,
                      max_terms: int | None = None, min_gain: float = 0.0,
                      min_drop: float = 0.0, prune: bool = False,
                      exclusive: Sequence | None = None) -> SparseLaw:
    """Greedy forward selection of terms with a BIC stopping rule.

    At each step the term that most reduces the residual sum of squares (RSS)
    is added; selection stops when the BIC ``N log(RSS/N) + k log N`` would
    not drop by more than ``min_gain``, or the term would remove less than
    ``min_drop`` of ``sum(d**2)`` (PAPER_NOTES §9.4: this finds the true terms
    where thresholded least squares keeps too many).

    Parameters
    ----------
    terms : array_like, shape (nterms, nsteps)
        Candidate terms evaluated on the data.
    d : array_like, shape (nsteps,) or (1, nsteps)
        Regressand (one channel).
    names : sequence of str, length nterms
    max_terms : int, optional
        Largest number of selected terms (default: nterms).
    min_gain : float
        Required BIC decrease per added term (0: plain BIC).
    min_drop : float
        Required RSS decrease per added term, as a fraction of ``sum(d**2)``
        (0: none). For a noisy, coloured regressand (such as an estimated
        model error d^) the BIC alone keeps negligible terms.
    prune : bool
        After the forward pass, repeatedly remove a selected term whose
        removal raises the RSS by less than ``min_drop * sum(d**2)`` (a greedy
        step can admit a proxy term before the true one). Has no effect with
        ``min_drop = 0``.
    exclusive : sequence, length nterms, optional
        Alternatives: terms with the same label other than None are never selected
        together (e.g. the odd shapes v^3, sign(v), v*|v| of one variable).

    Returns
    -------
    SparseLaw

    Raises
    ------
    DimensionError
        If ``terms``, ``d`` and ``names`` disagree in size.
    DataError
        If the data contain NaN or inf, or an option is out of range.

    Notes
    -----
    Terms are scaled to unit RMS and the Gram matrix :math:`X_s X_s^T` and
    :math:`X_s d` are formed once (:math:`O(n_{terms}^2 N)`); each candidate
    then costs a :math:`k \times k` solve, and the RSS follows from
    :math:`d^T d - c^T X_s d`. Candidates whose Gram block has a condition
    number above 1e12 (near-duplicates of selected terms) are passed over;
    terms that are identically zero are never selected. RSS values below
    ``1e-10 * sum(d**2)`` are treated as equal (the rounding level of the
    normal equations), so an exact fit stops instead of adding terms that
    only reduce round-off.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> x = rng.standard_normal((3, 500))
    >>> d = 2.0 * x[1] + 0.01 * rng.standard_normal(500)
    >>> law = forward_selection(x, d, ["a", "b", "c"])
    >>> law.names
    ('b',)
    """
    X = check_signal(terms, None, "terms")
    d = check_signal(d, 1, "d")[0]  # one channel: (nsteps,) or (1, nsteps)
    N = check_same_length(("terms", X), ("d", d[None, :]))
    names, max_terms, min_gain, min_drop = _selection_options(
        names, X.shape[0], max_terms, min_gain, min_drop)

    # unit-RMS scaling applied to the products, not to X: no nterms x N copies (each as
    # large as the terms themselves, 290 MB for 362 terms at N = 1e5)
    with single_thread_blas():  # thin products: threads only cost (and stall under load)
        gram, cross = X @ X.T, X @ d
    s, sel, coef_s, rss, path, pruned = _select_on_gram(
        gram, cross, float(d @ d), N, names, max_terms, min_gain, min_drop, prune,
        _exclusive(exclusive, X.shape[0]))
    coef = coef_s / s[sel] if sel else np.zeros(0)
    e = d - coef @ X[sel] if sel else d
    return SparseLaw(names=tuple(names[j] for j in sel), index=tuple(sel), coef=coef,
                     residual_var=float(e @ e) / N, bic_path=np.array(path),
                     pruned=tuple(pruned))


def forward_selection_gram(gram: ArrayLike, cross: ArrayLike, dd: float, nsteps: int,
                           names: Sequence[str], *, max_terms: int | None = None,
                           min_gain: float = 0.0, min_drop: float = 0.0,
                           prune: bool = False, exclusive: Sequence | None = None
                           ) -> SparseLaw:
    """:func:`forward_selection` from the products of the terms, not the terms.

    For callers that form ``X X^T`` and ``X d`` without holding X (or a
    filtered copy of it) in memory, e.g. accumulated over blocks of time.
    The selection is the same as :func:`forward_selection` on X and d; the
    law's ``residual_var`` is the RSS of the normal equations over nsteps.

    Parameters
    ----------
    gram : array_like, shape (nterms, nterms)
        ``X X^T`` of the candidate terms X (nterms, nsteps).
    cross : array_like, shape (nterms,)
        ``X d``.
    dd : float
        ``d^T d``.
    nsteps : int
        Number of samples N behind the products.
    names : sequence of str, length nterms
    max_terms : int, optional
        As :func:`forward_selection`.
    min_gain : float
        As :func:`forward_selection`.
    min_drop : float
        As :func:`forward_selection`.
    prune : bool
        As :func:`forward_selection`.
    exclusive : sequence, length nterms, optional
        As :func:`forward_selection`.

    Returns
    -------
    SparseLaw

    Raises
    ------
    DimensionError
        If gram is not square, or cross and names disagree with it.
    DataError
        If a product is not finite, or an option is out of range.
    """
    G = np.asarray(gram, dtype=float)
    b = np.asarray(cross, dtype=float).ravel()
    if G.ndim != 2 or G.shape[0] != G.shape[1]:
        raise DimensionError(f"gram has shape {G.shape}; expected (nterms, nterms) = X X^T")
    if b.size != G.shape[0]:
        raise DimensionError(f"cross has {b.size} entries; expected nterms = {G.shape[0]} "
                             f"(X d)")
    if not (np.all(np.isfinite(G)) and np.all(np.isfinite(b)) and np.isfinite(dd)):
        raise DataError("gram, cross and dd must be finite; found NaN or inf")
    N = check_positive(nsteps, "nsteps", integer=True)
    names, max_terms, min_gain, min_drop = _selection_options(
        names, G.shape[0], max_terms, min_gain, min_drop)
    s, sel, coef_s, rss, path, pruned = _select_on_gram(
        G, b, float(dd), N, names, max_terms, min_gain, min_drop, prune,
        _exclusive(exclusive, G.shape[0]))
    coef = coef_s / s[sel] if sel else np.zeros(0)
    return SparseLaw(names=tuple(names[j] for j in sel), index=tuple(sel), coef=coef,
                     residual_var=float(rss) / N, bic_path=np.array(path),
                     pruned=tuple(pruned))
