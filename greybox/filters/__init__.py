"""State and unknown-input filters."""

from .kernels import (
    FilterResult,
    SteadyStateFilter,
    check_rank_condition,
    kalman_filter,
    steady_state_filter,
)
from .uikf import uikf
from .delayed import RelativeDegree, delayed_uikf, detect_relative_degree, input_weights
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
    "input_weights",
    "feedthrough_uikf",
    "smooth_uikf",
    "with_sensor_error",
]

# nonlinear filters (section IV, issue 10)
from .ensemble import ensemble_uikf  # noqa: E402
from .sigma_points import MerweScaledSigmaPoints, robust_cholesky  # noqa: E402
from .ukf import ui_ukf, ukf  # noqa: E402
from .delayed_ukf import delayed_ui_ukf  # noqa: E402

__all__ += ["MerweScaledSigmaPoints", "robust_cholesky", "ui_ukf", "ukf", "ensemble_uikf",
            "delayed_ui_ukf"]
