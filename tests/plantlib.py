"""Test plants with an effect their nominal model omits (shared by trace/workflow tests).

Each true plant is a continuous ODE ``dx/dt = f(x, u)`` simulated by RK4 with
zero-order-hold inputs (``sub`` steps per sample), discrete process noise on
chosen states and white measurement noise; the nominal model is a named
continuous python-control StateSpace. Validation data carry measurement
noise only (PAPER_NOTES §8.6).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import control as ct
import numpy as np

import greybox as gb
from greybox._lti import lti_states
from greybox.system import named_ss


def rk4_simulate(f: Callable, x0, u, dt, *, sub=5, q_std=None, rng=None):
    """States (n, N) of ``dx/dt = f(x, u)`` with ZOH input u (m, N); noise added per sample.

    A linear ``f`` (:func:`linear_f`) takes the same RK4 steps as matrices, without a
    loop over samples (:func:`_rk4_linear`)."""
    if isinstance(f, LinearF):
        return _rk4_linear(f, x0, u, dt, sub, q_std, rng)
    N, h = u.shape[1], dt / sub
    xk = np.array(x0, dtype=float)
    x = np.empty((xk.size, N))
    for k in range(N):
        x[:, k] = xk
        uk = u[:, k]
        for _ in range(sub):
            a = f(xk, uk)
            b = f(xk + h / 2 * a, uk)
            c = f(xk + h / 2 * b, uk)
            d = f(xk + h * c, uk)
            xk = xk + h / 6 * (a + 2 * b + 2 * c + d)
        if q_std is not None:
            xk[:q_std.size] = xk[:q_std.size] + q_std * rng.standard_normal(q_std.size)
    return x


def _rk4_linear(f, x0, u, dt, sub, q_std, rng):
    """:func:`rk4_simulate` of ``dx/dt = A x + B u``: one RK4 step of a held input is
    ``x+ = T x + W u`` with T the degree-4 Taylor polynomial of exp(h A) and
    ``W = h (I + hA/2 + (hA)^2/6 + (hA)^3/24) B``, so a sample's ``sub`` steps are
    ``T^sub`` and ``sum_i T^i W``: the loop's numbers to rounding (~1e-12 relative over
    2e4 samples), the noise drawn in the loop's order (one (N, q) block equals N draws of
    q from a numpy Generator)."""
    A, B = f.A, f.B
    N, h = u.shape[1], dt / sub
    hA, eye = h * A, np.eye(A.shape[0])
    T = eye + hA @ (eye + hA @ (eye / 2 + hA @ (eye / 6 + hA / 24)))
    W = h * (eye + hA @ (eye / 2 + hA @ (eye / 6 + hA / 24))) @ B
    Ts, Ws = eye, np.zeros_like(W)
    for _ in range(sub):
        Ts, Ws = T @ Ts, T @ Ws + W
    v = Ws @ np.asarray(u, dtype=float)
    if q_std is not None:
        v[:q_std.size] += (q_std * rng.standard_normal((N, q_std.size))).T
    return lti_states(Ts, v, np.array(x0, dtype=float))


@dataclass
class Case:
    """One drawn data set: nominal model, records, covariances."""

    nominal: object
    y: np.ndarray
    u: np.ndarray
    y_val: np.ndarray
    u_val: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    dt: float


def draw(nominal, f, *, n_true, dt, rng, n_est=6000, n_val=3000, q_std, r_std,
         bandwidth=1.0, amplitude=2.0, sub=5):
    """Simulate estimation (process + measurement noise) and validation data (measurement noise).

    ``q_std`` (n_nominal,) is the discrete process-noise std on the nominal
    states; the nominal model's Q is diag(q_std^2) (+ a tiny jitter).
    """
    C = np.asarray(nominal.C, dtype=float)
    m = nominal.ninputs
    q_std = np.asarray(q_std, dtype=float)
    u = np.vstack([gb.lowpass_noise(n_est, dt=dt, bandwidth=bandwidth, amplitude=amplitude,
                                    rng=rng) for _ in range(m)])
    uv = np.vstack([gb.lowpass_noise(n_val, dt=dt, bandwidth=bandwidth, amplitude=amplitude,
                                     rng=rng) for _ in range(m)])
    n0 = C.shape[1]
    x = rk4_simulate(f, np.zeros(n_true), u, dt, sub=sub, q_std=q_std, rng=rng)
    xv = rk4_simulate(f, np.zeros(n_true), uv, dt, sub=sub)
    y = C @ x[:n0] + r_std * rng.standard_normal((C.shape[0], n_est))
    yv = C @ xv[:n0] + r_std * rng.standard_normal((C.shape[0], n_val))
    Q = np.diag(q_std**2) + 1e-12 * np.eye(n0)
    R = r_std**2 * np.eye(C.shape[0])
    return Case(nominal, y, u, yv, uv, Q, R, dt)


def msd(k=4.0, c=0.6, m=1.0, measured=("pos", "vel")):
    """Mass-spring-damper, states pos [m], vel [m/s], input F [N]."""
    A = np.array([[0.0, 1.0], [-k / m, -c / m]])
    B = np.array([[0.0], [1.0 / m]])
    idx = [("pos", "vel").index(s) for s in measured]
    C = np.eye(2)[idx]
    return named_ss(A, B, C, np.zeros((len(idx), 1)), 0, states=["pos", "vel"],
                    inputs=["F"], outputs=list(measured), name="msd")


class LinearF:
    """``f(x, u) = A x + B u`` of a continuous linear plant (:func:`rk4_simulate` steps it
    without a loop)."""

    def __init__(self, A, B):
        self.A, self.B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)

    def __call__(self, x, u):
        return self.A @ x + self.B @ u


def linear_f(sys):
    return LinearF(sys.A, sys.B)


def push_pair(measured=("p1", "v1", "p2", "v2")):
    """Two masses (1 kg, 2 kg) on springs to the wall (10, 20 N/m), dampers 0.5 N s/m,
    an actuator force F pushing them apart: B = [0, 1/m1, 0, -1/m2] (F enters two equations)."""
    k1, k2, c1, c2, m1, m2 = 10.0, 20.0, 0.5, 0.5, 1.0, 2.0
    A = np.array([[0, 1, 0, 0], [-k1 / m1, -c1 / m1, 0, 0],
                  [0, 0, 0, 1], [0, 0, -k2 / m2, -c2 / m2]], dtype=float)
    B = np.array([[0.0], [1.0 / m1], [0.0], [-1.0 / m2]])
    states = ["p1", "v1", "p2", "v2"]
    C = np.eye(4)[[states.index(s) for s in measured]]
    return named_ss(A, B, C, np.zeros((len(measured), 1)), 0, states=states, inputs=["F"],
                    outputs=list(measured), name="push_pair")


def with_actuator_lag(sys, tau):
    """True dynamics: the input reaches the plant through 1/(tau s + 1) (one extra state)."""
    A, B = np.asarray(sys.A, float), np.asarray(sys.B, float)
    n = A.shape[0]

    def f(x, u):
        dx = np.empty(n + 1)
        dx[:n] = A @ x[:n] + B[:, 0] * x[n]
        dx[n] = (u[0] - x[n]) / tau
        return dx
    return f


def with_input_gain(sys, gain):
    A, B = np.asarray(sys.A, float), np.asarray(sys.B, float)
    return LinearF(A, gain * B)


def chain(n_masses=2, k=20.0, c=0.5, m=1.0, k_wall=10.0, missing=(), measured=None,
          force_on=0):
    """Chain wall-k_wall-m1-k-m2-...-mN of masses; states p1, v1, ..., pN, vN; force F on mass
    ``force_on``. ``missing`` lists springs (i, j) (0-based masses) left out of the model.
    Returns the continuous StateSpace."""
    n = 2 * n_masses
    A = np.zeros((n, n))
    for i in range(n_masses):
        A[2 * i, 2 * i + 1] = 1.0
        A[2 * i + 1, 2 * i + 1] = -c / m
    springs = [(-1, 0, k_wall)] + [(i, i + 1, k) for i in range(n_masses - 1)]
    for i, j, kk in springs:
        if (i, j) in missing:
            continue
        for a, b in ((i, j), (j, i)):
            if a >= 0:
                A[2 * a + 1, 2 * a] -= kk / m
                if b >= 0:
                    A[2 * a + 1, 2 * b] += kk / m
    B = np.zeros((n, 1))
    B[2 * force_on + 1, 0] = 1.0 / m
    states = [f"{s}{i + 1}" for i in range(n_masses) for s in ("p", "v")]
    measured = states if measured is None else list(measured)
    C = np.eye(n)[[states.index(s) for s in measured]]
    return named_ss(A, B, C, np.zeros((len(measured), 1)), 0, states=states, inputs=["F"],
                    outputs=measured, name=f"chain{n_masses}")


def thermal_pair(seed, n_est=20000):
    """Two bodies (1, 2 J/K; losses 0.5, 0.4 W/K; heaters Q1, Q2 [W]) with temperatures T1,
    T2 [K] measured, and a hidden thermal mass Tm (4 J/K) the model lacks, coupled to both
    (1.0, 0.8 W/K): one shared state drives eq(T1) and eq(T2) along no fixed direction
    (d1 = (Tm - T1)/1, d2 = 0.8 (Tm - T2)/2). Returns (nominal, case, true discrete model)."""
    c1, c2, cm, l1, l2, g1, g2 = 1.0, 2.0, 4.0, 0.5, 0.4, 1.0, 0.8
    A = np.array([[-l1 / c1, 0.0], [0.0, -l2 / c2]])
    B = np.diag([1 / c1, 1 / c2])
    nom = named_ss(A, B, np.eye(2), np.zeros((2, 2)), 0, states=["T1", "T2"],
                   inputs=["Q1", "Q2"], outputs=["T1", "T2"], name="thermal_pair")
    At = np.array([[-(l1 + g1) / c1, 0, g1 / c1], [0, -(l2 + g2) / c2, g2 / c2],
                   [g1 / cm, g2 / cm, -(g1 + g2) / cm]])
    Bt = np.vstack([B, np.zeros((1, 2))])
    d = draw(nom, LinearF(At, Bt), n_true=3, dt=0.05,
             rng=np.random.default_rng(seed), q_std=np.array([1e-3, 1e-3]), r_std=1e-2,
             n_est=n_est, n_val=4000, sub=2, bandwidth=0.2)
    true = named_ss(At, Bt, np.eye(3)[:2], np.zeros((2, 2)), 0, states=["T1", "T2", "Tm"],
                    inputs=["Q1", "Q2"], outputs=["T1", "T2"], name="thermal_pair_true")
    return nom, d, gb.discretize(true, 0.05)


def linear_as_nlsys(s):
    """The linear model ``s.sys`` (a random_system namespace) as a discrete ``ct.nlsys``."""
    A, B, C, D = (np.asarray(m) for m in (s.sys.A, s.sys.B, s.sys.C, s.sys.D))
    return ct.nlsys(lambda t, x, u, p: A @ x + B @ u, lambda t, x, u, p: C @ x + D @ u,
                    states=s.sys.state_labels, inputs=s.sys.input_labels,
                    outputs=s.sys.output_labels, dt=s.dt, name="linear")


def thermal_three(seed, n_est=20000):
    """``thermal_pair`` plus a third body T3 (1.5 J/K, heater Q3) whose loss to ambient the
    model has as 0.3 W/K while the truth has 0.3 + 0.15 W/K: two independent effects, the
    hidden mass shared by eq(T1) and eq(T2) (as in ``thermal_pair``) and a missing
    conductance in eq(T3) (d3 = -0.1 T3). Returns (nominal, case, true discrete model)."""
    return _three_bodies(seed, n_est, (4.0,), "thermal_three")


def _three_bodies(seed, n_est, hidden, name):
    """Bodies T1, T2, T3 (1, 2, 1.5 J/K; losses 0.5, 0.4, 0.3 W/K in the model, T3's 0.15
    W/K more in the truth) and a hidden chain of masses of capacities ``hidden`` [J/K]: the
    first coupled to T1, T2 (1.0, 0.8 W/K), each next one to the one before (1.0 W/K)."""
    c1, c2, c3, l1, l2, l3, g1, g2, g3, gm = 1.0, 2.0, 1.5, 0.5, 0.4, 0.3, 1.0, 0.8, 0.15, 1.0
    A = np.diag([-l1 / c1, -l2 / c2, -l3 / c3])
    B = np.diag([1 / c1, 1 / c2, 1 / c3])
    st = ["T1", "T2", "T3"]
    nom = named_ss(A, B, np.eye(3), np.zeros((3, 3)), 0, states=st, inputs=["Q1", "Q2", "Q3"],
                   outputs=st, name=name)
    nh = len(hidden)
    nt = 3 + nh
    At = np.zeros((nt, nt))
    At[:3, :3] = A
    At[0, 0] -= g1 / c1
    At[1, 1] -= g2 / c2
    At[2, 2] -= g3 / c3
    At[0, 3], At[1, 3] = g1 / c1, g2 / c2
    for h, cm in enumerate(hidden):
        r = 3 + h
        into = (g1 + g2 if h == 0 else gm) + (gm if h + 1 < nh else 0.0)
        if h == 0:
            At[r, :2] = g1 / cm, g2 / cm
        else:
            At[r, r - 1] = gm / cm
        At[r, r] = -into / cm
        if h + 1 < nh:
            At[r, r + 1] = gm / cm
    Bt = np.vstack([B, np.zeros((nh, 3))])
    d = draw(nom, LinearF(At, Bt), n_true=nt, dt=0.05,
             rng=np.random.default_rng(seed), q_std=np.full(3, 1e-3), r_std=1e-2,
             n_est=n_est, n_val=4000, sub=2, bandwidth=0.2)
    names = st + (["Tm"] if nh == 1 else [f"Tm{h + 1}" for h in range(nh)])
    true = named_ss(At, Bt, np.eye(nt)[:3], np.zeros((3, 3)), 0, states=names,
                    inputs=["Q1", "Q2", "Q3"], outputs=st, name=f"{name}_true")
    return nom, d, gb.discretize(true, 0.05)


def thermal_row(seed, n_bodies=6, hidden=(1, 2, 3), n_est=20000):
    """``n_bodies`` bodies in a row (T1..Tn; capacities 1, 1.5, 2, 1, 1.5, 2, ... J/K; losses
    0.2 W/K to ambient; 0.5 W/K between neighbours; heaters Q1, Q3, Q5, ... [W]), all
    temperatures measured, and a hidden thermal mass Tm (4 J/K) the model lacks, coupled to
    the bodies ``hidden`` (0-based) by 1.0, 0.8, 0.6, ... W/K: one state shared by those
    equations along no fixed direction. ``hidden=()``: the model is right (no Tm). Returns
    (nominal, case, true discrete model)."""
    n = n_bodies
    cap = np.array([(1.0, 1.5, 2.0)[i % 3] for i in range(n)])
    A = np.zeros((n, n))
    for i in range(n):
        A[i, i] = -0.2
        for j in (i - 1, i + 1):
            if 0 <= j < n:
                A[i, i] -= 0.5
                A[i, j] += 0.5
    A /= cap[:, None]
    heat = list(range(0, n, 2))
    B = np.zeros((n, len(heat)))
    for q, i in enumerate(heat):
        B[i, q] = 1.0 / cap[i]
    st = [f"T{i + 1}" for i in range(n)]
    ins = [f"Q{i + 1}" for i in heat]
    nom = named_ss(A, B, np.eye(n), np.zeros((n, len(heat))), 0, states=st, inputs=ins,
                   outputs=st, name=f"thermal_row{n}")
    nt = n + (1 if hidden else 0)
    At = np.zeros((nt, nt))
    At[:n, :n] = A
    if hidden:
        cm = 4.0
        for q, i in enumerate(hidden):
            g = 1.0 - 0.2 * q
            At[i, i] -= g / cap[i]
            At[i, n] = g / cap[i]
            At[n, i] = g / cm
            At[n, n] -= g / cm
    Bt = np.vstack([B, np.zeros((nt - n, len(heat)))])
    d = draw(nom, LinearF(At, Bt), n_true=nt, dt=0.05,
             rng=np.random.default_rng(seed), q_std=np.full(n, 1e-3), r_std=1e-2,
             n_est=n_est, n_val=4000, sub=2, bandwidth=0.2)
    true = named_ss(At, Bt, np.eye(nt)[:n], np.zeros((n, len(heat))), 0,
                    states=st + ["Tm"] * (nt - n), inputs=ins, outputs=st,
                    name=f"thermal_row{n}_true")
    return nom, d, gb.discretize(true, 0.05)


def true_floor(true, d) -> float:
    """Validation SE [%] of the true discrete model ``true`` on the case ``d``: the floor.

    The true model's extra (hidden) states get no process noise (1e-12 jitter); its
    first states take the case's Q.
    """
    n, nt = d.Q.shape[0], true.nstates
    Qt = np.zeros((nt, nt))
    Qt[:n, :n] = d.Q
    return gb.validate_model(true, d.y_val, d.u_val, Q=Qt + 1e-12 * np.eye(nt), R=d.R).se.value


def thermal_chain_pair(seed, n_est=20000):
    """``thermal_pair`` with a hidden chain of two masses: Tm1 (2 J/K), coupled to T1 and T2
    (1.0, 0.8 W/K) as in ``thermal_pair``, and behind it Tm2 (4 J/K), coupled to Tm1 only
    (1.0 W/K). One second-order hidden subsystem (poles -0.15 and -1.5 1/s: time constants
    6.67 s and 0.667 s) whose output Tm1 enters eq(T1) and eq(T2) along no fixed direction:
    d1 = (Tm1 - T1)/1, d2 = 0.8 (Tm1 - T2)/2. Returns (nominal, case, true discrete model)."""
    c1, c2, cm1, cm2, l1, l2, g1, g2, g3 = 1.0, 2.0, 2.0, 4.0, 0.5, 0.4, 1.0, 0.8, 1.0
    A = np.array([[-l1 / c1, 0.0], [0.0, -l2 / c2]])
    B = np.diag([1 / c1, 1 / c2])
    nom = named_ss(A, B, np.eye(2), np.zeros((2, 2)), 0, states=["T1", "T2"],
                   inputs=["Q1", "Q2"], outputs=["T1", "T2"], name="thermal_chain_pair")
    At = np.array([[-(l1 + g1) / c1, 0, g1 / c1, 0], [0, -(l2 + g2) / c2, g2 / c2, 0],
                   [g1 / cm1, g2 / cm1, -(g1 + g2 + g3) / cm1, g3 / cm1],
                   [0, 0, g3 / cm2, -g3 / cm2]])
    Bt = np.vstack([B, np.zeros((2, 2))])
    d = draw(nom, LinearF(At, Bt), n_true=4, dt=0.05,
             rng=np.random.default_rng(seed), q_std=np.array([1e-3, 1e-3]), r_std=1e-2,
             n_est=n_est, n_val=4000, sub=2, bandwidth=0.2)
    true = named_ss(At, Bt, np.eye(4)[:2], np.zeros((2, 2)), 0,
                    states=["T1", "T2", "Tm1", "Tm2"], inputs=["Q1", "Q2"],
                    outputs=["T1", "T2"], name="thermal_chain_pair_true")
    return nom, d, gb.discretize(true, 0.05)


def thermal_chain_three(seed, n_est=20000):
    """``thermal_three`` with ``thermal_chain_pair``'s hidden chain of two masses behind T1
    and T2 (Tm1 2 J/K on T1, T2 by 1.0, 0.8 W/K; Tm2 4 J/K behind it by 1.0 W/K; poles -0.15
    and -1.5 1/s) and T3's missing 0.15 W/K loss (d3 = -0.1 T3): a second-order shared
    subsystem beside a static effect. Returns (nominal, case, true discrete model)."""
    return _three_bodies(seed, n_est, (2.0, 4.0), "thermal_chain_three")


def thermal_chain3_pair(seed, n_est=20000):
    """``thermal_chain_pair`` with a third hidden mass: Tm3 (8 J/K) behind Tm2, coupled to
    it only (1.0 W/K; Tm2 then loses 2 W/K in all). One third-order hidden subsystem
    (poles -1.525, -0.460 and -0.0401 1/s: time constants 0.656 s, 2.17 s and 24.9 s)
    whose output Tm1 enters eq(T1) and eq(T2) along no fixed direction, as in
    ``thermal_chain_pair``. Returns (nominal, case, true discrete model)."""
    c1, c2, cm1, cm2, cm3 = 1.0, 2.0, 2.0, 4.0, 8.0
    l1, l2, g1, g2, g3, g4 = 0.5, 0.4, 1.0, 0.8, 1.0, 1.0
    A = np.array([[-l1 / c1, 0.0], [0.0, -l2 / c2]])
    B = np.diag([1 / c1, 1 / c2])
    nom = named_ss(A, B, np.eye(2), np.zeros((2, 2)), 0, states=["T1", "T2"],
                   inputs=["Q1", "Q2"], outputs=["T1", "T2"], name="thermal_chain3_pair")
    At = np.array([[-(l1 + g1) / c1, 0, g1 / c1, 0, 0], [0, -(l2 + g2) / c2, g2 / c2, 0, 0],
                   [g1 / cm1, g2 / cm1, -(g1 + g2 + g3) / cm1, g3 / cm1, 0],
                   [0, 0, g3 / cm2, -(g3 + g4) / cm2, g4 / cm2],
                   [0, 0, 0, g4 / cm3, -g4 / cm3]])
    Bt = np.vstack([B, np.zeros((3, 2))])
    d = draw(nom, LinearF(At, Bt), n_true=5, dt=0.05,
             rng=np.random.default_rng(seed), q_std=np.array([1e-3, 1e-3]), r_std=1e-2,
             n_est=n_est, n_val=4000, sub=2, bandwidth=0.2)
    true = named_ss(At, Bt, np.eye(5)[:2], np.zeros((2, 2)), 0,
                    states=["T1", "T2", "Tm1", "Tm2", "Tm3"], inputs=["Q1", "Q2"],
                    outputs=["T1", "T2"], name="thermal_chain3_pair_true")
    return nom, d, gb.discretize(true, 0.05)


# --------------------------------------------------------------------- tanks with a spill
TANKS_K = {"k1": 0.045, "k2": 0.058, "k3": 0.082, "k4": 0.053}  # the benchmark's magnitudes


def tanks_declared(params: dict, ts: float = 4.0, nsub: int = 4) -> ct.NonlinearIOSystem:
    """Torricelli tanks (Ts, RK4 with nsub sub-steps), y = x2, with ``params`` declared.

    ``params`` holds any of k1..k4 (the others from TANKS_K); the update reads them
    from its ``params`` argument so that greybox can refit them. Scalar math (as a
    user's MODEL.py): one state vector per call.
    """
    h = ts / nsub

    def upd(t, x, u, p):
        k1, k2, k3, k4 = (p.get(k, TANKS_K[k]) for k in ("k1", "k2", "k3", "k4"))
        x1, x2, uk = float(x[0]), float(x[1]), float(u[0])

        def f(a, b):
            s1 = math.sqrt(max(a, 0.0))
            return -k1 * s1 + k4 * uk, k2 * s1 - k3 * math.sqrt(max(b, 0.0))
        for _ in range(nsub):
            a1, b1 = f(x1, x2)
            a2, b2 = f(x1 + h / 2 * a1, x2 + h / 2 * b1)
            a3, b3 = f(x1 + h / 2 * a2, x2 + h / 2 * b2)
            a4, b4 = f(x1 + h * a3, x2 + h * b3)
            x1 += h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
            x2 += h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
        return np.array([x1, x2])

    return ct.nlsys(upd, lambda t, x, u, p: np.array([x[1]]), states=["x1", "x2"],
                    inputs=["u"], outputs=["y"], dt=ts, params=dict(params), name="tanks")


def tanks_spill(seed: int, *, xmax: float = 8.0, gamma: float = 0.6, r_std: float = 0.01,
                n: int = 1024, ts: float = 4.0):
    """A two-tank plant whose upper tank overflows at xmax, a fraction gamma into the lower one.

    Truth: Torricelli with TANKS_K, RK4 with 20 sub-steps per sample, x1 clipped at
    xmax after every sub-step and gamma of the clipped volume added to x2 (same tank
    areas); pump voltage: 12 sines over 0-0.0144 Hz around 2.5 V (the benchmark's
    band); y = x2 + white noise r_std. Returns (u, y, u_val, y_val), shapes (1, n).
    """
    rng = np.random.default_rng(seed)
    k1, k2, k3, k4 = (TANKS_K[k] for k in ("k1", "k2", "k3", "k4"))
    h = ts / 20

    def f(x, uk):
        s1 = np.sqrt(max(x[0], 0.0))
        return np.array([-k1 * s1 + k4 * uk, k2 * s1 - k3 * np.sqrt(max(x[1], 0.0))])

    def record():
        t = np.arange(n) * ts
        u = 2.5 + sum(rng.uniform(0.2, 0.6) * np.sin(2 * np.pi * fq * t + rng.uniform(0, 6.3))
                      for fq in np.linspace(0.0005, 0.0144, 12))
        u = np.clip(u, 0, None)
        x, xs = np.array([5.0, 5.0]), np.empty((2, n))
        for k in range(n):
            xs[:, k] = x
            for _ in range(20):
                a = f(x, u[k])
                b = f(x + h / 2 * a, u[k])
                c = f(x + h / 2 * b, u[k])
                d = f(x + h * c, u[k])
                x = x + h / 6 * (a + 2 * b + 2 * c + d)
                over = max(x[0] - xmax, 0.0)
                x[0] -= over
                x[1] += gamma * over
        return u[None], xs[1:] + r_std * rng.standard_normal((1, n))

    u, y = record()
    uv, yv = record()
    return u, y, uv, yv


# --------------------------------------------------------------------- a fleet of chains

FLEET_EFFECTS = {
    "spring": ("v2", 2, "a wall spring on mass 2 the model lacks: d_v2 = -size * p2 [N/m]"),
    "damping": ("v1", 1, "a damper on mass 1 the model lacks: d_v1 = -size * v1 [N s/m]"),
    "right": (None, None, "the nominal model is right"),
}


def chain_unit(effect: str = "spring", size: float = 0.0, seed: int = 0, *, n_est: int = 2000,
               n_val: int = 1000) -> Case:
    """One unit of a fleet of two-mass chains whose nominal model is ``chain(2)``.

    ``effect`` (:data:`FLEET_EFFECTS`): "spring" adds a wall spring of ``size`` N/m on
    mass 2, "damping" a damper of ``size`` N s/m on mass 1, "right" nothing. Estimation
    data (``n_est`` samples at dt = 0.01 s) carry process noise 1e-4 on the velocities and
    1e-3 measurement noise; validation data (``n_val``) measurement noise only.
    """
    nom = chain(2)
    A, B = np.asarray(nom.A, float).copy(), np.asarray(nom.B, float)
    row, col, _ = FLEET_EFFECTS[effect]
    if row is not None:
        i = ["p1", "v1", "p2", "v2"].index(row)
        A[i, col] -= size
    return draw(nom, LinearF(A, B), n_true=4, dt=0.01,
                rng=np.random.default_rng(seed), n_est=n_est, n_val=n_val,
                q_std=np.array([0.0, 1e-4, 0.0, 1e-4]), r_std=1e-3)


def write_unit(folder, case: Case) -> None:
    """Write a unit's ``estimation.csv`` and ``validation.csv`` (header F, outputs) into
    ``folder`` (created)."""
    from pathlib import Path

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    head = ",".join(list(case.nominal.input_labels) + list(case.nominal.output_labels))
    for name, y, u in (("estimation", case.y, case.u), ("validation", case.y_val, case.u_val)):
        np.savetxt(folder / f"{name}.csv", np.vstack([u, y]).T, delimiter=",", header=head,
                   comments="", fmt="%.10g")
