"""A randomized plant zoo (issue 27 item 1): plants nobody tuned to, with their truth recorded.

Each plant class is a function ``draw(rng) -> ZooDraw`` that draws random
physical parameters, a size (2-24 states where it applies), a measured subset
(all states, positions only, a random observable subset), an excitation
(low-pass noise, multisine or random binary) and a signal-to-noise ratio of
40-60 dB per output; it simulates an estimation record (process noise on the
nominal states plus measurement noise) and a validation record (measurement
noise only, PAPER_NOTES §8.6), and records what the nominal model lacks as a
:class:`Truth`: the effects, each with its channel kind ("state", "input",
"sensor"), the equations / inputs / outputs concerned, the law's kind
("static", "dynamic"), its order, drivers and terms with coefficients. A
correct model has an empty list of effects. ``CLASSES`` maps each class name
to its draw function.

:func:`score` compares a :class:`greybox.workflow.LoopReport` with the truth
(right channel, kind, order, terms and drivers; coefficients within 10 %;
interval coverage; false flags of right parameters; validation SE against the
true model's; false updates of correct models). How greybox's report states
an effect is read in ONE function, :func:`found_effects`, so that the scorer
follows the report when it gains structured terms.

Conventions. Time is the last axis of every signal. Continuous-time truth:
a term's coefficient is in the units of its target: d(state)/dt for a state
equation (e.g. [m/s^2] in a velocity equation), the input's units for an
input channel (``u_plant = u + d``), the output's units for a sensor
(``y = C x + d``). Linear terms are stated one variable at a time (a spring
between two bodies is ``-k/m1 p1 + k/m1 p2`` in eq(v1)); a nonlinear term of
a relative coordinate keeps it (``(p2-p1)^3``). A dynamic law is a
continuous state-space subsystem from its drivers to ``d``
(:class:`HiddenDynamics`); its "coefficients" are its poles and its DC gains.

This module is a test helper: it imports only the bottom layers (numpy,
scipy, python-control, greybox.signals / system / metrics), never the trace,
update or workflow code it measures.
"""

from __future__ import annotations

import math
import re
import zlib
from dataclasses import dataclass, field
from typing import Callable

import control as ct
import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm, solve_discrete_are

from .metrics import relative_error
from .signals import lowpass_noise, multisine, random_binary
from .system import named_ss
from .terms import natural_key, term_kind

__all__ = [
    "Term", "HiddenDynamics", "TrueEffect", "Truth", "ZooDraw", "FoundEffect", "ZooScore",
    "CLASSES", "CORRECT_CLASSES", "draw_class", "class_rng", "score", "found_effects",
    "model_with_truth", "simulate_true", "SNR_DB",
]

#: Range of the signal-to-noise ratio of each measured output [dB].
SNR_DB = (40.0, 60.0)
#: Relative tolerance of a "right" coefficient (issue 27: within 10 %).
COEF_RTOL = 0.10
#: Leading samples left out of the validation SE (as the report's table does).
SKIP = 20

_FORMS = ("x", "x^3", "sign(x)", "|x|", "x|x|", "x*u", "rel^3", "1", "t", "sat", "deadzone")


# ----------------------------------------------------------------------------- the truth
@dataclass(frozen=True)
class Term:
    """One term of a static law: ``d_target += coefficient * form(variables)``.

    Attributes
    ----------
    target : str
        The state whose equation, the input, or the output the term adds to.
    form : str
        One of "x" (the variable itself), "x^3", "sign(x)", "|x|", "x|x|" (a
        signed square: quadratic drag), "x*u" (a
        product of two variables), "rel^3" (``(b - a)^3`` of variables
        ``(a, b)``), "1" (a constant), "t" (time [s] from the record's first
        sample), "sat" (``clip(v, -c, c) - v``: the coefficient is the level
        c) and "deadzone" (``-clip(v, -c, c)``: the coefficient is the
        half-width c).
    variables : tuple of str
        States or inputs the form reads (none for "1" and "t").
    coefficient : float
        In the target's units per the form's units (see the module notes);
        the level or half-width for "sat" and "deadzone".
    unit : str
        The coefficient's unit, for reading.
    smoothing : float
        "sign(x)" only: the truth simulates sign(x) as tanh(x / smoothing)
        when > 0 (a Coulomb friction integrable by RK4).
    """

    target: str
    form: str
    variables: tuple[str, ...]
    coefficient: float
    unit: str = ""
    smoothing: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "coefficient", float(self.coefficient))
        object.__setattr__(self, "variables", tuple(str(v) for v in self.variables))

    @property
    def expression(self) -> str:
        """Canonical text of the form, e.g. ``"sign(v1)"``, ``"(p2-p1)^3"``, ``"sat(F)"``."""
        v = self.variables
        return {"x": lambda: v[0], "x^3": lambda: f"{v[0]}^3", "sign(x)": lambda: f"sign({v[0]})",
                "|x|": lambda: f"|{v[0]}|", "x|x|": lambda: f"{v[0]}|{v[0]}|",
                "x*u": lambda: f"{v[0]}*{v[1]}",
                "rel^3": lambda: f"({v[1]}-{v[0]})^3", "1": lambda: "1", "t": lambda: "t",
                "sat": lambda: f"sat({v[0]})", "deadzone": lambda: f"deadzone({v[0]})"}[self.form]()

    def basis(self, values: dict[str, NDArray], t: NDArray | float = 0.0) -> NDArray:
        """The form's value (without the coefficient, except "sat" and "deadzone").

        ``values`` maps each variable to an array (any shape, the same for
        all); ``t`` is time [s].
        """
        v = [np.asarray(values[s], dtype=float) for s in self.variables]
        c = self.coefficient
        if self.form == "x":
            return v[0]
        if self.form == "x^3":
            return v[0] ** 3
        if self.form == "sign(x)":
            return np.tanh(v[0] / self.smoothing) if self.smoothing > 0 else np.sign(v[0])
        if self.form == "|x|":
            return np.abs(v[0])
        if self.form == "x|x|":
            return v[0] * np.abs(v[0])
        if self.form == "x*u":
            return v[0] * v[1]
        if self.form == "rel^3":
            return (v[1] - v[0]) ** 3
        if self.form == "1":
            return np.ones_like(np.asarray(t, dtype=float))
        if self.form == "t":
            return np.asarray(t, dtype=float)
        if self.form == "sat":
            return np.clip(v[0], -c, c) - v[0]
        if self.form == "deadzone":
            return -np.clip(v[0], -c, c)
        raise ValueError(f"unknown form {self.form!r}; one of {_FORMS}")

    def value(self, values: dict[str, NDArray], t: NDArray | float = 0.0) -> NDArray:
        """The term's contribution to ``d_target``."""
        b = self.basis(values, t)
        return b if self.form in ("sat", "deadzone") else self.coefficient * b


@dataclass(frozen=True, eq=False)
class HiddenDynamics:
    """A continuous subsystem ``dz/dt = A z + B w``, ``d = C z + D w`` (a dynamic law).

    Attributes
    ----------
    A : ndarray, shape (order, order)
        [1/s].
    B : ndarray, shape (order, ndrivers)
    C : ndarray, shape (ntargets, order)
    D : ndarray, shape (ntargets, ndrivers)
    drivers : tuple of str
        The states or inputs ``w`` (in that order).
    targets : tuple of str
        The components of ``d`` (equations, inputs or outputs, by the channel).
    """

    A: NDArray[np.float64]
    B: NDArray[np.float64]
    C: NDArray[np.float64]
    D: NDArray[np.float64]
    drivers: tuple[str, ...]
    targets: tuple[str, ...]

    @property
    def order(self) -> int:
        """Number of states of the law."""
        return int(self.A.shape[0])

    @property
    def poles(self) -> NDArray[np.complex128]:
        """Continuous poles [1/s], sorted by modulus."""
        p = np.linalg.eigvals(self.A)
        return p[np.argsort(np.abs(p))]

    @property
    def dc_gain(self) -> NDArray[np.float64]:
        """DC gain from each driver to each target, shape (ntargets, ndrivers)."""
        return self.D - self.C @ np.linalg.solve(self.A, self.B)


@dataclass(frozen=True)
class TrueEffect:
    """One effect the nominal model lacks.

    Attributes
    ----------
    channel : str
        "state" (it enters state equations), "input" (it adds to a known
        input: ``u_plant = u + d``) or "sensor" (it adds to a measured output).
    equations : tuple of str
        States whose equations it enters (for an input: those the input enters).
    inputs : tuple of str
        The input(s) it adds to ("input" channel), else ().
    outputs : tuple of str
        The output(s) it adds to ("sensor" channel), else ().
    law : str
        "static" (a function of the present states, inputs or time) or "dynamic".
    order : int
        States of the law (0 for static).
    drivers : tuple of str
        The signals the law reads (sorted).
    terms : tuple of Term
        A static law's terms (empty for a dynamic law).
    dynamics : HiddenDynamics or None
        A dynamic law.
    description : str
        One line, in physical words.
    """

    channel: str
    equations: tuple[str, ...]
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    law: str
    order: int
    drivers: tuple[str, ...]
    terms: tuple[Term, ...] = ()
    dynamics: HiddenDynamics | None = field(default=None, compare=False)
    description: str = ""

    @property
    def targets(self) -> tuple[str, ...]:
        """What d adds to: the equations, inputs or outputs by the channel."""
        return {"state": self.equations, "input": self.inputs, "sensor": self.outputs}[
            self.channel]


@dataclass(frozen=True)
class Truth:
    """What the nominal model lacks: a list of effects (empty for a correct model)."""

    effects: tuple[TrueEffect, ...] = ()

    @property
    def correct(self) -> bool:
        """The nominal model is right (no effect)."""
        return not self.effects


@dataclass(frozen=True, eq=False)
class ZooDraw:
    """One drawn plant: nominal model, true plant, data, covariances and the truth.

    Attributes
    ----------
    cls : str
        The class name (a key of ``CLASSES``).
    nominal : control.StateSpace or control.NonlinearIOSystem
        The engineer's model, continuous time, named signals. The data are
        ZOH-sampled (inputs held over each sample), so the ZOH
        discretization (``greybox.discretize(nominal, dt)``) is exact for it.
    true : control.StateSpace or control.NonlinearIOSystem
        The true plant, continuous time; its first states are the nominal's
        (the same names), then hidden states; outputs as the nominal's.
    true_x0 : ndarray, shape (true.nstates,)
        The true plant's initial state of both records.
    dt : float
        Sampling period [s].
    y, u : ndarray, shapes (p, N), (m, N)
        Estimation record (process noise on the nominal states + measurement noise).
    y_val, u_val : ndarray, shapes (p, Nv), (m, Nv)
        Validation record (measurement noise only).
    y_val_clean : ndarray, shape (p, Nv)
        The true plant's validation output without noise (the true model's
        simulation): the validation SE of the true model is that of it.
    Q : ndarray, shape (n, n)
        Suggested discrete process-noise covariance of the nominal model (the
        one the estimation record was drawn with, + 1e-12 jitter).
    R : ndarray, shape (p, p)
        Measurement-noise covariance (the true one).
    truth : Truth
    snr_db : ndarray, shape (p,)
        Drawn SNR of each output [dB] (rms of the clean output over the noise std).
    closed_loop : bool
        The records were measured in closed loop (u depends on the noisy y).
    description : str
        The draw in a few words (sizes, measured subset, excitation).
    substeps : int
        RK4 sub-steps per sample of a nonlinear truth's simulation.
    """

    cls: str
    nominal: object
    true: object
    true_x0: NDArray[np.float64]
    dt: float
    y: NDArray[np.float64]
    u: NDArray[np.float64]
    y_val: NDArray[np.float64]
    u_val: NDArray[np.float64]
    y_val_clean: NDArray[np.float64]
    Q: NDArray[np.float64]
    R: NDArray[np.float64]
    truth: Truth
    snr_db: NDArray[np.float64]
    closed_loop: bool = False
    description: str = ""
    substeps: int = 4

    @property
    def nonlinear_model(self) -> bool:
        """The nominal model is a NonlinearIOSystem."""
        return not isinstance(self.nominal, ct.StateSpace)

    def se_true(self) -> float:
        """Validation SE [%] of the true model: its noise-free simulation against y_val."""
        return relative_error(self.y_val, self.y_val_clean, skip=SKIP).value


# ---------------------------------------------------------------------- the simulator
@dataclass(frozen=True, eq=False)
class _Plant:
    """The true plant as the generator simulates it (continuous time, inputs held).

    ``A, B`` (linear dynamics, simulated exactly by ZOH) or ``f(x, u) -> dx/dt``
    (RK4, ``sub`` steps per sample, ``f`` reads states (n,) or (n, npts));
    ``inmap(u)`` a static elementwise map of the held input (dead zone,
    saturation); the clean output is ``C x`` (a sensor offset or drift is a
    state of the plant: ``true_x0`` holds it).
    """

    n: int
    C: NDArray
    A: NDArray | None = None
    B: NDArray | None = None
    f: Callable | None = None
    inmap: Callable | None = None
    x0: NDArray | None = None
    sub: int = 4

    def out(self, X: NDArray, U: NDArray | None = None) -> NDArray:
        """Clean output (p, N) of states (n, N)."""
        return self.C @ X

    def stepper(self, dt: float) -> Callable:
        """x[k+1] from (x[k], u[k]) over one sample."""
        if self.f is None:
            n, m = self.B.shape
            M = np.zeros((n + m, n + m))
            M[:n, :n], M[:n, n:] = self.A, self.B
            E = expm(M * dt)
            Ad, Bd = E[:n, :n], E[:n, n:]
            return lambda x, u: Ad @ x + Bd @ u
        f, h = self.f, dt / self.sub

        def step(x, u):
            for _ in range(self.sub):
                a = f(x, u)
                b = f(x + h / 2 * a, u)
                c = f(x + h / 2 * b, u)
                d = f(x + h * c, u)
                x = x + h / 6 * (a + 2 * b + 2 * c + d)
            return x
        return step


