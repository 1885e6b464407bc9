"""Covariances of fitted coefficients when the residuals are autocorrelated."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["hac_covariance"]


def hac_covariance(jac: NDArray, resid: NDArray, nout: int) -> NDArray[np.float64]:
    """Covariance of a least-squares estimate under autocorrelated residuals.

    ``(J^T J)^-1 Omega (J^T J)^-1`` with the Newey-West (Bartlett) estimate
    ``Omega = sum_l w_l (Gamma_l + Gamma_l^T)`` of the long-run covariance of
    the per-sample score ``s[t] = sum_o J[o, t] r[o, t]``. The bandwidth is
    twice the last lag at which the residual's mean autocorrelation is still
    at least 0.05 in magnitude (output-error residuals are coloured by the plant's own
    dynamics, so the textbook ``4 (T/100)^(2/9)`` lags would be far too few),
    at most T/4.

    Parameters
    ----------
    jac : ndarray, shape (nout * T, k)
        Jacobian of the stacked residual (output-major: ``r.reshape(nout, T)``).
    resid : ndarray, shape (nout * T,)
    nout : int
    """
    k = jac.shape[1]
    T = resid.size // nout
    r = resid.reshape(nout, T)
    s = np.einsum("otk,ot->tk", jac.reshape(nout, T, k), r)
    rc = r - r.mean(axis=1, keepdims=True)
    f = np.fft.rfft(rc, 2 * T, axis=1)
    acf = np.fft.irfft(f * np.conj(f), axis=1)[:, :T]
    acf = np.mean(acf / np.maximum(acf[:, :1], 1e-300), axis=0)
    above = np.flatnonzero(np.abs(acf[:T // 4]) >= 0.05)
    L = int(min(max(2 * (above[-1] if above.size else 1), 1), T // 4))
    # Gamma_l = sum_t s[t+l] s[t]^T for every lag at once (FFT), Bartlett weights
    fs = np.fft.rfft(s, 2 * T, axis=0)                       # (., k)
    gam = np.fft.irfft(fs[:, :, None] * np.conj(fs[:, None, :]), 2 * T, axis=0)[:L + 1]
    w = 1.0 - np.arange(1, L + 1) / (L + 1.0)
    G = np.einsum("l,lab->ab", w, gam[1:])
    Om = gam[0] + G + G.T
    JtJ = jac.T @ jac
    Ji = np.linalg.pinv(JtJ)
    return Ji @ Om @ Ji
