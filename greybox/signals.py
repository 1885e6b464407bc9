"""Excitation signals and a seeded simulator of the stochastic discrete system.

Every signal is an array of shape ``(nsignals, nsteps)``: time is the last axis.
Every random function takes ``rng`` (a ``numpy.random.Generator`` or a seed).
"""

from __future__ import annotations

from dataclasses import dataclass

import control as ct
import numpy as np
import scipy.signal as sps
from numpy.typing import ArrayLike, NDArray

from ._lti import lti_states
from ._validation import (
    check_input_record,
    check_covariance,
    check_discrete,
    check_positive,
    check_real,
    check_vector,
)
from .exceptions import DataError, DimensionError

__all__ = [
    "random_binary",
    "multisine",
    "lowpass_noise",
    "simulate",
    "SimulationResult",
]


#: Most samples (nsignals * nsteps) a generator returns: 8 GB of float64.
_MAX_VALUES = 10 ** 9


def _check_size(nsignals: int, nsteps: int) -> None:
    if nsignals * nsteps > _MAX_VALUES:
        raise DataError(f"nsignals * nsteps = {nsignals * nsteps:.3g} values would need "
                        f"{8 * nsignals * nsteps / 1e9:.3g} GB; at most {_MAX_VALUES:.0e} are "
                        f"generated at once")


def as_generator(rng) -> np.random.Generator:
    """A numpy Generator from ``rng``: a Generator (returned as is), an integer seed or None.

    Raises :class:`~greybox.exceptions.DimensionError` for anything else."""
    if isinstance(rng, np.random.Generator):
        return rng
    try:
        return np.random.default_rng(rng)
    except (TypeError, ValueError) as e:
        raise DimensionError(f"rng must be a numpy Generator, an integer seed or None; found "
                             f"{rng!r}") from e


