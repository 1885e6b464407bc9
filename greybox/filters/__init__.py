"""State and unknown-input filters."""

from .uikf import (
    FilterResult,
    SteadyStateFilter,
    check_rank_condition,
    kalman_filter,
    steady_state_filter,
    uikf,
)
from .delayed import RelativeDegree, delayed_uikf, detect_relative_degree
from .feedthrough import feedthrough_uikf, with_sensor_error
from .smoother import smooth_uikf

__all__ = [
    "FilterResult",
    "SteadyStateFilter",
    "check_rank_condition",
    "kalman_filter",
    "steady_state_filter",
    "uikf",
]

# unknown inputs behind the sensors (issue 11)
__all__ += [
    "RelativeDegree",
    "delayed_uikf",
    "detect_relative_degree",
    "feedthrough_uikf",
    "smooth_uikf",
    "with_sensor_error",
]
