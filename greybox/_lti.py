"""Run a discrete linear time-invariant recursion without a per-sample Python loop.

``x[k+1] = Phi x[k] + v[k]`` is split into n scalar first-order recursions,
each solved by :func:`scipy.signal.lfilter` (compiled):

* diagonal Phi: the rows are independent, no transform;
* diagonalizable Phi with a well-conditioned eigenvector matrix V
  (``cond(V) <= _MAX_COND``): modal coordinates ``z = V^-1 x`` in real
  arithmetic -- a real recursion per real eigenvalue, one complex recursion
  per complex-conjugate pair (its conjugate twin is implied), and real
  ``n x n`` transforms in and out;
* otherwise a complex Schur decomposition ``Phi = Z T Z^H`` (unitary Z,
  upper-triangular T), solved from the last coordinate up. The transform is
  unitary, so it is numerically benign even when Phi is not diagonalizable.

The cost is O(n^2 N) vectorized work; time is processed in chunks of
``CHUNK`` samples so the temporaries stay O(n * CHUNK). :class:`LTIRecursion`
keeps the decomposition and runs chunk after chunk (carrying the state), so
callers can fuse their own per-chunk work around it.
"""

from __future__ import annotations


import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray
from scipy.signal import lfilter

from ._jit import HAVE_NUMBA, lazy_njit

__all__ = ["lti_states", "lti_output", "LTIRecursion", "single_thread_blas", "spectral_radius"]

from ._blas import single_thread_blas  # noqa: E402  (re-exported for the filters)


CHUNK = 1 << 15
#: Largest condition number of the eigenvector matrix for the modal path; its
#: round-off is ~cond(V) * eps relative, the Schur path's ~eps.
_MAX_COND = 1e3


def _conditioned(V: NDArray, W: NDArray) -> bool:
    """Whether the 2-norm condition number of V (W its inverse) is at most ``_MAX_COND``,
    in the state's own coordinates or, failing that, in diagonally rescaled ones
    (:func:`_scaled`).

    The 1-norm one, from W at hand, brackets it (``cond_1 / n <= cond_2 <= n cond_1``):
    the singular values (an SVD, a tenth of a simulation of a small model) are needed
    only between the brackets.
    """
    if _cond_at_most(V, W):
        return True
    Vs, Ws = _scaled(V, W)
    return _cond_at_most(Vs, Ws)


def _cond_at_most(V: NDArray, W: NDArray) -> bool:
    """``np.linalg.cond(V) <= _MAX_COND`` (W its inverse), the 1-norm brackets first."""
    n = V.shape[0]
    with np.errstate(all="ignore"):
        c1 = float(np.abs(V).sum(axis=0).max() * np.abs(W).sum(axis=0).max())
    if not np.isfinite(c1):
        return False
    if c1 <= _MAX_COND / n:
        return True
    if c1 > _MAX_COND * n:
        return False
    with np.errstate(all="ignore"):
        c = np.linalg.cond(V)
    return bool(np.isfinite(c) and c <= _MAX_COND)


#: Sweeps of the diagonal equilibration of :func:`_scaled`, and the widest ratio of its
#: scales: a chain's positions and velocities need ~210; a Jordan block at one eigenvalue
#: would take 1e16, where V's inverse carries round-off of its own size (its simulation
#: was off by 1.7 of the state's RMS), so the scales are clipped and it stays with Schur
_EQUILIBRATE = 12
_SCALE_RANGE = 1e3


