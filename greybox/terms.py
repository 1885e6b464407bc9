"""Law terms: one class per kind of term, and the candidate libraries built from them.

A static law ``d = sum_j coef_j * term_j(x, u)`` (:class:`greybox.trace.StaticLaw`)
names each candidate term by a spec entry ``(display name, kind, index)``: the kind
string says what the term is (``"x"`` a state, ``"rel^3"`` the cube of a relative
coordinate, ``"u_dz"`` an input's dead zone, ...) and the index which variables it
reads. Everything greybox does with a term (evaluate it, take its linear part into a
``StateSpace``, tell its odd siblings, refit its breakpoint, draw it, describe a sensor
effect, write it in a zoo truth's canonical form) is asked of its kind here, through
:func:`term_kind`; no other module branches on a kind string. A new kind of term is one
class below, registered with :func:`register` and placed in :data:`LIBRARY` (or
:data:`OUTPUT_LIBRARY`): nothing else changes.

This module reads only numpy: it sits beside the metrics, under the filters, so the
plant zoo (which scores greybox's laws against its truths) can use it too.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from .exceptions import ModelError

#: Quantiles of a state's record where the saturation hinges are placed (upper, lower).
SAT_QUANTILES = ((0.6, 0.75, 0.9), (0.1, 0.25))
#: Quantiles of |u_j| where an input's dead-zone and saturation breakpoints start (each
#: selected one is then refitted freely by the static-law fit).
BREAK_QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9)


def natural_key(name: str) -> list:
    """Sort key that orders p2 before p10."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


@dataclass(frozen=True)
class Variables:
    """The signals a candidate library is built on.

    Attributes
    ----------
    x : ndarray, shape (nstates, N)
    u : ndarray, shape (ninputs, N)
    states, inputs : tuple of str
        Their names.
    relative : tuple of (i, j)
        State pairs offered as the relative coordinate ``x_j - x_i``.
    eps : ndarray, shape (nstates + len(relative),)
        Smoothing widths of ``sign(v) ~ tanh(v / eps)``: one per state, then one per
        relative coordinate.
    breaks : tuple of int
        Inputs offered a dead zone and a saturation.
    """

    x: NDArray
    u: NDArray
    states: tuple
    inputs: tuple
    relative: tuple
    eps: NDArray
    breaks: tuple = ()

    def rel_name(self, r: int) -> str:
        i, j = self.relative[r]
        return f"({self.states[j]}-{self.states[i]})"

    def over(self, what: str) -> list:
        """The variables a group of kinds is generated over (see :data:`LIBRARY`)."""
        n, m, N = self.x.shape[0], self.u.shape[0], self.x.shape[1]
        if what == "states":
            return list(range(n))
        if what == "inputs":
            return list(range(m))
        if what == "relative":
            return list(range(len(self.relative)))
        if what == "state_input":
            return [(i, j) for i in range(n) for j in range(m)]
        if what == "break_inputs":
            return list(self.breaks) if N else []
        if what == "hinge_states":
            return list(range(n)) if N else []
        return [None]  # "one": a single term


