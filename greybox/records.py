"""The records of close the loop: the effect found, its candidates and steps, the report.

Frozen dataclasses shared by the linear and the nonlinear pipelines
(:mod:`greybox.workflow`, :mod:`greybox.workflow_nonlinear`), which both
import them from here; neither imports the other's records.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import control as ct
import numpy as np

from .metrics import WhitenessTest
from .terms import term_kind
from .trace import Channel, ChannelTrace
from .update import UpdatedModel

if TYPE_CHECKING:  # annotations only
    from .trace import StaticLaw
    from .trace.dynamic import DynamicLaw, SharedLaw
    from .trace.shared_order2 import SharedLaw2
    from .update import Subsystem

__all__ = ["CRITERION", "CRITERION_PE", "STAGES", "Candidate", "CandidateScore", "Decision",
           "Effect", "EffectStep", "LoopReport", "explain"]

#: The stages of close the loop, in order, as a decision record names them.
STAGES = ("residual", "screen", "trace", "generate", "choose", "gate", "validate", "baseline",
          "loop", "refit", "recommend")


@dataclass(frozen=True)
class Decision:
    """One entry of a report's decision trail: at which stage, about what, and why.

    Attributes
    ----------
    stage : str
        One of :data:`STAGES`: "residual" (the nominal's innovations and noise
        model), "screen" (which channels are traced), "trace" (a channel's own
        trace), "generate" (a candidate law tried or not tried), "choose" (the
        selection criterion), "gate" (the evidence), "validate" (the validation
        rows), "baseline" (the parallel delta row), "loop" (further passes),
        "refit" (joint refits and re-traces), "recommend" (the final check
        against the nominal on validation data).
    subject : str
        What it is about: a channel's name, or "" for the whole model.
    reason : str
        The decision in words.
    """

    stage: str
    subject: str
    reason: str

    def __post_init__(self):
        if self.stage not in STAGES:
            raise ValueError(f"unknown stage {self.stage!r}; one of {STAGES}")

    def __str__(self) -> str:
        return f"{self.subject}: {self.reason}" if self.subject else self.reason

    def as_dict(self) -> dict:
        """``{"stage", "subject", "reason"}``."""
        return {"stage": self.stage, "subject": self.subject, "reason": self.reason}


@dataclass(frozen=True)
class Candidate:
    """One scored candidate of a pass: a channel's law and its estimation error.

    Attributes
    ----------
    se : float
        Estimation SE (or PE, for an unstable nominal) of the model with this
        candidate's law, on the search window [%]; inf when it cannot be simulated.
    npar : int
        Parameters the law adds.
    trace : ChannelTrace
        The channel's trace (filter, d^, laws, models).
    kind : str
        "static" (``trace.static``), "dynamic" (``trace.dynamic``) or "sparse"
        (the sparse or shared dynamic law in ``law``).
    law : DynamicLaw or SharedLaw or SharedLaw2 or None
        The sparse or shared dynamic law of a "sparse" candidate.
    fit : OutputFit or None
        Its output fit on the search window (SE per output, effective samples):
        what the selection criterion reads (:func:`greybox.metrics.criterion_scores`).
    """

    se: float
    npar: int
    trace: ChannelTrace = field(repr=False)
    kind: str
    law: object = field(default=None, repr=False)
    fit: object = field(default=None, repr=False)

    @property
    def channel(self):
        """The candidate's channel (``trace.channel``)."""
        return self.trace.channel


CRITERION = ("lowest output-error criterion of the augmented model on the estimation data: "
             "sum over outputs of n_eff log(mean squared simulation error) + bic_factor "
             "(parameters) log(n_eff), n_eff the effective independent samples of the "
             "best-fitting candidate's error")
CRITERION_PE = ("lowest output-error criterion of the augmented model on the estimation data, "
                "on one-step prediction errors (the nominal model is unstable, so SE is "
                "undefined): sum over outputs of n_eff log(mean squared PE) + bic_factor "
                "(parameters) log(n_eff)")

#: The evidence the gate of a ``StateSpace`` model's update reads (``gate["evidence"]``)
#: through a channel of relative degree 0 or 1 ...
EVIDENCE_DHAT = "d^: likelihood ratio of the law against d = 0 (BIC gain + penalty)"
#: ... and through a delayed one (relative degree >= 2), where d^ is mostly estimation
#: noise: the choice's criterion, the nominal model a candidate without parameters.
EVIDENCE_OE = ("output error: the chosen candidate's criterion against the nominal model's "
               "(no parameter added): bic_gain = sum over outputs of n_eff log(nominal's / "
               "candidate's mean squared error), bic_penalty = (parameters) log(n_eff), on "
               "the choice's {n:.0f} effective samples")