def _scaled(V: NDArray, W: NDArray) -> tuple[NDArray, NDArray]:
    """``(D V C, C^-1 W D^-1)``: the eigenvectors in diagonally rescaled states (D) with unit
    columns (C), D equilibrating the rows of V against the columns of W.

    States of different natural scales (a chain's positions and velocities: the two
    columns of a slow mode's conjugate pair are nearly parallel in (p, v)) make V
    ill-conditioned in the state's own units while the modes are well separated: a
    uniform chain of 16 masses by positions reads cond(V) = 2.2e3 and 17 once rescaled.
    The modal path's round-off relative to each state's own scale is ~cond(D V C) eps, so
    the modal form is taken on the rescaled condition number (the transforms themselves
    are V and W, unchanged). The scales stay within :data:`_SCALE_RANGE` of each other.
    Each sweep is O(n^2); no inverse is formed.
    """
    d = np.ones(V.shape[0])
    absV, absW = np.abs(V), np.abs(W)
    with np.errstate(all="ignore"):
        for _ in range(_EQUILIBRATE):
            c = 1.0 / np.sqrt(((absV * d[:, None]) ** 2).sum(axis=0))  # unit columns of D V
            rows = np.sqrt(((absV * d[:, None] * c[None, :]) ** 2).sum(axis=1))
            cols = np.sqrt(((absW / c[:, None] / d[None, :]) ** 2).sum(axis=0))
            d = d * np.sqrt(cols / rows)
            if not np.all(np.isfinite(d)) or np.any(d <= 0):
                return V, W
            g = np.exp(np.mean(np.log(d)))  # the scales within _SCALE_RANGE of each other
            d = np.clip(d / g, _SCALE_RANGE ** -0.5, _SCALE_RANGE ** 0.5)
        c = 1.0 / np.sqrt(((absV * d[:, None]) ** 2).sum(axis=0))
        return V * d[:, None] * c[None, :], W / c[:, None] / d[None, :]


