"""Nonlinear models as python-control ``NonlinearIOSystem`` objects (section IV).

A nominal nonlinear model is a ``control.NonlinearIOSystem`` (``ct.nlsys``)
with named states, inputs ``[u, d]`` (known inputs and unknown model-error
inputs) and outputs. The filters of section IV (:func:`greybox.ui_ukf`,
:func:`greybox.ensemble_uikf`) need a discrete-time model with a *linear*
output map ``y = C x + D u`` (the paper's (33)); :func:`linear_output_map`
extracts (C, D) and says so clearly when the output map is not linear.

Discretization (one documented rule): :func:`discretize_nonlinear` integrates
the continuous dynamics over each sample with classical fourth-order
Runge-Kutta (RK4) in ``substeps`` equal sub-steps, the inputs held constant
over the sample (zero-order hold, as for the linear models, so that ``d``
keeps its physical units). The sub-step count is chosen from the fastest
local time constant: the largest eigenvalue modulus ``|lambda|max`` of the
Jacobian of f at an operating point, with ``|lambda|max h <= 0.35`` (RK4's
local error per sub-step is then ~ (0.35)^5/120 ~ 4e-5 of the fast mode's
amplitude, well inside its stability limit 2.78). The motor-pump is stiff
(PAPER_NOTES §8.9): its speed mode has a 56 us time constant at our running
point, which gives 6 sub-steps at Ts = 1e-4 s. Pass ``substeps`` to override.
:func:`rk4_substeps_for` checks a count on a record by step doubling (a mode
faster away from the operating point, a phase error accumulating over a long
record); ``close_the_loop`` uses it on the estimation record.

Vectorized evaluation: if the update function accepts states of shape
``(nstates, npoints)`` (and inputs of shape ``(ninputs, npoints)``) and
returns the same shape - true of most functions written with ``x[0]``,
``x[1]``, ``np.sin`` ... - the filters evaluate all sigma points or ensemble
members in one call; otherwise they loop over the points. RK4-discretized
models inherit the property from the continuous function.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import control as ct
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._validation import (check_covariance, check_input_record, check_positive,
                          check_vector)
from .exceptions import DataError, DimensionError, ModelError
from .signals import SimulationResult, gaussian_noise, as_generator
from .hold import LawHold, as_hold
from .system import named_ss

__all__ = [
    "simulate_batch",
    "rk4_substeps",
    "rk4_substeps_for",
    "discretize_nonlinear",
    "linear_output_map",
    "simulate_nonlinear",
    "StateMap",
    "state_map",
    "as_nonlinear",
    "with_unknown_inputs",
    "add_law",
    "linearize_at",
    "kinematic_identities",
]

_RK4_H_LAMBDA = 0.35
"""Largest ``|lambda| h`` allowed per RK4 sub-step (see the module notes)."""


def _check_nlsys(sys, name: str = "sys") -> ct.NonlinearIOSystem:
    if isinstance(sys, ct.StateSpace) or not isinstance(sys, ct.NonlinearIOSystem):
        raise ModelError(f"{name} must be a control.NonlinearIOSystem (control.nlsys); found "
                         f"{type(sys).__name__}")
    if sys.nstates is None or sys.ninputs is None or sys.noutputs is None:
        raise ModelError(f"{name} must declare its states, inputs and outputs (names or "
                         f"counts) so that the filters can check shapes")
    return sys


def _jacobian(fun: Callable, z: NDArray) -> NDArray:
    """Central-difference Jacobian of the vector function ``fun(z)``, shape (len(fun), z.size)."""
    cols = []
    for i in range(z.size):
        h = 1e-6 * max(1.0, abs(z[i]))
        e = np.zeros(z.size)
        e[i] = h
        cols.append((np.asarray(fun(z + e), float).reshape(-1)
                     - np.asarray(fun(z - e), float).reshape(-1)) / (2 * h))
    if cols:
        return np.column_stack(cols)
    return np.zeros((np.asarray(fun(z), float).size, 0))


def _jacobian_x(fun: Callable, x: NDArray, u: NDArray) -> NDArray:
    """Central-difference Jacobian of ``fun(x, u)`` with respect to x."""
    return _jacobian(lambda z: fun(z, u), x)


def _op_point(sys, x_op, u_op):
    x = np.zeros(sys.nstates) if x_op is None else check_vector(x_op, sys.nstates, "x_op")
    u = np.zeros(sys.ninputs) if u_op is None else check_vector(u_op, sys.ninputs, "u_op")
    return x, u


def rk4_substeps(sys: ct.NonlinearIOSystem, dt: float, *, x_op: ArrayLike | None = None,
                 u_op: ArrayLike | None = None) -> int:
    """RK4 sub-steps per sample from the fastest local time constant.

    Parameters
    ----------
    sys : control.NonlinearIOSystem
        Continuous-time model.
    dt : float
        Sampling period [s].
    x_op : array_like, shape (nstates,), optional
        Operating point where the Jacobian of f is evaluated (zero by default;
        pick a typical running point for models that are stiffer there).
    u_op : array_like, shape (ninputs,), optional
        Input at the operating point (zero by default).

    Returns
    -------
    int
        ``ceil(dt |lambda|max / 0.35)``, at least 1.

    Raises
    ------
    ModelError
        If f is not finite at the operating point.
    """
    _check_nlsys(sys)
    dt = check_positive(dt, "dt")
    x, u = _op_point(sys, x_op, u_op)
    p = sys.params

    def f(xx, uu):
        return sys.updfcn(0.0, xx, uu, p)

    J = _jacobian_x(f, x, u)
    if not np.all(np.isfinite(J)):
        raise ModelError("the Jacobian of f is not finite at the operating point; pass x_op "
                         "and u_op where the model is defined, or give substeps directly")
    lam = float(np.max(np.abs(np.linalg.eigvals(J)))) if J.size else 0.0
    return max(1, int(np.ceil(dt * lam / _RK4_H_LAMBDA)))


def rk4_substeps_for(sys: ct.NonlinearIOSystem, dt: float, u: ArrayLike, *, x0: ArrayLike,
                     tol: ArrayLike, start: int = 1, cap: int = 64) -> int:
    """RK4 sub-steps per sample whose simulation of a record is as good as twice as many.

    Step doubling on the record itself: from ``start``, the output simulated with
    ``s`` sub-steps is compared with ``2 s`` and ``s`` doubled until every output's
    RMS difference is at most ``tol``. RK4's error falls 16-fold per doubling, so
    the difference bounds the error of ``s`` sub-steps. The local rule of
    :func:`rk4_substeps` (one operating point, one sub-step) misses a mode that is
    faster away from that point (a hardening spring at large amplitude) and a
    lightly damped mode whose phase error accumulates over a long record.

    Parameters
    ----------
    sys : control.NonlinearIOSystem
        Continuous-time model.
    dt : float
        Sampling period [s].
    u : array_like, shape (ninputs, nsteps)
        The record's inputs, held over each sample.
    x0 : array_like, shape (nstates,)
        Initial state.
    tol : array_like, shape (noutputs,)
        Largest RMS difference allowed per output, in its units (e.g. a tenth of
        the measurement noise's standard deviation: discretization error is then
        no detectable model error).
    start : int
        First count tried (e.g. :func:`rk4_substeps`).
    cap : int
        Largest count returned.

    Returns
    -------
    int
        Between ``start`` and ``max(start, cap)``; ``start`` when the simulation
        fails (a model unstable on this record: the filters handle it as it is).
    """
    tol = np.asarray(tol, dtype=float).reshape(-1)
    s = max(1, int(start))

    def run(k):
        return simulate_nonlinear(discretize_nonlinear(sys, dt, substeps=k), u,
                                  x0=x0).y_clean

    try:
        y_s = run(s)
        while s < cap:
            y_2 = run(2 * s)
            if np.all(np.sqrt(np.mean((y_2 - y_s) ** 2, axis=1)) <= tol):
                break
            s, y_s = 2 * s, y_2
    except (DataError, FloatingPointError):
        return max(1, int(start))
    return s



def discretize_nonlinear(sys: ct.NonlinearIOSystem, dt: float, *, substeps: int | None = None,
                         x_op: ArrayLike | None = None, u_op: ArrayLike | None = None
                         ) -> ct.NonlinearIOSystem:
    """Discretize a continuous nonlinear model with RK4 sub-steps (inputs held per sample).

    Parameters
    ----------
    sys : control.NonlinearIOSystem
        Continuous-time model ``dx/dt = f(t, x, u)``, ``y = h(t, x, u)``.
    dt : float
        Sampling period [s].
    substeps : int, optional
        RK4 sub-steps per sample; chosen by :func:`rk4_substeps` when omitted.
    x_op : array_like, shape (nstates,), optional
        Operating point for :func:`rk4_substeps`.
    u_op : array_like, shape (ninputs,), optional
        Input at the operating point.

    Returns
    -------
    control.NonlinearIOSystem
        Discrete-time model (``dt`` set) with the same signal names, params
        and output function; its update function accepts a batch of states
        ``(nstates, npoints)`` whenever the continuous f does.

    Raises
    ------
    ModelError
        ``sys`` is not a continuous-time NonlinearIOSystem.
    """
    _check_nlsys(sys)
    if not sys.isctime(strict=True):
        raise ModelError(f"sys is already discrete (dt={sys.dt}); discretize_nonlinear "
                         f"expects a continuous-time model")
    dt = check_positive(dt, "dt")
    if substeps is None:
        substeps = rk4_substeps(sys, dt, x_op=x_op, u_op=u_op)
    substeps = check_positive(substeps, "substeps", integer=True)
    f = sys.updfcn
    h = dt / substeps

    def _fix(r, shape):
        return np.asarray(r, dtype=float).reshape(shape)

    f64, arr = np.float64, np.ndarray

    def upd(t, x, u, params):
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        shp = x.shape
        tt = t
        h2, h6 = h / 2, h / 6
        for _ in range(substeps):  # f's result checked inline (24 calls per sample)
            k1 = f(tt, x, u, params)
            if type(k1) is not arr or k1.shape != shp or k1.dtype != f64:
                k1 = _fix(k1, shp)
            k2 = f(tt + h2, x + h2 * k1, u, params)
            if type(k2) is not arr or k2.shape != shp or k2.dtype != f64:
                k2 = _fix(k2, shp)
            k3 = f(tt + h2, x + h2 * k2, u, params)
            if type(k3) is not arr or k3.shape != shp or k3.dtype != f64:
                k3 = _fix(k3, shp)
            k4 = f(tt + h, x + h * k3, u, params)
            if type(k4) is not arr or k4.shape != shp or k4.dtype != f64:
                k4 = _fix(k4, shp)
            # x + h6 (k1 + 2 (k2 + k3) + k4), accumulated in place (same roundings)
            s = k2 + k3
            s *= 2.0
            s += k1
            s += k4
            s *= h6
            s += x
            x = s
            tt = tt + h
        return x

    out = sys.outfcn
    return ct.nlsys(upd, out, states=list(sys.state_labels), inputs=list(sys.input_labels),
                    outputs=list(sys.output_labels), dt=dt, params=dict(sys.params or {}),
                    name=f"{sys.name}_rk4x{substeps}")


def linear_output_map(sys, *, rtol: float = 1e-9) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(C, D) of an output map that is linear, ``y = C x + D u`` (the paper's (33)).

    Parameters
    ----------
    sys : control.NonlinearIOSystem or control.StateSpace
        The model; for a StateSpace its C and D are returned.
    rtol : float
        Relative tolerance of the linearity check at random test points.

    Returns
    -------
    C : ndarray, shape (noutputs, nstates)
    D : ndarray, shape (noutputs, ninputs)

    Raises
    ------
    ModelError
        If the output function is not linear in (x, u) (or has an offset):
        the unknown-input filters of section IV assume a linear output map.
    """
    if isinstance(sys, ct.StateSpace):
        return np.asarray(sys.C, float), np.asarray(sys.D, float)
    _check_nlsys(sys)
    n, m, p = sys.nstates, sys.ninputs, sys.noutputs
    if sys.outfcn is None:
        if p > n:
            raise ModelError(f"sys has no output function and {p} outputs > {n} states")
        return np.eye(n)[:p].copy(), np.zeros((p, m))
    par = sys.params

    def h(x, u):
        try:
            yv = np.asarray(sys.outfcn(0.0, x, u, par), dtype=float).reshape(-1)
        except Exception as e:  # a user function: report whatever it raised
            raise ModelError(f"the output function of sys failed at x = {x}, u = {u}: "
                             f"{e}") from e
        if yv.size != p:
            raise DimensionError(f"the output function returns {yv.size} values; expected "
                                 f"noutputs = {p}")
        return yv

    x0, u0 = np.zeros(n), np.zeros(m)
    y0 = h(x0, u0)
    C = np.column_stack([h(np.eye(n)[i], u0) - y0 for i in range(n)]) if n else np.zeros((p, 0))
    D = np.column_stack([h(x0, np.eye(m)[j]) - y0 for j in range(m)]) if m else np.zeros((p, 0))
    g = np.random.default_rng(0)
    worst = float(np.max(np.abs(y0))) / max(1.0, float(np.max(np.abs(C), initial=0.0)))
    for _ in range(3):
        x = g.standard_normal(n) * 3
        u = g.standard_normal(m) * 3
        yv = h(x, u)
        lin = C @ x + D @ u
        worst = max(worst, float(np.max(np.abs(yv - lin), initial=0.0))
                    / max(1.0, float(np.max(np.abs(lin), initial=0.0))))
    if not np.isfinite(worst) or worst > rtol:
        raise ModelError(
            f"the output map of {sys.name} is not linear in (x, u) (relative deviation "
            f"{worst:.2g}); the unknown-input filters assume y = C x + D u + v (the paper's "
            f"(33)). Make the measured quantity a state, or measure a linear function of them"
        )
    return C, D


