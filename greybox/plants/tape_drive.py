"""Tape drive of Gillijns & De Moor, section V-A, eqs. (36)-(41), Table I.

Two DC motors (voltages V1, V2 [V]) drive two wheels that carry one tape.
States ``x = [I1, I2, p1, p2, w1, w2]``: armature currents [A], tape positions
on the wheels [m], wheel speeds [rad/s].

Sign convention (PAPER_NOTES §8.1). The tape tension
``T = K/2 * dp + D/2 * d(dp)/dt`` with ``dp = p2 - p1`` [N] pulls wheel 1
forward and wheel 2 back:

    J1 dw1/dt = +r1 T - beta w1 + Kt I1
    J2 dw2/dt = -r2 T - beta w2 + Kt I2

so the tension is restoring (it reduces the stretch ``p2 - p1``). The tape
mode is heavily damped, not lightly: the true model's continuous poles are
0, -291, -917 +- 136j and -1000 +- 134j rad/s (damping ratios ~0.99; about
500 rad/s is only the undamped stretch frequency sqrt(K r^2 / J) of the
tape spring, which the tape damping D and the motors' back-EMF swamp). The
nominal model (no tension) has two integrators (0, 0) and the motor poles
twice. As printed, eq. (38) has ``-r T`` on
both wheels, which makes the tension cancel from ``dp`` and is not physical.
The unknown-input matrix of the nominal model is accordingly
``G = [0 0 0 0 +r1/J1 -r2/J2]^T`` (continuous time, per newton of tension),
eq. (41) with the sign of the first wheel flipped.
"""

from __future__ import annotations

from dataclasses import dataclass

import control as ct
import numpy as np

from .._validation import check_positive
from ..exceptions import DimensionError
from ..system import discretize, named_ss

__all__ = [
    "TapeDriveParams",
    "tape_drive_true",
    "tape_drive_nominal",
    "tape_drive_tension",
    "TAPE_DRIVE_STATES",
    "TAPE_DRIVE_INPUTS",
    "TAPE_DRIVE_DT",
    "TAPE_DRIVE_Q",
    "TAPE_DRIVE_R",
]

TAPE_DRIVE_STATES = ("I1", "I2", "p1", "p2", "w1", "w2")
TAPE_DRIVE_INPUTS = ("V1", "V2")
TAPE_DRIVE_DT = 1e-4
"""Sampling period of the paper's example [s]."""
TAPE_DRIVE_Q = np.diag([1e-6, 1e-6, 1e-8, 1e-8, 1e-4, 1e-4])
"""Process-noise covariance of the paper (section V-A), units of the states squared."""
TAPE_DRIVE_R = np.diag([1e-6, 1e-6, 1e-8, 1e-8, 1e-4, 1e-4])
"""Measurement-noise covariance of the paper (section V-A)."""
TAPE_DRIVE_Q.setflags(write=False)  # shared constants: read-only, so no call can change them
TAPE_DRIVE_R.setflags(write=False)


@dataclass(frozen=True)
class TapeDriveParams:
    """Physical parameters of the tape drive, Table I of Gillijns & De Moor.

    Both motors and wheels are identical in the paper.

    Attributes
    ----------
    L : float
        Armature inductance [H].
    R : float
        Armature resistance [Ohm].
    Ke : float
        Back-EMF constant [V s/rad].
    r : float
        Wheel radius [m].
    J : float
        Inertia of wheel and motor [kg m^2].
    beta : float
        Rotational friction [N m s/rad].
    Kt : float
        Torque constant [N m/A].
    K : float
        Tape spring constant [N/m].
    D : float
        Tape damping [N s/m].
    """

    L: float = 1e-3
    R: float = 1.0
    Ke: float = 3e-2
    r: float = 25e-3
    J: float = 5e-5
    beta: float = 5e-2
    Kt: float = 3e-2
    K: float = 2e4
    D: float = 10.0

    def __post_init__(self):
        for name in ("L", "R", "Ke", "r", "J", "Kt"):
            check_positive(getattr(self, name), f"TapeDriveParams.{name}")
        for name in ("beta", "K", "D"):
            check_positive(getattr(self, name), f"TapeDriveParams.{name}", allow_zero=True)