class TermKind:
    """What greybox knows of one kind of law term (subclass per kind; see :func:`register`).

    Class attributes
    ----------------
    kind : str
        The spec entry's kind string (also the JSON ``"kind"`` of a law term).
    linear : bool
        A linear function of the states and inputs: it enters the law's linear part
        (``Ddx``, ``Ddu``: the updated ``StateSpace``) exactly.
    family : str or None
        Odd forms of one variable share a family ("state": v, v^3, sign(v); "relative":
        the same of a relative coordinate): output error tells such siblings apart where
        d^ cannot. None: no sibling.
    level : str or None
        "input": a breakpoint refitted freely with the coefficient (it counts as a
        parameter); "state": a hinge at a quantile of a state (a grid of levels). None:
        no level.
    sensor_states : int
        States the term adds to the updated model as a sensor law (a lag: 1; a drift: 2).
    static : bool
        A function of the current sample (False: a sensor lag, a drift).
    smoothed : bool
        A sign taken as ``tanh(v / eps)``.
    time_constant : bool
        The coefficient is a time constant [s] (a sensor lag: pole -1/tau).
    reads_input : bool
        The term reads an input (an input, a product with one, a breakpoint).
    carries_offset : bool
        A sensor law with this term carries its offset as a state (a drift).
    """

    kind: ClassVar[str] = ""
    linear: ClassVar[bool] = False
    family: ClassVar[str | None] = None
    level: ClassVar[str | None] = None
    sensor_states: ClassVar[int] = 0
    static: ClassVar[bool] = True
    smoothed: ClassVar[bool] = False
    time_constant: ClassVar[bool] = False
    reads_input: ClassVar[bool] = False
    carries_offset: ClassVar[bool] = False
    constant: ClassVar[bool] = False

    @property
    def affine(self) -> bool:
        """Linear or the constant: the law's linear part plus an offset is exact."""
        return self.linear or self.constant

    # ---------------------------------------------------------------- evaluation
    def value(self, index, x: NDArray, u: NDArray, eps: NDArray) -> NDArray:
        """The term on x (nstates, ...) and u (ninputs, ...); shape x.shape[1:]."""
        raise NotImplementedError

    def batch(self, indices: list, eps: NDArray) -> Callable[[NDArray, NDArray], NDArray]:
        """``f(x, u)``: the terms of this kind at ``indices`` stacked, shape
        (len(indices),) + x.shape[1:], the same numbers as :meth:`value` of each. Built
        once per law: a simulation evaluates the law at every sample, and a kind whose
        form is one elementwise expression evaluates all its terms in one call."""
        value = self.value
        return lambda x, u: np.array([value(i, x, u, eps) for i in indices]).reshape(
            (len(indices),) + x.shape[1:])

    def add_linear(self, index, col: NDArray, Ddx: NDArray, Ddu: NDArray) -> None:
        """Add ``col`` (md,) times the term to the linear part ``(Ddx, Ddu)`` (linear kinds)."""

    def eps_slot(self, index) -> int | None:
        """The entry of the law's ``eps`` a smoothed term reads (None: not smoothed)."""
        return None

    def steepest(self, index, eps: NDArray) -> float:
        """The largest slope of a smoothed term in the states it reads (the sum over them of
        ``|d term / d x|`` at its steepest: ``1 / eps`` for ``tanh(v / eps)``, twice that
        for a relative coordinate); 0 for any other term (its slope is bounded by the
        record's scale, not by a width the fit may narrow)."""
        slot = self.eps_slot(index)
        return 0.0 if slot is None else 1.0 / float(eps[slot])

    # ---------------------------------------------------------------- library
    def candidates(self, V: Variables, var) -> list[tuple[NDArray, tuple]]:
        """``(row (N,), spec entry)`` of the term's candidates on variable ``var``."""
        raise NotImplementedError

    # ---------------------------------------------------------------- description
    def variable(self, index, x, u, states, inputs):
        """``(values, name)`` of the variable the term reads (a plot's abscissa); None."""
        return None

    def canonical(self, name: str, index, out_name: str = "") -> list[tuple[str, tuple, float]]:
        """The term in the zoo's canonical vocabulary: ``[(expression, variables, sign)]``
        (a relative coordinate is two terms); ``(name, (), 1)``: a form no truth uses."""
        return [(name, (), 1.0)]

    def sensor_note(self, out: str, c: float, pm: str, drift: bool) -> str | None:
        """What the term with coefficient c (interval text ``pm``) says about sensor ``out``
        (``drift``: the law carries its offset as a state)."""
        return None

    def continuous_sensor(self, A: NDArray, B: NDArray, C: NDArray, D: NDArray, i: int,
                          c: float) -> tuple[NDArray, NDArray, NDArray, NDArray] | None:
        """The continuous model ``(A, B, C, D)`` read through this sensor law on output
        ``i`` with coefficient c, the law's states last; None when the law has none or no
        continuous form (a later pass then starts from the discrete updated model)."""
        return None

    def column(self, index) -> tuple[str, int] | None:
        """``("A", i)`` or ``("B", j)``: the column of the nominal model's matrix a linear
        term of one state or input re-scales (a parameter note); None."""
        return None

    def pair(self, index) -> tuple[int, int] | None:
        """``(i, j)``: the two states of a relative coordinate ``x_j - x_i``; None."""
        return None


#: The registered kinds, by kind string (:func:`register`).
KINDS: dict[str, TermKind] = {}


def register(cls: type[TermKind]) -> type[TermKind]:
    """Class decorator: register a :class:`TermKind` under its ``kind`` string."""
    if not cls.kind or cls.kind in KINDS:
        raise ValueError(f"term kind {cls.kind!r} is empty or registered twice")
    KINDS[cls.kind] = cls()
    return cls


def term_kind(kind: str) -> TermKind:
    """The registered :class:`TermKind` of a spec entry's kind string."""
    try:
        return KINDS[kind]
    except KeyError:
        raise ModelError(f"unknown law term kind {kind!r}; expected one of "
                         f"{sorted(KINDS)}. Hint: register the kind in greybox.terms") from None


def kinds_where(**attrs) -> tuple[str, ...]:
    """Kind strings whose class attributes equal ``attrs`` (registry order)."""
    return tuple(k for k, t in KINDS.items() if all(getattr(t, a) == v for a, v in attrs.items()))


# ============================================================= states, inputs, pairs
def _per_row(a: NDArray, rows) -> dict[int, NDArray]:
    """``a[rows]`` shaped to broadcast against ``x[rows]``, by the number of dimensions of
    x: ``{1: (g,), 2: (g, 1), 3: (g, 1, 1)}``."""
    v = np.asarray(a, dtype=float)[rows]
    return {d: v.reshape((-1,) + (1,) * (d - 1)) for d in (1, 2, 3)}