def choice_note(labels, npars, ses, crit, order, n_eff, factor: float, shown: int = 4) -> str:
    """The decision record of the choice between candidates: the leading ones' criterion
    (``labels``, ``npars``, ``ses``, ``crit`` per candidate; ``order`` best first)."""
    best = crit[order[0]]
    rows = "; ".join(f"{labels[i]} ({npars[i]} par, SE {ses[i]:.3g} %): "
                     + ("best" if i == order[0] else f"+{crit[i] - best:.1f}")
                     for i in order[:shown])
    return (f"choose: output-error criterion (each output's n_eff log(mean squared "
            f"simulation error) + {factor:g} log(n_eff) per parameter, on "
            f"{np.sum(n_eff):.0f} effective samples; lower is better): {rows}")


@dataclass(frozen=True)
class Effect:
    """The effect the model lacked, as found.

    Attributes
    ----------
    kind : str
        "static", "dynamic", "sensor", "parameters" or "none". "parameters":
        a nonlinear nominal's declared parameters were wrong and refitting
        them alone left white innovations (no law; ``formula`` lists the
        changes, ``report.nonlinear.parameters`` holds them). "sensor": a sensor-error law
        the updated model carries as sensor states (a first-order lag: the
        reading; a drift: offset and drift rate); a static sensor law (gain,
        offset, |.|, saturation) is "static".
    order : int
        Subsystem order (0 for a static law or none; the number of sensor
        states for "sensor").
    formula : str
        Readable law in the physical names.
    channel : str
        Name of the channel (which state equations).
    equations : tuple of str
        States whose equations the error enters.
    nonlinear : bool
        A nonlinear static law was found.
    linearized : bool
        The updated StateSpace carries only the best linear part of a
        nonlinear law (a StateSpace cannot hold it); ``law`` has the full one.
    parameter_notes : tuple of str
        Which existing model parameters the law re-scales, and by how much.
    law : StaticLaw or None
    subsystem : Subsystem or None
    dynamic_law : DynamicLaw or SharedLaw or SharedLaw2 or None
        A sparse first-order law in continuous time (pole, drivers, intervals);
        a SharedLaw for one state shared by the equations of a pair; a
        SharedLaw2 for a second-order subsystem shared by them.
    """

    kind: str
    order: int = 0
    formula: str = ""
    channel: str = ""
    equations: tuple[str, ...] = ()
    nonlinear: bool = False
    linearized: bool = False
    parameter_notes: tuple[str, ...] = ()
    law: StaticLaw | None = field(default=None, repr=False)
    subsystem: Subsystem | None = field(default=None, repr=False)
    dynamic_law: DynamicLaw | SharedLaw | SharedLaw2 | None = field(default=None, repr=False)

    def as_dict(self) -> dict:
        """JSON-ready summary."""
        return {"kind": self.kind, "order": self.order, "formula": self.formula,
                "channel": self.channel, "equations": list(self.equations),
                "nonlinear": self.nonlinear, "linearized": self.linearized,
                "parameter_notes": list(self.parameter_notes)}


@dataclass(frozen=True)
class CandidateScore:
    """One (channel, kind) candidate and its score.

    Attributes
    ----------
    channel : str
    kind : str
        "static" or "dynamic" (or "-" for a skipped channel).
    order : int
    se_estimation : float
        SE [%] of the augmented model on the estimation data (inf if it diverged).
    npar : int
        Number of fitted parameters.
    status : str
        "ok", "skipped" or "failed".
    reason : str
    """

    channel: str
    kind: str
    order: int
    se_estimation: float
    npar: int
    status: str
    reason: str = ""


@dataclass(frozen=True)
class EffectStep:
    """One effect added by :func:`close_the_loop` (one row of the several-effects loop).

    Attributes
    ----------
    effect : Effect
    channel : str
        Name of the channel.
    message : str
        The step's one-sentence conclusion.
    se_before, se_after : float
        Validation SE [%] of the model before and after this step (NaN when
        undefined: an unstable model).
    model : UpdatedModel
        The model after this step (it holds this and every earlier effect).
    """

    effect: Effect
    channel: str
    message: str
    se_before: float
    se_after: float
    model: UpdatedModel = field(repr=False)

    def as_dict(self) -> dict:
        """JSON-ready row."""
        return {"channel": self.channel, "effect": self.effect.as_dict(),
                "message": self.message, "se_before": self.se_before,
                "se_after": self.se_after}