def _motor_matrices(p: TapeDriveParams):
    """A and B of the nominal model (36), (37), (40): no tension."""
    A = np.zeros((6, 6))
    B = np.zeros((6, 2))
    for j in range(2):
        iI, ip, iw = j, 2 + j, 4 + j
        A[iI, iI] = -p.R / p.L
        A[iI, iw] = -p.Ke / p.L
        B[iI, j] = 1.0 / p.L
        A[ip, iw] = p.r
        A[iw, iw] = -p.beta / p.J
        A[iw, iI] = p.Kt / p.J
    return A, B


def _g_matrix(p: TapeDriveParams) -> np.ndarray:
    """Continuous-time tension input vector [rad/s^2 per N], shape (6, 1)."""
    return np.array([[0.0], [0.0], [0.0], [0.0], [p.r / p.J], [-p.r / p.J]])


def tape_drive_tension(params: TapeDriveParams | None = None) -> np.ndarray:
    """Row vector ``c_T`` with tension ``T = c_T @ x`` [N], eq. (39).

    ``T = K/2 (p2 - p1) + D/2 (r w2 - r w1)``.

    Parameters
    ----------
    params : TapeDriveParams, optional
        Physical parameters; Table I by default.

    Returns
    -------
    ndarray, shape (1, 6)
        [N per unit of each state].
    """
    p = params or TapeDriveParams()
    c = np.zeros((1, 6))
    c[0, 2], c[0, 3] = -p.K / 2, p.K / 2
    c[0, 4], c[0, 5] = -p.D / 2 * p.r, p.D / 2 * p.r
    return c


def tape_drive_true(params: TapeDriveParams | None = None, *, dt: float | None = None
                    ) -> ct.StateSpace:
    """True tape drive (with tape tension), eqs. (36)-(39).

    Parameters
    ----------
    params : TapeDriveParams, optional
        Physical parameters; Table I by default.
    dt : float, optional
        Sampling period [s]. None returns the continuous-time model; a value
        returns its ZOH discretization.

    Returns
    -------
    control.StateSpace
        Inputs ``V1, V2`` [V]; states and outputs ``I1, I2`` [A], ``p1, p2``
        [m], ``w1, w2`` [rad/s] (C = I6, as in the paper).
    """
    p = params or TapeDriveParams()
    A, B = _motor_matrices(p)
    A = A + _g_matrix(p) @ tape_drive_tension(p)
    sys = named_ss(A, B, np.eye(6), np.zeros((6, 2)), 0, states=TAPE_DRIVE_STATES,
                   inputs=TAPE_DRIVE_INPUTS, outputs=TAPE_DRIVE_STATES, name="tape_drive_true")
    return sys if dt is None else discretize(sys, dt)


def tape_drive_nominal(params: TapeDriveParams | None = None, *, dt: float | None = None,
                       with_tension_input: bool = True) -> ct.StateSpace:
    """Nominal tape-drive model: tension omitted, eqs. (36), (37), (40).

    Parameters
    ----------
    params : TapeDriveParams, optional
        Physical parameters; Table I by default.
    dt : float, optional
        Sampling period [s]; None for continuous time. The tension channel is
        discretized together with the voltages (ZOH), so the estimated unknown
        input is in newtons.
    with_tension_input : bool
        If True (default) the model has a third input ``T`` [N], the unknown
        tape tension entering through ``G = [0 0 0 0 r/J -r/J]^T`` (41).

    Returns
    -------
    control.StateSpace
        Inputs ``V1, V2`` [V] (and ``T`` [N]); states and outputs as in
        :func:`tape_drive_true`.
    """
    p = params or TapeDriveParams()
    if not isinstance(with_tension_input, (bool, np.bool_)):
        raise DimensionError(f"with_tension_input must be True or False; found "
                             f"{with_tension_input!r}")
    A, B = _motor_matrices(p)
    inputs = list(TAPE_DRIVE_INPUTS)
    if with_tension_input:
        B = np.hstack([B, _g_matrix(p)])
        inputs.append("T")
    sys = named_ss(A, B, np.eye(6), np.zeros((6, B.shape[1])), 0, states=TAPE_DRIVE_STATES,
                   inputs=inputs, outputs=TAPE_DRIVE_STATES, name="tape_drive_nominal")
    return sys if dt is None else discretize(sys, dt)