@dataclass(frozen=True)
class StateMap:
    """The discrete state map ``x[k+1] = F(t, x[k], u[k])`` of a model, evaluated in batches.

    Attributes
    ----------
    fun : callable
        ``fun(t, X, U)`` with X of shape (nstates, npoints) and U of shape
        (ninputs,) or (ninputs, npoints) (the full input vector, unknown
        inputs included); returns shape (nstates, npoints).
    vectorized : bool
        True when the model's update function took all points in one call.
    nstates, ninputs : int
        Sizes.
    """

    fun: Callable
    vectorized: bool
    nstates: int
    ninputs: int


def state_map(sys) -> StateMap:
    """Batch evaluator of a discrete model's state update (linear or nonlinear).

    Parameters
    ----------
    sys : control.StateSpace or control.NonlinearIOSystem
        Discrete-time model.

    Returns
    -------
    StateMap

    Raises
    ------
    ModelError
        If ``sys`` is continuous-time or of another type.
    """
    if isinstance(sys, ct.StateSpace):
        A, B = np.asarray(sys.A, float), np.asarray(sys.B, float)

        def lin(t, X, u):
            bu = B @ u
            return A @ X + (bu[:, None] if bu.ndim == 1 else bu)

        return StateMap(lin, True, sys.nstates, sys.ninputs)
    _check_nlsys(sys)
    if not sys.isdtime(strict=True) or sys.dt is True:
        raise ModelError(
            f"{sys.name} is continuous-time (or has no numeric dt); the filters need a "
            f"discrete-time model. Discretize it with greybox.discretize_nonlinear(sys, dt)")
    n, m, upd, par = sys.nstates, sys.ninputs, sys.updfcn, sys.params

    def loop(t, X, u):
        out = np.empty_like(X)
        u = np.asarray(u, dtype=float)
        for i in range(X.shape[1]):
            ui = u if u.ndim == 1 else u[:, i]
            out[:, i] = np.asarray(upd(t, X[:, i], ui, par), dtype=float).reshape(-1)
        return out

    # probe: does f take a batch of states (and broadcast inputs)?
    vec = False
    X = np.outer(np.ones(n), [0.0, 1e-3]) + np.arange(n)[:, None] * 1e-4
    u = np.zeros(m)
    try:
        with np.errstate(all="ignore"):
            Yb = np.asarray(upd(0.0, X, np.repeat(u[:, None], 2, axis=1), par), dtype=float)
            Yl = loop(0.0, X, u)
        vec = Yb.shape == (n, 2) and bool(np.allclose(Yb, Yl, rtol=1e-12, atol=1e-300,
                                                      equal_nan=True))
    except Exception:  # noqa: BLE001 - a model that cannot take a batch is looped over
        vec = False
    if vec:
        def batch(t, X, u):
            if type(u) is not np.ndarray or u.ndim == 1 or u.dtype != np.float64:
                u = np.asarray(u, dtype=float)
                if u.ndim == 1:
                    u = np.broadcast_to(u[:, None], (m, X.shape[1]))
            r = upd(t, X, u, par)
            if type(r) is not np.ndarray or r.shape != X.shape or r.dtype != np.float64:
                r = np.asarray(r, dtype=float).reshape(X.shape)
            return r

        return StateMap(batch, True, n, m)
    return StateMap(loop, False, n, m)


