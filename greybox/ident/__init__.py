"""System identification: subspace methods for open- and closed-loop data."""

from .closedloop import pbsid
from .modal_oe import ModalOEResult, refine_output_error
from .n4sid import N4SIDResult, n4sid

__all__ = ["N4SIDResult", "n4sid", "pbsid", "ModalOEResult", "refine_output_error"]
