"""Model plumbing on python-control ``StateSpace`` objects.

ZOH discretization that keeps signal names, and the split of a model's inputs
into known inputs ``u`` (matrix B) and unknown model-error inputs ``d``
(matrix G), as in eqs. (5)-(6) of Gillijns & De Moor.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import control as ct
import numpy as np
from numpy.typing import NDArray

from ._validation import (
    float_array,
    check_discrete,
    check_matrix,
    check_positive,
    check_signal,
    check_statespace,
    resolve_channels,
)
from .exceptions import DimensionError, ModelError

__all__ = ["discretize", "split_inputs", "SplitModel", "named_ss", "zoh_equivalent_input"]


def _names(names, what):
    try:
        out = None if isinstance(names, str) else list(names)
    except TypeError:
        out = None
    if out is None or not all(isinstance(v, str) for v in out):
        raise DimensionError(f"{what} must be a sequence of names; found {names!r}")
    return out


def _matrix(M, shape, name):
    """A real matrix of the given shape (any array with as many entries is reshaped)."""
    try:
        a = float_array(M)
    except (TypeError, ValueError) as e:
        raise DimensionError(f"{name} must be a real numeric array; could not convert it "
                             f"({e})") from e
    if a.size == shape[0] * shape[1]:
        a = a.reshape(shape)
    return check_matrix(a, shape, name)


def named_ss(A, B, C, D, dt, *, states, inputs, outputs, name=None) -> ct.StateSpace:
    """Build a ``StateSpace`` with the given signal names (thin wrapper of ``ct.ss``).

    Parameters
    ----------
    A, B, C, D : array_like
        Shapes (n, n), (n, m), (p, n), (p, m); B, C, D are reshaped to them.
    dt : float, True or 0
        Sampling period [s]; 0 for continuous time.
    states, inputs, outputs : sequence of str
        Names; their lengths set n, m and p.
    name : str, optional
        System name.

    Returns
    -------
    control.StateSpace

    Raises
    ------
    ModelError
        For a model without inputs and with one state or one output, which
        python-control 0.10 cannot represent.
    """
    states, inputs, outputs = (_names(v, k) for v, k in ((states, "states"), (inputs, "inputs"),
                                                          (outputs, "outputs")))
    n, m, p = len(states), len(inputs), len(outputs)
    A, B, C, D = (_matrix(M, s, k) for M, s, k in
                  ((A, (n, n), "A"), (B, (n, m), "B"), (C, (p, n), "C"), (D, (p, m), "D")))
    if not (dt is True or (not isinstance(dt, (bool, str)) and dt is not None and
                           np.isscalar(dt) and np.isfinite(dt) and dt >= 0)):
        raise DimensionError(f"dt must be a sampling period >= 0 [s] (0: continuous) or True; "
                             f"found {dt!r}")
    if len(inputs) == 0 and (n == 1 or len(outputs) == 1):
        raise ModelError(
            "python-control cannot represent a model with no inputs when it has one state or "
            "one output (it reshapes the empty (1, 0) matrices); add a known input channel "
            "with zero gain (e.g. a column of zeros in B named 'none') and pass zeros for it"
        )
    kw = {} if name is None else {"name": name}
    return ct.ss(A, B, C, D, dt, states=list(states), inputs=list(inputs),
                 outputs=list(outputs), **kw)


def discretize(sys: ct.StateSpace, dt: float, *, method: str = "zoh") -> ct.StateSpace:
    """Discretize a continuous-time model, keeping state, input and output names.

    All inputs, known and unknown alike, are discretized together, so that an
    unknown-input channel ``d`` keeps its physical units (PAPER_NOTES §1).

    Parameters
    ----------
    sys : control.StateSpace
        Continuous-time model (``dt == 0``).
    dt : float
        Sampling period [s].
    method : {"zoh", "foh", "tustin"}
        Discretization method; ZOH by default.

    Returns
    -------
    control.StateSpace
        Discrete-time model with ``dt`` set and the same signal names.

    Raises
    ------
    ModelError
        If ``sys`` is already discrete.
    """
    check_statespace(sys)
    dt = check_positive(dt, "dt")
    if method not in ("zoh", "foh", "tustin", "bilinear", "euler", "backward_diff"):
        raise ModelError(f"method must be 'zoh' (default), 'foh' or 'tustin'; found {method!r}")
    if ct.isdtime(sys, strict=True):
        raise ModelError(
            f"sys is already discrete (dt={sys.dt}); discretize expects a continuous-time model"
        )
    d = ct.sample_system(sys, dt, method=method)
    return named_ss(d.A, d.B, d.C, d.D, dt, states=sys.state_labels,
                    inputs=sys.input_labels, outputs=sys.output_labels, name=sys.name)


def _freq_response(A, B, C, D, z, chunk):
    """C (z I - A)^-1 B + D at each complex point of ``z``, shape (len(z), p, m)."""
    n = A.shape[0]
    out = np.empty((z.size, C.shape[0], B.shape[1]), dtype=complex)
    eye = np.eye(n)
    for k in range(0, z.size, chunk):
        zk = z[k:k + chunk, None, None]
        X = np.linalg.solve(zk * eye - A, np.broadcast_to(B, (zk.shape[0],) + B.shape))
        out[k:k + chunk] = C @ X + D
    return out


def zoh_equivalent_input(sys: ct.StateSpace, u, dt: float) -> NDArray[np.float64]:
    """The held input under which the ZOH model responds as ``sys`` to a band-limited input.

    A measured input that is band-limited (filtered noise, a multisine from a
    generator with a reconstruction filter) is not held between samples:
    feeding its samples to the ZOH-discretized model (:func:`discretize`)
    distorts their effect by the hold, increasingly with frequency (at
    omega dt = 0.7 rad the hold's gain error is a few per cent). This returns
    the sequence ``u_eq`` whose held samples drive the ZOH model of ``sys``
    to the same outputs, at the samples, as the band-limited signal through
    ``u``'s samples drives ``sys``: in the frequency domain, for each input
    j, ``U_eq,j = F_j U_j`` with ``F_j = sum_i conj(Hd_ij) Hc_ij /
    sum_i |Hd_ij|^2`` (``Hc`` the continuous, ``Hd`` the ZOH frequency
    response on the DFT grid; exact when ``sys`` has one output, a least
    squares match over the outputs otherwise). The DC gain is 1 (a constant
    input is held exactly), so offsets pass through unchanged. An input that
    IS held between samples (a digital controller's DAC output) needs nothing:
    the ZOH model is exact for it.

    The record is treated as one period (DFT): the first and last samples of
    a non-periodic record carry a short wrap-around transient, to be
    discarded like a simulation's initial transient. ``|F|`` grows towards
    the Nyquist frequency (the ZOH zero near z = -1 of a relative-degree-2
    path): the input's content must lie well below fs / 2, as a
    band-limited input's does; noise on ``u`` near fs / 2 is amplified.

    Parameters
    ----------
    sys : control.StateSpace
        Continuous-time nominal model whose inputs are the rows of ``u``.
    u : array_like, shape (ninputs, nsteps)
        Samples of the band-limited input, taken every ``dt``.
    dt : float
        Sampling period [s].

    Returns
    -------
    numpy.ndarray, shape (ninputs, nsteps)
        The equivalent held input, in ``u``'s units, to feed the ZOH model
        (and every greybox function that discretizes ``sys``) instead of ``u``.

    Raises
    ------
    ModelError
        If ``sys`` is discrete.
    DimensionError
        If ``u`` does not have one row per input of ``sys``.
    """
    check_statespace(sys)
    dt = check_positive(dt, "dt")
    if ct.isdtime(sys, strict=True):
        raise ModelError(f"sys is discrete (dt={sys.dt}); zoh_equivalent_input expects the "
                         "continuous-time nominal model")
    u = check_signal(u, sys.ninputs, "u", min_steps=2)
    N = u.shape[1]
    sd = discretize(sys, dt)
    w = 2 * np.pi * np.fft.rfftfreq(N)[1:]              # rad/sample, DC excluded
    mats = [np.asarray(M, dtype=float) for M in (sys.A, sys.B, sys.C, sys.D)]
    dmats = [np.asarray(M, dtype=float) for M in (sd.A, sd.B, sd.C, sd.D)]
    chunk = max(1, 2_000_000 // max(1, sys.nstates) ** 2)
    Hc = _freq_response(*mats, 1j * w / dt, chunk)
    Hd = _freq_response(*dmats, np.exp(1j * w), chunk)
    num = np.einsum("kij,kij->kj", Hd.conj(), Hc)
    den = np.einsum("kij,kij->kj", Hd.conj(), Hd).real
    F = np.ones((w.size + 1, sys.ninputs), dtype=complex)
    ok = den > 1e-12 * den.max(axis=0, initial=0.0)
    F[1:][ok] = num[ok] / den[ok]
    return np.fft.irfft(np.fft.rfft(u, axis=1) * F.T, N, axis=1)


@dataclass(frozen=True)
class SplitModel:
    """A discrete model split into known inputs and unknown (model-error) inputs.

    Attributes
    ----------
    sys : control.StateSpace
        Model from the known inputs ``u`` only: ``(A, B, C, D)``, names kept.
    G : ndarray, shape (nstates, md)
        Input matrix of the unknown inputs ``d``.
    H : ndarray, shape (noutputs, md)
        Feedthrough of ``d`` into the outputs (must be zero for the filter).
    unknown_labels : tuple of str
        Names of the unknown input channels.
    unknown_index : tuple of int
        Their indices among the original model's inputs.
    """

    sys: ct.StateSpace
    G: NDArray[np.float64]
    H: NDArray[np.float64]
    unknown_labels: tuple[str, ...]
    unknown_index: tuple[int, ...]


def split_inputs(sys: ct.StateSpace, unknown: int | str | Sequence[int | str]) -> SplitModel:
    """Split a discrete model's inputs into known ``u`` and unknown ``d``.

    Parameters
    ----------
    sys : control.StateSpace
        Discrete-time model with inputs ``[u, d]`` in any order.
    unknown : int, str or sequence of them
        Labels or indices of the unknown-input channels (at least one).

    Returns
    -------
    SplitModel
    """
    check_discrete(sys)
    idx = resolve_channels(unknown, sys.input_labels, "unknown")
    if not idx:
        raise DimensionError("unknown: at least one unknown-input channel is needed")
    known = [i for i in range(sys.ninputs) if i not in idx]
    A, B, C, D = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D))
    known_sys = named_ss(
        A, B[:, known], C, D[:, known], sys.dt,
        states=sys.state_labels, inputs=[sys.input_labels[i] for i in known],
        outputs=sys.output_labels, name=sys.name,
    )
    return SplitModel(
        sys=known_sys,
        G=B[:, idx].copy(),
        H=D[:, idx].copy(),
        unknown_labels=tuple(sys.input_labels[i] for i in idx),
        unknown_index=tuple(idx),
    )