def simulate_batch(sys, u: NDArray, X0: NDArray) -> NDArray:
    """Noise-free states of a discrete model from several initial states at once.

    One pass over the samples with the model's batch evaluator
    (:func:`state_map`): for a vectorized model, about the cost of one
    simulation. A start whose state becomes non-finite stays NaN from then on
    (no error: the caller judges it).

    Parameters
    ----------
    sys : control.NonlinearIOSystem or control.StateSpace
        Discrete-time model.
    u : ndarray, shape (ninputs, nsteps)
    X0 : ndarray, shape (nstates, nstarts)

    Returns
    -------
    ndarray, shape (nstates, nstarts, nsteps)
    """
    smap = state_map(sys)
    u = np.asarray(u, dtype=float)
    X0 = np.asarray(X0, dtype=float)
    n, S, N = X0.shape[0], X0.shape[1], u.shape[1]
    X = np.empty((n, S, N))
    X[:, :, 0] = X0
    dt = float(sys.dt)
    for k in range(N - 1):
        with np.errstate(all="ignore"):
            X[:, :, k + 1] = smap.fun(k * dt, X[:, :, k], u[:, k])
    return X


def simulate_nonlinear(sys, u: ArrayLike | None = None, *, x0: ArrayLike | None = None,
                       Q: ArrayLike | None = None, R: ArrayLike | None = None,
                       nsteps: int | None = None, rng=None) -> SimulationResult:
    """Simulate ``x[k+1] = F(x, u) + w``, ``y = h(x, u) + v`` for a discrete model.

    Parameters
    ----------
    sys : control.NonlinearIOSystem
        Discrete-time model (e.g. from :func:`discretize_nonlinear`).
    u : array_like, shape (ninputs, nsteps), optional
        Inputs (all of them; omit for a model without inputs).
    x0 : array_like, shape (nstates,), optional
        Initial state (zero by default).
    Q : array_like, shape (nstates, nstates), optional
        Process-noise covariance; None for none.
    R : array_like, shape (noutputs, noutputs), optional
        Measurement-noise covariance; None for noise-free outputs.
    nsteps : int, optional
        Number of samples when ``u`` is None.
    rng : numpy.random.Generator or int, optional
        Source of the noise.

    Returns
    -------
    SimulationResult
        With ``sys`` the nonlinear model.

    Raises
    ------
    DataError
        If the state becomes NaN or inf (naming the step and the state).
    """
    smap = state_map(sys)
    n, m, p = sys.nstates, sys.ninputs, sys.noutputs
    u = check_input_record(u, m, nsteps)
    N = u.shape[1]
    x = np.empty((n, N))
    x[:, 0] = np.zeros(n) if x0 is None else check_vector(x0, n, "x0")
    g = as_generator(rng)
    w = None
    if Q is not None:
        w = gaussian_noise(check_covariance(Q, n, "Q", definite=False), N, g)
    dt = float(sys.dt)
    for k in range(N - 1):
        with np.errstate(all="ignore"):
            xn = smap.fun(k * dt, x[:, k:k + 1], u[:, k])[:, 0]
        if not np.isfinite(xn).all():
            i = int(np.flatnonzero(~np.isfinite(xn))[0])
            raise DataError(f"the simulation of {sys.name} gave a non-finite state "
                            f"{sys.state_labels[i]!r} at step {k + 1}; check the inputs and "
                            f"dt (a stiff model needs more RK4 sub-steps)")
        x[:, k + 1] = xn if w is None else xn + w[:, k]
    if isinstance(sys, ct.StateSpace):
        y_clean = np.asarray(sys.C, float) @ x + np.asarray(sys.D, float) @ u
    else:
        y_clean = np.empty((p, N))
        for k in range(N):
            y_clean[:, k] = np.asarray(sys.output(k * dt, x[:, k], u[:, k]),
                                       dtype=float).reshape(-1)
    y = y_clean.copy()
    if R is not None:
        y = y + gaussian_noise(check_covariance(R, p, "R", definite=False), N, g)
    return SimulationResult(t=np.arange(N) * dt, x=x, y=y, u=u, y_clean=y_clean, sys=sys)