def random_binary(nsteps: int, *, nsignals: int = 1, amplitude: float = 1.0,
                  hold: int = 1, rng=None) -> NDArray[np.float64]:
    """Random binary signal (a PRBS-like telegraph signal) of levels ±amplitude.

    Parameters
    ----------
    nsteps : int
        Number of samples.
    nsignals : int
        Number of independent channels.
    amplitude : float
        Level [signal units]; the signal takes values ``±amplitude``.
    hold : int
        Clock period in samples: the level can switch every ``hold`` samples,
        which sets the bandwidth to about ``1/(2 hold dt)`` [Hz].
    rng : numpy.random.Generator or int, optional

    Returns
    -------
    ndarray, shape (nsignals, nsteps)
    """
    nsteps = check_positive(nsteps, "nsteps", integer=True)
    nsignals = check_positive(nsignals, "nsignals", integer=True)
    _check_size(nsignals, nsteps)
    hold = min(check_positive(hold, "hold", integer=True), nsteps)
    amplitude = check_real(amplitude, "amplitude")
    g = as_generator(rng)
    nclk = -(-nsteps // hold)
    lv = g.choice([-1.0, 1.0], size=(nsignals, nclk))
    return amplitude * np.repeat(lv, hold, axis=1)[:, :nsteps]


def multisine(nsteps: int, *, dt: float, nsignals: int = 1, amplitude: float = 1.0,
              fmin: float | None = None, fmax: float | None = None, nfreq: int = 20,
              rng=None) -> NDArray[np.float64]:
    """Random-phase multisine with equal-amplitude lines between fmin and fmax.

    Parameters
    ----------
    nsteps : int
        Number of samples.
    dt : float
        Sampling period [s].
    nsignals : int
        Number of channels (independent random phases).
    amplitude : float
        Root-mean-square value of each channel [signal units].
    fmin, fmax : float, optional
        Band [Hz]; defaults: the lowest frequency resolvable in the record and
        a quarter of the sampling frequency.
    nfreq : int
        Number of lines, log-spaced in the band.
    rng : numpy.random.Generator or int, optional

    Returns
    -------
    ndarray, shape (nsignals, nsteps)
    """
    nsteps = check_positive(nsteps, "nsteps", integer=True)
    nsignals = check_positive(nsignals, "nsignals", integer=True)
    _check_size(nsignals, nsteps)
    nfreq = check_positive(nfreq, "nfreq", integer=True)
    dt = check_positive(dt, "dt")
    amplitude = check_real(amplitude, "amplitude")
    if nfreq > nsteps:
        raise DataError(f"nfreq = {nfreq} lines need at least as many samples; found nsteps = "
                        f"{nsteps}")
    fs = 1.0 / dt
    fmin = check_real(fmin, "fmin") if fmin is not None else 1.0 / (nsteps * dt)
    fmax = check_real(fmax, "fmax") if fmax is not None else fs / 4
    if not 0 < fmin < fmax <= fs / 2:
        raise DataError(f"need 0 < fmin < fmax <= fs/2 = {fs / 2:g} Hz; found fmin={fmin:g}, "
                        f"fmax={fmax:g}")
    g = as_generator(rng)
    f = np.geomspace(fmin, fmax, nfreq)
    t = np.arange(nsteps) * dt
    out = np.zeros((nsignals, nsteps))
    for i in range(nsignals):
        ph = g.uniform(0, 2 * np.pi, nfreq)
        out[i] = np.sum(np.cos(2 * np.pi * f[:, None] * t[None, :] + ph[:, None]), axis=0)
    rms = np.sqrt(np.mean(out**2, axis=1, keepdims=True))
    return amplitude * out / rms


def lowpass_noise(nsteps: int, *, dt: float, bandwidth: float, nsignals: int = 1,
                  amplitude: float = 1.0, order: int = 4, rng=None) -> NDArray[np.float64]:
    """Gaussian white noise through a Butterworth low-pass filter.

    Parameters
    ----------
    nsteps : int
    dt : float
        Sampling period [s].
    bandwidth : float
        Cut-off frequency [Hz].
    nsignals : int
    amplitude : float
        Standard deviation of each channel [signal units].
    order : int
        Butterworth filter order.
    rng : numpy.random.Generator or int, optional

    Returns
    -------
    ndarray, shape (nsignals, nsteps)
    """
    nsteps = check_positive(nsteps, "nsteps", integer=True)
    dt = check_positive(dt, "dt")
    nsignals = check_positive(nsignals, "nsignals", integer=True)
    _check_size(nsignals, nsteps)
    order = check_positive(order, "order", integer=True)
    if order > 20:
        raise DataError(f"order = {order}: a Butterworth filter above order 20 is numerically "
                        f"meaningless; use 1..20")
    amplitude = check_real(amplitude, "amplitude")
    bandwidth = check_positive(bandwidth, "bandwidth")
    if bandwidth >= 0.5 / dt:
        raise DataError(f"bandwidth {bandwidth:g} Hz must be below the Nyquist frequency "
                        f"{0.5 / dt:g} Hz")
    g = as_generator(rng)
    sos = sps.butter(order, bandwidth, fs=1.0 / dt, output="sos")
    w = g.standard_normal((nsignals, nsteps))
    out = sps.sosfilt(sos, w, axis=1)
    sd = out.std(axis=1, keepdims=True)
    sd[sd == 0] = 1.0
    return amplitude * out / sd


@dataclass(frozen=True)
class SimulationResult:
    """Simulated response of a discrete stochastic system.

    Attributes
    ----------
    t : ndarray, shape (nsteps,)
        Time [s].
    x : ndarray, shape (nstates, nsteps)
        True states.
    y : ndarray, shape (noutputs, nsteps)
        Measured outputs (with measurement noise if R was given).
    u : ndarray, shape (ninputs, nsteps)
        Inputs.
    y_clean : ndarray, shape (noutputs, nsteps)
        Outputs without measurement noise, ``C x + D u``.
    sys : control.StateSpace
        The simulated model.
    """

    t: NDArray[np.float64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    u: NDArray[np.float64]
    y_clean: NDArray[np.float64]
    sys: ct.StateSpace


def simulate(sys: ct.StateSpace, u: ArrayLike | None = None, *, x0: ArrayLike | None = None,
             Q: ArrayLike | None = None, R: ArrayLike | None = None, nsteps: int | None = None,
             rng=None) -> SimulationResult:
    """Simulate ``x[k+1] = A x + B u + w``, ``y = C x + D u + v`` (w ~ N(0,Q), v ~ N(0,R)).

    Parameters
    ----------
    sys : control.StateSpace
        Discrete-time model.
    u : array_like, shape (ninputs, nsteps), optional
        Input; None (or omitted) for a model without inputs, then ``nsteps``
        must be given.
    x0 : array_like, shape (nstates,), optional
        Initial state (zero by default).
    Q : array_like, shape (nstates, nstates), optional
        Process-noise covariance; None for no process noise. May be singular.
    R : array_like, shape (noutputs, noutputs), optional
        Measurement-noise covariance; None for noise-free measurements.
    nsteps : int, optional
        Number of samples; required when ``u`` is None, else it must equal
        ``u.shape[1]``.
    rng : numpy.random.Generator or int, optional
        Source of the noise.

    Returns
    -------
    SimulationResult
    """
    check_discrete(sys)
    n, m, p = sys.nstates, sys.ninputs, sys.noutputs
    u = check_input_record(u, m, nsteps)
    N = u.shape[1]
    x0 = np.zeros(n) if x0 is None else check_vector(x0, n, "x0")
    g = as_generator(rng)
    A, B, C, D = (np.asarray(a, dtype=float) for a in (sys.A, sys.B, sys.C, sys.D))
    drive = B @ u
    if Q is not None:
        Q = check_covariance(Q, n, "Q", definite=False)
        drive = drive + gaussian_noise(Q, N, g)
    x = lti_states(A, drive, x0)
    if not np.all(np.isfinite(x)):
        raise DataError("the simulation diverged: the model is unstable over this record "
                        "(check dt and that sys is discrete-time)")
    y_clean = C @ x + D @ u
    y = y_clean.copy()  # never the same object as y_clean
    if R is not None:
        R = check_covariance(R, p, "R", definite=False)
        y = y_clean + gaussian_noise(R, N, g)
    t = np.arange(N) * float(sys.dt)
    return SimulationResult(t=t, x=x, y=y, u=u, y_clean=y_clean, sys=sys)


def gaussian_noise(S: NDArray, N: int, g: np.random.Generator) -> NDArray[np.float64]:
    """N draws of a zero-mean Gaussian with covariance S (PSD allowed), shape (n, N)."""
    w, V = np.linalg.eigh(S)
    L = V * np.sqrt(np.clip(w, 0, None))
    return L @ g.standard_normal((S.shape[0], N))
