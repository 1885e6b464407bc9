"""Candidate error channels: which state equations (or inputs) a model error enters."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import control as ct
import numpy as np
from numpy.typing import NDArray

from ..exceptions import DataError, DimensionError, ModelError
from ..system import discretize, named_ss



# Largest number of outputs whose sensor channels default_channels offers by default
_AUTO_OUTPUTS = 6


# --------------------------------------------------------------------------- channels
@dataclass(frozen=True, eq=False)
class Channel:
    """A candidate error channel: the model error enters as ``G d``.

    Attributes
    ----------
    name : str
        Readable name, e.g. ``"eq(v1)"`` or ``"eq(v1)+eq(v2)"`` or a user name.
    G : ndarray, shape (nstates, md)
        Input matrix of d in the nominal model's own time base (continuous
        if the nominal model is continuous; it is then ZOH-discretized
        together with B).
    labels : tuple of str
        Names of the md components of d.
    units : tuple of str
        Units of the components of d ("" if unknown).
    equations : tuple of str
        Names of the states whose equations the channel enters.
    kind : str
        "equation" (d enters state equations directly), "input" (d adds to
        a known input: ``G = B[:, j]``), "force" (one force inside a pair of
        equations), "output" (d adds to one measured output: a sensor error,
        ``y_i = C_i x + D_i u + d``; G is zero) or "user".
    input : str
        The input's name for an input channel ("" otherwise).
    output : str
        The output's name for an output channel ("" otherwise).
    relative : tuple of (int, int)
        State pairs (i, j) whose relative coordinate ``x_j - x_i`` the static
        law may use (a force between two bodies); kind "force".
    """

    name: str
    G: NDArray[np.float64]
    labels: tuple[str, ...]
    units: tuple[str, ...] = ()
    equations: tuple[str, ...] = ()
    kind: str = "equation"
    input: str = ""
    relative: tuple[tuple[int, int], ...] = ()
    output: str = ""

    @property
    def md(self) -> int:
        """Number of unknown-input components."""
        return self.G.shape[1]

    def _key(self):
        G = np.asarray(self.G, dtype=float)
        return (self.name, G.shape, G.tobytes(), tuple(self.labels), tuple(self.units),
                tuple(self.equations), self.kind, self.input, tuple(self.relative), self.output)

    def __eq__(self, other):  # G is an array: the generated __eq__ would be ambiguous
        if not isinstance(other, Channel):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self):
        return hash(self._key())


def _eq_channel(sys: ct.StateSpace, idx: Sequence[int]) -> Channel:
    n = sys.nstates
    G = np.zeros((n, len(idx)))
    for c, i in enumerate(idx):
        G[i, c] = 1.0
    names = [sys.state_labels[i] for i in idx]
    cont = not ct.isdtime(sys, strict=True)
    return Channel(name="+".join(f"eq({s})" for s in names), G=G,
                   labels=tuple(f"d_{s}" for s in names),
                   units=tuple((f"[{s}]/s" if cont else f"[{s}]/sample") for s in names),
                   equations=tuple(names))


def equation_subset(ch: Channel, keep: Sequence[int]) -> Channel:
    """The channel of some of the equations of an equation channel (kind "equation", one
    column of G per equation, as :func:`resolve_channel_spec` forms them): the columns
    ``keep`` of G, their labels, units and equations, named as such a channel is named
    (``"eq(v2)"``, ``"eq(v2)+eq(v4)"``)."""
    if ch.kind != "equation" or len(ch.equations) != ch.md:
        raise ValueError(f"equation_subset: {ch.name} is not a channel of state equations")
    keep = list(keep)
    eqs = tuple(ch.equations[k] for k in keep)
    return Channel(name="+".join(f"eq({s})" for s in eqs), G=np.asarray(ch.G)[:, keep],
                   labels=tuple(ch.labels[k] for k in keep),
                   units=tuple(ch.units[k] for k in keep) if len(ch.units) == ch.md else (),
                   equations=eqs)


def input_channel(sys: ct.StateSpace, j: int) -> Channel:
    """The channel of input j: G = B[:, j], d in the input's units (an actuator error).

    Parameters
    ----------
    sys : control.StateSpace
        Nominal model.
    j : int
        Index of the input.

    Returns
    -------
    Channel
        ``input(name)``, md = 1, kind "input".
    """
    B = np.asarray(sys.B, dtype=float)
    name = sys.input_labels[j]
    rows = tuple(sys.state_labels[i] for i in np.flatnonzero(B[:, j]))
    return Channel(name=f"input({name})", G=B[:, [j]].copy(), labels=(f"d_{name}",),
                   units=(f"[{name}]",), equations=rows, kind="input", input=name)


def output_channel(sys: ct.StateSpace, output: int | str) -> Channel:
    """The channel of a sensor error on one output: ``y_i = C_i x + D_i u + d`` (G = 0).

    Parameters
    ----------
    sys : control.StateSpace
        Nominal model.
    output : int or str
        Index or name of the output.

    Raises
    ------
    DimensionError
        If the output does not exist.
    """
    labels = list(sys.output_labels)
    if isinstance(output, str):
        if output not in labels:
            raise DimensionError(f"output_channel: no output named {output!r}; outputs are "
                                 f"{labels}")
        i = labels.index(output)
    else:
        i = int(output)
        if not 0 <= i < len(labels):
            raise DimensionError(f"output_channel: output index {output} out of range "
                                 f"0..{len(labels) - 1}")
    name = labels[i]
    return Channel(name=f"output({name})", G=np.zeros((sys.nstates, 1)), labels=(f"d_{name}",),
                   units=(f"[{name}]",), equations=(), kind="output", output=name)


def default_channels(sys: ct.StateSpace, *, pairs: bool | str = "auto",
                     inputs: bool = True, outputs: bool | str = "auto") -> tuple[Channel, ...]:
    """Every single state equation, every input and output, and pairs where p allows.

    Parameters
    ----------
    sys : control.StateSpace
        Nominal model (continuous or discrete).
    pairs : bool or "auto"
        Also try pairs of equations (md = 2, PAPER_NOTES §9.6: an internal
        force between two bodies enters two equations). "auto": only when
        ``noutputs >= 2`` and ``nstates <= 4`` (the number of pairs grows as
        n^2; name channels explicitly for larger models).
    inputs : bool
        Also try each input's own channel ``G = B[:, j]`` (an actuator error:
        gain, lag or dead zone of input j enters every equation the input
        enters, with B's ratios). Skipped for inputs that enter a single
        state equation (the equation's channel is the same).
    outputs : bool or "auto"
        Also try each output's sensor-error channel (:func:`output_channel`:
        offset, gain error, |.| or saturation of one sensor, traced with the
        unknown-input filter with direct feedthrough). "auto": only when
        ``noutputs <= 6`` (each costs a trace; name them explicitly for
        larger models).
    """
    if not (isinstance(pairs, (bool, np.bool_)) or pairs == "auto"):
        raise DataError(f"pairs must be True, False or 'auto'; found {pairs!r}")
    n = sys.nstates
    out = [_eq_channel(sys, [i]) for i in range(n)]
    if inputs:
        B = np.asarray(sys.B, dtype=float)
        out += [input_channel(sys, j) for j in range(sys.ninputs)
                if np.count_nonzero(B[:, j]) >= 2]
    use_pairs = (sys.noutputs >= 2 and n <= 4) if pairs == "auto" else bool(pairs)
    if use_pairs and sys.noutputs >= 2:
        out += [_eq_channel(sys, [i, j]) for i in range(n) for j in range(i + 1, n)]
    if not (isinstance(outputs, (bool, np.bool_)) or outputs == "auto"):
        raise DataError(f"outputs must be True, False or 'auto'; found {outputs!r}")
    if (sys.noutputs <= _AUTO_OUTPUTS) if outputs == "auto" else outputs:
        out += [output_channel(sys, i) for i in range(sys.noutputs)]
    return tuple(out)


def resolve_channel_spec(sys: ct.StateSpace, spec) -> tuple[Channel, ...]:
    """Turn a user's channel specification into :class:`Channel` records.

    ``spec`` may be None (:func:`default_channels`), a sequence whose items
    are Channel records, state names, or tuples of state names (equations
    entered together), or a mapping ``{name: G}`` with G of shape
    (nstates,) or (nstates, md) in the nominal model's time base.
    """
    if spec is None:
        return default_channels(sys)
    if isinstance(spec, str):  # one state name, not a sequence of one-letter names
        spec = [spec]
    n = sys.nstates
    labels = list(sys.state_labels)
    out = []
    items = spec.items() if isinstance(spec, Mapping) else [(None, s) for s in spec]
    for key, s in items:
        if isinstance(s, Channel):
            out.append(s)
            continue
        if isinstance(s, str) or (isinstance(s, (tuple, list)) and s and
                                  all(isinstance(t, str) for t in s)):
            names = [s] if isinstance(s, str) else list(s)
            bad = [t for t in names if t not in labels]
            if bad:
                raise DimensionError(f"channels: no state named {bad}; states are {labels}")
            ch = _eq_channel(sys, [labels.index(t) for t in names])
            out.append(ch if key is None else Channel(key, ch.G, ch.labels, ch.units,
                                                       ch.equations))
            continue
        try:
            G = np.array(s, dtype=float)
        except (TypeError, ValueError) as e:
            raise DimensionError(f"channels[{key!r}] must be a G matrix or state names; "
                                 f"found {s!r}") from e
        if G.ndim == 1:
            G = G.reshape(-1, 1)
        if G.ndim != 2 or G.shape[0] != n or G.shape[1] < 1:
            raise DimensionError(f"channels[{key!r}] has shape {G.shape}; expected "
                                 f"({n},) or ({n}, md)")
        if not np.all(np.isfinite(G)):
            raise DimensionError(f"channels[{key!r}] contains NaN or inf")
        zero = np.flatnonzero(np.all(G == 0, axis=0))
        if zero.size:
            raise DimensionError(f"channels[{key!r}] is all zero"
                                 f"{f' in column {zero[0]}' if G.shape[1] > 1 else ''}: it "
                                 f"enters no state equation; remove it or give its G entries")
        name = str(key) if key is not None else f"G{len(out)}"
        md = G.shape[1]
        eqs = tuple(labels[i] for i in range(n) if np.any(G[i] != 0))
        out.append(Channel(name=name, G=G,
                           labels=(name,) if md == 1 else tuple(f"{name}[{j}]" for j in range(md)),
                           units=("",) * md, equations=eqs, kind="user"))
    if not out:
        raise DimensionError("channels: give at least one candidate channel")
    return tuple(out)


def channel_model(sys: ct.StateSpace, channel: Channel, dt: float | None = None) -> ct.StateSpace:
    """Discrete model with inputs ``[u, d]`` for one channel (ZOH once, PAPER_NOTES §1).

    For an output channel d enters the output equation (D column e_i), not B.

    Parameters
    ----------
    sys : control.StateSpace
        Nominal model, continuous or discrete.
    channel : Channel
    dt : float, optional
        Sampling period [s]; needed if ``sys`` is continuous, and must agree
        with ``sys.dt`` if it is discrete.

    Raises
    ------
    ModelError
        If ``sys`` is continuous and ``dt`` is missing, or ``dt`` disagrees
        with a discrete ``sys``.
    DimensionError
        If ``channel.G`` does not have ``sys.nstates`` rows.
    """
    disc = ct.isdtime(sys, strict=True)
    if not disc and dt is None:
        raise ModelError("sys is continuous-time; give the sampling period dt [s] so that "
                         "it can be discretized (ZOH)")
    if disc and dt is not None and abs(float(dt) - float(sys.dt)) > 1e-9 * float(sys.dt):
        raise ModelError(f"dt = {dt} disagrees with the discrete model's dt = {sys.dt}")
    if channel.G.shape[0] != sys.nstates:
        raise DimensionError(f"channel {channel.name!r} has G of shape {channel.G.shape}; "
                             f"expected ({sys.nstates}, md)")
    A, B, C, D = (np.asarray(a, dtype=float) for a in (sys.A, sys.B, sys.C, sys.D))
    p, md = C.shape[0], channel.md
    inputs = list(sys.input_labels) + list(channel.labels)
    H = np.zeros((p, md))
    if channel.kind == "output":
        if channel.output not in list(sys.output_labels):
            raise DimensionError(f"channel {channel.name!r}: no output {channel.output!r}; "
                                 f"outputs are {list(sys.output_labels)}")
        H[list(sys.output_labels).index(channel.output), 0] = 1.0
    full = named_ss(A, np.hstack([B, channel.G]), C, np.hstack([D, H]),
                    sys.dt if ct.isdtime(sys, strict=True) else 0,
                    states=sys.state_labels, inputs=inputs, outputs=sys.output_labels,
                    name=sys.name)
    if ct.isdtime(sys, strict=True):
        return full
    return discretize(full, dt)


def kinematic_partner(A: NDArray, i: int) -> int | None:
    """The state p with ``dp/dt = x_i`` (row p of A has its only nonzero at column i), or None."""
    A = np.asarray(A, dtype=float)
    for p in range(A.shape[0]):
        row = A[p]
        if row[i] != 0 and np.count_nonzero(row) == 1:
            return p
    return None


def relative_coordinates(sys: ct.StateSpace, pair: Channel) -> tuple[tuple[int, int], ...]:
    """State pairs (i, j) whose difference ``x_j - x_i`` a force inside ``pair`` may depend on.

    The two states whose equations the pair enters and, for a continuous
    model, their kinematic partners (the positions whose derivatives they are).
    """
    labels = list(sys.state_labels)
    a, b = (labels.index(e) for e in pair.equations)
    rel = []
    if not ct.isdtime(sys, strict=True):
        pa, pb = kinematic_partner(sys.A, a), kinematic_partner(sys.A, b)
        if pa is not None and pb is not None:
            rel.append((pa, pb))
    rel.append((a, b))
    return tuple(rel)


def linked_forces(sys: ct.StateSpace, equations: Sequence[str]) -> tuple[Channel, ...]:
    """One force between each two bodies the model already links, along the link's own
    direction.

    Equations a and b are linked when each reads the other's state (``A[a, b]`` and
    ``A[b, a]`` nonzero) or, for a continuous model, the other's kinematic partner (the
    position whose derivative it is): a spring, damper or heat path between two
    bodies. An element there that the model has wrong, or lacks beside it, acts on
    both bodies equally and oppositely, so it enters the two equations in the ratio
    the link already has: ``(A[a, b'], -A[b, a'])`` (1/m_a : -1/m_b for a spring
    between masses, 1/C_a : -1/C_b for a heat path), b', a' the linking columns. These
    are the forces to trace when nothing ranks the equations (no equation screen):
    one law (md = 1) per linked pair, which may use the two bodies' relative
    coordinates (:func:`force_channel`). A discrete model mixes its rows (every pair
    would read as linked): none returned.

    Parameters
    ----------
    sys : control.StateSpace
        Nominal model.
    equations : sequence of str
        State names: the candidate equations (kinematic identities left out).

    Returns
    -------
    tuple of Channel
        The forces (kind "force", md = 1), in state order of their pairs.
    """
    if ct.isdtime(sys, strict=True):
        return ()
    A = np.asarray(sys.A, dtype=float)
    labels = list(sys.state_labels)
    idx = sorted(labels.index(e) for e in equations)
    partner = {i: kinematic_partner(A, i) for i in idx}  # each an O(n^2) scan: once
    out = []
    for k, a in enumerate(idx):
        for b in idx[k + 1:]:
            pa, pb = partner[a], partner[b]
            links = [(b, a)] + ([(pb, pa)] if pa is not None and pb is not None else [])
            g = next((np.array([A[a, lb], -A[b, la]]) for lb, la in links[::-1]
                      if A[a, lb] != 0 and A[b, la] != 0), None)
            if g is not None:
                out.append(force_channel(sys, _eq_channel(sys, [a, b]), g / np.abs(g).max()))
    return tuple(out)


def force_channel(sys: ct.StateSpace, pair: Channel, direction: NDArray) -> Channel:
    """One force acting along ``direction`` inside a pair of equations (md = 1).

    ``G = pair.G @ direction``; the law may use the relative coordinates of
    the two bodies: the states whose equations the pair enters, and (for a
    continuous model) their kinematic partners (positions whose derivative
    they are).

    Parameters
    ----------
    sys : control.StateSpace
        Nominal model (continuous for kinematic partners).
    pair : Channel
        A channel with md = 2 entering single equations.
    direction : ndarray, shape (2,)
        Ratio of the force's effect on the two equations.
    """
    labels = list(sys.state_labels)
    a, b = (labels.index(e) for e in pair.equations)
    rel = relative_coordinates(sys, pair)
    g = np.asarray(direction, dtype=float).reshape(-1)
    G = np.asarray(pair.G, dtype=float) @ g
    name = f"force({labels[a]},{labels[b]})"
    unit = pair.units[0] if pair.units else ""
    return Channel(name=name, G=G[:, None], labels=(f"d_{labels[a]}{labels[b]}",),
                   units=(unit,), equations=pair.equations, kind="force", relative=rel)