# --------------------------------------------------------------------------- model building
def as_nonlinear(sys) -> ct.NonlinearIOSystem:
    """A linear ``StateSpace`` as a ``NonlinearIOSystem`` (same names, dt, C and D).

    Parameters
    ----------
    sys : control.StateSpace or control.NonlinearIOSystem
        A NonlinearIOSystem is returned unchanged.

    Returns
    -------
    control.NonlinearIOSystem
        ``f(t, x, u) = A x + B u`` and ``h(t, x, u) = C x + D u``; both accept
        a batch of states ``(nstates, npoints)``.
    """
    if not isinstance(sys, ct.StateSpace):
        return _check_nlsys(sys)
    A, B, C, D = (np.asarray(M, dtype=float) for M in (sys.A, sys.B, sys.C, sys.D))

    def upd(t, x, u, params):
        return A @ np.asarray(x, dtype=float) + B @ np.asarray(u, dtype=float)

    def out(t, x, u, params):
        return C @ np.asarray(x, dtype=float) + D @ np.asarray(u, dtype=float)

    return ct.nlsys(upd, out, states=list(sys.state_labels), inputs=list(sys.input_labels),
                    outputs=list(sys.output_labels), dt=sys.dt, name=sys.name)


def _columns(G, n: int, name: str = "G") -> NDArray[np.float64]:
    G = np.asarray(G, dtype=float)
    if G.ndim == 1:
        G = G[:, None]
    if G.ndim != 2 or G.shape[0] != n or G.shape[1] < 1:
        raise DimensionError(f"{name} has shape {G.shape}; expected (nstates, md) = ({n}, md)")
    if not np.all(np.isfinite(G)):
        raise DataError(f"{name} contains NaN or inf")
    return G


