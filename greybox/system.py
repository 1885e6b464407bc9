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

from ._validation import check_discrete, check_positive, check_statespace, resolve_channels
from .exceptions import DimensionError, ModelError

__all__ = ["discretize", "split_inputs", "SplitModel", "named_ss"]


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
    A = np.atleast_2d(np.asarray(A, dtype=float))
    n = A.shape[0]
    B = np.asarray(B, dtype=float).reshape(n, len(inputs))
    C = np.asarray(C, dtype=float).reshape(len(outputs), n)
    D = np.asarray(D, dtype=float).reshape(len(outputs), len(inputs))
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
