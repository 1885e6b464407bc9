"""The last word of close the loop: is the updated model better on the validation data?

A model whose update fits the estimation record but predicts the validation
record worse than the nominal one is never handed over as a success: the
report keeps the nominal model, says "not recommended" first with both
figures, and keeps the refused model's validation row beside the nominal's.

What is compared: the simulation error SE (eq. 42) when both models simulate
and the nominal model has no pole on or outside the unit circle; otherwise
the one-step prediction error PE. A model with marginal modes (integrators, a
double integrator) drifts in simulation with any initial-state or input error,
so its SE says little (a ball on a beam: SE 1780 % -> 1030 % while the
prediction error went 2.93 % -> 30.9 %).
"""

from __future__ import annotations

from dataclasses import replace

import control as ct
import numpy as np

from .records import LoopReport
from .update import UpdatedModel
from .validate import MARGINAL_TOL, before_after, has_marginal_pole

__all__ = ["MARGINAL_TOL", "judged_measure", "recommend"]

def judged_measure(rep: LoopReport) -> tuple[str, float, float]:
    """``(measure, nominal, updated)`` on the validation record [%]: "SE" or "PE".

    PE when either SE is undefined (an unstable model) or the nominal model
    has a pole on or outside the unit circle; SE otherwise.
    """
    marginal = isinstance(rep.nominal, ct.StateSpace) and has_marginal_pole(rep.nominal)
    if not marginal:
        return before_after(rep.table)  # SE where both simulate, else PE
    a, b = rep.table["nominal"], rep.table["updated"]
    return "PE", float(a.pe.value), float(b.pe.value)


def recommend(rep: LoopReport, Q, R) -> LoopReport:
    """The report as it is when the update predicts the validation record better (or
    nothing was updated); else the nominal model kept and the update "not recommended".

    Parameters
    ----------
    rep : LoopReport
        A report of :func:`greybox.close_the_loop` on a linear nominal model.
    Q : array_like, shape (nstates, nstates)
        The nominal model's process-noise covariance (the caller's).
    R : array_like, shape (noutputs, noutputs)
        Its measurement-noise covariance.

    Returns
    -------
    LoopReport
        ``rep`` itself, or a copy with ``updated`` and ``recommended`` False, the
        nominal model, the message starting "not recommended", and the refused
        model's row as ``table["not recommended"]`` (``table["updated"]`` is the
        nominal's row, as for any report without an update).
    """
    if not rep.updated:
        return rep
    measure, before, after = judged_measure(rep)
    if not (np.isfinite(before) and np.isfinite(after)) or after <= before:
        return rep
    table = {k: v for k, v in rep.table.items() if k not in ("updated", "updated (linearized)")}
    table["updated"] = rep.table["nominal"]
    table["not recommended"] = rep.table["updated"]
    msg = (f"not recommended: the update found predicts the validation data worse than the "
           f"nominal model (validation {measure} {before:.3g}% -> {after:.3g}%); the nominal "
           f"model is kept. The update was: {rep.message}")
    model = UpdatedModel(sys=rep.nominal, Q=np.asarray(Q, dtype=float),
                         R=np.asarray(R, dtype=float), order=rep.nominal.nstates, kind="nominal")
    note = f"update refused on the validation record: {measure} {before:.3g}% -> {after:.3g}%"
    return replace(rep, updated=False, recommended=False, message=msg, table=table,
                   model=model, nonlinear=None).with_decision("recommend", "", note)
