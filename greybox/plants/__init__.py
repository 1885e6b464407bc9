"""Physical example plants (python-control StateSpace factories)."""

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