def _one(name: str, row: NDArray, kind: str, index) -> list[tuple[NDArray, tuple]]:
    return [(row, (name, kind, index))]


class _OfState(TermKind):
    """A form of state x_i (index i)."""

    def variable(self, index, x, u, states, inputs):
        return x[index], states[index]

    def form(self, v: NDArray, eps: float) -> NDArray:
        raise NotImplementedError

    def value(self, index, x, u, eps):
        return self.form(x[index], eps[index] if self.smoothed else None)

    def eps_slot(self, index):
        return int(index) if self.smoothed else None

    def batch(self, indices, eps):
        rows, form = np.asarray(indices, dtype=np.intp), self.form
        e = _per_row(eps, rows) if self.smoothed else None
        return lambda x, u: form(x[rows], None if e is None else e[x.ndim])

    def display(self, s: str) -> str:
        raise NotImplementedError

    def candidates(self, V, i):
        return _one(self.display(V.states[i]), self.form(V.x[i], V.eps[i]), self.kind, i)


class _OfPair(TermKind):
    """A form of the relative coordinate ``x_j - x_i`` (index (i, j, e), e its eps)."""

    family = "relative"

    def variable(self, index, x, u, states, inputs):
        return x[index[1]] - x[index[0]], f"{states[index[1]]} - {states[index[0]]}"

    def form(self, v: NDArray, eps: float) -> NDArray:
        raise NotImplementedError

    def value(self, index, x, u, eps):
        a, b, e = index
        return self.form(x[b] - x[a], eps[e] if self.smoothed else None)

    def eps_slot(self, index):
        return int(index[2]) if self.smoothed else None

    def steepest(self, index, eps):
        return 2.0 * super().steepest(index, eps)  # x_j - x_i reads two states

    def batch(self, indices, eps):
        a, b, e = (np.asarray([ix[k] for ix in indices], dtype=np.intp) for k in range(3))
        form, w = self.form, _per_row(eps, e) if self.smoothed else None
        return lambda x, u: form(x[b] - x[a], None if w is None else w[x.ndim])

    def display(self, s: str) -> str:
        raise NotImplementedError

    def candidates(self, V, r):
        i, j = V.relative[r]
        e = V.x.shape[0] + r
        return _one(self.display(V.rel_name(r)), self.form(V.x[j] - V.x[i], V.eps[e]),
                    self.kind, (i, j, e))


_REL = re.compile(r"^\((.+)-(.+)\)(\^3)?$")


@register
class State(_OfState):
    """The state itself (linear)."""

    kind, linear, family = "x", True, "state"

    def form(self, v, eps):
        return v

    def display(self, s):
        return s

    def add_linear(self, index, col, Ddx, Ddu):
        Ddx[:, index] += col

    def column(self, index):
        return "A", index

    def canonical(self, name, index, out_name=""):
        return [(name, (name,), 1.0)]


@register
class Input(TermKind):
    """An input (linear)."""

    kind, linear, reads_input = "u", True, True

    def value(self, index, x, u, eps):
        return u[index]

    def batch(self, indices, eps):
        rows = np.asarray(indices, dtype=np.intp)
        return lambda x, u: u[rows]

    def add_linear(self, index, col, Ddx, Ddu):
        Ddu[:, index] += col

    def column(self, index):
        return "B", index

    def candidates(self, V, j):
        return _one(V.inputs[j], V.u[j], self.kind, j)

    def variable(self, index, x, u, states, inputs):
        return u[index], inputs[index]

    def canonical(self, name, index, out_name=""):
        return [(name, (name,), 1.0)]


@register
class Relative(_OfPair):
    """A relative coordinate ``x_j - x_i`` (linear): a force between two bodies."""

    kind, linear = "rel", True

    def form(self, v, eps):
        return v

    def display(self, s):
        return s

    def add_linear(self, index, col, Ddx, Ddu):
        Ddx[:, index[1]] += col
        Ddx[:, index[0]] -= col

    def pair(self, index):
        return index[0], index[1]

    def canonical(self, name, index, out_name=""):
        m = _REL.match(name)
        if not m:
            return super().canonical(name, index)
        b, a = m.group(1), m.group(2)  # (b - a)
        return [(b, (b,), 1.0), (a, (a,), -1.0)]


@register
class Cube(_OfState):
    """``x_i^3``: a hardening (or softening) spring."""

    kind, family = "x^3", "state"

    def form(self, v, eps):
        return v * v * v

    def display(self, s):
        return f"{s}^3"

    def canonical(self, name, index, out_name=""):
        return [(f"{name[:-2]}^3", (name[:-2],), 1.0)]


