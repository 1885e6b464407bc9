"""Chunked accumulation of block-Hankel R factors for subspace identification.

The block Hankel matrix of a long record has ``nblock * nsig`` rows and about
``nsteps`` columns; it is never formed. Its columns are built a chunk at a
time and folded into the triangular factor ``R`` of ``H.T = Q R`` (LAPACK
``dtpqrt``, a QR update of a triangle by a rectangle), so memory is
``O(rows**2 + rows * chunk)``, independent of ``nsteps``.

All later computations work in "Q coordinates": a block of rows ``H[I]``
equals ``L[I] @ Q.T`` with ``L = R.T``, and ``Q`` has orthonormal columns, so
projections, regressions and sample covariances of the row spaces follow from
the small matrix ``L`` alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from .._blas import single_thread_blas
from .._validation import float_array
from ..exceptions import DataError, DimensionError

__all__: list[str] = []

#: Target number of float64 entries in one chunk of Hankel columns (8 MB).
_CHUNK_ENTRIES = 1 << 20


def small_blas():
    """Context limiting BLAS to one thread (see :mod:`greybox._blas`).

    Every BLAS call here is either small (a few hundred rows) or a thin
    ``syrk`` update; on a loaded 2-core machine a multithreaded BLAS was 25x
    slower (5 s instead of 0.08 s at N = 1e4, 32 s instead of ~1.5 s at 1e6).
    """
    return single_thread_blas()


def _as_signal(a, name: str, nrows: int | None) -> NDArray[np.float64]:
    """Return ``a`` as a 2-D float64 array (no copy when already float64).

    Mirrors :func:`greybox._validation.check_signal` (same messages) but avoids
    copying long records; finiteness is checked in chunks.
    """
    try:
        x = a if type(a) is np.ndarray and a.dtype == np.float64 else float_array(a)
    except (TypeError, ValueError) as e:
        raise DimensionError(f"{name} must be a numeric array; could not convert it ({e})") from e
    if x.ndim == 1 and nrows in (None, 1):
        x = x.reshape(1, -1)
    if x.ndim != 2 or (nrows is not None and x.shape[0] != nrows):
        exp = "nsignals" if nrows is None else str(nrows)
        hint = ""
        if x.ndim == 2 and nrows is not None and x.shape[1] == nrows:
            hint = " (time must be the last axis: pass the transpose)"
        elif x.ndim == 2 and nrows is None and x.shape[0] > x.shape[1]:
            hint = " (more signals than samples: time must be the last axis, pass the transpose?)"
        raise DimensionError(f"{name} has shape {x.shape}; expected ({exp}, nsteps){hint}")
    step = max(1, _CHUNK_ENTRIES // max(1, x.shape[0]))
    for c0 in range(0, x.shape[1], step):
        blk = x[:, c0:c0 + step]
        if not np.all(np.isfinite(blk)):
            bad = np.argwhere(~np.isfinite(blk))[0]
            raise DataError(
                f"{name} contains NaN or inf (first at signal {bad[0]}, sample {c0 + bad[1]}); "
                f"remove or interpolate those samples, or split the record into experiments "
                f"(pass lists of arrays)"
            )
    return x


def prepare_data(y, u) -> tuple[list[NDArray], list[NDArray], int, int]:
    """Validate one or several experiments.

    Returns lists ``ys`` (noutputs, N_e) and ``us`` (ninputs, N_e), and
    ``(noutputs, ninputs)``. ``y`` is either one array or a list/tuple of
    arrays (one per experiment); ``u`` likewise, or ``None`` / 0 rows.
    """
    multi = isinstance(y, (list, tuple)) and len(y) > 0 and all(
        isinstance(e, np.ndarray) for e in y
    )
    if multi:
        ylist = list(y)
        if u is None:
            ulist = [None] * len(ylist)
        elif isinstance(u, (list, tuple)) and len(u) == len(ylist) and all(
            e is None or isinstance(e, np.ndarray) for e in u
        ):
            ulist = list(u)
        else:
            nu = len(u) if isinstance(u, (list, tuple)) else "an array"
            raise DimensionError(
                f"y is a list of {len(ylist)} experiments but u is {nu!r}; expected a list of "
                f"{len(ylist)} input arrays (or None for no inputs)"
            )
    else:
        ylist, ulist = [y], [u]
    ys: list[NDArray] = []
    us: list[NDArray] = []
    nout = nin = None
    for e, (ye, ue) in enumerate(zip(ylist, ulist)):
        tag = f"[{e}]" if multi else ""
        ya = _as_signal(ye, f"y{tag}", nout)
        nout = ya.shape[0]
        if nout == 0:
            raise DimensionError(f"y{tag} has 0 outputs; expected at least one output signal")
        if ue is None:
            ua = np.zeros((0, ya.shape[1]))
        else:
            ua = np.asarray(ue) if np.ndim(ue) == 2 and np.shape(ue)[0] == 0 else ue
            if np.ndim(ua) == 2 and np.shape(ua)[0] == 0:
                ua = np.zeros((0, np.shape(ua)[1]))
            else:
                ua = _as_signal(ua, f"u{tag}", nin)
        if nin is not None and ua.shape[0] != nin:
            raise DimensionError(
                f"u{tag} has {ua.shape[0]} inputs; expected {nin} as in the first experiment"
            )
        nin = ua.shape[0]
        if ua.shape[1] != ya.shape[1]:
            hint = ("; time must be the last axis: pass the transpose of u"
                    if ua.shape[0] == ya.shape[1] else " (time is the last axis)")
            raise DimensionError(
                f"signals have different numbers of samples (y{tag}: {ya.shape[1]}, "
                f"u{tag}: {ua.shape[1]}); they must match{hint}"
            )
        ys.append(ya)
        us.append(ua)
    return ys, us, int(nout), int(nin)


def channel_rms(arrays: Sequence[NDArray]) -> NDArray[np.float64]:
    """Root mean square of every channel over all experiments (chunked)."""
    nch = arrays[0].shape[0]
    # scale by the largest magnitude first: squares of 1e200 (or 1e-200) would
    # overflow (underflow) and give an infinite (zero) RMS
    big = np.zeros(nch)
    for a in arrays:
        if a.shape[1]:
            big = np.maximum(big, np.max(np.abs(a), axis=1))
    inv = np.where(big > 0, 1.0 / np.where(big > 0, big, 1.0), 0.0)
    acc = np.zeros(nch)
    n = 0
    for a in arrays:
        step = max(1, _CHUNK_ENTRIES // max(1, nch))
        for c0 in range(0, a.shape[1], step):
            blk = a[:, c0:c0 + step] * inv[:, None]
            acc += np.einsum("ij,ij->i", blk, blk)
        n += a.shape[1]
    return big * np.sqrt(acc / max(n, 1))


@dataclass(frozen=True, eq=False)
class HankelR:
    """Lower factor ``L`` of a block Hankel matrix, ``H H.T / ncols = L L.T``.

    Row ``t * nsig + s`` of ``L`` is signal ``s`` of time block ``t`` (time
    major), with signals ordered ``[u; y]``.
    """

    L: NDArray[np.float64]
    ncols: int
    nblock: int
    ninputs: int
    noutputs: int

    def rows(self, sig: str, t0: int, t1: int) -> NDArray[np.float64]:
        """Rows of ``L`` for signal ``'u'`` or ``'y'``, time blocks t0..t1-1."""
        m, l = self.ninputs, self.noutputs
        nz = m + l
        off, w = (0, m) if sig == "u" else (m, l)
        idx = [t * nz + off + k for t in range(t0, t1) for k in range(w)]
        return self.L[idx]

    def z(self, t0: int, t1: int) -> NDArray[np.float64]:
        """Rows of ``L`` for ``[u; y]`` blocks t0..t1-1 (time major)."""
        nz = self.ninputs + self.noutputs
        return self.L[t0 * nz:t1 * nz]


def ncolumns(lengths: Sequence[int], nblock: int) -> int:
    """Number of Hankel columns over experiments of the given lengths."""
    return int(sum(max(0, n - nblock + 1) for n in lengths))


def hankel_r(
    ys: Sequence[NDArray],
    us: Sequence[NDArray],
    sy: NDArray,
    su: NDArray,
    nblock: int,
    *,
    chunk_size: int | None = None,
    method: str = "auto",
) -> HankelR:
    """Accumulate the R factor of the scaled block Hankel matrix in chunks.

    Parameters
    ----------
    ys, us : lists of arrays, shapes (noutputs, N_e), (ninputs, N_e)
    sy, su : arrays, shapes (noutputs,), (ninputs,)
        Scale factors; the Hankel matrix is built from ``y / sy``, ``u / su``.
    nblock : int
        Number of block rows (time blocks).
    chunk_size : int, optional
        Hankel columns per chunk; default keeps a chunk near 8 MB.
    method : {"auto", "gram", "qr"}
        ``"qr"`` folds every chunk into ``R`` by a QR update (backward stable,
        about 4x slower). ``"gram"`` accumulates ``H H.T`` (one BLAS ``syrk``
        per chunk) and takes its Cholesky factor; it loses the singular
        directions of ``H`` below ``sqrt(eps)`` of the largest. ``"auto"``
        uses ``"gram"`` and falls back to ``"qr"`` (a second pass) when the
        Cholesky factor fails or its diagonal spans more than ``1 / _GRAM_RTOL``.
    """
    if chunk_size is not None:
        if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) \
                or chunk_size < 1:
            raise DimensionError(f"chunk_size must be a positive integer (Hankel columns per "
                                 f"chunk) or None for the default; found {chunk_size!r}")
        chunk_size = int(chunk_size)
    with small_blas():
        if method == "auto":
            out = _hankel_r(ys, us, sy, su, nblock, chunk_size, "gram")
            if out is not None:
                return out
            method = "qr"
        out = _hankel_r(ys, us, sy, su, nblock, chunk_size, method)
    assert out is not None
    return out


#: Smallest accepted ratio min/max of the Cholesky diagonal in the Gram path.
#: Below it, the squared condition number of the Gram matrix would cost more
#: than half of the float64 digits in the weakest direction.
_GRAM_RTOL = 1e-6


def _hankel_r(ys, us, sy, su, nblock, chunk_size, method):
    m, l = us[0].shape[0], ys[0].shape[0]
    nz = m + l
    nrows = nblock * nz
    if chunk_size is None:
        chunk_size = max(256, _CHUNK_ENTRIES // nrows)
    inv = np.concatenate([1.0 / su, 1.0 / sy])[:, None]
    R = np.zeros((nrows, nrows), order="F")
    G = np.zeros((nrows, nrows))
    ncols = 0
    for ye, ue in zip(ys, us):
        nsteps = ye.shape[1]
        ncol_e = nsteps - nblock + 1
        for c0 in range(0, max(ncol_e, 0), chunk_size):
            c1 = min(ncol_e, c0 + chunk_size)
            seg = np.concatenate([ue[:, c0:c1 + nblock - 1], ye[:, c0:c1 + nblock - 1]], axis=0)
            seg *= inv
            # windows: (nz, ncol, nblock) -> rows of H.T: (ncol, nblock * nz), time major
            win = sliding_window_view(seg, nblock, axis=1)
            B = np.ascontiguousarray(win.transpose(1, 2, 0)).reshape(c1 - c0, nrows)
            if method == "gram":
                G += B.T @ B
            else:
                B = np.asfortranarray(B)
                R, _, _, info = sla.lapack.dtpqrt(
                    0, min(nrows, 16), R, B, overwrite_a=1, overwrite_b=1
                )
                if info != 0:  # pragma: no cover - LAPACK argument error
                    raise RuntimeError(f"dtpqrt failed with info={info}")
            ncols += c1 - c0
    if method == "gram":
        try:
            L = np.linalg.cholesky(G / max(ncols, 1))
        except np.linalg.LinAlgError:
            return None
        d = np.abs(np.diag(L))
        if d.size and d.min() < _GRAM_RTOL * d.max():
            return None
        return HankelR(L=L, ncols=ncols, nblock=nblock, ninputs=m, noutputs=l)
    R = np.triu(R)
    L = R.T / np.sqrt(max(ncols, 1))
    return HankelR(L=np.ascontiguousarray(L), ncols=ncols, nblock=nblock, ninputs=m, noutputs=l)