def _simulate(plant: _Plant, dt: float, u: NDArray, *, q_std: NDArray | None = None,
              r_std: NDArray | None = None, rng=None, controller=None):
    """Simulate the plant; returns (x (n, N), u (m, N), y_clean (p, N), y (p, N)).

    Open loop: ``u`` (m, N) is the input. Closed loop (``controller = K``):
    ``u`` is the reference r and the plant's input is ``r[k] - K y[k]`` with
    the noisy measurement y[k]. ``q_std`` (n0,): discrete process noise on
    the first n0 states; ``r_std`` (p,): measurement noise.
    """
    step = plant.stepper(dt)
    N = u.shape[1]
    xk = np.zeros(plant.n) if plant.x0 is None else np.array(plant.x0, dtype=float)
    X = np.empty((plant.n, N))
    U = np.array(u, dtype=float)
    inmap = plant.inmap if plant.inmap is not None else (lambda v: v)
    if controller is None:
        for k in range(N):
            X[:, k] = xk
            xk = step(xk, inmap(U[:, k]))
            if q_std is not None:
                xk[:q_std.size] += q_std * rng.standard_normal(q_std.size)
        yc = plant.out(X, U)
        y = yc + (r_std[:, None] * rng.standard_normal(yc.shape) if r_std is not None else 0)
        return X, U, yc, y
    K = controller
    p = K.shape[1]
    yc, y = np.empty((p, N)), np.empty((p, N))
    for k in range(N):
        X[:, k] = xk
        yc[:, k] = plant.out(xk[:, None], np.zeros((U.shape[0], 1)))[:, 0]
        y[:, k] = yc[:, k] + (r_std * rng.standard_normal(p) if r_std is not None else 0)
        U[:, k] = u[:, k] - K @ y[:, k]
        xk = step(xk, inmap(U[:, k]))
        if q_std is not None:
            xk[:q_std.size] += q_std * rng.standard_normal(q_std.size)
    return X, U, yc, y


def _excitation(rng, kind: str, m: int, N: int, dt: float, bandwidth: float,
                amplitude: float) -> NDArray:
    """(m, N) input of ``kind`` ("lowpass", "multisine", "binary") and std ``amplitude``.

    ``bandwidth`` [Hz] is the low-pass cut-off, the multisine's highest line
    and about the binary signal's bandwidth (hold = 1 / (2 bandwidth dt)).
    """
    bw = min(bandwidth, 0.4 / dt)
    if kind == "multisine":
        return multisine(N, dt=dt, nsignals=m, amplitude=amplitude, fmin=min(0.02, bw / 20),
                         fmax=bw, nfreq=30, rng=rng)
    if kind == "binary":
        hold = max(1, int(round(1.0 / (2.0 * bw * dt))))
        return random_binary(N, nsignals=m, amplitude=amplitude, hold=hold, rng=rng)
    return lowpass_noise(N, dt=dt, bandwidth=bw, nsignals=m, amplitude=amplitude, rng=rng)


@dataclass(frozen=True)
class _Setup:
    """What a class hands to :func:`_make_draw` besides the nominal and the truth."""

    plant: _Plant
    dt: float
    bandwidth: float           # excitation bandwidth [Hz]
    amplitude: float           # excitation std [input units]
    q_states: tuple[int, ...]  # nominal states that receive process noise
    n_est: int = 4000
    n_val: int = 2000
    controller: NDArray | None = None
    excitation: str | None = None   # None: drawn
    q_level: float = 0.03      # process-noise std per sample, relative to the noise level x rms
    limit: tuple | None = None  # (state index, bound): a record beyond it is drawn again