@register
class Sign(_OfState):
    """``sign(x_i)`` smoothed as ``tanh(x_i / eps_i)``: Coulomb friction."""

    kind, family, smoothed = "sign", "state", True

    def form(self, v, eps):
        return np.tanh(v / eps)

    def display(self, s):
        return f"sign({s})"

    def canonical(self, name, index, out_name=""):
        inner = name[len("sign("):-1]
        return [(f"sign({inner})", (inner,), 1.0)]


@register
class Abs(_OfState):
    """``|x_i|``: an even term (a rectifier); no sibling of x_i."""

    kind = "abs"

    def form(self, v, eps):
        return np.abs(v)

    def display(self, s):
        return f"|{s}|"

    def canonical(self, name, index, out_name=""):
        inner = name.strip("|")
        return [(f"|{inner}|", (inner,), 1.0)]


@register
class SignedSquare(_OfState):
    """``x_i |x_i|``: a quadratic drag (a fan, a pump, a hull, a vehicle in air); odd, a
    sibling of x_i, x_i^3 and sign(x_i)."""

    kind, family = "x|x|", "state"

    def form(self, v, eps):
        return v * np.abs(v)

    def display(self, s):
        return f"{s}*|{s}|"

    def canonical(self, name, index, out_name=""):
        inner = name.split("*", 1)[0]
        return [(f"{inner}|{inner}|", (inner,), 1.0)]


@register
class RelativeCube(_OfPair):
    """``(x_j - x_i)^3``: a hardening spring between two bodies."""

    kind = "rel^3"

    def form(self, v, eps):
        return v * v * v

    def display(self, s):
        return f"{s}^3"

    def canonical(self, name, index, out_name=""):
        m = _REL.match(name)
        if not m:
            return super().canonical(name, index)
        b, a, sign = m.group(1), m.group(2), 1.0
        if natural_key(a) > natural_key(b):
            a, b, sign = b, a, -1.0
        return [(f"({b}-{a})^3", (a, b), sign)]


@register
class RelativeSign(_OfPair):
    """``sign(x_j - x_i)`` smoothed: friction between two bodies."""

    kind, smoothed = "rel_sign", True

    def form(self, v, eps):
        return np.tanh(v / eps)

    def display(self, s):
        return f"sign{s}"


@register
class RelativeAbs(_OfPair):
    """``|x_j - x_i|`` (even; no sibling)."""

    kind, family = "rel_abs", None

    def form(self, v, eps):
        return np.abs(v)

    def display(self, s):
        return f"|{s}|"


@register
class Product(TermKind):
    """``x_i * u_j`` (index (i, j)): a flow times a temperature, a field times a speed."""

    kind, reads_input = "x*u", True

    def value(self, index, x, u, eps):
        return x[index[0]] * u[index[1]]

    def candidates(self, V, ij):
        i, j = ij
        return _one(f"{V.states[i]}*{V.inputs[j]}", V.x[i] * V.u[j], self.kind, (i, j))

    def variable(self, index, x, u, states, inputs):
        return x[index[0]], states[index[0]]

    def canonical(self, name, index, out_name=""):
        return [(name, tuple(name.split("*")), 1.0)]


# ============================================================= breakpoints and hinges
def break_name(inp: str, kind: str, level: float, half: float = np.nan) -> str:
    """Display name of an input breakpoint term: ``clip(F, ±0.53)``, ``(F - clip(F, ±1.2))``;
    with the level's 95 % half-width ``clip(F, ±(0.53 ± 0.01))``."""
    lv = f"{level:.4g}" if not np.isfinite(half) else f"({level:.4g} ± {half:.2g})"
    return f"clip({inp}, ±{lv})" if kind == "u_dz" else f"({inp} - clip({inp}, ±{lv}))"


def break_row(v: NDArray, kind: str, level: float) -> NDArray:
    """The breakpoint term's value on the input record v (any shape)."""
    cl = np.clip(v, -level, level)
    return cl if kind == "u_dz" else v - cl


def break_slope(v: NDArray, kind: str, level: float) -> NDArray:
    """d(break_row)/d(level): ``sign(v)`` where ``|v| > level`` (negated for "u_sat")."""
    s = np.sign(v) * (np.abs(v) > level)
    return s if kind == "u_dz" else -s


class _Break(TermKind):
    """An input breakpoint term; index ``(j, level, half-width of the level, input name)``.

    With coefficient -1 (in the input's units) ``clip(u, -c, c)`` is a dead zone of
    half-width c and ``u - clip(u, -c, c)`` a saturation at +-c.
    """

    level, reads_input = "input", True
    #: The zoo's name of the effect whose level is the breakpoint.
    effect: ClassVar[str] = ""

    def value(self, index, x, u, eps):
        return break_row(u[index[0]], self.kind, index[1])

    def slope(self, index, u: NDArray) -> NDArray:
        """d(term)/d(level) on the input record."""
        return break_slope(u[index[0]], self.kind, index[1])

    def candidates(self, V, j):
        out = []
        for c in np.nanquantile(np.abs(V.u[j]), BREAK_QUANTILES):
            c = float(c)
            out.append((break_row(V.u[j], self.kind, c),
                        (break_name(V.inputs[j], self.kind, c), self.kind,
                         (j, c, np.nan, V.inputs[j]))))
        return out

    def at_level(self, entry: tuple, level: float, half: float = np.nan) -> tuple:
        """The spec entry at a refitted level (with its 95 % half-width)."""
        j, inp = entry[2][0], entry[2][3]
        return (break_name(inp, self.kind, level, half), self.kind, (j, float(level), half, inp))

    def variable(self, index, x, u, states, inputs):
        return u[index[0]], inputs[index[0]]


