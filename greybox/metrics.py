"""Error metrics and residual tests.

Relative error of eq. (42), sample auto- and cross-correlations with their
confidence bands, and the Ljung-Box whiteness test. Signals are arrays of
shape ``(nsignals, nsteps)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2, norm

from ._validation import as_signal, check_positive, check_same_length, check_signal
from .exceptions import DataError

__all__ = [
    "RelativeError",
    "relative_error",
    "autocorrelation",
    "cross_correlation",
    "correlation_band",
    "WhitenessTest",
    "whiteness_test",
    "innovation_test",
    "effective_samples",
    "independent_samples",
    "oe_criterion",
    "OutputFit",
    "output_fit",
    "criterion_scores",
]


@dataclass(frozen=True)
class RelativeError:
    """Relative error of eq. (42).

    Attributes
    ----------
    value : float
        Mean over outputs [%].
    per_output : ndarray, shape (noutputs,)
        Per output [%].
    squared : bool
        False: relative RMS, ``100 sqrt(sum e^2 / sum y^2)`` (the default);
        True: ``100 sum e^2 / sum y^2`` (the other reading of eq. 42).
    """

    value: float
    per_output: NDArray[np.float64]
    squared: bool

    def __float__(self) -> float:
        return float(self.value)


def _row_norms(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """2-norm of each row, each scaled by a power of two near its peak first (exact).

    Squares of 1e-300 do not underflow to a false "identically zero", nor
    do those of 1e150 overflow.
    """
    peak = np.max(np.abs(a), axis=1, initial=0.0)
    scale = np.ldexp(1.0, np.minimum(-np.frexp(peak)[1], 1000))
    return np.sqrt(np.sum((a * scale[:, None]) ** 2, axis=1)) / scale


def relative_error(y: ArrayLike, y_hat: ArrayLike, *, squared: bool = False,
                   skip: int = 0) -> RelativeError:
    """Relative error of eq. (42), per output and averaged over outputs.

    .. math::

        E = \\frac{100}{p} \\sum_{i=1}^{p}
            \\sqrt{\\frac{\\sum_k (y_i[k] - \\hat y_i[k])^2}{\\sum_k y_i[k]^2}}\\ \\%

    Parameters
    ----------
    y : array_like, shape (noutputs, nsteps)
        Measured outputs.
    y_hat : array_like, shape (noutputs, nsteps)
        Estimated, simulated or predicted outputs.
    squared : bool
        Drop the square root (PAPER_NOTES §8.3: eq. 42 is ambiguous; the
        square-root form is the default and every greybox table says which).
    skip : int
        Leading samples to leave out (e.g. a filter's transient).

    Returns
    -------
    RelativeError
    """
    y = check_signal(y, None, "y")
    y_hat = check_signal(y_hat, y.shape[0], "y_hat")
    check_same_length(("y", y), ("y_hat", y_hat))
    skip = check_positive(skip, "skip", integer=True, allow_zero=True)
    y, y_hat = y[:, skip:], y_hat[:, skip:]
    if np.any(np.max(np.abs(y), axis=1, initial=0.0) == 0):
        raise DataError("an output of y is identically zero; its relative error is undefined")
    with np.errstate(over="ignore", invalid="ignore"):
        rel = _row_norms(y - y_hat) / _row_norms(y)  # a diverged model gives inf
        per = 100 * (rel**2 if squared else rel)
    return RelativeError(value=float(per.mean()), per_output=per, squared=squared)


def autocorrelation(e: ArrayLike, maxlag: int = 20) -> NDArray[np.float64]:
    """Normalized sample autocorrelation of each channel, lags 0..maxlag.

    Parameters
    ----------
    e : array_like, shape (nsignals, nsteps)
    maxlag : int

    Returns
    -------
    ndarray, shape (nsignals, maxlag + 1)
        ``r[i, 0] == 1``.
    """
    e = check_signal(e, None, "e", min_steps=2)
    maxlag = check_positive(maxlag, "maxlag", integer=True)
    N = e.shape[1]
    if maxlag >= N:
        raise DataError(f"maxlag = {maxlag} must be below the number of samples {N}")
    e = e - e.mean(axis=1, keepdims=True)
    c0 = np.sum(e * e, axis=1)
    c0[c0 == 0] = 1.0
    r = np.empty((e.shape[0], maxlag + 1))
    for lag in range(maxlag + 1):
        r[:, lag] = np.sum(e[:, lag:] * e[:, :N - lag], axis=1) / c0
    return r


def cross_correlation(u: ArrayLike, e: ArrayLike, maxlag: int = 20) -> NDArray[np.float64]:
    """Normalized sample cross-correlation ``r_ue(tau) = E[e[k+tau] u[k]]``.

    Parameters
    ----------
    u : array_like, shape (ninputs, nsteps)
    e : array_like, shape (noutputs, nsteps)
    maxlag : int

    Returns
    -------
    ndarray, shape (ninputs, noutputs, 2 maxlag + 1)
        Lags ``-maxlag..maxlag`` along the last axis.
    """
    u = check_signal(u, None, "u", min_steps=2)
    e = check_signal(e, None, "e", min_steps=2)
    N = check_same_length(("u", u), ("e", e))
    maxlag = check_positive(maxlag, "maxlag", integer=True)
    if maxlag >= N:
        raise DataError(f"maxlag = {maxlag} must be below the number of samples {N}")
    u = u - u.mean(axis=1, keepdims=True)
    e = e - e.mean(axis=1, keepdims=True)
    su = np.sqrt(np.sum(u * u, axis=1))
    se = np.sqrt(np.sum(e * e, axis=1))
    su[su == 0] = 1.0
    se[se == 0] = 1.0
    out = np.empty((u.shape[0], e.shape[0], 2 * maxlag + 1))
    for j, tau in enumerate(range(-maxlag, maxlag + 1)):
        if tau >= 0:
            c = u[:, :N - tau] @ e[:, tau:].T
        else:
            c = u[:, -tau:] @ e[:, :N + tau].T
        out[:, :, j] = c / np.outer(su, se)
    return out


def correlation_band(nsteps: int, level: float = 0.99) -> float:
    """Half-width of the ``level`` band of a sample correlation of white noise.

    ``z_{(1+level)/2} / sqrt(nsteps)``.
    """
    nsteps = check_positive(nsteps, "nsteps", integer=True)
    if not 0 < level < 1:
        raise DataError(f"level must be in (0, 1); found {level}")
    return float(norm.ppf(0.5 + level / 2) / np.sqrt(nsteps))


@dataclass(frozen=True)
class WhitenessTest:
    """Ljung-Box test of the hypothesis "the residual is white", per channel.

    Attributes
    ----------
    statistic : ndarray, shape (nsignals,)
        ``Q = N (N + 2) sum_{l=1}^{L} r_l^2 / (N - l)``.
    pvalue : ndarray, shape (nsignals,)
        Upper-tail probability of chi-square with ``lags`` degrees of freedom.
    lags : int
        Number of lags L.
    alpha : float
        Significance level used for ``white``.
    white : ndarray of bool, shape (nsignals,)
        ``pvalue >= alpha``; with ``mean_pvalue`` set, the joint test of the
        autocorrelations and the mean at ``alpha`` (:func:`innovation_test`).
    mean_pvalue : ndarray, shape (nsignals,), optional
        Two-sided p-value of the residual's mean alone being zero
        (:func:`innovation_test`); None for the Ljung-Box test alone.
    n_eff : ndarray, shape (nsignals,), optional
        The effective samples that test used (:func:`effective_samples`), kept
        for the callers that weigh the same residual's mean again.
    """

    statistic: NDArray[np.float64]
    pvalue: NDArray[np.float64]
    lags: int
    alpha: float
    white: NDArray[np.bool_]
    mean_pvalue: NDArray[np.float64] | None = None
    n_eff: NDArray[np.float64] | None = None

    @property
    def all_white(self) -> bool:
        """True if no channel rejects whiteness at ``alpha``."""
        return bool(np.all(self.white))


def whiteness_test(e: ArrayLike, lags: int = 20, *, alpha: float = 1e-3) -> WhitenessTest:
    """Ljung-Box whiteness test of each channel of a residual.

    Parameters
    ----------
    e : array_like, shape (nsignals, nsteps)
        Residual, e.g. one-step prediction errors.
    lags : int
        Number of autocorrelation lags summed (20 by default).
    alpha : float
        Significance level for the ``white`` flags. The default 1e-3 is
        strict on purpose (PAPER_NOTES §9.1): with long records a tiny
        correlation is "significant" but not worth a model change.

    Returns
    -------
    WhitenessTest

    References
    ----------
    G. M. Ljung and G. E. P. Box, "On a measure of lack of fit in time series
    models", Biometrika 65 (1978) 297-303.
    """
    e = as_signal(e, "e")
    N = e.shape[-1]
    alpha = check_positive(alpha, "alpha")
    if not 0 < alpha < 1:
        raise DataError(f"alpha must be in (0, 1); found {alpha}")
    lags = check_positive(lags, "lags", integer=True)
    if N < 2 * lags + 1:
        raise DataError(f"whiteness test with {lags} lags needs at least {2 * lags + 1} samples; "
                        f"found {N}")
    r = autocorrelation(e, lags)[:, 1:]
    ell = np.arange(1, lags + 1)
    stat = N * (N + 2) * np.sum(r**2 / (N - ell), axis=1)
    pv = chi2.sf(stat, lags)
    return WhitenessTest(statistic=stat, pvalue=pv, lags=lags, alpha=alpha, white=pv >= alpha)


def innovation_test(e: ArrayLike, lags: int = 20, *, alpha: float = 1e-3) -> WhitenessTest:
    """Test of the hypothesis "the residual is zero-mean white noise", per channel.

    A Kalman filter's one-step innovations under the right model are zero-mean
    and white. The Ljung-Box test (:func:`whiteness_test`) measures
    correlation around the residual's own mean, so it is blind to a constant
    error: a sensor offset of 50 noise deviations passes it. This test adds
    the mean, ``t = mean / (std / sqrt(n_eff))`` with ``n_eff`` the effective
    samples (:func:`effective_samples`; ~N for a white residual), as one more
    term of the same statistic: under the hypothesis the mean and the
    autocorrelations are asymptotically independent, so ``Q + t^2`` is
    chi-square on ``lags + 1`` degrees of freedom, and a channel is ``white``
    when that joint p-value is at least ``alpha``: one test at one level, not
    two tests at ``alpha`` each.

    Parameters
    ----------
    e : array_like, shape (nsignals, nsteps)
        Residual, e.g. one-step prediction errors.
    lags : int
        Lags of the Ljung-Box part.
    alpha : float
        Significance level of the joint test.

    Returns
    -------
    WhitenessTest
        With ``mean_pvalue`` set; ``statistic`` and ``pvalue`` are Ljung-Box's,
        ``white`` the joint test's.
    """
    lb = whiteness_test(e, lags, alpha=alpha)
    e = as_signal(e, "e")
    n = effective_samples(e)
    sd = e.std(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(sd > 0, e.mean(axis=1) * np.sqrt(n) / np.where(sd > 0, sd, 1.0), 0.0)
    joint = chi2.sf(lb.statistic + t ** 2, lb.lags + 1)
    return WhitenessTest(statistic=lb.statistic, pvalue=lb.pvalue, lags=lb.lags,
                         alpha=lb.alpha, white=joint >= lb.alpha,
                         mean_pvalue=2.0 * norm.sf(np.abs(t)), n_eff=n)


def effective_samples(e: ArrayLike) -> NDArray[np.float64]:
    """Effective number of independent samples of each residual channel.

    ``N / tau`` with ``tau = 1 + 2 sum_k rho_k`` the integrated
    autocorrelation time, the sum running over Geyer's initial positive
    sequence (pairs of lags while their sum stays positive; at most N/4
    lags). An output-error residual under process noise is strongly
    autocorrelated: its N samples carry the information of far fewer.

    Parameters
    ----------
    e : array_like, shape (nsignals, nsteps)

    Returns
    -------
    ndarray, shape (nsignals,)
        Between 1 and nsteps.
    """
    e = np.atleast_2d(np.asarray(e, dtype=float))
    N = e.shape[1]
    out = np.empty(e.shape[0])
    L = max(2, N // 4)
    for i, row in enumerate(e):
        r = row - row.mean()
        f = np.fft.rfft(r, 2 * N)
        acf = np.fft.irfft(f * np.conj(f))[:L]
        if acf[0] <= 0:
            out[i] = N
            continue
        rho = acf / acf[0]
        tau = 1.0
        for k in range(1, L - 1, 2):
            pair = rho[k] + rho[k + 1]
            if pair <= 0:
                break
            tau += 2 * pair
        out[i] = float(np.clip(N / tau, 1.0, N))
    return out


def independent_samples(e: ArrayLike) -> NDArray[np.float64]:
    """Effective samples of each output's error, shared out over correlated outputs.

    :func:`effective_samples` counts the independent samples in time of each
    output alone; outputs driven by the same error (a chain's positions all
    carry one missing force) repeat one another, and summing their
    log-likelihoods would count that information once per output. Each
    count is scaled by ``m_eff / m``, ``m_eff = m^2 / sum(lambda^2)`` the
    participation ratio of the eigenvalues of the outputs' error correlation
    matrix (m for uncorrelated outputs, 1 for outputs that repeat one error).

    Parameters
    ----------
    e : array_like, shape (noutputs, nsteps)

    Returns
    -------
    ndarray, shape (noutputs,)
    """
    e = np.atleast_2d(np.asarray(e, dtype=float))
    n = effective_samples(e)
    m = e.shape[0]
    live = np.std(e, axis=1) > 0
    if m < 2 or live.sum() < 2:
        return n
    lam = np.linalg.eigvalsh(np.corrcoef(e[live]))
    k = int(live.sum())
    m_eff = float(np.clip(k * k / max(float(np.sum(lam ** 2)), 1e-300), 1.0, k))
    return np.maximum(n * (m_eff + (m - k)) / m, 1.0)


def oe_criterion(e: ArrayLike, npar: int, n_eff: ArrayLike, factor: float = 1.0) -> float:
    """The one selection criterion of greybox: an output-error BIC on effective samples.

    ``sum_i n_i log(mean(e_i^2)) + npar log(sum_i n_i)`` with ``n_i`` the
    effective samples of output i (:func:`independent_samples`, taken once,
    from the residual of the largest candidate, so that every candidate of a
    comparison is scored on the same count). Lower is better. A term is
    worth its parameter only where it lowers the output error by more than
    the noise's own correlation can explain.

    Parameters
    ----------
    e : array_like, shape (noutputs, nsteps)
        Output error (any per-output scaling: it cancels between candidates).
    npar : int
        Parameters of the candidate (a breakpoint or a pole counts as one).
    n_eff : array_like, shape (noutputs,)
    factor : float
        The evidence each parameter must bring, in units of its BIC penalty (1: the
        BIC; close the loop chooses its candidates and prunes the chosen law's terms
        at its ``bic_factor``, :func:`criterion_scores`).

    Returns
    -------
    float
    """
    e = np.atleast_2d(np.asarray(e, dtype=float))
    return _criterion(np.mean(e ** 2, axis=1), float(factor) * int(npar), n_eff)


def _criterion(mse, npar: float, n_eff) -> float:
    """``sum_i n_i log(mse_i) + npar log(sum_i n_i)`` (see :func:`oe_criterion`); ``npar``
    the parameters times their price in BIC penalties."""
    n = np.asarray(n_eff, dtype=float).reshape(-1)
    mse = np.maximum(np.asarray(mse, dtype=float).reshape(-1), 1e-300)
    return float(n @ np.log(mse) + npar * np.log(max(float(n.sum()), 2.0)))


@dataclass(frozen=True)
class OutputFit:
    """How a candidate model's output follows the measured one on the estimation record.

    Attributes
    ----------
    se : float
        SE (eq. 42) [%]; inf when the model's output diverged.
    per_output : ndarray, shape (noutputs,)
        SE of each output [%] (its square is the output's mean squared error
        over its mean square: the criterion's scale cancels between candidates).
    n_eff : ndarray, shape (noutputs,)
        Effective independent samples of each output's error, shared out
        over correlated outputs (:func:`independent_samples`).
    """

    se: float
    per_output: NDArray[np.float64]
    n_eff: NDArray[np.float64]


def output_fit(y: ArrayLike, y_hat: ArrayLike, *, skip: int = 0) -> OutputFit:
    """The :class:`OutputFit` of ``y_hat`` (simulated or one-step predicted) against ``y``.

    Parameters
    ----------
    y, y_hat : array_like, shape (noutputs, nsteps)
    skip : int
        Leading samples left out (the filters' or the simulation's transient).

    Returns
    -------
    OutputFit
        ``se = inf`` (and ``per_output`` inf) when ``y_hat`` is not finite or
        beyond the magnitude the metrics accept.
    """
    y, y_hat = np.atleast_2d(np.asarray(y, dtype=float)), np.atleast_2d(
        np.asarray(y_hat, dtype=float))
    ny = y.shape[0]
    bad = OutputFit(se=np.inf, per_output=np.full(ny, np.inf), n_eff=np.ones(ny))
    if not np.all(np.isfinite(y_hat)):
        return bad
    try:
        re = relative_error(y, y_hat, skip=skip)
    except DataError:  # values beyond the magnitude check (1e252 from a diverged candidate)
        return bad
    if not np.isfinite(re.value):
        return bad
    return OutputFit(se=re.value, per_output=re.per_output,
                     n_eff=independent_samples(y[:, skip:] - y_hat[:, skip:]))


def criterion_scores(fits, npars, n_eff: ArrayLike | None = None,
                     factor: float = 1.0) -> NDArray[np.float64]:
    """Every candidate's :func:`oe_criterion` on one effective sample count.

    The count is the effective samples of the best-fitting candidate (the
    lowest SE: its error is the closest to the noise alone), so that every
    candidate of one choice is scored on the same ``n``; a candidate that
    does not fit (``se`` inf) scores inf. Lower is better.

    :func:`greybox.close_the_loop` chooses between a ``StateSpace`` model's
    candidates by it with ``factor = bic_factor`` (10): the candidates' laws
    are fitted on d^ or by output error, not as maximum-likelihood fits of
    one model class, and the effective sample count of a slow output error
    is estimated from a few thousand samples; at the BIC's own penalty an
    input's gain error (1 parameter) lost to the same force fitted freely in
    the two equations it enters (2 parameters, SE 0.114 % against 0.115 %, a
    likelihood ratio of 35 on 2189 effective samples,
    ``tests/test_trace_actuator.py``).

    Parameters
    ----------
    fits : sequence of OutputFit
    npars : sequence of int
        Parameters each candidate adds (a breakpoint, a pole, a level counts
        as one).
    n_eff : array_like, shape (noutputs,), optional
        The effective sample count to score on (to score later candidates of
        the same choice on the same count); default: the best-fitting one's.
    factor : float
        The evidence each parameter must bring, in units of its BIC penalty
        (1: the BIC).

    Returns
    -------
    ndarray, shape (ncandidates,)
    """
    fits, npars = list(fits), list(npars)
    if len(fits) != len(npars):
        raise DataError(f"{len(fits)} fits but {len(npars)} parameter counts")
    out = np.full(len(fits), np.inf)
    finite = [i for i, f in enumerate(fits) if np.isfinite(f.se)]
    if not finite:
        return out
    n = fits[min(finite, key=lambda i: fits[i].se)].n_eff if n_eff is None else n_eff
    n = np.asarray(n, dtype=float).reshape(-1)
    for i in finite:
        out[i] = _criterion((fits[i].per_output / 100.0) ** 2, float(factor) * int(npars[i]), n)
    return out