class LTIRecursion:
    """``x[k+1] = Phi x[k] + v[:, k]`` run chunk by chunk.

    Parameters
    ----------
    Phi : ndarray, shape (n, n)
        Real transition matrix.
    """

    def __init__(self, Phi: NDArray):
        Phi = np.asarray(Phi, dtype=float)
        self.Phi = Phi
        n = self.n = Phi.shape[0]
        self.kind = "schur"
        if n == 0:
            self.kind = "empty"
            return
        if not np.any(Phi - np.diag(np.diag(Phi))):
            self.kind = "diagonal"
            self.lam = np.diag(Phi).copy()
            return
        if self._try_modal(Phi):
            self.kind = "modal"
            return
        self.T, self.Z = sla.schur(np.asarray(Phi, dtype=complex), output="complex")
        self.ZH = self.Z.conj().T

    # ----------------------------------------------------------------- set-up
    def _try_modal(self, Phi) -> bool:
        """Real modal form: True if Phi is diagonalizable with cond(V) <= _MAX_COND."""
        n = Phi.shape[0]
        try:
            lam, V = np.linalg.eig(Phi)
        except np.linalg.LinAlgError:  # pragma: no cover - eig failed to converge
            return False
        if not np.all(np.isfinite(lam)) or not np.all(np.isfinite(V)):
            return False
        # LAPACK dgeev returns exact-real eigenvalues (imag == 0) for real modes
        # and consecutive conjugate pairs (positive imaginary part first)
        modes = []  # (index, is_pair)
        i = 0
        while i < n:
            if lam[i].imag == 0:
                modes.append((i, False))
                i += 1
            elif i + 1 < n and lam[i + 1] == np.conj(lam[i]):
                modes.append((i, True))
                i += 2
            else:
                return False
        try:
            W = np.linalg.inv(V)
        except np.linalg.LinAlgError:  # exactly singular: not diagonalizable
            return False
        if not np.all(np.isfinite(W)) or not _conditioned(V, W):
            return False
        # real coordinates r: a real mode -> one row; a pair -> (Re z, Im z)
        # x = Vr @ r, r_in = Wr @ v (Wr rows: W_i, or Re W_i and Im W_i)
        Vr = np.empty((n, n))
        Wr = np.empty((n, n))
        lam_r = []  # per mode: eigenvalue (real float or complex)
        rows = []  # per mode: first row of r, is_pair
        r = 0
        for i, pair in modes:
            if pair:
                Vr[:, r] = 2.0 * V[:, i].real
                Vr[:, r + 1] = -2.0 * V[:, i].imag
                Wr[r] = W[i].real
                Wr[r + 1] = W[i].imag
                lam_r.append(complex(lam[i]))
                rows.append((r, True))
                r += 2
            else:
                Vr[:, r] = V[:, i].real
                Wr[r] = W[i].real
                lam_r.append(float(lam[i].real))
                rows.append((r, False))
                r += 1
        self.Vr, self.Wr, self.mode_lam, self.mode_rows = Vr, Wr, lam_r, rows
        self._modes = (np.array([r for r, _ in rows], dtype=np.int64),
                       np.array([p for _, p in rows], dtype=np.bool_),
                       np.array([complex(v).real for v in lam_r]),
                       np.array([complex(v).imag for v in lam_r]))
        return True

    # ----------------------------------------------------------------- run
    @property
    def in_map(self) -> NDArray | None:
        """Real matrix S with ``run(S @ v, ..., mapped=True) == run(v, ...)``, or None.

        Callers that build v as a sum of products can fold S into their
        matrices and save one pass over the chunk (modal path only).
        """
        return self.Wr if self.kind == "modal" else None

    def run(self, v: NDArray, x0: NDArray, out: NDArray, *, mapped: bool = False) -> NDArray:
        """Write ``x[0..c-1]`` of one chunk into ``out`` (n, c); return ``x[c]``.

        ``x[0] = x0``; ``v`` (n, c) is the driving term of the chunk, or
        ``in_map @ v`` if ``mapped`` (only when :attr:`in_map` is not None).
        ``out`` may be a strided view (e.g. columns of a longer preallocated array).
        """
        c = v.shape[1]
        x0 = np.asarray(x0, dtype=float)
        if self.kind == "empty" or c == 0:
            return x0
        if self.kind == "modal":
            return self._modal_chunk(v if mapped else self.Wr @ v, x0, out)
        if mapped:
            raise ValueError("mapped=True needs in_map (modal path)")
        if self.kind == "diagonal":
            for i in range(self.n):
                lam = self.lam[i]
                out[i, 0] = x0[i]
                if c > 1:
                    out[i, 1:] = lfilter([1.0], [1.0, -lam], v[i, :-1], zi=[lam * x0[i]])[0]
        else:
            self._schur_chunk(v, x0, out)
        return self.Phi @ out[:, c - 1] + v[:, c - 1]

    def _modal_chunk(self, w, x0, out, Cv=None):
        """Modal coordinates r (x = Vr r); ``w = Wr @ v``. Returns x[c].

        With ``Cv = C @ Vr`` (p, n), ``out`` (p, c) receives ``C x`` instead of x.
        """
        n, c = w.shape
        r0 = self.Wr @ x0
        rr = np.empty((n, c + 1))  # r[0..c]; r[c] is the next chunk's start
        rr[:, 0] = r0
        if HAVE_NUMBA:  # the modes' first-order recursions in one compiled loop
            _modal_recursions(np.ascontiguousarray(w, dtype=float), *self._modes, rr)
        else:
            for lam, (r, pair) in zip(self.mode_lam, self.mode_rows):
                if pair:
                    z0 = complex(r0[r], r0[r + 1])
                    wc = np.empty(c, dtype=complex)
                    wc.real, wc.imag = w[r], w[r + 1]
                    z = lfilter([1.0], [1.0, -lam], wc, zi=[lam * z0])[0]
                    rr[r, 1:] = z.real
                    rr[r + 1, 1:] = z.imag
                else:
                    rr[r, 1:] = lfilter([1.0], [1.0, -lam], w[r], zi=[lam * r0[r]])[0]
        np.matmul(self.Vr if Cv is None else Cv, rr[:, :c], out=out)
        return self.Vr @ rr[:, c]

    def _schur_chunk(self, v, x0, out):
        n, c = v.shape
        T, Z, ZH = self.T, self.Z, self.ZH
        w = ZH @ v  # (n, c) complex
        z0 = ZH @ np.asarray(x0, dtype=complex)
        z = np.empty((n, c), dtype=complex)
        for i in range(n - 1, -1, -1):
            drive = w[i, :-1].copy()
            if i + 1 < n:
                drive += T[i, i + 1:] @ z[i + 1:, :-1]
            lam = T[i, i]
            z[i, 0] = z0[i]
            if c > 1:
                z[i, 1:] = lfilter([1.0], [1.0, -lam], drive, zi=[lam * z0[i]])[0]
        out[:] = (Z @ z).real


def spectral_radius(A: NDArray) -> float:
    """``max |eig(A)|`` of a square matrix (0 for an empty one; inf where the
    eigenvalues cannot be computed)."""
    A = np.asarray(A, dtype=float)
    if not A.size:
        return 0.0
    try:
        return float(np.max(np.abs(np.linalg.eigvals(A))))
    except np.linalg.LinAlgError:
        return np.inf