@dataclass(frozen=True)
class LoopReport:
    """Result of :func:`close_the_loop`.

    Attributes
    ----------
    model_error_detected : bool
        The nominal residual is not zero-mean white noise on some output
        (Ljung-Box or the mean's t-test, p < alpha).
    updated : bool
        The model was changed (all gates passed).
    message : str
        One-sentence conclusion.
    residual : WhitenessTest
        Ljung-Box test of the nominal one-step residuals, estimation data, with
        the t-test of their mean (``mean_pvalue``, :func:`greybox.innovation_test`).
    effect : Effect
    channel : Channel or None
    candidates : tuple of CandidateScore
    gate : dict
        The gate's signals: whiteness p-values, BIC gain and penalty,
        estimation SE before and after, and which gates passed.
    criterion : str
        The stated selection criterion.
    nominal : control.StateSpace
        The discrete nominal model.
    model : UpdatedModel
        The updated model (kind "static" or "dynamic"), or the nominal one
        (kind "nominal") when nothing was changed.
    table : dict of str -> ModelValidation
        Validation-data rows: "nominal", "updated", "delta" (when computed);
        for a nonlinear law also "updated (linearized)".
    trace : ChannelTrace or None
        The chosen channel's filter, laws and models (d^ for plots).
    decisions : tuple of Decision
        The decision trail, in the order taken: each stage's (stage, subject,
        reason); ``notes`` renders it as text.
    steps : tuple of EffectStep
        One row per effect added, in order (several effects: after each
        update the updated model's innovations are tested again, and traced
        again while they are not white). ``effect``, ``channel``,
        ``candidates``, ``gate`` and ``trace`` describe the first step;
        ``model`` and ``table["updated"]`` hold every effect.
    nonlinear : greybox.NonlinearUpdate or None
        Set when the updated model is nonlinear (a nonlinear nominal model,
        or a nonlinear law): the ``NonlinearIOSystem`` that the "updated"
        row simulates and its linearization at a stated operating point. The
        row of a nonlinear law starts from
        ``estimate_initial_state(model.sys, y_val, u_val, slow_modes=False)``
        (for an affine law, one with a constant term, with ``free=`` the
        law's own response from x0 = 0).
    recommended : bool
        False when the update the trace found predicts the validation data
        worse than the nominal model (:func:`greybox.recommend.recommend`):
        ``updated`` is then False too, ``model`` the nominal, the message
        starts "not recommended", and ``table["not recommended"]`` holds the
        refused model's row.
    """

    model_error_detected: bool
    updated: bool
    message: str
    residual: WhitenessTest
    effect: Effect
    channel: Channel | None
    candidates: tuple[CandidateScore, ...]
    gate: dict
    criterion: str
    nominal: ct.StateSpace = field(repr=False)
    model: UpdatedModel = field(repr=False)
    table: dict = field(repr=False)
    trace: ChannelTrace | None = field(default=None, repr=False)
    decisions: tuple[Decision, ...] = ()
    steps: tuple[EffectStep, ...] = ()
    nonlinear: object = field(default=None, repr=False)
    recommended: bool = True

    @property
    def notes(self) -> tuple[str, ...]:
        """The decision trail as text, one line per :class:`Decision` ("subject: reason")."""
        return tuple(str(d) for d in self.decisions)

    def with_decision(self, stage: str, subject: str, reason: str) -> "LoopReport":
        """A copy with one more decision at the end of the trail."""
        return replace(self, decisions=self.decisions + (Decision(stage, subject, reason),))

    def se_ratio(self) -> float:
        """Validation SE of the nominal model divided by that of the updated model.

        NaN when either SE is undefined (an unstable model): compare the PE then.
        """
        a, b = self.table["nominal"], self.table["updated"]
        if not (a.se_defined and b.se_defined):
            return float("nan")
        return a.se.value / b.se.value

    def explanation(self) -> list[dict]:
        """Each effect found as data (:func:`explain`), in the order added; empty when
        no error was found or no candidate could explain it."""
        if self.effect.kind == "none":
            return []
        if len(self.steps) > 1:
            return [explain(st.effect, self.channel if i == 0 else None)
                    for i, st in enumerate(self.steps)]
        return [explain(self.effect, self.channel)]

    def as_dict(self) -> dict:
        """JSON-ready summary (the ``greybox update --json`` document)."""
        return {
            "model_error_detected": self.model_error_detected,
            "updated": self.updated,
            "recommended": self.recommended,
            "message": self.message,
            "residual": {"pvalue": self.residual.pvalue.tolist(),
                         "statistic": self.residual.statistic.tolist(),
                         "lags": self.residual.lags, "alpha": self.residual.alpha,
                         **({} if self.residual.mean_pvalue is None else
                            {"mean_pvalue": self.residual.mean_pvalue.tolist()})},
            "channels": list(self.effect.equations),
            "channel": self.channel.name if self.channel is not None else None,
            "effect": self.effect.as_dict(),
            "criterion": self.criterion,
            "gate": {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                     for k, v in self.gate.items()},
            "candidates": [c.__dict__.copy() for c in self.candidates],
            "table": {k: v.as_dict() for k, v in self.table.items()},
            "notes": list(self.notes),
            "decisions": [d.as_dict() for d in self.decisions],
            "steps": [st.as_dict() for st in self.steps],
            "explanation": self.explanation(),
            **({"nonlinear": self.nonlinear.as_dict()} if self.nonlinear is not None else {}),
        }


