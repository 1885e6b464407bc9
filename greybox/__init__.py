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