def lti_states(Phi: NDArray, v: NDArray, x0: NDArray) -> NDArray[np.float64]:
    """States of ``x[k+1] = Phi x[k] + v[:, k]`` for k = 0..N-1.

    Parameters
    ----------
    Phi : ndarray, shape (n, n)
    v : ndarray, shape (n, N)
        Driving term at each step.
    x0 : ndarray, shape (n,)
        Initial state x[0].

    Returns
    -------
    ndarray, shape (n, N)
        ``x[0], ..., x[N-1]`` (the state after the last driving sample is not
        returned; it is ``Phi @ x[:, -1] + v[:, -1]``). An unstable recursion
        may overflow to inf/NaN without a warning: callers check finiteness
        and raise their own error.
    """
    n, N = v.shape
    x = np.empty((n, N))
    if N == 0 or n == 0:
        return x
    rec = LTIRecursion(Phi)
    xk = np.asarray(x0, dtype=float)
    with single_thread_blas(), np.errstate(over="ignore", invalid="ignore"):
        for a in range(0, N, CHUNK):
            b = min(N, a + CHUNK)
            xk = rec.run(v[:, a:b], xk, x[:, a:b])
    return x


def lti_output(Phi: NDArray, B: NDArray, C: NDArray, D: NDArray, u: NDArray,
               x0: NDArray) -> NDArray[np.float64]:
    """Outputs ``C x[k] + D u[k]`` of ``x[k+1] = Phi x[k] + B u[k]``, k = 0..N-1.

    The same numbers as ``C @ lti_states(Phi, B @ u, x0) + D @ u`` (to rounding) without
    the (n, N) state history where Phi has the modal form: the input enters the modal
    coordinates through ``Wr B`` (n x m) and leaves through ``C Vr`` (p x n), so a
    simulation costs O((m + p) n N) rather than O(n^2 N) (an output-error fit of a large
    model with few inputs and outputs simulates it hundreds of times).

    Parameters
    ----------
    Phi : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    C : ndarray, shape (p, n)
    D : ndarray, shape (p, m)
    u : ndarray, shape (m, N)
    x0 : ndarray, shape (n,)

    Returns
    -------
    ndarray, shape (p, N)
        Not finite where the recursion diverged (callers check).
    """
    n, N = Phi.shape[0], u.shape[1]
    C = np.asarray(C, dtype=float)
    rec = LTIRecursion(Phi) if n and N else None
    if rec is None or rec.kind != "modal":
        with np.errstate(over="ignore", invalid="ignore"):
            return C @ lti_states(Phi, B @ u, x0) + D @ u
    y = np.empty((C.shape[0], N))
    WB, Cv = rec.Wr @ B, C @ rec.Vr
    xk = np.asarray(x0, dtype=float)
    with single_thread_blas(), np.errstate(over="ignore", invalid="ignore"):
        for a in range(0, N, CHUNK):
            b = min(N, a + CHUNK)
            # one input: an outer product (the same numbers as the matmul, faster)
            w = WB * u[:, a:b] if WB.shape[1] == 1 else WB @ u[:, a:b]
            xk = rec._modal_chunk(w, xk, y[:, a:b], Cv)  # xk: x[b]
        if np.any(D):
            y += D @ u
    return y


@lazy_njit
def _modal_recursions(w, rows, pairs, lre, lim, rr):
    """``r[t+1] = lam r[t] + w[t]`` of every mode (a pair in complex arithmetic on its two
    rows, as ``lfilter([1], [1, -lam])`` computes it) into rr[:, 1:] (rr[:, 0] = r[0])."""
    c = w.shape[1]
    for q in range(rows.shape[0]):
        r = rows[q]
        a, b = lre[q], lim[q]
        if pairs[q]:
            zr, zi = rr[r, 0], rr[r + 1, 0]
            for t in range(c):
                nr = (a * zr - b * zi) + w[r, t]
                zi = (a * zi + b * zr) + w[r + 1, t]
                zr = nr
                rr[r, t + 1] = zr
                rr[r + 1, t + 1] = zi
        else:
            z = rr[r, 0]
            for t in range(c):
                z = a * z + w[r, t]
                rr[r, t + 1] = z
