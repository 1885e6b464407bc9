"""Physical example plants (python-control StateSpace and NonlinearIOSystem factories)."""

from .motor_pump import (
    MOTOR_PUMP_DT,
    MOTOR_PUMP_Q,
    MOTOR_PUMP_R,
    MOTOR_PUMP_STATES,
    MOTOR_PUMP_X_OP,
    MotorPumpParams,
    motor_pump_nominal,
    motor_pump_true,
)
from .tape_drive import (
    TAPE_DRIVE_DT,
    TAPE_DRIVE_INPUTS,
    TAPE_DRIVE_Q,
    TAPE_DRIVE_R,
    TAPE_DRIVE_STATES,
    TapeDriveParams,
    tape_drive_nominal,
    tape_drive_tension,
    tape_drive_true,
)

__all__ = [
    "MotorPumpParams",
    "motor_pump_true",
    "motor_pump_nominal",
    "MOTOR_PUMP_STATES",
    "MOTOR_PUMP_DT",
    "MOTOR_PUMP_Q",
    "MOTOR_PUMP_R",
    "MOTOR_PUMP_X_OP",
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
