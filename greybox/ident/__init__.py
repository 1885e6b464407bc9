"""System identification: subspace methods for open- and closed-loop data."""

from .closedloop import pbsid
from .n4sid import N4SIDResult, n4sid

__all__ = ["N4SIDResult", "n4sid", "pbsid"]
