"""Exception and warning classes of greybox.

Every error greybox raises on bad input is a :class:`GreyboxError`. The
concrete classes also subclass the matching builtin (``ValueError``,
``RuntimeError``) so that code catching builtins keeps working, as in
python-control's ``ControlDimension(ValueError)``.

Messages follow one pattern: what was found, what was expected, and a hint on
how to fix it.
"""

from __future__ import annotations

__all__ = [
    "GreyboxError",
    "DimensionError",
    "DataError",
    "ModelError",
    "RankConditionError",
    "CovarianceError",
    "IdentificationError",
    "OutputExistsError",
    "MissingDependencyError",
    "GreyboxWarning",
]


class GreyboxError(Exception):
    """Base class of every error raised by greybox."""


class DimensionError(GreyboxError, ValueError):
    """An array or model has the wrong shape or the wrong number of signals."""


class DataError(GreyboxError, ValueError):
    """Measured data are unusable: NaN or inf, too short, not exciting, ..."""


class ModelError(GreyboxError, ValueError):
    """A model is of the wrong kind (e.g. continuous where discrete is needed)."""


class RankConditionError(GreyboxError, ValueError):
    """A rank condition of the method fails, e.g. rank(C G) = rank(G) = md (17)."""


class CovarianceError(GreyboxError, ValueError):
    """A covariance matrix is not symmetric, not positive (semi)definite, or not finite."""


class IdentificationError(GreyboxError, RuntimeError):
    """An identification step could not produce a usable model."""


class OutputExistsError(GreyboxError, FileExistsError):
    """An output would overwrite files that greybox did not write."""


class MissingDependencyError(GreyboxError, ImportError):
    """An optional dependency is not installed (the message names the pip command)."""


class GreyboxWarning(UserWarning):
    """A result was produced but deserves attention (e.g. weak excitation)."""