def with_unknown_inputs(sys, G: ArrayLike, labels=None) -> ct.NonlinearIOSystem:
    """The model with unknown inputs d entering its state equations through G.

    ``dx/dt = f(t, x, u) + G d`` (continuous) or ``x[k+1] = F(k, x, u) + G d``
    (discrete); inputs ``[u, d]``, the same output map (d does not feed
    through). A continuous result is discretized by
    :func:`discretize_nonlinear` with d held over the sample like u, so d
    keeps its physical units and G its continuous meaning.

    Parameters
    ----------
    sys : control.NonlinearIOSystem or control.StateSpace
        Nominal model (continuous or discrete).
    G : array_like, shape (nstates,) or (nstates, md)
        Input matrix of d in the model's own time base.
    labels : sequence of str, optional
        Names of the md unknown inputs (default ``d``, or ``d0, d1, ...``).

    Returns
    -------
    control.NonlinearIOSystem
        Vectorized in x whenever ``sys`` is.

    Raises
    ------
    DimensionError
        G has the wrong number of rows, or the labels the wrong count.
    ModelError
        A label clashes with an input name.
    """
    base = as_nonlinear(sys)
    n, m = base.nstates, base.ninputs
    G = _columns(G, n)
    md = G.shape[1]
    labels = (["d"] if md == 1 else [f"d{j}" for j in range(md)]) if labels is None else \
        [str(s) for s in labels]
    if len(labels) != md:
        raise DimensionError(f"labels has {len(labels)} names; expected md = {md}")
    clash = sorted(set(labels) & set(base.input_labels))
    if clash:
        raise ModelError(f"unknown-input names {clash} clash with inputs of {base.name}; "
                         f"rename them")
    f, h, par = base.updfcn, base.outfcn, base.params

    def upd(t, x, ud, params):
        ud = np.asarray(ud, dtype=float)
        return np.asarray(f(t, x, ud[:m], params), dtype=float) + G @ ud[m:]

    def out(t, x, ud, params):
        return h(t, x, np.asarray(ud, dtype=float)[:m], params)

    return ct.nlsys(upd, out if h is not None else None, states=list(base.state_labels),
                    inputs=list(base.input_labels) + labels, outputs=list(base.output_labels),
                    dt=base.dt, params=dict(par or {}), name=f"{base.name}_with_d")


