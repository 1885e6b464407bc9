"""The paper's nonlinear motor-pump example (section V-B, eqs. 43-46, Table IV).

States ``x = [I, omega, Mdot]``: armature current [A], speed [rad/s] and
mass flow rate [kg/s]; input V [V]. The printed (44) and (46) are garbled
(PAPER_NOTES §8.9); we read them as

.. math::

    L \\dot I = V - R(I) I - K_e \\omega,\\qquad R(I) = \\alpha I^2 + R_0      (43, 44)

    \\theta \\dot\\omega = \\Psi I - \\beta_0 - \\beta_1 \\omega - h_p \\dot M \\omega   (45)

    \\ddot M = h_n \\omega^2 - h_r(t) \\dot M^2                                   (46)

with the pump load ``h_r(t)`` unknown. The nominal model replaces the load
term by an unknown input ``d = -h_r Mdot^2`` added to (46), in the units of
``dMdot/dt`` [kg/s^2]; it is recovered as ``h_r = -d / Mdot^2``. Table IV's
"R = 1 Ohm" has no place in this reading (R follows from I by (44)) and is
not used. All three states are measured (C = I); rank(C G) = 1 needs Mdot.

The model is stiff: the speed mode has a time constant of 56 us at the
running point ``MOTOR_PUMP_X_OP`` with h_r = 150 (PAPER_NOTES §8.9 quotes
~30 us), so the RK4 discretization at Ts = 1e-4 s takes 6 sub-steps there
(:func:`greybox.rk4_substeps`; ~10 at the notes' 30 us).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import control as ct
import numpy as np

__all__ = [
    "MotorPumpParams",
    "motor_pump_true",
    "motor_pump_nominal",
    "MOTOR_PUMP_STATES",
    "MOTOR_PUMP_DT",
    "MOTOR_PUMP_Q",
    "MOTOR_PUMP_R",
    "MOTOR_PUMP_X_OP",
]

MOTOR_PUMP_STATES = ("I", "omega", "Mdot")
MOTOR_PUMP_DT = 1e-4
"""Sampling period [s] of our reproduction (the paper gives none)."""
MOTOR_PUMP_Q = np.diag([1e-8, 1e-8, 1e-10])
"""Process-noise covariance of the discrete model [A^2, (rad/s)^2, (kg/s)^2] (ours: "very small")."""
MOTOR_PUMP_R = np.diag([1e-6, 1e-6, 1e-8])
"""Measurement-noise covariance [A^2, (rad/s)^2, (kg/s)^2]: 1 mA, 1 mrad/s, 0.1 g/s std."""
MOTOR_PUMP_X_OP = np.array([6.0, 4.0, 1.2])
"""A typical running point (V ~ 10 V, h_r ~ 100), used to choose the RK4 sub-steps."""


@dataclass(frozen=True)
class MotorPumpParams:
    """Parameters of the motor-pump (Table IV of the paper).

    Attributes
    ----------
    L : float
        Armature inductance [H].
    Ke : float
        Electrical (back-emf) constant [V s].
    alpha : float
        Current dependence of the armature resistance [Ohm / A^2].
    R0 : float
        Armature resistance at zero current [Ohm].
    theta : float
        Inertia of motor and pump [kg m^2].
    Psi : float
        Motor flux linkage (torque constant) [N m / A].
    beta0 : float
        Static friction torque [N m].
    beta1 : float
        Viscous friction coefficient [N m s].
    hp : float
        Pump constant [m^2].
    hn : float
        Piping flow constant of (46) [kg^-1 as printed].
    """

    L: float = 2e-3
    Ke: float = 5e-2
    alpha: float = 5e-3
    R0: float = 1.5
    theta: float = 5e-4
    Psi: float = 5.0
    beta0: float = 1e-4
    beta1: float = 2e-5
    hp: float = 7.5
    hn: float = 10.0

    def as_dict(self) -> dict:
        """Plain-JSON form."""
        return asdict(self)


def _rhs(x, V, load, p: MotorPumpParams):
    """dx/dt with the load term ``load`` added to (46), for one state x of shape (3,).

    Batches (sigma points, ensemble members) go through :func:`_rhs_batch`,
    the same right-hand side as one matrix product.
    """
    i, w, mdot = x[0], x[1], x[2]
    out = np.empty(np.shape(x))
    out[0] = (V - (p.alpha * i * i + p.R0) * i - p.Ke * w) * (1.0 / p.L)
    out[1] = (p.Psi * i - p.beta0 - p.beta1 * w - p.hp * mdot * w) * (1.0 / p.theta)
    out[2] = p.hn * w * w + load
    return out


def _batch_matrix(p: MotorPumpParams) -> tuple[np.ndarray, np.ndarray]:
    """(W, c) of the batch right-hand side, W of shape (3, 8), c of shape (3, 1)."""
    L, th = p.L, p.theta
    W = np.array([
        # I            omega          Mdot  V        load  I^3          omega^2  Mdot omega
        [-p.R0 / L,    -p.Ke / L,     0.0,  1.0 / L, 0.0,  -p.alpha / L, 0.0,    0.0],
        [p.Psi / th,   -p.beta1 / th, 0.0,  0.0,     0.0,  0.0,          0.0,    -p.hp / th],
        [0.0,          0.0,           0.0,  0.0,     1.0,  0.0,          p.hn,   0.0],
    ])
    c = np.array([[0.0], [-p.beta0 / th], [0.0]])
    return W, c


def _rhs_batch(x, u, Wc, load=None):
    """:func:`_rhs` for x of shape (3, npoints): ``W [I, omega, Mdot, V, load, I^3,
    omega^2, Mdot omega]' + c``, about half the numpy calls of the row-by-row form
    (the two agree to rounding: tests/test_ukf_paths.py).

    ``u`` holds the rows [V, d] (nominal model: d is the load term); the true
    model passes its load ``-h_r Mdot^2`` in ``load`` instead.
    """
    W, c = Wc
    if u.ndim == 1:  # one input for every state
        u = u[:, None]
    phi = np.empty((8, x.shape[1]))
    phi[:3] = x
    if load is None:
        phi[3:5] = u
    else:
        phi[3] = u[0]
        phi[4] = load
    i, w = x[0], x[1]
    cube = phi[5]
    np.multiply(i, i, out=cube)
    cube *= i
    np.multiply(x[1:3], w, out=phi[6:8])  # omega^2, Mdot omega
    out = W @ phi
    out += c
    return out


def motor_pump_true(params: MotorPumpParams | None = None) -> ct.NonlinearIOSystem:
    """The true motor-pump: continuous-time, inputs ``[V, h_r]``, outputs ``[I, omega, Mdot]``.

    Parameters
    ----------
    params : MotorPumpParams, optional
        Defaults to Table IV.

    Returns
    -------
    control.NonlinearIOSystem
        Continuous-time model (``dt = 0``); its update function takes a
        batch of states ``(3, npoints)``. Discretize it with
        :func:`greybox.discretize_nonlinear`.

    Examples
    --------
    >>> import greybox as gb
    >>> gb.motor_pump_true().input_labels
    ['V', 'h_r']
    """
    p = params or MotorPumpParams()
    Wc = _batch_matrix(p)

    def f(t, x, u, prm):
        if type(x) is np.ndarray and x.ndim == 2:  # a batch of states, one per column
            u = np.asarray(u, dtype=float)
            return _rhs_batch(x, u, Wc, load=-u[1] * x[2] * x[2])
        return _rhs(x, u[0], -u[1] * x[2] * x[2], p)

    return ct.nlsys(f, lambda t, x, u, prm: x, states=list(MOTOR_PUMP_STATES),
                    inputs=["V", "h_r"], outputs=list(MOTOR_PUMP_STATES), dt=0,
                    name="motor_pump_true")


def motor_pump_nominal(params: MotorPumpParams | None = None) -> ct.NonlinearIOSystem:
    """The nominal motor-pump: the load replaced by an unknown input ``d`` in (46).

    Parameters
    ----------
    params : MotorPumpParams, optional
        Defaults to Table IV.

    Returns
    -------
    control.NonlinearIOSystem
        Continuous-time model with inputs ``[V, d]`` (d [kg/s^2] adds to
        dMdot/dt; the true d is ``-h_r Mdot^2``) and outputs ``[I, omega, Mdot]``.

    Examples
    --------
    >>> import greybox as gb
    >>> gb.motor_pump_nominal().input_labels
    ['V', 'd']
    """
    p = params or MotorPumpParams()
    Wc = _batch_matrix(p)

    def f(t, x, u, prm):
        if type(x) is np.ndarray and x.ndim == 2:  # a batch of states, one per column
            return _rhs_batch(x, np.asarray(u, dtype=float), Wc)
        return _rhs(x, u[0], u[1], p)

    return ct.nlsys(f, lambda t, x, u, prm: x, states=list(MOTOR_PUMP_STATES),
                    inputs=["V", "d"], outputs=list(MOTOR_PUMP_STATES), dt=0,
                    name="motor_pump_nominal")