@register
class DeadZone(_Break):
    """``clip(u_j, -c, c)``: with coefficient -1 an input dead zone of half-width c."""

    kind, effect = "u_dz", "deadzone"


@register
class InputSaturation(_Break):
    """``u_j - clip(u_j, -c, c)``: with coefficient -1 an input saturation at +-c."""

    kind, effect = "u_sat", "sat"


def hinge_name(state: str, kind: str, level: float) -> str:
    """Display name of a saturation hinge: ``max(x1 - 7.9, 0)`` or ``min(x1 + 0.4, 0)``."""
    sign = "-" if level >= 0 else "+"
    return f"{'max' if kind == 'x_hi' else 'min'}({state} {sign} {abs(level):.4g}, 0)"


class _Hinge(TermKind):
    """``max(x_i - c, 0)`` / ``min(x_i - c, 0)``; index ``(i, c)``: a level that stops at c
    (an overflow, a stop) is a stiff restoring term beyond c."""

    level = "state"
    fn: ClassVar = staticmethod(np.maximum)
    quantiles: ClassVar[tuple] = ()

    def value(self, index, x, u, eps):
        return self.fn(x[index[0]] - index[1], 0.0)

    def batch(self, indices, eps):
        rows = np.asarray([ix[0] for ix in indices], dtype=np.intp)
        c, fn = _per_row(np.asarray([ix[1] for ix in indices], dtype=float), slice(None)), self.fn
        return lambda x, u: fn(x[rows] - c[x.ndim], 0.0)

    def candidates(self, V, i):
        out = []
        for c in np.nanquantile(V.x[i], self.quantiles):
            c = float(c)
            out.append((self.fn(V.x[i] - c, 0.0),
                        (hinge_name(V.states[i], self.kind, c), self.kind, (i, c))))
        return out

    #: Quantiles of a fine grid of levels (a stiff clip's level matters: the law's few
    #: quantile levels may miss it by more than the hinge can make up).
    fine: ClassVar[NDArray] = np.linspace(0.5, 0.99, 9)

    def entry(self, i: int, state: str, level: float) -> tuple:
        """The spec entry of the hinge of state i (named ``state``) at ``level``."""
        return hinge_name(state, self.kind, float(level)), self.kind, (i, float(level))

    @staticmethod
    def state_name(entry: tuple) -> str:
        """The state's name in a hinge's display name."""
        return entry[0][4:-4].rsplit(" ", 2)[0]

    def at_level(self, entry: tuple, level: float, half: float = np.nan) -> tuple:
        """The spec entry at another level."""
        return self.entry(entry[2][0], self.state_name(entry), level)

    def interval_name(self, entry: tuple, half: float) -> str:
        """The display name with the level's 95 % half-width: ``max(x1 - (7.995 ± 0.012), 0)``
        (the plain name when ``half`` is not finite or wider than ``max(|level|, 1)``: a
        degenerate covariance)."""
        level = entry[2][1]
        if not (np.isfinite(half) and half <= max(abs(level), 1.0)):
            return entry[0]
        return (f"{'max' if self.kind == 'x_hi' else 'min'}({self.state_name(entry)} - "
                f"({level:.4g} ± {half:.2g}), 0)")

    def variable(self, index, x, u, states, inputs):
        return x[index[0]], states[index[0]]


@register
class HingeAbove(_Hinge):
    """``max(x_i - c, 0)`` at the 60, 75 and 90 % quantiles of x_i."""

    kind, quantiles = "x_hi", SAT_QUANTILES[0]


@register
class HingeBelow(_Hinge):
    """``min(x_i - c, 0)`` at the 10 and 25 % quantiles of x_i."""

    kind, fn, quantiles = "x_lo", staticmethod(np.minimum), SAT_QUANTILES[1]
    fine = np.linspace(0.01, 0.5, 9)


@register
class Constant(TermKind):
    """The constant 1: an offset (a constant force, a biased sensor)."""

    kind, constant = "const", True

    def value(self, index, x, u, eps):
        return np.ones(x.shape[1:])

    def candidates(self, V, _):
        return _one("1", np.ones(V.x.shape[1]), self.kind, 0)

    def canonical(self, name, index, out_name=""):
        return [("1", (), 1.0)]

    def sensor_note(self, out, c, pm, drift):
        if drift:
            return (f"sensor {out}: offset {c:.4g}{pm} [{out}] at the estimation record's "
                    f"first sample (0 in the model; the updated model's state "
                    f"{out}_offset, estimated with the initial state of every record)")
        return f"sensor {out}: offset {c:.4g}{pm} [{out}] (0 in the model)"


