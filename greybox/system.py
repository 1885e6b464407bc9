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
    _float_array,
    check_discrete,
    check_matrix,
    check_positive,
    check_statespace,
    resolve_channels,
)
from .exceptions import DimensionError, ModelError

__all__ = ["discretize", "split_inputs", "SplitModel", "named_ss"]


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
        a = _float_array(M)
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
