"""State and unknown-input filters."""

from .uikf import (
    FilterResult,
    SteadyStateFilter,
    check_rank_condition,
    kalman_filter,
    steady_state_filter,
    uikf,
)

__all__ = [
    "FilterResult",
    "SteadyStateFilter",
    "check_rank_condition",
    "kalman_filter",
    "steady_state_filter",
    "uikf",
]

# nonlinear filters (section IV, issue 10)
from .ensemble import ensemble_uikf  # noqa: E402
from .sigma_points import MerweScaledSigmaPoints, robust_cholesky  # noqa: E402
from .ukf import ui_ukf, ukf  # noqa: E402

__all__ += ["MerweScaledSigmaPoints", "robust_cholesky", "ui_ukf", "ukf", "ensemble_uikf"]