# ============================================================= sensor terms
class _OfOutput(TermKind):
    """A form of the model's own output ``c x + d u``; index ``(c, d)`` (tuples)."""

    #: The term in the zoo's vocabulary, ``{}`` standing for the output's name.
    written: ClassVar[str] = "{}"

    def canonical(self, name, index, out_name=""):
        return [(self.written.format(out_name), (out_name,), 1.0)]

    def reading(self, index, x, u):
        return np.asarray(index[0]) @ x + (np.asarray(index[1]) @ u if len(index[1]) else 0.0)

    def form(self, v: NDArray, index) -> NDArray:
        raise NotImplementedError

    def value(self, index, x, u, eps):
        return self.form(self.reading(index, x, u), index)


@register
class Reading(_OfOutput):
    """The model's output itself (linear): a gain error."""

    kind, linear = "yhat", True

    def form(self, v, index):
        return v

    def add_linear(self, index, col, Ddx, Ddu):
        Ddx += np.outer(col, index[0])
        if len(index[1]):
            Ddu += np.outer(col, index[1])

    def sensor_note(self, out, c, pm, drift):
        return (f"sensor {out}: gain 1 in the model; the data want {1 + c:.4g}{pm} "
                f"({100 * c:+.1f} %)")


@register
class ReadingCube(_OfOutput):
    """The output's cube (negative: a soft saturation)."""

    kind, written = "yhat^3", "{}^3"

    def form(self, v, index):
        return v * v * v

    def sensor_note(self, out, c, pm, drift):
        return f"sensor {out}: {c:.4g}{pm} * {out}^3 (negative: saturation)"


@register
class ReadingAbs(_OfOutput):
    """The output's absolute value (with the gain at 0: a rectifying sensor)."""

    kind, written = "yhat_abs", "|{}|"

    def form(self, v, index):
        return np.abs(v)

    def sensor_note(self, out, c, pm, drift):
        return (f"sensor {out}: {c:.4g}{pm} * |{out}| (with the gain at 0 a rectifier: "
                f"the sensor reads |{out}|)")


@register
class ReadingSaturation(_OfOutput):
    """``(clip(y, -L, L) - y) / L`` (index ``(c, d, L)``): its coefficient is L itself."""

    kind, written = "yhat_sat", "sat({})"

    def form(self, v, index):
        return (np.clip(v, -index[2], index[2]) - v) / index[2]

    def sensor_note(self, out, c, pm, drift):
        return (f"sensor {out}: saturates at +-{c:.4g}{pm} [{out}] (the sensor reads "
                f"clip({out}, -L, L); none in the model)")


class _NotStatic(TermKind):
    static = False
    what: ClassVar[str] = ""

    def value(self, index, x, u, eps):
        raise ModelError(f"{self.what} is not a function of the current sample; found a "
                         f"{self.kind!r} term; expected a static term. Hint: simulate the "
                         f"trace's static_model (it carries the sensor's states last)")


@register
class SensorLag(_NotStatic):
    """A first-order sensor lag 1/(tau s + 1): coefficient tau [s]; one sensor state."""

    kind, sensor_states, what, time_constant = "yhat_lag", 1, "a first-order sensor lag", True

    def sensor_note(self, out, c, pm, drift):
        return (f"sensor {out}: first-order lag 1/(tau s + 1), tau = {c:.4g}{pm} s "
                f"(none in the model: the reading is the updated model's state "
                f"{out}_sensor)")

    def continuous_sensor(self, A, B, C, D, i, c):
        """``dz/dt = (C_i x + D_i u - z) / tau``, output i reads z (tau = c)."""
        if not (np.isfinite(c) and c > 0):
            return None
        n = A.shape[0]
        Aa = np.zeros((n + 1, n + 1))
        Aa[:n, :n], Aa[n, :n], Aa[n, n] = A, C[i] / c, -1.0 / c
        Ba = np.vstack([B, D[i][None, :] / c])
        Ca = np.hstack([C, np.zeros((C.shape[0], 1))])
        Ca[i] = 0.0
        Ca[i, n] = 1.0
        Da = D.copy()
        Da[i] = 0.0
        return Aa, Ba, Ca, Da


@register
class Drift(_NotStatic):
    """A sensor drift: coefficient the drift rate [output units/s]; two sensor states."""

    kind, sensor_states, what, carries_offset = "drift", 2, "a sensor drift", True

    def canonical(self, name, index, out_name=""):
        return [("t", (), 1.0)]

    def sensor_note(self, out, c, pm, drift):
        return (f"sensor {out}: drifts at {c:.4g}{pm} [{out}]/s (0 in the model; the "
                f"updated model's state {out}_drift: d{out}_offset/dt = {out}_drift)")


