"""State and unknown-input filters."""

from .ensemble import ensemble_uikf
from .sigma_points import MerweScaledSigmaPoints, robust_cholesky
from .ukf import ui_ukf, ukf
from .uikf import (
    FilterResult,
    SteadyStateFilter,
    check_rank_condition,
    kalman_filter,
    steady_state_filter,
    uikf,
)

__all__ = [
    "MerweScaledSigmaPoints",
    "robust_cholesky",
    "ui_ukf",
    "ukf",
    "ensemble_uikf",
    "FilterResult",
    "SteadyStateFilter",
    "check_rank_condition",
    "kalman_filter",
    "steady_state_filter",
    "uikf",
]