def add_law(sys, G: ArrayLike, law: Callable, *, name: str | None = None,
            hold: LawHold | tuple | None = None) -> ct.NonlinearIOSystem:
    """The model with a law added to its state equations: ``f(t, x, u) + G law(x, u)``.

    Parameters
    ----------
    sys : control.NonlinearIOSystem or control.StateSpace
        Nominal model (continuous or discrete); a StateSpace is wrapped by
        :func:`as_nonlinear`.
    G : array_like, shape (nstates,) or (nstates, md)
        Where the law enters, in the model's own time base (the channel's G).
    law : callable
        ``law(x, u)`` with x of shape (nstates,) or (nstates, npoints) and u
        of shape (ninputs,) or (ninputs, npoints); returns (md,) or
        (md, npoints) (e.g. ``StaticLaw.evaluate``).
    name : str, optional
        Name of the new model (default ``<name>_updated``).
    hold : greybox.hold.LawHold or (ndarray (nstates, md), ndarray (nstates, md)), optional
        Discrete models only: a continuous law integrated over each sample
        (``StaticLaw.hold``: :meth:`greybox.hold.LawHold.step`, fourth order;
        G is not used). A pair ``(Gamma0, Gamma1)`` is a first-order hold of the
        law, each step the Heun step ``x+ = f(x, u) + Gamma0 law(x, u) +
        Gamma1 law(xs, u)`` with the predictor ``xs = f(x, u) + (Gamma0 +
        Gamma1) law(x, u)``.

    Returns
    -------
    control.NonlinearIOSystem
        Same states, inputs, outputs, dt and output map; simulates the law
        exactly (vectorized in x when ``sys`` and ``law`` are).

    Raises
    ------
    DimensionError
        G (or the hold's weights) has the wrong number of rows.
    ModelError
        ``law`` is not callable; a hold with a continuous model; a
        :class:`~greybox.hold.LawHold` with a model that is not a StateSpace.
    """
    base = as_nonlinear(sys)
    G = _columns(G, base.nstates)
    if not callable(law):
        raise ModelError(f"law must be callable as law(x, u); found {type(law).__name__}")
    f, par = base.updfcn, base.params

    if hold is not None and not base.isdtime(strict=True):
        raise ModelError("a first-order hold of the law needs a discrete model; found a "
                         "continuous one. Hint: add the law to the continuous model without "
                         "hold")
    hold = as_hold(hold)
    if hold is not None:
        hold = replace(hold, G0=_columns(hold.G0, base.nstates),
                       G1=_columns(hold.G1, base.nstates))
    if hold is not None and hold.E2 is not None and not isinstance(sys, ct.StateSpace):
        raise ModelError("a law integrated over each sample (a LawHold) needs the discrete "
                         f"StateSpace it was found on; found {type(sys).__name__}. Hint: pass "
                         "the model as a StateSpace, or the hold as (hold.G0, hold.G1)")
    AB = None if hold is None or hold.E2 is None else \
        (np.asarray(sys.A, dtype=float), np.asarray(sys.B, dtype=float))

    def upd(t, x, u, params):
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        if hold is not None and hold.E2 is not None:
            return _law_step(AB, hold, law, x, u)
        fx, d = np.asarray(f(t, x, u, params), dtype=float), np.asarray(law(x, u), float)
        if hold is None:
            return fx + G @ d
        xs = fx + (hold.G0 + hold.G1) @ d  # Heun: the predictor holds d over the sample
        return fx + hold.G0 @ d + hold.G1 @ np.asarray(law(xs, u), float)

    return ct.nlsys(upd, base.outfcn, states=list(base.state_labels),
                    inputs=list(base.input_labels), outputs=list(base.output_labels),
                    dt=base.dt, params=dict(par or {}), name=name or f"{base.name}_updated")