# ============================================================= libraries
#: The candidate library of a state-equation or input law, in order: groups of kinds
#: generated over one kind of variable (for each variable, each kind of the group),
#: with the switch of :func:`law_terms` that offers them (None: always). The linear
#: terms come first (the static-law fit relies on it) and the constant last.
LIBRARY: tuple[tuple[str, tuple[str, ...], str | None], ...] = (
    ("states", ("x",), None),
    ("inputs", ("u",), None),
    ("relative", ("rel",), None),
    ("states", ("x^3", "sign", "abs", "x|x|"), "nonlinear"),
    ("relative", ("rel^3", "rel_sign", "rel_abs"), "nonlinear"),
    ("state_input", ("x*u",), "nonlinear"),
    ("break_inputs", ("u_dz", "u_sat"), "breaks"),
    ("hinge_states", ("x_hi", "x_lo"), "saturation"),
    ("one", ("const",), "nonlinear"),
)
#: The candidates of a sensor-error law on the model's own output (:func:`output_terms`).
OUTPUT_LIBRARY: tuple[tuple[str, str | None], ...] = (
    ("yhat", None), ("yhat^3", "nonlinear"), ("yhat_abs", "nonlinear"), ("const", "nonlinear"))


def law_terms(x: NDArray, u: NDArray, state_labels: Sequence[str],
              input_labels: Sequence[str], *, nonlinear: bool = True,
              eps: NDArray | None = None,
              relative: Sequence[tuple[int, int]] = (),
              saturation: bool = False,
              breaks: Sequence[int] = ()) -> tuple[NDArray, list, NDArray]:
    """Candidate terms of a static law, evaluated on (x, u): the :data:`LIBRARY`.

    Returns ``(terms, spec, eps)``: terms of shape (nterms, nsteps), a spec
    list of ``(display name, kind, index)`` (the kinds registered here), and the
    eps of each ``tanh(v/eps)`` (5 % of v's RMS unless given; one per state, then
    one per relative coordinate). ``relative`` lists state pairs (i, j): the
    relative coordinate ``x_j - x_i`` (a force between two bodies depends on it,
    PAPER_NOTES §9.6) is offered like a state, with index ``(i, j, k)`` where k
    indexes its eps. The linear terms (x, u, rel) come first; with ``nonlinear``
    the cubes, signs and absolute values, the bilinear products ``x_i*u_j`` and
    the constant "1" (last) follow. With ``saturation`` (and ``nonlinear``) each
    state also gets hinges ``max(x_i - c, 0)`` at the 60, 75 and 90 % quantiles of
    its record and ``min(x_i - c, 0)`` at the 10 and 25 % ones (kinds "x_hi",
    "x_lo"). With ``breaks`` (and ``nonlinear``) each input j listed gets
    ``clip(u_j, -c, c)`` and ``u_j - clip(u_j, -c, c)`` (kinds "u_dz", "u_sat") at
    the :data:`BREAK_QUANTILES` of ``|u_j|``: with coefficient -1 an input dead zone
    of half-width c and a saturation at +-c.
    """
    n = x.shape[0]
    rel = [x[j] - x[i] for i, j in relative]
    if eps is None:
        eps = 0.05 * np.sqrt(np.nanmean(np.array(list(x) + rel) ** 2, axis=1)) + 1e-300 \
            if n + len(rel) else np.zeros(0)
    V = Variables(x, u, tuple(state_labels), tuple(input_labels), tuple(relative), eps,
                  tuple(breaks))
    on = {None: True, "nonlinear": nonlinear, "breaks": nonlinear,
          "saturation": nonlinear and saturation}
    rows, spec = [], []
    for over, kinds, switch in LIBRARY:
        if not on[switch]:
            continue
        for var in V.over(over):
            for k in kinds:
                for row, entry in KINDS[k].candidates(V, var):
                    rows.append(row)
                    spec.append(entry)
    N = x.shape[1]
    return (np.array(rows) if rows else np.zeros((0, N))), spec, eps


def output_terms(x: NDArray, u: NDArray, c: NDArray, dd: NDArray, name: str, *,
                 nonlinear: bool = True) -> tuple[NDArray, list, NDArray]:
    """Candidate terms of a sensor-error law on the model's own output ``c x + dd u``.

    Returns ``(terms, spec, eps)`` as :func:`law_terms` (the :data:`OUTPUT_LIBRARY`):
    ``<name>_model`` (a gain error), and with ``nonlinear`` its cube (a soft
    saturation), its absolute value (a rectifying sensor: ``|y| - y``) and the offset
    "1".
    """
    c = np.asarray(c, dtype=float).reshape(-1)
    dd = np.asarray(dd, dtype=float).reshape(-1)
    idx = (tuple(float(v) for v in c), tuple(float(v) for v in dd))
    yh = KINDS["yhat"].value(idx, x, u, np.zeros(0))
    nm = f"{name}_model"
    display = {"yhat": nm, "yhat^3": f"{nm}^3", "yhat_abs": f"|{nm}|", "const": "1"}
    rows, spec = [], []
    for k, switch in OUTPUT_LIBRARY:
        if switch is None or nonlinear:
            i = 0 if k == "const" else idx
            rows.append(KINDS[k].value(i, x, u, np.zeros(0)))
            spec.append((display[k], k, i))
    eps = np.array([0.05 * np.sqrt(np.mean(yh**2)) + 1e-300])
    return np.array(rows), spec, eps


