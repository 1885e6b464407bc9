"""Covariances of fitted coefficients when the residuals are autocorrelated."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.fft import next_fast_len

__all__ = ["UNDETERMINED_COND", "hac_covariance", "residual_colour", "undetermined"]

#: The data do not determine a coefficient that weighs on a direction of the fit whose
#: Jacobian singular value (columns scaled to unit norm) is below the largest over this
#: factor: the least-squares covariance ``(J^T J)^-1`` then has a condition number above
#: its square, 1e12, where a pseudo-inverse's variances lose every digit that matters (a
#: singular direction gets variance 0: "± 2.8e-19" on a coefficient of 2.4e-4).
UNDETERMINED_COND = 1e6


def undetermined(jac: NDArray) -> NDArray[np.bool_]:
    """Which coefficients of a least-squares fit the data do not determine, shape (k,).

    A coefficient whose Jacobian column is zero, or that takes part (weight above
    1e-3 in the right singular vector) in a direction whose singular value is below
    ``1 / UNDETERMINED_COND`` of the largest, columns scaled to unit norm. Its
    interval is "not determined", never a half-width from a singular covariance.

    Parameters
    ----------
    jac : ndarray, shape (nresiduals, k)
    """
    J = np.asarray(jac, dtype=float)
    k = J.shape[1]
    if k == 0:
        return np.zeros(0, dtype=bool)
    norms = np.sqrt(np.einsum("ij,ij->j", J, J))
    dead = ~(norms > 0) | ~np.isfinite(norms)
    if dead.all():
        return dead
    live = np.flatnonzero(~dead)
    _, s, Vt = np.linalg.svd(J[:, live] / norms[live], full_matrices=False)
    weak = s < s[0] / UNDETERMINED_COND
    out = dead.copy()
    if weak.any():
        out[live] = np.any(np.abs(Vt[weak]) > 1e-3, axis=0)
    return out


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
    # zero padding to >= 2T makes the circular correlations linear; a 5-smooth length keeps
    # the FFT fast (2T itself may have a large prime factor: 16x slower at T ~ 1e6)
    nfft = next_fast_len(2 * T, real=True)
    f = np.fft.rfft(rc, nfft, axis=1)
    acf = np.fft.irfft(f * np.conj(f), nfft, axis=1)[:, :T]
    acf = np.mean(acf / np.maximum(acf[:, :1], 1e-300), axis=0)
    above = np.flatnonzero(np.abs(acf[:T // 4]) >= 0.05)
    L = int(min(max(2 * (above[-1] if above.size else 1), 1), T // 4))
    # Gamma_l = sum_t s[t+l] s[t]^T for every lag at once (FFT), Bartlett weights; one
    # (a, b) pair at a time: the whole (nfft, k, k) cross-spectrum would need
    # 16 k^2 nfft bytes (1.3 GB for 9 terms at T = 1e6)
    fs = np.fft.rfft(s, nfft, axis=0)                        # (., k)
    w = 1.0 - np.arange(1, L + 1) / (L + 1.0)
    Om = np.empty((k, k))
    for a in range(k):
        for b in range(a, k):
            g = np.fft.irfft(fs[:, a] * np.conj(fs[:, b]), nfft)   # g[l] = Gamma_l[a, b]
            g_ab, g_ba = g[1:L + 1] @ w, g[nfft - L:][::-1] @ w     # Gamma_l[b, a] = g[-l]
            Om[a, b] = g[0] + g_ab + g_ba
            Om[b, a] = Om[a, b]
    JtJ = jac.T @ jac
    Ji = np.linalg.pinv(JtJ)
    return Ji @ Om @ Ji


def residual_colour(r: NDArray) -> float:
    """Colour c >= 1 of residuals r (noutputs, nsteps): long-run variance over variance.

    Per output (scaled to unit variance) the long-run variance of its mean
    (:func:`hac_covariance` of a constant fit: the Bartlett-weighted sum of its
    autocorrelations), averaged over outputs, over the mean square: the residual
    carries about nsteps / c independent samples per output (an output error
    integrates the process noise: a BIC on every sample would take terms that only
    fit its colour).
    """
    with np.errstate(over="ignore", invalid="ignore"):
        sd = np.std(r, axis=1)
    live = np.isfinite(sd) & (sd > 0)  # a constant row (a diverged trial, clipped) has none
    if not live.any():
        return 1.0
    r = r[live] / sd[live, None]
    T = r.shape[1]
    # long-run variance of the mean residual per output: hac_covariance of a constant fit
    lr = [float(hac_covariance(np.ones((T, 1)), ro, 1)[0, 0]) * T for ro in r]
    return max(1.0, float(np.mean(lr)) / float(np.mean(r**2)))
