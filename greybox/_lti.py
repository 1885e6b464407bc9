"""Run a discrete linear time-invariant recursion without a per-sample Python loop.

``x[k+1] = Phi x[k] + v[k]`` is turned, by a complex Schur decomposition
``Phi = Z T Z^H`` (unitary Z, upper-triangular T), into n scalar first-order
recursions solved from the last coordinate up, each by
:func:`scipy.signal.lfilter` (compiled). The transform is unitary, so it is
numerically benign even when Phi is not diagonalizable; the cost is
O(n^2 N) vectorized work.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray
from scipy.signal import lfilter

__all__ = ["lti_states"]


_CHUNK = 1 << 15


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
        returned; it is ``Phi @ x[:, -1] + v[:, -1]``).
    """
    n, N = v.shape
    x = np.empty((n, N))
    if N == 0:
        return x
    if n == 0:
        return x
    if np.allclose(Phi, np.diag(np.diag(Phi)), rtol=0, atol=0) and np.isrealobj(Phi):
        # diagonal: independent real recursions, no transform needed
        for i in range(n):
            lam = Phi[i, i]
            x[i, 0] = x0[i]
            if N > 1:
                x[i, 1:] = lfilter([1.0], [1.0, -lam], v[i, :-1], zi=[lam * x0[i]])[0]
        return x
    T, Z = sla.schur(np.asarray(Phi, dtype=complex), output="complex")
    # time chunks bound the complex temporaries to O(n * _CHUNK) memory
    xk = np.asarray(x0, dtype=float)
    for a in range(0, N, _CHUNK):
        b = min(N, a + _CHUNK)
        _schur_chunk(T, Z, v[:, a:b], xk, x[:, a:b])
        xk = Phi @ x[:, b - 1] + v[:, b - 1]
    return x


def _schur_chunk(T, Z, v, x0, out):
    """One chunk of :func:`lti_states` in the Schur basis, written into ``out``."""
    n, N = v.shape
    ZH = Z.conj().T
    w = ZH @ v  # (n, N) complex
    z0 = ZH @ np.asarray(x0, dtype=complex)
    z = np.empty((n, N), dtype=complex)
    for i in range(n - 1, -1, -1):
        drive = w[i, :-1].copy()
        if i + 1 < n:
            drive += T[i, i + 1:] @ z[i + 1:, :-1]
        lam = T[i, i]
        z[i, 0] = z0[i]
        if N > 1:
            z[i, 1:] = lfilter([1.0], [1.0, -lam], drive, zi=[lam * z0[i]])[0]
    out[:] = (Z @ z).real