def evaluate_terms(spec, eps: NDArray, x: NDArray, u: NDArray) -> NDArray:
    """Every term of ``spec`` on x (nstates, ...) and u (ninputs, ...): (nterms, ...)."""
    return evaluator(spec, eps)(x, u)


def evaluator(spec, eps: NDArray):
    """``f(x, u)``: :func:`evaluate_terms` of ``spec`` with the kinds looked up once (a
    simulation evaluates a law at every sample)."""
    groups: dict[str, tuple[list, list]] = {}  # per kind: (rows of the result, indices)
    for r, (_, kind, i) in enumerate(spec):
        rows, idx = groups.setdefault(kind, ([], []))
        rows.append(r)
        idx.append(i)
    n, calls = len(spec), []
    for kind, (rows, idx) in groups.items():
        t = term_kind(kind)
        if len(idx) == 1:  # one term: no gather
            calls.append((rows[0], partial(t.value, idx[0], eps=eps)))
        else:
            calls.append((slice(None) if len(groups) == 1 else np.asarray(rows, dtype=np.intp),
                          t.batch(idx, eps)))

    def evaluate(x: NDArray, u: NDArray) -> NDArray:
        out = np.empty((n,) + x.shape[1:])
        for rows, f in calls:
            out[rows] = f(x, u)
        return out
    return evaluate


def linear_part(spec, coef: NDArray, n: int, m: int) -> tuple[NDArray, NDArray]:
    """(Ddx (md, n), Ddu (md, m)) of the linear terms (x, u, rel, yhat) of a law's
    coefficients coef (md, nterms)."""
    md = coef.shape[0]
    Ddx, Ddu = np.zeros((md, n)), np.zeros((md, m))
    for j, (_, kind, i) in enumerate(spec):
        t = term_kind(kind)
        if t.linear:
            t.add_linear(i, coef[:, j], Ddx, Ddu)
    return Ddx, Ddu


def own_state_terms(spec, i: int) -> list[int]:
    """Indices of the terms of ``spec`` that are forms of state ``i`` an equation's own law
    is offered (:data:`OWN_STATE_KINDS`: v, v^3, sign(v), v|v|)."""
    return [j for j, sp in enumerate(spec) if sp[1] in OWN_STATE_KINDS and sp[2] == i]


def shapes(spec) -> list:
    """Per term, a label shared by the nonlinear odd shapes of one variable (v^3, sign(v),
    v*|v|: alternatives, at most one in a law's selection on d^), else None.

    Several of them together fit a shape mismatch (a smoothed sign of another width
    than the plant's), not the physics; output error exchanges the chosen one for its
    siblings where the data say so (:func:`siblings`)."""
    out = []
    for _, kind, i in spec:
        t = term_kind(kind)
        out.append((t.family, i) if t.family is not None and not t.linear else None)
    return out


def siblings(spec, j: int) -> list[int]:
    """Indices of the terms of ``spec`` that are the other odd forms of term j's variable
    (the same :attr:`TermKind.family` and index: v, v^3, sign(v)); empty for any other
    kind."""
    kind, var = spec[j][1], spec[j][2]
    fam = term_kind(kind).family
    if fam is None:
        return []
    return [q for q, (_, k, i) in enumerate(spec) if q != j and term_kind(k).family == fam
            and i == var]


#: Kinds entering a law's linear part exactly.
LINEAR_KINDS = kinds_where(linear=True)
#: The forms of a state a one-equation law is offered when it lacks its own equation's
#: state (its damping, loss, friction, drag: :func:`greybox.trace.oe.offer_terms`).
OWN_STATE_KINDS = ("x", "x^3", "sign", "x|x|")
#: Input breakpoint kinds (a refitted level: one more parameter).
BREAK_KINDS = kinds_where(level="input")
#: State hinge kinds (a level on a grid of quantiles).
HINGE_KINDS = kinds_where(level="state")
#: Sensor-law kinds the updated model carries as sensor states (number of states each).
SENSOR_STATE_KINDS = {k: t.sensor_states for k, t in KINDS.items() if t.sensor_states}
#: The odd forms of one variable, per family (output error tells them apart).
SIBLING_KINDS = tuple(kinds_where(family=f) for f in dict.fromkeys(
    t.family for t in KINDS.values() if t.family))