def _law_step(AB: tuple, hold, law: Callable, x: NDArray, u: NDArray) -> NDArray:
    """One sample of ``A x + B u`` (``AB``: the discrete model's matrices) with the law
    integrated over it (``hold.step``); x of shape (nstates,) or (nstates, npoints), u
    (ninputs,) or (ninputs, npoints)."""
    A, B = AB
    col = x.ndim == 1
    bu = B @ u
    X, bu = (x[:, None], bu[:, None]) if col else (x, bu if bu.ndim == 2 else bu[:, None])
    md = hold.G0.shape[1]

    def f(Z):
        return np.asarray(law(Z[:, 0] if col else Z, u), dtype=float).reshape(md, -1)

    out = hold.step(A, X, bu, f)
    return out[:, 0] if col else out


def kinematic_identities(sys, X: ArrayLike, U: ArrayLike, *, rtol: float = 1e-9) -> list[str]:
    """The kinematic identities of a continuous nonlinear model: the state equations
    ``dx_i/dt = x_j`` (another state, unscaled, no input), checked on given points.

    The nonlinear counterpart of :func:`greybox.workflow.definitions`: equation i
    is an identity when ``f_i(x, u) = x_j`` for one j != i at every point given
    (to ``rtol`` relative), so a law there would rewrite what a state means.

    Parameters
    ----------
    sys : control.NonlinearIOSystem
        Continuous-time model (a discrete one mixes the rows: none returned).
    X : array_like, shape (nstates, k)
        States to check at (e.g. filtered states of the record, in the model's units);
        they should vary, as the record's do.
    U : array_like, shape (ninputs, k)
        Inputs at the same points.
    rtol : float
        Relative tolerance of ``f_i = x_j`` (to ``1 + max |x_j|``).

    Returns
    -------
    list of str
        The identities' state names, in state order.
    """
    base = _check_nlsys(sys)
    if base.isdtime(strict=True):
        return []
    X = np.atleast_2d(np.asarray(X, dtype=float))
    U = np.asarray(U, dtype=float).reshape(base.ninputs, -1)
    if X.shape[1] < 2:
        return []
    F = np.column_stack([np.asarray(base.updfcn(0.0, X[:, k], U[:, k], base.params),
                                    dtype=float).reshape(-1) for k in range(X.shape[1])])
    out = []
    for i, name in enumerate(base.state_labels):
        if not np.all(np.isfinite(F[i])) or np.ptp(F[i]) == 0:
            continue  # a constant is no definition of a varying state
        tol = rtol * (1.0 + np.max(np.abs(F[i])))
        if any(j != i and np.max(np.abs(F[i] - X[j])) <= tol for j in range(X.shape[0])):
            out.append(name)
    return out