def _num(v) -> float | None:
    """A finite float, or None (strict JSON)."""
    v = float(v)
    return v if np.isfinite(v) else None


def explain(effect: Effect, channel=None) -> dict:
    """One effect as data: where it enters and which law, for programs (the JSON's
    ``explanation``; the formula string says the same to a person).

    Returns
    -------
    dict
        ``{"channel": {"name", "kind", "equations", "input", "direction"},
        "law": {"kind", "order", "formula", "terms": [{"expression", "variables",
        "coefficient", "ci95", "determined"}], "poles", "time_constants"}}``.
        ``kind`` of the channel: "equation", "input", "force", "output" (None when
        unknown); ``direction``: the channel's column of G over its equations;
        ``terms`` of a static law (a sensor law's too; an input's dead zone
        ``clip(u, ±c)`` or saturation ``u - clip(u, ±c)`` also gives its
        ``breakpoint`` c, ``breakpoint_ci95`` and ``input``): each selected term with its
        coefficient and 95 % half-width (None when not computed; ``determined``
        False when the data do not determine it); ``poles`` [1/s] and
        ``time_constants`` [s] of a dynamic law, where it states them.
    """
    ch = {"name": effect.channel, "kind": getattr(channel, "kind", None),
          "equations": list(effect.equations), "input": getattr(channel, "input", "") or None,
          "direction": None}
    G = getattr(channel, "G", None)
    if G is not None and np.asarray(G).ndim == 2 and np.asarray(G).shape[1] == 1:
        g = np.asarray(G, dtype=float)[:, 0]  # over the state equations it enters, in order
        ch["direction"] = [_num(v) for v in g[g != 0]]
    law = {"kind": effect.kind, "order": effect.order, "formula": effect.formula,
           "terms": [], "poles": None, "time_constants": None}
    st = effect.law
    if st is not None and getattr(st, "coef", None) is not None:
        ci = st.ci if st.ci is not None else np.full_like(st.coef, np.nan)
        for c, j in zip(*np.nonzero(st.coef)):
            name, kind, idx = st.spec[j]
            h = float(ci[c, j])
            law["terms"].append({"component": int(c), "expression": name, "kind": kind,
                                 "coefficient": _num(st.coef[c, j]),
                                 "ci95": _num(h) if np.isfinite(h) else None,
                                 "determined": bool(h != np.inf)})
            if term_kind(kind).level == "input":  # a dead zone / saturation: its level
                law["terms"][-1].update({
                    "breakpoint": _num(idx[1]),
                    "breakpoint_ci95": _num(idx[2]) if np.isfinite(idx[2]) else None,
                    "input": idx[3]})
    dl = effect.dynamic_law
    if dl is not None:
        poles = getattr(dl, "poles", None)
        poles = [getattr(dl, "pole", np.nan)] if poles is None else list(np.ravel(poles))
        law["poles"] = [_num(np.real(p)) for p in poles]
        taus = getattr(dl, "taus", None)
        taus = [getattr(dl, "tau", np.nan)] if taus is None else list(np.ravel(taus))
        law["time_constants"] = [_num(t) for t in taus]
    return {"channel": ch, "law": law}
