"""greybox: close the loop between a physical state-space model and measured data."""

from .exceptions import (
    CovarianceError,
    DataError,
    DimensionError,
    GreyboxError,
    GreyboxWarning,
    IdentificationError,
    ModelError,
    RankConditionError,
)

__version__ = "0.1.0"

__all__ = [
    "GreyboxError",
    "DimensionError",
    "DataError",
    "ModelError",
    "RankConditionError",
    "CovarianceError",
    "IdentificationError",
    "GreyboxWarning",
]

from .filters import (  # noqa: E402
    FilterResult,
    SteadyStateFilter,
    check_rank_condition,
    kalman_filter,
    steady_state_filter,
    uikf,
)
from .plants import (  # noqa: E402
    TAPE_DRIVE_DT,
    TAPE_DRIVE_Q,
    TAPE_DRIVE_R,
    TapeDriveParams,
    tape_drive_nominal,
    tape_drive_tension,
    tape_drive_true,
)
from .signals import SimulationResult, lowpass_noise, multisine, random_binary, simulate  # noqa: E402
from .system import SplitModel, discretize, named_ss, split_inputs  # noqa: E402

__all__ += [
    "FilterResult",
    "SteadyStateFilter",
    "check_rank_condition",
    "kalman_filter",
    "steady_state_filter",
    "uikf",
    "TAPE_DRIVE_DT",
    "TAPE_DRIVE_Q",
    "TAPE_DRIVE_R",
    "TapeDriveParams",
    "tape_drive_nominal",
    "tape_drive_tension",
    "tape_drive_true",
    "SimulationResult",
    "lowpass_noise",
    "multisine",
    "random_binary",
    "simulate",
    "SplitModel",
    "discretize",
    "named_ss",
    "split_inputs",
]