def linearize_at(sys, x_op: ArrayLike, u_op: ArrayLike | None = None) -> ct.StateSpace:
    """Linearization of a nonlinear model at an operating point, as a named StateSpace.

    Parameters
    ----------
    sys : control.NonlinearIOSystem
        Continuous or discrete model.
    x_op : array_like, shape (nstates,)
        State of the operating point (in the model's units).
    u_op : array_like, shape (ninputs,), optional
        Inputs at the operating point (zero by default).

    Returns
    -------
    control.StateSpace
        ``A = df/dx``, ``B = df/du``, ``C = dh/dx``, ``D = dh/du`` at
        (x_op, u_op) (central differences), same names and dt: ready for
        ``control.dlqr``/``control.dlqe`` when discrete. The operating point
        need not be an equilibrium: the drift ``f(x_op, u_op)`` (or
        ``F(x_op, u_op) - x_op``) is not part of the StateSpace.

    Raises
    ------
    ModelError
        f or h is not finite at the operating point.
    """
    base = _check_nlsys(sys)
    x, u = _op_point(base, x_op, u_op)
    par = base.params
    n, m = x.size, u.size

    def f(xx, uu):
        return np.asarray(base.updfcn(0.0, xx, uu, par), dtype=float).reshape(-1)

    def h(xx, uu):
        return np.asarray(base.output(0.0, xx, uu), dtype=float).reshape(-1)

    p = base.noutputs
    with np.errstate(all="ignore"):  # checked below: one clear error for a non-finite one
        A, B, C, D = _jacobians(f, h, base.outfcn is None, x, u, n, m, p)
    if not all(np.all(np.isfinite(M)) for M in (A, B, C, D)):
        raise ModelError(f"the linearization of {base.name} is not finite at x = {x}, "
                         f"u = {u}; choose an operating point where f is differentiable")
    return named_ss(A, B, C, D, base.dt, states=list(base.state_labels),
                    inputs=list(base.input_labels), outputs=list(base.output_labels),
                    name=f"{base.name}_linearized")


def _jacobians(f, h, no_out, x, u, n, m, p):
    """(A, B, C, D) of f and h at (x, u) by central differences."""
    A = _jacobian(lambda z: f(z, u), x)
    B = _jacobian(lambda z: f(x, z), u) if m else np.zeros((n, 0))
    if no_out:
        C, D = np.eye(n)[:p], np.zeros((p, m))
    else:
        C = _jacobian(lambda z: h(z, u), x)
        D = _jacobian(lambda z: h(x, z), u) if m else np.zeros((p, 0))
    return A, B, C, D