def _make_draw(cls: str, rng: np.random.Generator, nominal, true, truth: Truth, s: _Setup,
               description: str, n_est: int | None = None) -> ZooDraw:
    """Draw the noise levels and excitation, simulate both records, assemble the draw."""
    N = n_est if n_est is not None else s.n_est
    Nv = max(300, N // 2) if n_est is not None else s.n_val
    n0 = len(nominal.state_labels)
    m = len(nominal.input_labels)
    p = len(nominal.output_labels)
    exc = s.excitation or str(rng.choice(["lowpass", "multisine", "binary"]))
    snr = rng.uniform(*SNR_DB, size=p)
    u = _excitation(rng, exc, m, N, s.dt, s.bandwidth, s.amplitude)
    uv = _excitation(rng, exc, m, Nv, s.dt, s.bandwidth, s.amplitude)
    # a clean pilot run of the estimation input sets the noise levels
    Xp, _, ycp, _ = _simulate(s.plant, s.dt, u, controller=s.controller)
    if not (np.all(np.isfinite(Xp)) and np.all(np.abs(Xp) < 1e8)):
        raise _Redraw("the true plant diverged on the estimation input")
    r_std = np.sqrt(np.mean(ycp ** 2, axis=1)) * 10 ** (-snr / 20)
    level = 10 ** (-snr.mean() / 20)
    q_std = np.zeros(n0)
    rms_x = np.sqrt(np.mean(Xp[:n0] ** 2, axis=1))
    for i in s.q_states:
        q_std[i] = s.q_level * level * rms_x[i]
    _, U, _, y = _simulate(s.plant, s.dt, u, q_std=q_std, r_std=r_std, rng=rng,
                           controller=s.controller)
    _, Uv, ycv, yv = _simulate(s.plant, s.dt, uv, r_std=r_std, rng=rng, controller=s.controller)
    if not np.all(np.isfinite(y)) or not np.all(np.isfinite(yv)):
        raise _Redraw("the simulation diverged")
    if s.limit is not None and np.max(np.abs(Xp[s.limit[0]])) > s.limit[1]:
        raise _Redraw("a state left its range")
    x0 = np.zeros(s.plant.n) if s.plant.x0 is None else np.asarray(s.plant.x0, float)
    draw = ZooDraw(cls=cls, nominal=nominal, true=true, true_x0=x0, dt=s.dt, y=y, u=U,
                   y_val=yv, u_val=Uv, y_val_clean=ycv, Q=np.diag(q_std ** 2) + 1e-12 * np.eye(n0),
                   R=np.diag(r_std ** 2), truth=truth, snr_db=snr,
                   closed_loop=s.controller is not None, substeps=s.plant.sub,
                   description=f"{description}; {exc} input, {s.dt:.3g} s, N = {N}")
    if not draw.closed_loop and min(effect_visibility(draw), default=np.inf) < VISIBLE:
        raise _Redraw("an effect is hidden in the noise")
    return draw


#: Leaving any one effect out must change the validation output by this many noise stds.
VISIBLE = 5.0


def effect_visibility(draw: ZooDraw, nsteps: int = 1000) -> list[float]:
    """How far each effect stands above the noise: for each recorded effect, the rms gap
    between the true plant and the nominal plus the other effects (``model_with_truth``,
    RK4 with 4 sub-steps) on the first ``nsteps`` validation samples, over the noise's std,
    largest over the outputs. Draws below ``VISIBLE`` are drawn again (an effect the data
    cannot show is not a test of the method); closed-loop draws are not checked (their
    open-loop simulation diverges).

    Parameters
    ----------
    draw : ZooDraw
    nsteps : int
        Validation samples compared.

    Returns
    -------
    list of float
        One ratio per effect (empty for a correct model).
    """
    from .nonlinear import discretize_nonlinear, simulate_nonlinear
    k = min(nsteps, draw.u_val.shape[1])
    out = []
    for q in range(len(draw.truth.effects)):
        rest = Truth(draw.truth.effects[:q] + draw.truth.effects[q + 1:])
        m, x0 = model_with_truth(_with_truth(draw, rest))
        y = simulate_nonlinear(discretize_nonlinear(m, draw.dt, substeps=4),
                               draw.u_val[:, :k], x0=x0).y_clean
        gap = np.sqrt(np.mean((y - draw.y_val_clean[:, :k]) ** 2, axis=1))
        out.append(float(np.max(gap / np.sqrt(np.diag(draw.R)))))
    return out


def _with_truth(draw: ZooDraw, truth: Truth) -> ZooDraw:
    """The draw with another truth (for leave-one-out checks)."""
    from dataclasses import replace
    return replace(draw, truth=truth)


class _Redraw(Exception):
    """A drawn plant is unusable (unobservable, diverging): draw again."""


# ------------------------------------------------------------------- building blocks
def _loguniform_int(rng, lo: int, hi: int) -> int:
    """An integer in [lo, hi], log-uniform (small sizes as likely as large decades)."""
    return int(min(hi, max(lo, math.floor(math.exp(rng.uniform(math.log(lo),
                                                                math.log(hi + 1)))))))


def _observable(A: NDArray, C: NDArray) -> bool:
    """PBH test: no eigenvector of A is invisible in C (relative tolerance 1e-7)."""
    n = A.shape[0]
    scale = max(1.0, np.linalg.norm(A, 2))
    for lam in np.linalg.eigvals(A):
        M = np.vstack([(lam * np.eye(n) - A) / scale, C])
        if np.linalg.svd(M, compute_uv=False)[-1] < 1e-7:
            return False
    return True


def _measured(rng, states: list[str], A: NDArray, options=("all", "positions", "subset"),
              must=(), min_outputs: int = 1) -> tuple[str, list[int]]:
    """(kind, indices) of a measured subset: all states, the positions, or a random subset.

    Positions are the states named p*, th* (a mechanical model); a subset
    keeps between a quarter and all but one of the states, always the
    indices ``must``; every choice is checked for observability (PBH) and for at
    least ``min_outputs`` outputs, else drawn again (all states as the last resort).
    """
    n = len(states)
    pos = [i for i, s in enumerate(states) if s.startswith(("p", "th"))]
    opts = [o for o in options if o != "positions" or pos]
    kind = str(rng.choice(opts))
    for _ in range(30):
        if kind == "all" or n == 1:
            return "all", list(range(n))
        if kind == "positions":
            idx = pos
        else:
            k = int(rng.integers(max(1, n // 4), n))
            idx = sorted(set(rng.choice(n, size=k, replace=False).tolist()) | set(must))
        if len(idx) >= min_outputs and _observable(A, np.eye(n)[idx]):
            return kind, list(idx)
        kind = str(rng.choice(opts))
    return "all", list(range(n))


def _named(A, B, states, inputs, measured: list[int], name: str) -> ct.StateSpace:
    """Continuous named StateSpace measuring the states ``measured`` (outputs named as them)."""
    outs = [states[i] for i in measured]
    C = np.eye(len(states))[measured]
    return named_ss(A, B, C, np.zeros((len(measured), len(inputs))), 0, states=states,
                    inputs=inputs, outputs=outs, name=name)


def _mech(m, springs, dampers, forces):
    """Continuous (A, B, states) of masses on a line.

    ``m`` (N,) masses [kg]; ``springs`` / ``dampers``: (i, j, k) with k [N/m]
    or [N s/m] between masses i and j (j = -1: to the ground); ``forces``:
    one list of (mass, gain) per input (a force F [N] on mass i times gain).
    States p1, v1, ..., pN, vN [m, m/s].
    """
    N = len(m)
    A = np.zeros((2 * N, 2 * N))
    for i in range(N):
        A[2 * i, 2 * i + 1] = 1.0
    for elems, off in ((springs, 0), (dampers, 1)):
        for i, j, k in elems:
            A[2 * i + 1, 2 * i + off] -= k / m[i]
            if j >= 0:
                A[2 * i + 1, 2 * j + off] += k / m[i]
                A[2 * j + 1, 2 * j + off] -= k / m[j]
                A[2 * j + 1, 2 * i + off] += k / m[j]
    B = np.zeros((2 * N, len(forces)))
    for q, f in enumerate(forces):
        for i, g in f:
            B[2 * i + 1, q] += g / m[i]
    states = [f"{s}{i + 1}" for i in range(N) for s in ("p", "v")]
    return A, B, states


@dataclass
class _Chain:
    """Drawn parameters of a chain of masses (mutable while a class edits them)."""

    m: NDArray
    springs: list
    dampers: list
    forces: list
    amplitude: float = 2.0   # excitation std [N]

    def matrices(self):
        """Continuous (A, B, states) of the chain (see :func:`_mech`)."""
        return _mech(self.m, self.springs, self.dampers, self.forces)


def _chain(rng, n_masses: int | None = None, lo: int = 1, hi: int = 12) -> _Chain:
    """A wall-spring-mass chain of random size: masses 0.5-2 kg, springs 5-40 N/m to the
    wall and between neighbours (and to a second wall half of the time), a damper of
    0.2-1 N s/m from every mass to the ground, one force F on a random mass."""
    N = n_masses if n_masses is not None else _loguniform_int(rng, lo, hi)
    m = rng.uniform(0.5, 2.0, N)
    springs = [(0, -1, rng.uniform(5, 40))] + [(i, i + 1, rng.uniform(5, 40))
                                               for i in range(N - 1)]
    if N > 1 and rng.random() < 0.5:
        springs.append((N - 1, -1, rng.uniform(5, 40)))
    dampers = [(i, -1, rng.uniform(0.2, 1.0)) for i in range(N)]
    forces = [[(int(rng.integers(N)), 1.0)]]
    return _Chain(m, springs, dampers, forces)


def _mech_timing(rng, A) -> tuple[float, float]:
    """(dt, excitation bandwidth [Hz]) of a mechanical model: 20-40 samples per period of
    its fastest mode; the excitation reaches 0.4-1 of that mode's frequency."""
    wmax = max(np.abs(np.linalg.eigvals(A)).max(), 1e-3)
    dt = 2 * np.pi / (wmax * rng.uniform(20, 40))
    return dt, wmax / (2 * np.pi) * rng.uniform(0.4, 1.0)


def _linear_terms(A_nom, A_true, B_nom, B_true, states, inputs, rows=None) -> tuple[Term, ...]:
    """The linear terms the model lacks: each nonzero entry of the truth minus the model.

    Rows are the nominal states (or ``rows``); columns states then inputs. Unit
    "1/s" per column unit.
    """
    n = len(states)
    dA = np.asarray(A_true)[:n, :n] - np.asarray(A_nom)
    dB = np.asarray(B_true)[:n] - np.asarray(B_nom)
    out = []
    for i in (range(n) if rows is None else rows):
        for j in range(n):
            if abs(dA[i, j]) > 1e-12 * max(1.0, np.abs(A_nom).max()):
                out.append(Term(states[i], "x", (states[j],), float(dA[i, j])))
        for j in range(len(inputs)):
            if abs(dB[i, j]) > 1e-12 * max(1.0, np.abs(B_nom).max()):
                out.append(Term(states[i], "x", (inputs[j],), float(dB[i, j])))
    return tuple(out)


def _state_effect(terms: tuple[Term, ...], description: str) -> TrueEffect:
    """A static effect in the state equations its terms name."""
    eqs = tuple(dict.fromkeys(t.target for t in terms))
    drivers = tuple(sorted({v for t in terms for v in t.variables}))
    return TrueEffect("state", eqs, (), (), "static", 0, drivers, terms,
                      description=description)


def _true_system(plant: _Plant, nominal, hidden: list[str], name: str):
    """The true plant as a continuous python-control system (StateSpace when linear)."""
    states = list(nominal.state_labels) + list(hidden)
    ins, outs = list(nominal.input_labels), list(nominal.output_labels)
    if plant.f is None and plant.inmap is None:
        return named_ss(plant.A, plant.B, plant.C, np.zeros((len(outs), len(ins))), 0,
                        states=states, inputs=ins, outputs=outs, name=name)
    inmap = plant.inmap if plant.inmap is not None else (lambda v: v)
    if plant.f is not None:
        fx = plant.f
    else:
        A, B = plant.A, plant.B
        fx = lambda x, u: A @ x + B @ u  # noqa: E731
    C = plant.C
    return ct.nlsys(lambda t, x, u, p: fx(x, inmap(u)), lambda t, x, u, p: C @ x,
                    states=states, inputs=ins, outputs=outs, dt=0, name=name)


def _vel(states) -> tuple[int, ...]:
    """Indices of the states that receive process noise: the velocities v*, om* and the
    current i of a mechanical model (not its kinematic positions), else every state (the
    temperatures of bodies)."""
    idx = tuple(i for i, s in enumerate(states) if s.startswith(("v", "om", "i")))
    return idx or tuple(range(len(states)))


def _sign_smooth(v, eps):
    """sign(v) as the truth simulates it: tanh(v / eps) with eps 2 % of the velocity's rms."""
    return np.tanh(v / eps)


def _retry(fn: Callable) -> Callable:
    """``draw(rng, *, n_est=None)`` from ``fn(rng, n_est)``: draws again (up to 30 times) while
    the drawn plant is unusable (unobservable, diverging, a closed loop the truth destabilizes).

    ``rng``: a numpy Generator or an integer seed. ``n_est``: estimation samples
    (the validation record has half as many, at least 300); None for the
    class's own length (4000 and 2000).
    """
    def draw(rng, *, n_est: int | None = None) -> ZooDraw:
        g = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        for _ in range(30):
            try:
                return fn(g, n_est)
            except _Redraw:
                continue
        raise RuntimeError(f"{fn.__name__}: no usable plant in 30 draws")
    draw.__name__ = fn.__name__
    draw.__doc__ = (fn.__doc__ or "") + _DRAW_DOC
    return draw


_DRAW_DOC = """

    Parameters
    ----------
    rng : numpy.random.Generator or int
        Source of every random choice (a seed: a fresh generator from it).
    n_est : int, optional
        Estimation samples (the validation record gets half as many, at least
        300); default 4000 and 2000.

    Returns
    -------
    ZooDraw
"""


def _factor(rng) -> float:
    """The model's value over the true one: 0 (missing, 40 %), 0.3-0.6 or 1.6-2.5 (wrong)."""
    r = rng.random()
    return 0.0 if r < 0.4 else rng.uniform(0.3, 0.6) if r < 0.7 else rng.uniform(1.6, 2.5)


def _linear_case(cls, rng, n_est, nom_AB, true_AB, states, inputs, effects, text, *,
                 options=("all", "positions", "subset"), hidden=(), must=(), timing=None,
                 amplitude=None, x0=None, C_true=None, excitation=None, inmap=None,
                 measured=None, min_outputs=1):
    """A draw whose truth is linear in the states (inputs through ``inmap``).

    ``nom_AB``, ``true_AB``: continuous (A, B) of the nominal model and of the
    true plant (its states: the nominal's, then ``hidden``); ``timing``: (dt,
    bandwidth [Hz]), default from the true A (mechanical rule). ``C_true``: the true
    output matrix (a sensor effect), default the measured states; ``measured``: (kind,
    indices) already drawn; ``min_outputs``: fewest measured outputs (2 where one output
    of a one-input plant could not tell an input effect from a sensor effect: with one
    input and one output, a gain or a lag before the plant and after it are the same
    transfer function).
    """
    (A, B), (At, Bt) = nom_AB, true_AB
    kind, meas = measured if measured is not None else _measured(rng, states, A, options,
                                                                   must, min_outputs)
    nom = _named(A, B, states, inputs, meas, cls)
    dt, bw = timing if timing is not None else _mech_timing(rng, At)
    Ct = C_true if C_true is not None else np.hstack([np.eye(len(states))[meas],
                                                       np.zeros((len(meas), len(hidden)))])
    plant = _Plant(At.shape[0], Ct, At, Bt, inmap=inmap, x0=x0)
    true = _true_system(plant, nom, list(hidden), f"{cls}_true")
    amp = amplitude if amplitude is not None else rng.uniform(1.0, 3.0)
    setup = _Setup(plant, dt, bw, amp, _vel(states), excitation=excitation)
    return _make_draw(cls, rng, nom, true, Truth(tuple(effects)), setup,
                      f"{text}; {len(states)} states, measured: {kind} ({len(meas)})", n_est)


def _element(rng, ch: _Chain, what: str, i: int, j: int = -1):
    """(true element, model's element or None, text) of an element the model lacks or has
    wrong (factor from :func:`_factor`): "damping" (a damper i-j, 0.5-2 N s/m per kg of
    mass i) or "stiffness" (a spring i-j, 5-40 N/m); j = -1: to the ground."""
    val = rng.uniform(0.5, 2.0) * ch.m[i] if what == "damping" else rng.uniform(5, 40)
    fac = _factor(rng)
    where = f"m{i + 1}-ground" if j < 0 else f"m{i + 1}-m{j + 1}"
    state = "missing" if fac == 0 else f"x{fac:.2f} in the model"
    return (what, (i, j, val)), ((what, (i, j, fac * val)) if fac > 0 else None), \
        f"{what} {val:.3g} at {where} ({state})"


def _with(ch: _Chain, *elements) -> _Chain:
    """The chain with extra elements ``(what, (i, j, value))`` (None entries skipped)."""
    out = _Chain(ch.m, list(ch.springs), list(ch.dampers), ch.forces)
    for e in elements:
        if e is not None:
            (out.dampers if e[0] == "damping" else out.springs).append(e[1])
    return out


def _elements_case(rng, n_est, cls, ch: _Chain, picks, *, options=("all", "positions",
                                                                    "subset")):
    """A chain whose elements ``picks`` ((what, i, j) each) the model lacks or has wrong: one
    static state effect per element."""
    drawn = [_element(rng, ch, w, i, j) for w, i, j in picks]
    nom = _with(ch, *[d[1] for d in drawn])
    A, B, states = nom.matrices()
    At, Bt, _ = _with(ch, *[d[0] for d in drawn]).matrices()
    effects = []
    for k, (tr, md, text) in enumerate(drawn):
        one = _with(ch, *[d[1] if q != k else d[0] for q, d in enumerate(drawn)])
        A1, B1, _ = one.matrices()
        effects.append(_state_effect(_linear_terms(A, A1, B, B1, states, ["F"]), text))
    text = "; ".join(d[2] for d in drawn)
    return _linear_case(cls, rng, n_est, (A, B), (At, Bt), states, ["F"], effects,
                        f"chain of {len(ch.m)}: {text}", options=options)


def _chain_static(rng, n_est, cls, pair=False):
    """A chain of random size with one static element wrong (see :func:`_element`)."""
    ch = _chain(rng, lo=2 if pair else 1)
    N = len(ch.m)
    what = str(rng.choice(["damping", "stiffness"]))
    i = int(rng.integers(N - 1 if pair else N))
    return _elements_case(rng, n_est, cls, ch, [(what, i, i + 1 if pair else -1)])


def _thermal_params(rng, lo=2, hi=12):
    """(capacities [J/K], losses [W/K], links [W/K], heated bodies) of a row of bodies."""
    n = _loguniform_int(rng, lo, hi)
    heaters = sorted(rng.choice(n, size=int(rng.integers(1, max(1, n // 2) + 1)),
                                replace=False).tolist())
    return (rng.uniform(0.5, 3.0, n), rng.uniform(0.1, 0.5, n), rng.uniform(0.3, 1.5, n - 1),
            heaters)


def _thermal(cap, loss, link, heaters):
    """Continuous (A, B, states, inputs) of bodies in a row: temperatures T1..Tn [K above
    ambient], heaters Q<i> [W] on the heated bodies."""
    n = len(cap)
    A = np.diag(-np.asarray(loss, dtype=float))
    for i, g in enumerate(link):
        A[i, i] -= g
        A[i + 1, i + 1] -= g
        A[i, i + 1] += g
        A[i + 1, i] += g
    A = A / np.asarray(cap)[:, None]
    B = np.zeros((n, len(heaters)))
    for q, i in enumerate(heaters):
        B[i, q] = 1.0 / cap[i]
    return A, B, [f"T{i + 1}" for i in range(n)], [f"Q{i + 1}" for i in heaters]


def _thermal_timing(rng, A) -> tuple[float, float]:
    """(dt, bandwidth [Hz]): dt 0.2-0.5 of the fastest time constant; the excitation's band
    0.5-2 times the geometric mean of the slowest and fastest rates."""
    lam = np.abs(np.linalg.eigvals(A))
    dt = rng.uniform(0.2, 0.5) / lam.max()
    return dt, min(np.sqrt(lam.min() * lam.max()) / (2 * np.pi) * rng.uniform(0.5, 2.0),
                   0.3 / dt)


def _thermal_static(rng, n_est, cls, count=1):
    """A row of bodies with ``count`` losses to ambient wrong in the model (separate effects)."""
    cap, loss, link, heat = _thermal_params(rng, lo=max(2, count))
    n = len(cap)
    bodies = rng.choice(n, size=count, replace=False)
    loss[bodies] = rng.uniform(0.3, 1.0, count)   # a loss that matters beside the links
    nom_loss = np.array(loss)
    effects, texts = [], []
    At, Bt, states, inputs = _thermal(cap, loss, link, heat)
    for i in bodies:
        f = _factor(rng)
        nom_loss[i] = f * loss[i]
        one = np.array(loss)
        one[i] = nom_loss[i]
        A1, B1, _, _ = _thermal(cap, one, link, heat)
        text = f"loss of T{i + 1} {loss[i]:.3g} W/K (x{f:.2f} in the model)"
        effects.append(_state_effect(_linear_terms(A1, At, B1, Bt, states, inputs), text))
        texts.append(text)
    A, B, _, _ = _thermal(cap, nom_loss, link, heat)
    return _linear_case(cls, rng, n_est, (A, B), (At, Bt), states, inputs, effects,
                        f"row of {n} bodies: " + "; ".join(texts), options=("all", "subset"),
                        timing=_thermal_timing(rng, At))


# ------------------------------------------------------------------------ the classes
@_retry
def static_state(rng, n_est):
    """A static state law: a damper or a spring to the ground on one mass of a chain of 1-12
    masses (missing, or wrong by 0.3-0.6x / 1.6-2.5x), or a body's loss coefficient in a row
    of 2-12 bodies. Truth: linear terms in that equation."""
    if rng.random() < 1 / 3:
        return _thermal_static(rng, n_est, "static_state")
    return _chain_static(rng, n_est, "static_state")


@_retry
def linear_force(rng, n_est):
    """A linear force between two neighbouring bodies of a chain of 2-12 masses (a spring or
    a damper, missing or wrong in the model): terms in both bodies' equations."""
    return _chain_static(rng, n_est, "linear_force", pair=True)


@_retry
def two_static(rng, n_est):
    """Two effects of the same kind: two static state laws in different equations (a damper
    and a spring to the ground on two masses of a chain of 2-12, or two bodies' losses)."""
    if rng.random() < 1 / 3:
        return _thermal_static(rng, n_est, "two_static", count=2)
    ch = _chain(rng, lo=2)
    i, j = (int(v) for v in rng.choice(len(ch.m), size=2, replace=False))
    return _elements_case(rng, n_est, "two_static", ch, [("damping", i, -1),
                                                         ("stiffness", j, -1)])


def _nonlinear_chain_case(cls, rng, n_est, ch: _Chain, extra: Callable, effects, text, *,
                          options, stiffness: float, sub: int = 4):
    """A chain whose truth adds ``extra(x) -> dx`` (nonlinear forces) to the nominal's
    linear dynamics; ``stiffness`` [1/s] is the largest rate the extra force adds (it sets
    the RK4 sub-steps: rate x step <= 0.5)."""
    A, B, states = ch.matrices()
    kind, meas = _measured(rng, states, A, options)
    nom = _named(A, B, states, ["F"], meas, cls)
    dt, bw = _mech_timing(rng, A)
    sub = max(sub, int(math.ceil(dt * stiffness / 0.5)))
    plant = _Plant(A.shape[0], np.eye(len(states))[meas],
                   f=lambda x, u: A @ x + B @ u + extra(x), sub=sub)
    true = _true_system(plant, nom, [], f"{cls}_true")
    setup = _Setup(plant, dt, bw, ch.amplitude, _vel(states))
    return _make_draw(cls, rng, nom, true, Truth(tuple(effects)), setup,
                      f"chain of {len(ch.m)}: {text}; {len(states)} states, measured: {kind} "
                      f"({len(meas)})", n_est)


@_retry
def cubic_force(rng, n_est):
    """A hardening (cubic) spring between two neighbouring masses of a chain of 2-12, beside
    the linear spring the model has: k3 (p_j - p_i)^3 with k3 such that at the pair's rms
    deflection the cubic force is 0.3-1x the linear one. Positions only or a random subset
    measured (partial measurement)."""
    ch = _chain(rng, lo=2)
    ch.amplitude = rng.uniform(1.0, 3.0)
    A, B, states = ch.matrices()
    i = int(rng.integers(len(ch.m) - 1))
    j = i + 1
    k = next(kk for a, b, kk in ch.springs if (a, b) == (i, j))
    dt, bw = _mech_timing(np.random.default_rng(rng.integers(2**32)), A)
    X = _pilot_states(A, B, dt, bw, ch.amplitude, rng)
    defl = np.sqrt(np.mean((X[2 * j] - X[2 * i]) ** 2))
    if not defl > 0:
        raise _Redraw("no deflection")
    k3 = rng.uniform(0.3, 1.0) * k / defl ** 2
    mi, mj = ch.m[i], ch.m[j]
    pi_, pj = f"p{i + 1}", f"p{j + 1}"

    def extra(x):
        dx = np.zeros_like(x)
        f = k3 * (x[2 * j] - x[2 * i]) ** 3
        dx[2 * i + 1] = f / mi
        dx[2 * j + 1] = -f / mj
        return dx
    terms = (Term(f"v{i + 1}", "rel^3", (pi_, pj), k3 / mi, "1/(m^2 s^2)"),
             Term(f"v{j + 1}", "rel^3", (pi_, pj), -k3 / mj, "1/(m^2 s^2)"))
    text = f"cubic spring {k3:.3g} N/m^3 between m{i + 1} and m{j + 1} (linear {k:.3g} N/m)"
    stiff = 3 * k3 * (3 * defl) ** 2 / min(mi, mj)
    return _nonlinear_chain_case("cubic_force", rng, n_est, ch, extra,
                                 [_state_effect(terms, text)], text,
                                 options=("positions", "subset"), stiffness=np.sqrt(stiff))


def _pilot_states(A, B, dt, bandwidth, amplitude, rng, N: int = 2000) -> NDArray:
    """States (n, N) of the linear plant (A, B) under low-pass noise (a pilot run)."""
    u = _excitation(rng, "lowpass", B.shape[1], N, dt, bandwidth, amplitude)
    X, _, _, _ = _simulate(_Plant(A.shape[0], np.eye(A.shape[0]), A, B), dt, u)
    return X


def _one_mass_of_a_chain(rng) -> tuple[_Chain, int, float]:
    """(chain of 1-6 with its force amplitude, one mass i, the rms of v_i on a pilot run):
    the set-up of a velocity force on one mass (Coulomb friction, quadratic drag)."""
    ch = _chain(rng, lo=1, hi=6)
    ch.amplitude = rng.uniform(1.0, 3.0)
    A, B, _ = ch.matrices()
    i = int(rng.integers(len(ch.m)))
    dt, bw = _mech_timing(np.random.default_rng(rng.integers(2**32)), A)
    X = _pilot_states(A, B, dt, bw, ch.amplitude, rng)
    return ch, i, float(np.sqrt(np.mean(X[2 * i + 1] ** 2)))


@_retry
def coulomb(rng, n_est):
    """Coulomb friction on one mass of a chain of 1-6: -Fc sign(v_i), Fc 10-40 % of the
    force's std (the truth simulates sign as tanh(v / eps), eps 2 % of v_i's rms in a pilot
    run without the friction: 3-8 % of the measured record's rms on the draws looked at,
    where greybox's default width is 5 %, fitted where the criterion pays for it)."""
    ch, i, vr = _one_mass_of_a_chain(rng)
    eps = 0.02 * vr
    fc = rng.uniform(0.1, 0.4) * ch.amplitude
    mi = ch.m[i]

    def extra(x):
        dx = np.zeros_like(x)
        dx[2 * i + 1] = -fc / mi * _sign_smooth(x[2 * i + 1], eps)
        return dx
    text = f"Coulomb friction {fc:.3g} N on m{i + 1}"
    eff = _state_effect((Term(f"v{i + 1}", "sign(x)", (f"v{i + 1}",), -fc / mi, "m/s^2",
                              smoothing=eps),), text)
    return _nonlinear_chain_case("coulomb", rng, n_est, ch, extra, [eff], text,
                                 options=("all", "positions", "subset"),
                                 stiffness=fc / (mi * eps))


@_retry
def quadratic_drag(rng, n_est):
    """Quadratic drag on one mass of a chain of 1-6: -cq v_i |v_i|, cq such that at v_i's rms
    the drag is 10-40 % of the force's std (a fan, a pump, a hull); the model has none."""
    ch, i, vr = _one_mass_of_a_chain(rng)
    if not vr > 0:
        raise _Redraw("no velocity")
    cq = rng.uniform(0.1, 0.4) * ch.amplitude / vr ** 2
    mi = ch.m[i]

    def extra(x):
        dx = np.zeros_like(x)
        dx[2 * i + 1] = -cq / mi * x[2 * i + 1] * np.abs(x[2 * i + 1])
        return dx
    text = f"quadratic drag {cq:.3g} N s^2/m^2 on m{i + 1}"
    eff = _state_effect((Term(f"v{i + 1}", "x|x|", (f"v{i + 1}",), -cq / mi, "1/m"),), text)
    return _nonlinear_chain_case("quadratic_drag", rng, n_est, ch, extra, [eff], text,
                                 options=("all", "positions", "subset"),
                                 stiffness=2 * cq * 3 * vr / mi)


def _input_chain(rng, lo=1, hi=12) -> _Chain:
    """A chain whose force F acts on one mass, or (40 %, two masses or more) pushes two masses
    apart (F enters two equations: the input channel differs from any one equation's)."""
    ch = _chain(rng, lo=lo, hi=hi)
    N = len(ch.m)
    if N >= 2 and rng.random() < 0.4:
        i, j = sorted(int(v) for v in rng.choice(N, size=2, replace=False))
        ch.forces = [[(i, 1.0), (j, -1.0)]]
    ch.amplitude = rng.uniform(1.0, 3.0)
    return ch


def _input_effect(B, states, law, order, terms=(), dynamics=None, text=""):
    """An effect on the input F (``u_plant = F + d``), entering the equations B's column does."""
    eqs = tuple(states[i] for i in np.flatnonzero(np.abs(B[:, 0]) > 0))
    return TrueEffect("input", eqs, ("F",), (), law, order, ("F",), tuple(terms), dynamics,
                      text)


@_retry
def actuator_gain(rng, n_est):
    """An actuator gain error: the plant receives g F with g 0.6-0.85 or 1.15-1.4 (chain of
    1-12 masses; F on one mass or pushing two apart). Truth: d_F = (g - 1) F."""
    ch = _input_chain(rng)
    A, B, states = ch.matrices()
    g = rng.uniform(0.6, 0.85) if rng.random() < 0.5 else rng.uniform(1.15, 1.4)
    text = f"actuator gain {g:.3g}"
    eff = _input_effect(B, states, "static", 0, (Term("F", "x", ("F",), g - 1, "N/N"),),
                        text=text)
    return _linear_case("actuator_gain", rng, n_est, (A, B), (A, g * B), states, ["F"], [eff],
                        f"chain of {len(ch.m)}: {text}", amplitude=ch.amplitude,
                        min_outputs=2)


def _lag_model(rng, order: int, w_bw: float, dt: float):
    """(A, B, C, text) of an actuator's own dynamics, unit DC gain: 1/(tau s + 1) with tau
    0.3-1.5 / w_bw (at least 3 dt), or w^2/(s^2 + 2 zeta w s + w^2) with w 0.8-2.5 w_bw (at
    most 0.6 / dt) and zeta 0.3-0.8."""
    if order == 1:
        tau = max(rng.uniform(0.3, 1.5) / w_bw, 3 * dt)
        return (np.array([[-1 / tau]]), np.array([[1 / tau]]), np.array([[1.0]]),
                f"first-order lag {tau:.3g} s")
    w = min(rng.uniform(0.8, 2.5) * w_bw, 0.6 / dt)
    z = rng.uniform(0.3, 0.8)
    return (np.array([[0.0, 1.0], [-w * w, -2 * z * w]]), np.array([[0.0], [w * w]]),
            np.array([[1.0, 0.0]]), f"second-order lag {w:.3g} rad/s, damping {z:.2f}")


def _actuator_lag(rng, n_est, order: int):
    """A chain whose force reaches it through an actuator lag of ``order`` 1 or 2."""
    ch = _input_chain(rng)
    A, B, states = ch.matrices()
    dt, bw = _mech_timing(rng, A)
    Al, Bl, Cl, text = _lag_model(rng, order, 2 * np.pi * bw, dt)
    n = A.shape[0]
    At = np.block([[A, B @ Cl], [np.zeros((order, n)), Al]])
    Bt = np.vstack([np.zeros_like(B), Bl])
    hid = HiddenDynamics(Al, Bl, Cl, -np.ones((1, 1)), ("F",), ("F",))
    eff = _input_effect(B, states, "dynamic", order, dynamics=hid, text=text)
    hidden = ["F_plant"] if order == 1 else ["F_plant", "dF_plant"]
    return _linear_case(f"actuator_lag{order}", rng, n_est, (A, B), (At, Bt), states, ["F"],
                        [eff], f"chain of {len(ch.m)}: actuator {text}", hidden=hidden,
                        timing=(dt, bw), amplitude=ch.amplitude, min_outputs=2)


@_retry
def actuator_lag1(rng, n_est):
    """Actuator lag of order 1: F reaches the chain (1-12 masses) through 1/(tau s + 1).
    Truth: input channel, dynamic, order 1, driver F, d = (1/(tau s + 1) - 1) F."""
    return _actuator_lag(rng, n_est, 1)


@_retry
def actuator_lag2(rng, n_est):
    """Actuator lag of order 2: F reaches the chain through w^2/(s^2 + 2 zeta w s + w^2).
    Truth: input channel, dynamic, order 2, driver F."""
    return _actuator_lag(rng, n_est, 2)


def _input_nonlinearity(rng, n_est, cls, form: str):
    """A chain whose force passes a static input map: "deadzone" or "sat" (saturation)."""
    ch = _input_chain(rng, hi=6)
    A, B, states = ch.matrices()
    amp = ch.amplitude
    c = rng.uniform(0.1, 0.4) * amp if form == "deadzone" else rng.uniform(0.8, 1.6) * amp
    term = Term("F", form, ("F",), c, "N")
    text = (f"input dead zone +-{c:.3g} N" if form == "deadzone" else
            f"input saturation at +-{c:.3g} N") + f" (F's std {amp:.3g} N)"
    eff = _input_effect(B, states, "static", 0, (term,), text=text)
    inmap = lambda v: v + term.value({"F": v})  # noqa: E731
    return _linear_case(cls, rng, n_est, (A, B), (A, B), states, ["F"], [eff],
                        f"chain of {len(ch.m)}: {text}", amplitude=amp, inmap=inmap,
                        excitation=str(rng.choice(["lowpass", "multisine"])))


@_retry
def dead_zone(rng, n_est):
    """An input dead zone (a valve, a motor's static friction in the drive): the plant
    receives F - clip(F, -c, c), c 10-40 % of F's std (chain of 1-6 masses). Low-pass or
    multisine input (a binary one would make it a gain)."""
    return _input_nonlinearity(rng, n_est, "dead_zone", "deadzone")


@_retry
def saturation(rng, n_est):
    """Input saturation: the plant receives clip(F, -c, c), c 0.8-1.6 of F's std."""
    return _input_nonlinearity(rng, n_est, "saturation", "sat")


@_retry
def flexible_shaft(rng, n_est):
    """A hidden subsystem driven by one state (order 2): a DC motor (current i [A], speed om
    [rad/s]; voltage V) whose model lacks the load behind a flexible
    shaft. Shaft stiffness k and damping c (torsional mode 15-60 rad/s, damping 0.05-0.2),
    load inertia 0.5-3x the motor's, load friction. The shaft's torque on the motor is a
    function of om alone: d_om = (-k tw - c om + c om_l) / Jm with the hidden twist tw and
    load speed om_l (dtw/dt = om - om_l, Jl dom_l/dt = k tw + c (om - om_l) - bl om_l).
    The speed is always measured (the current alone barely sees the load)."""
    Jm = rng.uniform(0.01, 0.05)
    Jl = Jm * rng.uniform(0.5, 3.0)
    wt = rng.uniform(15, 60)
    k = wt ** 2 / (1 / Jm + 1 / Jl)
    c = 2 * rng.uniform(0.05, 0.2) * wt * Jm * Jl / (Jm + Jl)
    bl, bm = Jl * rng.uniform(0.1, 0.5), Jm * rng.uniform(0.2, 1.0)
    R = rng.uniform(0.5, 3.0)
    # the electromechanical time constant R (Jm + Jl) / Kt^2: 0.5-3 torsional periods, so
    # that the speed (and through the back-EMF the current) feels the load
    Kt = np.sqrt(R * (Jm + Jl) / (rng.uniform(0.5, 3.0) * 2 * np.pi / wt))
    dt = 2 * np.pi / (wt * rng.uniform(15, 30))
    L = R * dt * rng.uniform(1.0, 4.0)
    states = ["i", "om"]   # no motor angle: an integrator's drift would swamp the SE
    n, io = 2, 1
    A = np.zeros((n, n))
    A[0, 0], A[0, io] = -R / L, -Kt / L
    A[io, 0], A[io, io] = Kt / Jm, -bm / Jm
    B = np.zeros((n, 1))
    B[0, 0] = 1 / L
    Ah = np.array([[0.0, -1.0], [k / Jl, -(c + bl) / Jl]])
    Bh = np.array([[1.0], [c / Jl]])
    Ch = np.array([[-k / Jm, c / Jm]])
    Dh = np.array([[-c / Jm]])
    At = np.block([[A, np.zeros((n, 2))], [np.zeros((2, n)), Ah]])
    At[io, io] += Dh[0, 0]
    At[io, n:] = Ch[0]
    At[n:, io] = Bh[:, 0]
    Bt = np.vstack([B, np.zeros((2, 1))])
    text = (f"flexible shaft to a hidden load: torsional mode {wt:.3g} rad/s, Jl/Jm "
            f"{Jl / Jm:.2f}")
    eff = TrueEffect("state", ("om",), (), (), "dynamic", 2, ("om",),
                     dynamics=HiddenDynamics(Ah, Bh, Ch, Dh, ("om",), ("om",)),
                     description=text)
    return _linear_case("flexible_shaft", rng, n_est, (A, B), (At, Bt), states, ["V"], [eff],
                        f"DC motor: {text}", options=("all", "subset"), must=(1,),
                        hidden=["tw", "om_l"],
                        timing=(dt, wt / (2 * np.pi) * rng.uniform(0.5, 1.2)),
                        amplitude=rng.uniform(2.0, 10.0))


@_retry
def thermal_mass(rng, n_est):
    """One hidden state shared by two equations (order 1): a row of 2-12 bodies and a hidden
    thermal mass Tm (2-8x the mean capacity) coupled to two of them (0.3-1.5 W/K each):
    d_Ta = ga/Ca (Tm - Ta), d_Tb = gb/Cb (Tm - Tb), Cm dTm/dt = ga (Ta - Tm) + gb (Tb - Tm)."""
    cap, loss, link, heat = _thermal_params(rng)
    A, B, states, inputs = _thermal(cap, loss, link, heat)
    n = len(cap)
    a, b = sorted(int(v) for v in rng.choice(n, size=2, replace=False))
    cm = rng.uniform(2, 8) * cap.mean()
    ga, gb = rng.uniform(0.3, 1.5, 2)
    Ah = np.array([[-(ga + gb) / cm]])
    Bh = np.array([[ga / cm, gb / cm]])
    Ch = np.array([[ga / cap[a]], [gb / cap[b]]])
    Dh = np.diag([-ga / cap[a], -gb / cap[b]])
    At = np.zeros((n + 1, n + 1))
    At[:n, :n] = A
    for q, i in enumerate((a, b)):
        At[i, (a, b)] += Dh[q]
        At[i, n] = Ch[q, 0]
    At[n, (a, b)] = Bh[0]
    At[n, n] = Ah[0, 0]
    Bt = np.vstack([B, np.zeros((1, B.shape[1]))])
    Ta, Tb = states[a], states[b]
    text = f"hidden thermal mass {cm:.3g} J/K on {Ta} ({ga:.2f} W/K) and {Tb} ({gb:.2f} W/K)"
    eff = TrueEffect("state", (Ta, Tb), (), (), "dynamic", 1, (Ta, Tb),
                     dynamics=HiddenDynamics(Ah, Bh, Ch, Dh, (Ta, Tb), (Ta, Tb)),
                     description=text)
    return _linear_case("thermal_mass", rng, n_est, (A, B), (At, Bt), states, inputs, [eff],
                        f"row of {n} bodies: {text}", options=("all", "subset"), must=(a, b),
                        hidden=["Tm"], timing=_thermal_timing(rng, At))


def _sensor_base(rng):
    """(A, B, states, inputs, timing, amplitude, options, text) of a chain (1-12 masses) or a
    row of bodies (2-12), the plant a sensor effect is drawn on."""
    if rng.random() < 0.5:
        cap, loss, link, heat = _thermal_params(rng)
        A, B, states, inputs = _thermal(cap, loss, link, heat)
        return (A, B, states, inputs, _thermal_timing(rng, A), rng.uniform(0.5, 2.0),
                ("all", "subset"), f"row of {len(cap)} bodies")
    ch = _chain(rng)
    A, B, states = ch.matrices()
    return (A, B, states, ["F"], _mech_timing(rng, A), rng.uniform(1.0, 3.0),
            ("all", "positions", "subset"), f"chain of {len(ch.m)}")


def _sensor_case(rng, n_est, cls, what: str, state_effect: bool = False):
    """A sensor effect ("gain_offset", "lag", "drift") on one measured output of a chain or a
    row of bodies; with ``state_effect`` also a wrong damper / loss (a state effect)."""
    A, B, states, inputs, (dt, bw), amp, opts, base = _sensor_base(rng)
    kind, meas = _measured(rng, states, A, opts, min_outputs=2)
    o = meas[int(rng.integers(len(meas)))]
    s = states[o]
    effects, texts, At, Bt = [], [], A, B
    if state_effect:
        i = int(rng.integers(len(states) // 2 if inputs == ["F"] else len(states)))
        A, At, eff = _static_on(rng, A, B, states, inputs, i)
        effects.append(eff)
        texts.append(eff.description)
    rms = np.sqrt(np.mean(_pilot_states(At, Bt, dt, bw, amp, rng)[o] ** 2))
    n = len(states)
    N = n_est if n_est is not None else 4000
    Ct = np.eye(n)[meas]
    row = meas.index(o)
    hidden, x0 = [], np.zeros(n)
    if what == "gain_offset":
        v = str(rng.choice(["gain", "offset", "both"]))
        terms = []
        if v in ("gain", "both"):
            g = 1 + rng.choice([-1, 1]) * rng.uniform(0.05, 0.25)
            Ct[row, o] = g
            terms.append(Term(s, "x", (s,), g - 1))
        if v in ("offset", "both"):
            off = rng.choice([-1, 1]) * rng.uniform(0.05, 0.5) * rms
            hidden, x0 = [f"{s}_offset"], np.append(x0, off)
            terms.append(Term(s, "1", (), off))
        eff = TrueEffect("sensor", (), (), (s,), "static", 0,
                         tuple(sorted({v for t in terms for v in t.variables})), tuple(terms),
                         description=f"sensor {s}: " + ", ".join(
                             f"{t.expression} {t.coefficient:.3g}" for t in terms))
    elif what == "lag":
        tau = max(rng.uniform(0.3, 1.5) / (2 * np.pi * bw), 3 * dt)
        hidden, x0 = [f"{s}_read"], np.append(x0, 0.0)
        dyn = HiddenDynamics(np.array([[-1 / tau]]), np.array([[1 / tau]]), np.array([[1.0]]),
                             -np.ones((1, 1)), (s,), (s,))
        eff = TrueEffect("sensor", (), (), (s,), "dynamic", 1, (s,), dynamics=dyn,
                         description=f"sensor {s} lags by {tau:.3g} s")
    else:
        off = rng.choice([-1, 1]) * rng.uniform(0.0, 0.3) * rms
        rate = rng.choice([-1, 1]) * rng.uniform(0.1, 0.5) * rms / (N * dt)
        hidden, x0 = [f"{s}_offset", f"{s}_rate"], np.append(x0, [off, rate])
        eff = TrueEffect("sensor", (), (), (s,), "static", 0, (),
                         (Term(s, "1", (), off), Term(s, "t", (), rate, "/s")),
                         description=f"sensor {s} drifts {rate:.3g}/s from {off:.3g}")
    effects.append(eff)
    texts.append(eff.description)
    At, Bt, Ct = _with_sensor(At, Bt, Ct, row, o, what, hidden, eff)
    return _linear_case(cls, rng, n_est, (A, B), (At, Bt), states, inputs, effects,
                        f"{base}: " + "; ".join(texts), options=(kind,), must=meas,
                        hidden=hidden, timing=(dt, bw), amplitude=amp, x0=x0,
                        C_true=Ct, measured=(kind, meas))


def _with_sensor(At, Bt, Ct, row, o, what, hidden, eff):
    """The true (A, B, C) with the sensor's states appended (offset: a constant; drift: an
    offset driven by a constant rate; lag: the reading)."""
    n, h = At.shape[0], len(hidden)
    A2 = np.zeros((n + h, n + h))
    A2[:n, :n] = At
    B2 = np.vstack([Bt, np.zeros((h, Bt.shape[1]))])
    C2 = np.hstack([Ct, np.zeros((Ct.shape[0], h))])
    if what == "lag":
        tau = -1 / eff.dynamics.A[0, 0]
        A2[n, o], A2[n, n] = 1 / tau, -1 / tau
        C2[row, :n] = 0.0
        C2[row, n] = 1.0
    elif what == "drift":
        A2[n, n + 1] = 1.0
        C2[row, n] = 1.0
    elif h:
        C2[row, n] = 1.0
    return A2, B2, C2


def _static_on(rng, A, B, states, inputs, i):
    """(nominal A, true A, effect): a damper on mass i (chain) or body i's loss (thermal)
    that the model lacks or has wrong; returns the nominal A with the error."""
    mech = inputs == ["F"]
    row = 2 * i + 1 if mech else i
    col = row
    val = rng.uniform(0.5, 2.0) if mech else rng.uniform(0.05, 0.3)
    fac = _factor(rng)
    At = np.array(A)
    At[row, col] -= val
    An = np.array(A)
    An[row, col] -= fac * val
    what = f"damping of m{i + 1}" if mech else f"loss of {states[row]}"
    eff = _state_effect(_linear_terms(An, At, B, B, states, inputs),
                        f"{what}: {val:.3g} 1/s, x{fac:.2f} in the model")
    return An, At, eff


@_retry
def sensor_gain_offset(rng, n_est):
    """A sensor's gain (1 +- 5-25 %) and/or offset (5-50 % of the output's rms) on one measured
    output of a chain or a row of bodies. Truth: sensor channel, static, terms (g - 1) x_s
    and/or the offset."""
    return _sensor_case(rng, n_est, "sensor_gain_offset", "gain_offset")


@_retry
def sensor_lag(rng, n_est):
    """A sensor lag (a thermocouple, a filtered encoder): one output reads x_s through
    1/(tau s + 1), tau 0.3-1.5 over the excitation's band (at least 3 dt). Truth: sensor
    channel, dynamic, order 1, driver x_s."""
    return _sensor_case(rng, n_est, "sensor_lag", "lag")


@_retry
def sensor_drift(rng, n_est):
    """A drifting sensor: one output reads x_s + o + r t, the drift r t reaching 10-50 % of
    the output's rms over the estimation record (both records start at the offset o).
    Truth: sensor channel, static, terms "1" (o) and "t" (r)."""
    return _sensor_case(rng, n_est, "sensor_drift", "drift")


@_retry
def state_sensor(rng, n_est):
    """Two effects of different kinds: a wrong damper (chain) or loss (bodies) in one state
    equation, and a sensor lag or gain/offset on one output (the issue's heat loss +
    thermocouple lag)."""
    return _sensor_case(rng, n_est, "state_sensor", str(rng.choice(["lag", "gain_offset"])),
                        state_effect=True)


@_retry
def state_input(rng, n_est):
    """Two effects of different kinds: a wrong damper on one mass of a chain of 1-12 and an
    actuator gain error (0.6-0.85 or 1.15-1.4) on F."""
    ch = _input_chain(rng)
    A, B, states = ch.matrices()
    An, At, e1 = _static_on(rng, A, B, states, ["F"], int(rng.integers(len(ch.m))))
    g = rng.uniform(0.6, 0.85) if rng.random() < 0.5 else rng.uniform(1.15, 1.4)
    e2 = _input_effect(B, states, "static", 0, (Term("F", "x", ("F",), g - 1, "N/N"),),
                       text=f"actuator gain {g:.3g}")
    return _linear_case("state_input", rng, n_est, (An, B), (At, g * B), states, ["F"],
                        [e1, e2], f"chain of {len(ch.m)}: {e1.description}; "
                        f"{e2.description}", amplitude=ch.amplitude, min_outputs=2)


@_retry
def correct_linear(rng, n_est):
    """A correct linear model (a chain of 1-12 masses or a row of 2-12 bodies): the model
    must stay unchanged."""
    A, B, states, inputs, timing, amp, opts, base = _sensor_base(rng)
    return _linear_case("correct_linear", rng, n_est, (A, B), (A, B), states, inputs, [],
                        f"{base}, model right", options=opts, timing=timing, amplitude=amp)


def _closed_loop(rng, n_est, cls, effect: str | None):
    """An open-loop unstable chain (1-3 masses; the first on a negative spring, 5-30 N/m, an
    inverted pendulum's linearization) measured in closed loop: F = r - K y, K a discrete
    LQR gain designed on the nominal model, every state measured (noisy), r low-pass
    noise. ``effect``: "damping" (a damper the model lacks or has wrong), "gain" (an
    actuator gain error) or None (the model is right). The loop must stay stable with the
    truth (spectral radius < 0.998), else the plant is drawn again."""
    ch = _chain(rng, lo=1, hi=3)
    k_rest = sum(k for a, b, k in ch.springs[1:] if 0 in (a, b))
    ch.springs[0] = (0, -1, -rng.uniform(5, 30) - k_rest)
    A, B, states = ch.matrices()
    if np.max(np.linalg.eigvals(A).real) <= 0.05:
        raise _Redraw("not unstable")
    At, Bt, An, effects = A, B, A, []
    if effect == "damping":
        An, At, e = _static_on(rng, A, B, states, ["F"], int(rng.integers(len(ch.m))))
        effects.append(e)
    elif effect == "gain":
        g = rng.uniform(0.7, 0.85) if rng.random() < 0.5 else rng.uniform(1.15, 1.3)
        Bt = g * B
        effects.append(_input_effect(B, states, "static", 0,
                                     (Term("F", "x", ("F",), g - 1, "N/N"),),
                                     text=f"actuator gain {g:.3g}"))
    dt, bw = _mech_timing(rng, At)
    n = A.shape[0]
    Ad, Bd = _zoh(An, B, dt)
    P = solve_discrete_are(Ad, Bd, np.eye(n), 0.1 * np.eye(1))
    K = np.linalg.solve(0.1 * np.eye(1) + Bd.T @ P @ Bd, Bd.T @ P @ Ad)
    Adt, Bdt = _zoh(At, Bt, dt)
    if np.max(np.abs(np.linalg.eigvals(Adt - Bdt @ K))) > 0.998:
        raise _Redraw("the truth destabilizes the loop")
    nom = _named(An, B, states, ["F"], list(range(n)), cls)
    plant = _Plant(n, np.eye(n), At, Bt)
    true = _true_system(plant, nom, [], f"{cls}_true")
    setup = _Setup(plant, dt, bw, rng.uniform(1.0, 3.0), _vel(states), controller=K,
                   excitation="lowpass")
    text = "; ".join(e.description for e in effects) or "model right"
    return _make_draw(cls, rng, nom, true, Truth(tuple(effects)), setup,
                      f"unstable chain of {len(ch.m)} in closed loop (LQR): {text}; "
                      f"{n} states, all measured", n_est)


def _zoh(A, B, dt):
    """ZOH-discretized (Ad, Bd)."""
    n, m = B.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n], M[:n, n:] = A, B
    E = expm(M * dt)
    return E[:n, :n], E[:n, n:]


@_retry
def unstable_closed_loop(rng, n_est):
    """An open-loop unstable plant measured in closed loop with an effect: a damper the
    model lacks or has wrong (state), or an actuator gain error (input)."""
    return _closed_loop(rng, n_est, "unstable_closed_loop",
                        str(rng.choice(["damping", "gain"])))


@_retry
def correct_closed_loop(rng, n_est):
    """An open-loop unstable plant measured in closed loop, its model right: it must stay
    unchanged."""
    return _closed_loop(rng, n_est, "correct_closed_loop", None)


def _oscillator(rng):
    """(name, f(x, u) continuous, T std, dt, bandwidth [Hz], text, units) of a nonlinear
    nominal: a pendulum (length 0.2-1.5 m, damping ratio 0.02-0.1, torque T) or a
    hardening Duffing oscillator (mass 0.5-2 kg, k 5-40 N/m, cubic 0.3-1x k at the rms
    deflection, force F). States (th, om) or (p, v)."""
    if rng.random() < 0.5:
        w0 = np.sqrt(9.81 / rng.uniform(0.2, 1.5))
        b = 2 * rng.uniform(0.02, 0.1) * w0
        J = rng.uniform(0.2, 2.0) * 9.81 / w0 ** 2   # m l^2
        amp = J * w0 ** 2 * rng.uniform(0.3, 0.6)

        def f(x, u):
            return np.array([x[1], -w0 ** 2 * np.sin(x[0]) - b * x[1] + u[0] / J])
        return ("pendulum", f, amp, 2 * np.pi / (w0 * rng.uniform(30, 60)),
                w0 / (2 * np.pi) * rng.uniform(0.5, 1.2), ["th", "om"], ["T"],
                f"pendulum {9.81 / w0 ** 2:.3g} m")
    m, k, c = rng.uniform(0.5, 2.0), rng.uniform(5, 40), rng.uniform(0.1, 0.5)
    amp = rng.uniform(1.0, 3.0)
    x_rms = amp / k
    k3 = rng.uniform(0.3, 1.0) * k / x_rms ** 2
    w0 = np.sqrt(k / m)

    def f(x, u):
        return np.array([x[1], (-k * x[0] - k3 * x[0] ** 3 - c * x[1] + u[0]) / m])
    return ("duffing", f, amp, 2 * np.pi / (2 * w0 * rng.uniform(20, 40)),
            w0 / (2 * np.pi) * rng.uniform(0.5, 1.2), ["p", "v"], ["F"],
            f"Duffing oscillator {m:.2g} kg, {k:.3g} N/m, {k3:.3g} N/m^3")


def _nonlinear(rng, n_est, cls, effect: str | None):
    """A NonlinearIOSystem nominal (pendulum or Duffing) whose truth adds ``effect`` to the
    velocity equation: "cubic" drag -c3 v^3, "coulomb" -fc sign(v), "viscous" -cv v (each
    10-30 % of the input's std at the velocity's rms; Coulomb 5-20 %), or None."""
    kind, f, amp, dt, bw, states, inputs, text = _oscillator(rng)
    u = _excitation(rng, "lowpass", 1, 1000, dt, bw, 1.0)
    X, _, _, _ = _simulate(_Plant(2, np.eye(2), f=f, sub=4), dt, amp * u)
    if kind == "pendulum":     # swings of 0.3-0.8 rad rms (a lightly damped pendulum resonates)
        amp *= rng.uniform(0.3, 0.8) / max(np.sqrt(np.mean(X[0] ** 2)), 1e-9)
        X, _, _, _ = _simulate(_Plant(2, np.eye(2), f=f, sub=4), dt, amp * u)
        if np.max(np.abs(X[0])) > 2.5:
            raise _Redraw("the pendulum goes over the top")
    vr = np.sqrt(np.mean(X[1] ** 2))
    scale = amp * f(np.zeros(2), np.ones(1))[1]   # the input's std in d's units
    eps = 0.02 * vr
    v = states[1]
    terms, extra, stiff = (), (lambda x: 0.0), 0.0
    if effect == "cubic":
        c3 = rng.uniform(0.1, 0.3) * scale / vr ** 3
        terms, extra, stiff = (Term(v, "x^3", (v,), -c3),), (lambda x: -c3 * x[1] ** 3), \
            3 * c3 * (3 * vr) ** 2
    elif effect == "coulomb":
        fc = rng.uniform(0.05, 0.2) * scale
        terms, extra, stiff = (Term(v, "sign(x)", (v,), -fc, smoothing=eps),), \
            (lambda x: -fc * _sign_smooth(x[1], eps)), fc / eps
    elif effect == "viscous":
        cv = rng.uniform(0.1, 0.3) * scale / vr
        terms, extra, stiff = (Term(v, "x", (v,), -cv),), (lambda x: -cv * x[1]), cv
    effects = [_state_effect(terms, f"{effect} {terms[0].coefficient:.3g} in eq({v})")] \
        if terms else []
    meas = [0, 1] if rng.random() < 0.5 else [0]
    C = np.eye(2)[meas]
    nom = ct.nlsys(lambda t, x, u, p: f(x, u), lambda t, x, u, p: C @ x, states=states,
                   inputs=inputs, outputs=[states[i] for i in meas], dt=0, name=cls)

    def ft(x, u):
        dx = f(x, u)
        return np.array([dx[0], dx[1] + extra(x)])
    sub = max(4, int(math.ceil(dt * max(stiff, 1e-9) / 0.5)))
    plant = _Plant(2, C, f=ft, sub=sub)
    true = _true_system(plant, nom, [], f"{cls}_true")
    setup = _Setup(plant, dt, bw, amp, (1,), excitation=str(rng.choice(["lowpass",
                                                                         "multisine"])),
                   limit=(0, 2.5) if kind == "pendulum" else None)
    return _make_draw(cls, rng, nom, true, Truth(tuple(effects)), setup,
                      f"{text} (NonlinearIOSystem): "
                      f"{effects[0].description if effects else 'model right'}; measured "
                      f"{', '.join(states[i] for i in meas)}", n_est)


@_retry
def nonlinear_model(rng, n_est):
    """A NonlinearIOSystem nominal (pendulum or Duffing oscillator) with an omitted effect in
    its velocity equation: cubic drag, Coulomb friction or viscous damping."""
    return _nonlinear(rng, n_est, "nonlinear_model", str(rng.choice(["cubic", "coulomb",
                                                                       "viscous"])))


@_retry
def correct_nonlinear(rng, n_est):
    """A correct NonlinearIOSystem nominal (pendulum or Duffing): it must stay unchanged."""
    return _nonlinear(rng, n_est, "correct_nonlinear", None)


#: Every class: name -> ``draw(rng, *, n_est=None) -> ZooDraw``.
CLASSES: dict[str, Callable[..., ZooDraw]] = {
    "static_state": static_state,
    "linear_force": linear_force,
    "cubic_force": cubic_force,
    "coulomb": coulomb,
    "quadratic_drag": quadratic_drag,
    "actuator_gain": actuator_gain,
    "actuator_lag1": actuator_lag1,
    "actuator_lag2": actuator_lag2,
    "dead_zone": dead_zone,
    "saturation": saturation,
    "flexible_shaft": flexible_shaft,
    "thermal_mass": thermal_mass,
    "sensor_gain_offset": sensor_gain_offset,
    "sensor_lag": sensor_lag,
    "sensor_drift": sensor_drift,
    "two_static": two_static,
    "state_sensor": state_sensor,
    "state_input": state_input,
    "unstable_closed_loop": unstable_closed_loop,
    "nonlinear_model": nonlinear_model,
    "correct_linear": correct_linear,
    "correct_nonlinear": correct_nonlinear,
    "correct_closed_loop": correct_closed_loop,
}

#: The classes whose model is right (the score counts false updates).
CORRECT_CLASSES = ("correct_linear", "correct_nonlinear", "correct_closed_loop")


def class_rng(seed: int, cls: str, i: int) -> np.random.Generator:
    """The generator of draw ``i`` of class ``cls`` in a run seeded ``seed``.

    Replayable, and independent of which other classes or draws run.

    Parameters
    ----------
    seed : int
        The run's seed.
    cls : str
        Class name (a key of ``CLASSES``).
    i : int
        Draw index within the class.

    Returns
    -------
    numpy.random.Generator
    """
    return np.random.default_rng([int(seed), zlib.crc32(cls.encode()), int(i)])


def draw_class(cls: str, seed: int, i: int = 0, *, n_est: int | None = None) -> ZooDraw:
    """Draw ``i`` of class ``cls`` in a run seeded ``seed``.

    Parameters
    ----------
    cls : str
        Class name (a key of ``CLASSES``).
    seed : int
        The run's seed.
    i : int
        Draw index within the class.
    n_est : int, optional
        Estimation samples (default the class's own, 4000).

    Returns
    -------
    ZooDraw

    Raises
    ------
    KeyError
        For an unknown class.
    """
    if cls not in CLASSES:
        raise KeyError(f"unknown zoo class {cls!r}; one of {', '.join(CLASSES)}")
    return CLASSES[cls](class_rng(seed, cls, i), n_est=n_est)


# ------------------------------------------------------------- the truth, independently
def simulate_true(draw: ZooDraw, u: NDArray, x0: NDArray | None = None) -> NDArray:
    """The true plant's noise-free output for a held input.

    Independent of the generator: ``draw.true`` is discretized by greybox
    (ZOH for a StateSpace, RK4 with ``draw.substeps`` sub-steps for a
    NonlinearIOSystem) and simulated.

    Parameters
    ----------
    draw : ZooDraw
    u : ndarray, shape (ninputs, nsteps)
        Input, held over each sample.
    x0 : ndarray, shape (true.nstates,), optional
        Initial state (default ``draw.true_x0``).

    Returns
    -------
    ndarray, shape (noutputs, nsteps)
    """
    from .nonlinear import discretize_nonlinear, simulate_nonlinear
    from .signals import simulate
    from .system import discretize
    x0 = draw.true_x0 if x0 is None else x0
    if isinstance(draw.true, ct.StateSpace):
        return simulate(discretize(draw.true, draw.dt), u, x0=x0).y_clean
    sysd = discretize_nonlinear(draw.true, draw.dt, substeps=draw.substeps)
    return simulate_nonlinear(sysd, u, x0=x0).y_clean


def model_with_truth(draw: ZooDraw) -> tuple[ct.NonlinearIOSystem, NDArray]:
    """The nominal model plus the recorded truth, built from the records alone.

    Parameters
    ----------
    draw : ZooDraw

    Returns
    -------
    system : control.NonlinearIOSystem
        Continuous time (see below).
    x0 : ndarray, shape (system.nstates,)
        Its initial state (the nominal's part of ``draw.true_x0``, zeros else).

    Notes
    -----
    Continuous NonlinearIOSystem with the nominal's states, then each dynamic
    effect's states (``z<k>_<j>``) and a clock ``t`` [s] when a term reads
    time. Input effects add to the input the nominal receives, state effects
    to its derivatives, sensor effects to its outputs. Simulated on the same
    input it must give the true plant's output: the truth is then exactly
    what the nominal lacks.
    """
    nom, effects = draw.nominal, draw.truth.effects
    states, ins = list(nom.state_labels), list(nom.input_labels)
    outs = list(nom.output_labels)
    n0 = len(states)
    dyn = [(k, e) for k, e in enumerate(effects) if e.dynamics is not None]
    zs = {k: list(range(len(states) + sum(e2.order for k2, e2 in dyn if k2 < k),
                        len(states) + sum(e2.order for k2, e2 in dyn if k2 <= k)))
          for k, e in dyn}
    names = states + [f"z{k}_{j}" for k, e in dyn for j in range(e.order)]
    clock = any(t.form == "t" for e in effects for t in e.terms)
    nt = len(names) + int(clock)
    if isinstance(nom, ct.StateSpace):
        A, B, C, D = (np.asarray(M, float) for M in (nom.A, nom.B, nom.C, nom.D))
        fnom = lambda x, u: A @ x + B @ u  # noqa: E731
        hnom = lambda x, u: C @ x + D @ u  # noqa: E731
    else:
        fnom = lambda x, u: np.asarray(nom.updfcn(0.0, x, u, nom.params), float)  # noqa
        hnom = lambda x, u: np.asarray(nom.outfcn(0.0, x, u, nom.params), float)  # noqa

    def d_of(e, k, vals, x, t):
        """d (ntargets,) of effect k."""
        if e.dynamics is None:
            d = np.zeros(len(e.targets))
            for term in e.terms:
                d[e.targets.index(term.target)] += term.value(vals, t)
            return d
        h = e.dynamics
        w = np.array([vals[s] for s in h.drivers])
        return h.C @ x[zs[k]] + h.D @ w

    def parts(x, u):
        t = x[-1] if clock else 0.0
        vals = dict(zip(states, x[:n0])) | dict(zip(ins, u))
        ue = np.array(u, dtype=float)
        for k, e in enumerate(effects):
            if e.channel == "input":
                ue = ue + _scatter(ins, e.targets, d_of(e, k, vals, x, t))
        return t, vals, ue

    def upd(_t, x, u, _p):
        t, vals, ue = parts(x, u)
        vals_e = vals | dict(zip(ins, ue))
        dx = np.zeros(nt)
        dx[:n0] = fnom(x[:n0], ue)
        for k, e in enumerate(effects):
            if e.channel == "state":
                dx[:n0] += _scatter(states, e.targets, d_of(e, k, vals, x, t))
            if e.dynamics is not None:
                h = e.dynamics
                src = vals if e.channel != "input" else vals_e | dict(zip(ins, u))
                dx[zs[k]] = h.A @ x[zs[k]] + h.B @ np.array([src[s] for s in h.drivers])
        if clock:
            dx[-1] = 1.0
        return dx

    def out(_t, x, u, _p):
        t, vals, ue = parts(x, u)
        y = hnom(x[:n0], ue)
        for k, e in enumerate(effects):
            if e.channel == "sensor":
                y = y + _scatter(outs, e.targets, d_of(e, k, vals, x, t))
        return y
    x0 = np.zeros(nt)
    x0[:n0] = draw.true_x0[:n0]
    sys = ct.nlsys(upd, out, states=names + (["t"] if clock else []), inputs=ins, outputs=outs,
                   dt=0, name=f"{draw.cls}_nominal_plus_truth")
    return sys, x0


def _scatter(names: list[str], targets: tuple[str, ...], d: NDArray) -> NDArray:
    """A vector over ``names`` with ``d`` at the ``targets``."""
    out = np.zeros(len(names))
    for tname, v in zip(targets, d):
        out[names.index(tname)] += v
    return out


# -------------------------------------------------------- what the report says, and the score
@dataclass(frozen=True)
class FoundTerm:
    """One term of a reported static law, in the truth's canonical form (see :class:`Term`).

    Attributes
    ----------
    target : str
    expression : str
        Canonical text (``Term.expression``) or greybox's own name for a form
        the zoo's truth does not use (a hinge, ``sign(p2-p1)``).
    variables : tuple of str
    coefficient : float
    ci95 : float
        95 % half-width (NaN when the report gives none).
    """

    target: str
    expression: str
    variables: tuple[str, ...]
    coefficient: float
    ci95: float = float("nan")

    def __post_init__(self):
        object.__setattr__(self, "coefficient", float(self.coefficient))
        object.__setattr__(self, "ci95", float(self.ci95))


@dataclass(frozen=True, eq=False)
class FoundEffect:
    """One effect as the report states it, mapped onto the truth's vocabulary.

    Attributes
    ----------
    channel : str
        "state", "input", "sensor", "parameters" (a nonlinear model's declared
        parameters refitted) or "unknown".
    targets : tuple of str
        Equations, inputs or outputs d adds to.
    law : str
        "static" or "dynamic" ("parameters" for a parameter refit).
    order : int
    drivers : tuple of str
        Signals the law reads (relative coordinates expanded into their states).
    terms : tuple of FoundTerm
        A static law's terms (linear terms one variable at a time).
    poles : ndarray, shape (order,)
        A dynamic law's continuous poles [1/s], sorted by modulus.
    pole_ci : ndarray, shape (order,)
        95 % half-widths of the poles (of their real and imaginary parts
        alike for a complex pair; NaN where not given).
    dc_gain : dict of (target, driver) -> float
        A dynamic law's DC gains.
    formula : str
        The report's formula.
    notes : tuple of str
        The report's parameter notes for this effect.
    """

    channel: str
    targets: tuple[str, ...]
    law: str
    order: int
    drivers: tuple[str, ...]
    terms: tuple[FoundTerm, ...] = ()
    poles: NDArray = field(default_factory=lambda: np.zeros(0, complex))
    pole_ci: NDArray = field(default_factory=lambda: np.zeros(0))
    dc_gain: dict = field(default_factory=dict)
    formula: str = ""
    notes: tuple[str, ...] = ()


_natural = natural_key  # p2 before p10


_REL = re.compile(r"^\((.+)-(.+)\)(\^3)?$")


def _canonical_terms(target: str, name: str, kind: str, c: float, h: float,
                     out_name: str = "") -> list[FoundTerm]:
    """Canonical FoundTerms of one greybox law term ``(name, kind)`` with coefficient c and
    95 % half-width h. ``out_name``: the output a sensor law's "yhat" terms read."""
    return [FoundTerm(target, expr, var, sign * c, h)
            for expr, var, sign in term_kind(kind).canonical(name, None, out_name)]


def _channel_of(name: str, equations) -> tuple[str, tuple[str, ...]]:
    """(channel kind, targets) from a channel's name ("eq(a)+eq(b)", "force(a,b)",
    "input(F)", "output(y)") and the effect's equations."""
    m = re.match(r"^input\((.+)\)$", name)
    if m:
        return "input", (m.group(1),)
    m = re.match(r"^output\((.+)\)$", name)
    if m:
        return "sensor", (m.group(1),)
    if name.startswith(("eq(", "force(")) or equations:
        return "state", tuple(equations)
    return "unknown", tuple(equations)


def _force_direction(rep, step_index: int, ch_name: str, eqs) -> NDArray | None:
    """The weights of a force channel in its equations: from ``report.channel.G`` for the
    first effect, else from the message "(it enters ... as [g1 g2])"."""
    if step_index == 0 and getattr(rep, "channel", None) is not None and \
            rep.channel.name == ch_name:
        labels = list(_base_model(rep, 0).state_labels)
        return np.asarray(rep.channel.G, float)[[labels.index(e) for e in eqs], 0]
    steps = getattr(rep, "steps", ()) or ()
    text = steps[step_index].message if step_index < len(steps) else rep.message
    m = re.search(r"as \[([^\]]+)\]", text)
    return np.array([float(v) for v in m.group(1).split()]) if m else None


def _static_found(ef, rep, k_step, ch_name, kind, targets, nominal=None) -> FoundEffect:
    """A static law (or a drift) from ``effect.law`` (a greybox StaticLaw)."""
    law = ef.law
    terms = []
    md = law.coef.shape[0]
    g = None
    if kind == "state" and md == 1 and len(targets) > 1:
        g = _force_direction(rep, k_step, ch_name, targets)
    for k in range(md):
        for j, (name, tkind, _idx) in enumerate(law.spec):
            c = float(law.coef[k, j])
            if c == 0:
                continue
            h = float(law.ci[k, j]) if law.ci is not None else float("nan")
            if term_kind(tkind).level == "input":
                tgt = targets[k] if k < len(targets) else targets[-1]
                terms.append(_break_found(rep, nominal, law, tgt, name, tkind, _idx, c, h))
                continue
            if g is not None:                          # one force: per equation
                for e, ge in zip(targets, g):
                    terms += _canonical_terms(e, name, tkind, c * ge, h * abs(ge))
            else:
                tgt = targets[k] if k < len(targets) else targets[-1]
                terms += _canonical_terms(tgt, name, tkind, c, h,
                                          out_name=targets[0] if kind == "sensor" else "")
    terms = _merge(terms)
    drivers = tuple(sorted({v for t in terms for v in t.variables}, key=_natural))
    return FoundEffect(kind, targets, "static", 0, drivers, tuple(terms), formula=ef.formula,
                       notes=tuple(ef.parameter_notes))


def _break_found(rep, nominal, law, target: str, name: str, kind: str, idx, c: float,
                 h: float) -> FoundTerm:
    """A dead zone ("deadzone(u)") or a saturation ("sat(u)") with its level as coefficient,
    when the term's coefficient is the plain one (-1 on the input, -B[e, u] in the one
    equation e the input enters, within COEF_RTOL); else the term as named (a form the
    truth never uses)."""
    inp, level, hl = idx[3], float(idx[1]), float(idx[2])
    expect = -1.0
    # d is in the channel's physical units in either time base: the continuous B (the
    # draw's nominal) where it is known
    nom = nominal if nominal is not None else rep.nominal
    st, ins = list(nom.state_labels), list(nom.input_labels)
    if target in st and inp in ins:
        expect = -float(np.asarray(nom.B)[st.index(target), ins.index(inp)])
    if expect != 0 and abs(c / expect - 1) <= COEF_RTOL:
        form = term_kind(kind).effect
        return FoundTerm(target, f"{form}({inp})", (inp,), level, hl)
    return FoundTerm(target, name, (), c, h)


def _merge(terms: list[FoundTerm]) -> list[FoundTerm]:
    """Sum the coefficients of equal (target, expression) terms (a relative coordinate
    expanded beside a plain term); half-widths add (conservative)."""
    out: dict = {}
    for t in terms:
        key = (t.target, t.expression)
        if key in out:
            o = out[key]
            out[key] = FoundTerm(o.target, o.expression, o.variables,
                                 o.coefficient + t.coefficient, o.ci95 + t.ci95)
        else:
            out[key] = t
    return [t for t in out.values() if t.coefficient != 0]


def _driver_weights(names: list[str], drivers) -> NDArray:
    """Rows over ``names`` (states then inputs) of each driver: a unit row, or e_b - e_a for
    a relative coordinate "(b-a)" (zeros for a name not found)."""
    W = np.zeros((len(drivers), len(names)))
    for r, d in enumerate(drivers):
        rel = _REL.match(d)
        if d in names:
            W[r, names.index(d)] = 1.0
        elif rel and rel.group(1) in names and rel.group(2) in names:
            W[r, names.index(rel.group(1))], W[r, names.index(rel.group(2))] = 1.0, -1.0
    return W


def _dc_dict(targets, names, DC: NDArray) -> dict:
    """{(target, name): gain} of the nonzero entries of DC (ntargets, len(names))."""
    return {(t, nm): float(DC[c, j]) for c, t in enumerate(targets)
            for j, nm in enumerate(names) if DC[c, j] != 0}


def _base_model(rep, k_step: int):
    """The model effect ``k_step`` was traced on: the nominal for the first, else the model
    after the step before (it carries the earlier effects' states)."""
    steps = list(getattr(rep, "steps", ()) or ())
    if 0 < k_step <= len(steps):
        return steps[k_step - 1].model.sys
    return rep.nominal


def _dynamic_found(ef, rep, k_step, kind, targets, g=None) -> FoundEffect:
    """A dynamic law from ``effect.dynamic_law`` (first-order, shared first- or higher-order)
    or ``effect.subsystem`` (an unstructured discrete subsystem)."""
    base = _base_model(rep, k_step)
    names = list(base.state_labels) + list(base.input_labels)
    law, sub = getattr(ef, "dynamic_law", None), getattr(ef, "subsystem", None)
    tg = list(targets)
    if law is not None and hasattr(law, "poles") and hasattr(law, "alpha"):      # order >= 2
        W = _driver_weights(names, law.drivers)
        z_dc = (law.beta[-1] / law.alpha[-1]) @ W
        DC = np.outer(law.k, z_dc) + law.E
        poles, pci = np.asarray(law.poles, complex), np.asarray(law.pole_ci, float)
    elif law is not None and hasattr(law, "Bz"):                                  # shared, order 1
        DC = -np.outer(law.k, law.Bz) / law.pole + law.E
        poles, pci = np.array([law.pole], complex), np.array([law.ci[0]], float)
    elif law is not None:                                                         # first order
        W = _driver_weights(names, law.drivers)
        DC = ((law.e - law.b / law.pole) @ W)[None, :]
        poles, pci = np.array([law.pole], complex), np.array([law.ci[0]], float)
    elif sub is not None:
        dt = float(rep.nominal.dt)
        I = np.eye(sub.order)
        Bd, Dd = np.hstack([sub.Bdx, sub.Bdu]), np.hstack([sub.Ddx, sub.Ddu])
        DC = sub.Cd @ np.linalg.solve(I - sub.Ad, Bd) + Dd
        poles = np.log(np.linalg.eigvals(sub.Ad).astype(complex)) / dt
        pci = np.full(sub.order, np.nan)
    else:
        return FoundEffect(kind, targets, "dynamic", ef.order, (), formula=ef.formula)
    if g is not None and DC.shape[0] == 1 and len(tg) > 1:         # one force along g
        DC = np.outer(g, DC[0])
    o = np.argsort(np.abs(poles))
    used = np.flatnonzero(np.any(np.abs(DC) > 0, axis=0))
    if sub is not None:
        used = np.flatnonzero(np.any(np.abs(np.hstack([sub.Bdx, sub.Bdu])) > 0, axis=0) |
                              np.any(np.abs(np.hstack([sub.Ddx, sub.Ddu])) > 0, axis=0))
    drivers = tuple(sorted((names[j] for j in used), key=_natural))
    return FoundEffect(kind, targets, "dynamic", len(poles), drivers, (), poles[o], pci[o],
                       _dc_dict(tg[:DC.shape[0]], names, DC), formula=ef.formula,
                       notes=tuple(ef.parameter_notes))


def _sensor_found(ef, kind, targets) -> FoundEffect:
    """A sensor law with a first-order lag (a "yhat_lag" term, coefficient tau [s]): dynamic,
    order 1, pole -1/tau; its other terms kept (a gain or an offset beside the lag)."""
    law, o = ef.law, targets[0]
    j = next(q for q, sp in enumerate(law.spec) if term_kind(sp[1]).time_constant)
    tau = float(law.coef[0, j])
    h = float(law.ci[0, j]) if law.ci is not None else float("nan")
    terms = []
    for q, (name, tkind, _i) in enumerate(law.spec):
        if q != j and law.coef[0, q] != 0 and term_kind(tkind).static:
            terms += _canonical_terms(o, name, tkind, float(law.coef[0, q]),
                                      float(law.ci[0, q]) if law.ci is not None else np.nan,
                                      out_name=o)
    return FoundEffect(kind, targets, "dynamic", 1, (o,), tuple(terms),
                       np.array([-1 / tau], complex), np.array([h / tau ** 2]),
                       {(o, o): 0.0}, formula=ef.formula, notes=tuple(ef.parameter_notes))


def found_effects(report, nominal=None) -> tuple[FoundEffect, ...]:
    """What a LoopReport says the model lacked, in the truth's vocabulary.

    Parameters
    ----------
    report : greybox.workflow.LoopReport
        From ``greybox.close_the_loop`` (linear or nonlinear nominal).
    nominal : control.StateSpace, optional
        The continuous nominal model given to close the loop (the draw's): the B
        a continuous-time dead zone or saturation in one state equation is read
        against (default: the report's discrete nominal).

    Returns
    -------
    tuple of FoundEffect
        One per effect added, in order; empty when the model was left unchanged.

    Notes
    -----
    The ONE place that reads how greybox states an effect (the step's channel name, the
    Effect's kind and order, its StaticLaw / DynamicLaw / SharedLaw / SharedLaw2 /
    Subsystem, its formula and parameter notes), with its helpers ``_channel_of``,
    ``_force_direction``, ``_static_found``, ``_canonical_terms``, ``_dynamic_found``
    and ``_sensor_found``: when the report gains structured terms, only these change.
    """
    if not getattr(report, "updated", False):
        return ()
    steps = list(getattr(report, "steps", ()) or ())
    items = [(s.effect, s.channel) for s in steps] or [
        (report.effect, report.channel.name if report.channel is not None else
         report.effect.channel)]
    out = []
    for k, (ef, name) in enumerate(items):
        kind, targets = _channel_of(name, ef.equations)
        if ef.kind == "parameters":
            out.append(FoundEffect("parameters", (), "parameters", 0, (), formula=ef.formula,
                                   notes=tuple(ef.parameter_notes)))
            continue
        law = getattr(ef, "law", None)
        if ef.kind in ("static", "sensor") and law is not None:
            if any(term_kind(sp[1]).time_constant and np.any(law.coef[:, j])
                   for j, sp in enumerate(law.spec)):
                out.append(_sensor_found(ef, kind, targets))
            else:
                out.append(_static_found(ef, report, k, name, kind, targets, nominal))
            continue
        if ef.kind != "dynamic":          # a kind this mapping does not know yet
            out.append(FoundEffect(kind, targets, ef.kind, ef.order, (), formula=ef.formula,
                                   notes=tuple(ef.parameter_notes)))
            continue
        g = _force_direction(report, k, name, targets) if name.startswith("force(") else None
        out.append(_dynamic_found(ef, report, k, kind, targets, g))
    return tuple(out)


@dataclass(frozen=True)
class ZooScore:
    """How a LoopReport's explanation compares with a draw's truth.

    Attributes
    ----------
    cls : str
    description : str
    correct_model : bool
        The draw's model was right (no true effect).
    updated : bool
        The report changed the model.
    right : bool
        The right explanation: for a correct model, no update; else every true
        effect found with the right channel (kind and targets), law kind,
        order, exactly the true terms (static) or drivers (dynamic), every
        coefficient within 10 % (static terms; dynamic: poles and DC gains),
        and no other effect.
    right_channel, right_kind, right_order, right_terms, coefficients_within : bool
        The parts of ``right`` (each over all true effects; False when an
        effect is missing or an extra one was added).
    covered : int
        True coefficients (static terms' coefficients, dynamic poles) inside
        the report's 95 % interval.
    n_coefficients : int
        True coefficients in all.
    false_flags : int
        Parameter notes that flag a parameter the truth has right.
    error_nominal, error_updated, error_true : float
        Validation error [%] of the nominal, the updated and the true model
        (SE; PE when the report's SE is undefined: an unstable model; the true
        model's is its noise-free output's, the measurement noise alone).
    error_kind : str
        "SE" or "PE".
    false_update : bool or None
        A correct model was changed (None for a draw with effects).
    seconds : float
        Run time of the report [s] (NaN if not given).
    found : str
        What the report found, one line per effect.
    why : str
        The first reason the explanation is not right ("" when right).
    """

    cls: str
    description: str
    correct_model: bool
    updated: bool
    right: bool
    right_channel: bool
    right_kind: bool
    right_order: bool
    right_terms: bool
    coefficients_within: bool
    covered: int
    n_coefficients: int
    false_flags: int
    error_nominal: float
    error_updated: float
    error_true: float
    error_kind: str
    false_update: bool | None
    seconds: float
    found: str
    why: str

    @property
    def coverage(self) -> float:
        """Fraction of true coefficients inside the reported 95 % intervals (NaN if none)."""
        return self.covered / self.n_coefficients if self.n_coefficients else float("nan")

    @property
    def error_ratio(self) -> float:
        """Validation error of the updated model over the true model's."""
        return self.error_updated / self.error_true


def _canon_key(target: str, expression: str) -> tuple[str, str]:
    """(target, expression) with a relative cube's coordinates in natural order."""
    rel = _REL.match(expression)
    if rel and rel.group(3) and _natural(rel.group(2)) > _natural(rel.group(1)):
        expression = f"({rel.group(2)}-{rel.group(1)})^3"
    return target, expression


def _true_coefs(te: TrueEffect) -> dict:
    """{canonical key: coefficient} of a static truth (orientation folded into the sign)."""
    out = {}
    for t in te.terms:
        key = _canon_key(t.target, t.expression)
        out[key] = -t.coefficient if key[1] != t.expression else t.coefficient
    return out


def _alternatives(te: TrueEffect, draw: ZooDraw) -> list[TrueEffect]:
    """The effect and its observationally equivalent forms: an input effect on an input that
    enters one equation e only is also a state effect in e (terms times B[e, input])."""
    out = [te]
    if te.channel != "input" or len(te.equations) != 1 or draw.nonlinear_model or \
            len(te.inputs) != 1:
        return out
    st, ins = list(draw.nominal.state_labels), list(draw.nominal.input_labels)
    b = float(np.asarray(draw.nominal.B)[st.index(te.equations[0]), ins.index(te.inputs[0])])
    e = te.equations[0]
    terms = tuple(Term(e, t.form, t.variables, t.coefficient if t.form in ("sat", "deadzone")
                       else b * t.coefficient, t.unit) for t in te.terms)  # a level: as is
    dyn = None
    if te.dynamics is not None:
        h = te.dynamics
        dyn = HiddenDynamics(h.A, h.B, b * h.C, b * h.D, h.drivers, (e,))
    out.append(TrueEffect("state", (e,), (), (), te.law, te.order, te.drivers, terms, dyn,
                          te.description))
    return out


def _compare(te: TrueEffect, fe: FoundEffect) -> tuple[dict, int, int, str]:
    """(checks, covered, n, why) of one true effect against the found effect paired with it."""
    chk = {"kind": fe.law == te.law, "order": fe.order == te.order}
    if te.law == "static":
        tc = _true_coefs(te)
        fc = {_canon_key(t.target, t.expression): t for t in fe.terms}
        chk["terms"] = set(tc) == set(fc)
        inside = [k for k in tc if k in fc and abs(fc[k].coefficient - tc[k]) <=
                  COEF_RTOL * abs(tc[k])]
        chk["coef"] = len(inside) == len(tc)
        cov = sum(1 for k in tc if k in fc and np.isfinite(fc[k].ci95) and
                  abs(fc[k].coefficient - tc[k]) <= fc[k].ci95)
        n = len(tc)
    else:
        h = te.dynamics
        chk["terms"] = set(fe.drivers) == set(te.drivers) and not fe.terms
        tp = h.poles
        ok = len(fe.poles) == len(tp) and bool(np.all(np.abs(fe.poles - tp) <=
                                                      COEF_RTOL * np.abs(tp)))
        DC = h.dc_gain
        # a DC gain near zero (an actuator's lag: d = (H - 1) F) is judged against half the
        # law's scale (its largest DC or high-frequency gain), not against itself
        floor = 0.5 * max(np.abs(DC).max(), np.abs(h.D).max())
        for c, tname in enumerate(h.targets):
            for j, dname in enumerate(h.drivers):
                got = fe.dc_gain.get((tname, dname), 0.0)
                ok &= abs(got - DC[c, j]) <= COEF_RTOL * max(abs(DC[c, j]), floor)
        chk["coef"] = bool(ok)
        cov, n = 0, len(tp)
        if len(fe.poles) == len(tp):
            for p, q, hw in zip(tp, fe.poles, fe.pole_ci):
                cov += int(np.isfinite(hw) and abs(p.real - q.real) <= hw and
                           abs(p.imag - q.imag) <= hw)
    why = "" if all(chk.values()) else (
        f"{te.channel} {','.join(te.targets)}: wrong " +
        ", ".join(k for k, v in chk.items() if not v))
    return chk, int(cov), n, why


def _right_entries(draw: ZooDraw) -> tuple[set, dict]:
    """({(equation, variable)} of the model entries the truth changes; {output: sensor forms}
    the truth has)."""
    entries, sensors = set(), {}
    for te in draw.truth.effects:
        if te.channel == "sensor":
            forms = sensors.setdefault(te.outputs[0], set())
            forms |= {t.form for t in te.terms} | ({"lag"} if te.law == "dynamic" else set())
            continue
        rows = te.targets if te.channel == "state" else te.equations
        for v in te.drivers:
            entries |= {(r, v) for r in rows}
    return entries, sensors


_NOTE_AB = re.compile(r"^([AB])\[([^;\]]+); ([^\]]+)\]")
_NOTE_REL = re.compile(r"^\[([^\]]+)\] lacks a term in the relative coordinate "
                       r"\(([^()-]+)-([^()]+)\)")
_NOTE_SENSOR = {"gain": "x", "offset": "1", "drifts": "t", "first-order lag": "lag"}


def _false_flags(draw: ZooDraw, found) -> int:
    """Parameter notes flagging an entry, or a sensor property, the truth has right."""
    entries, sensors = _right_entries(draw)
    bad = 0
    for fe in found:
        for note in fe.notes:
            m, r = _NOTE_AB.match(note), _NOTE_REL.match(note)
            if m or r:
                rows = [s.strip() for s in (m or r).group(2 if m else 1).split(",")]
                names = [m.group(3)] if m else [r.group(2), r.group(3)]
                bad += not any((row, nm) in entries for row in rows for nm in names)
                continue
            s = re.match(r"^sensor (\S+): (.*)$", note)
            if s:
                what = next((f for k, f in _NOTE_SENSOR.items() if s.group(2).startswith(k) or
                             f" {k}" in s.group(2)[:40]), None)
                bad += what is not None and what not in sensors.get(s.group(1), set())
    return bad


def _errors(draw: ZooDraw, report) -> tuple[float, float, str]:
    """(nominal, updated, "SE" or "PE") validation errors [%] from the report's table."""
    nom, upd = report.table["nominal"], report.table.get("updated", report.table["nominal"])
    if getattr(nom, "se_defined", True) and getattr(upd, "se_defined", True):
        return float(nom.se.value), float(upd.se.value), "SE"
    return float(nom.pe.value), float(upd.pe.value), "PE"


def _describe(found) -> str:
    """One line per found effect."""
    out = []
    for fe in found:
        many = len(fe.targets) > 1
        what = (", ".join((f"[{t.target}] " if many else "") + f"{t.coefficient:+.3g}*"
                          f"{t.expression}" for t in fe.terms)
                if fe.law == "static" else
                f"poles {np.array2string(fe.poles, precision=3)} driven by "
                f"{','.join(fe.drivers)}")
        out.append(f"{fe.channel}({','.join(fe.targets)}) {fe.law} {fe.order}: {what}")
    return "; ".join(out) or "model unchanged"


def _split_components(found, draw: ZooDraw) -> tuple[FoundEffect, ...]:
    """Found static state laws read as separate effects where the truth has separate
    effects there: the true effects (or their one-equation forms, see
    :func:`_alternatives`) whose equations lie in the found channel, two or more, covering
    it. Each found term goes to the effect that has it (else to the first one in its
    equation). An md > 1 equation channel carries one law per component, and an input
    that enters one equation adds to that equation's law: two springs traced together, or
    a damper and an actuator gain in the same equation, are the same model as two
    effects. Notes stay with the first part."""
    out = []
    for fe in found:
        views = [] if fe.channel != "state" or fe.law != "static" else [
            a for a in (next((v for v in _alternatives(te, draw) if v.channel == "state" and
                              v.law == "static" and set(v.targets) <= set(fe.targets)), None)
                        for te in draw.truth.effects) if a is not None]
        if len(views) < 2 or {t for v in views for t in v.targets} != set(fe.targets):
            out.append(fe)
            continue
        keys = [set(_true_coefs(v)) for v in views]
        parts: list[list[FoundTerm]] = [[] for _ in views]
        for t in fe.terms:
            k = _canon_key(t.target, t.expression)
            q = next((q for q, ks in enumerate(keys) if k in ks), None)
            if q is None:
                q = next(q for q, v in enumerate(views) if t.target in v.targets)
            parts[q].append(t)
        for q, (v, terms) in enumerate(zip(views, parts)):
            drivers = tuple(sorted({x for t in terms for x in t.variables}, key=_natural))
            out.append(FoundEffect("state", v.targets, "static", 0, drivers, tuple(terms),
                                   formula=fe.formula, notes=fe.notes if q == 0 else ()))
    return tuple(out)


def _pair(te: TrueEffect, found, used: set, draw: ZooDraw):
    """(true form, index) of the found effect paired with ``te``: same channel kind and
    targets (any equivalent form), the one sharing most terms (static) or the same drivers
    (dynamic) first; None when there is none."""
    best, best_score = None, -1
    for alt in _alternatives(te, draw):
        keys = set(_true_coefs(alt))
        for i, fe in enumerate(found):
            if i in used or fe.channel != alt.channel or set(fe.targets) != set(alt.targets):
                continue
            sc = (len(keys & {_canon_key(t.target, t.expression) for t in fe.terms})
                  if alt.law == "static" else int(set(fe.drivers) == set(alt.drivers)))
            if sc > best_score:
                best, best_score = (alt, i), sc
    return best


def score(draw: ZooDraw, report, seconds: float = float("nan")) -> ZooScore:
    """Score a LoopReport against the draw's truth.

    Parameters
    ----------
    draw : ZooDraw
    report : greybox.workflow.LoopReport
        ``greybox.close_the_loop`` on the draw's records.
    seconds : float
        The run time of ``close_the_loop`` [s], recorded as given.

    Returns
    -------
    ZooScore

    Notes
    -----
    True effects are paired with found ones by channel kind and targets (an
    input effect on an input that enters one equation also pairs with a state
    effect in that equation, its terms scaled by B; the two cannot be told
    apart from data; a static law counts as separate effects where the truth
    has separate effects in the equations it enters, see
    ``_split_components``). Static laws compare term by term (linear terms one
    variable at a time, so a spring in a relative coordinate equals its two
    expanded terms); dynamic laws compare order, drivers, continuous poles
    and DC gains (a DC gain near zero against half the law's scale).
    """
    found = _split_components(found_effects(report, draw.nominal), draw)
    e_nom, e_upd, kind = _errors(draw, report)
    common = dict(cls=draw.cls, description=draw.description, updated=bool(report.updated),
                  false_flags=_false_flags(draw, found), error_nominal=e_nom,
                  error_updated=e_upd, error_true=draw.se_true(), error_kind=kind,
                  seconds=float(seconds), found=_describe(found))
    if draw.truth.correct:
        ok = not report.updated
        return ZooScore(correct_model=True, right=ok, right_channel=ok, right_kind=ok,
                        right_order=ok, right_terms=ok, coefficients_within=ok, covered=0,
                        n_coefficients=0, false_update=not ok,
                        why="" if ok else "a correct model was changed", **common)
    used, checks, cov, n, whys = set(), [], 0, 0, []
    for te in draw.truth.effects:
        pair = _pair(te, found, used, draw)
        n += len(te.terms) if te.law == "static" else te.order
        if pair is None:
            checks.append({"channel": False, "kind": False, "order": False, "terms": False,
                           "coef": False})
            whys.append(f"{te.channel} {','.join(te.targets)}: not found")
            continue
        used.add(pair[1])
        chk, c, _, why = _compare(pair[0], found[pair[1]])
        checks.append({"channel": True, **chk})
        cov += c
        whys.append(why)
    extra = len(found) - len(used)
    if extra:
        whys.append(f"{extra} effect(s) beyond the truth")
    allk = {k: all(c[k] for c in checks) for k in ("channel", "kind", "order", "terms",
                                                   "coef")}
    allk["channel"] &= extra == 0
    return ZooScore(correct_model=False, right=all(allk.values()),
                    right_channel=allk["channel"], right_kind=allk["kind"],
                    right_order=allk["order"], right_terms=allk["terms"],
                    coefficients_within=allk["coef"], covered=cov, n_coefficients=n,
                    false_update=None, why=next((w for w in whys if w), ""), **common)
