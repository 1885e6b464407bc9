"""Close the loop on measured data in one call: residual, trace, add, before/after.

:func:`close_the_loop` takes a nominal physical model, its noise covariances,
an estimation record and a validation record, and returns a
:class:`LoopReport`:

1. **Residual.** Ljung-Box test (per output) of the nominal Kalman
   predictor's one-step residuals on the estimation data.
2. **Trace.** For every candidate channel (default: each state equation,
   and pairs of equations where p allows) :func:`greybox.trace.trace_channel`
   estimates d^ and fits a static law and a dynamic subsystem.
3. **Choose.** One criterion for every candidate: the output-error BIC of
   each augmented model on the *estimation* data (each output's log mean
   squared simulation error on its effective independent samples, plus
   ``bic_factor log n`` per parameter; :func:`greybox.metrics.criterion_scores`);
   lowest wins.
4. **Gate** (PAPER_NOTES §9.1): the model is changed only if all of: some
   output rejects whiteness (p < alpha), the chosen law's BIC gain on d^ is
   more than ``bic_factor`` times its penalty ``npar log N``, and the
   estimation SE drops below ``min_se_drop`` times the nominal one.
5. **Before/after.** SE, PE and whiteness on the validation data for the
   nominal model, the updated model and the parallel delta baseline.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field, replace

import control as ct
import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import block_diag
from scipy.stats import chi2

from ._blas import single_thread_blas
from ._lti import lti_states
from ._validation import (
    check_covariance,
    check_flag,
    check_parsimony,
    check_positive,
    check_records,
    check_statespace,
)
from .exceptions import DataError, GreyboxError, ModelError
from .progress import ProgressClock
from .recommend import recommend
from .filters import feedthrough_uikf, kalman_filter, uikf
from .metrics import (
    OutputFit,
    WhitenessTest,
    criterion_scores,
    effective_samples,
    innovation_test,
    output_fit,
    relative_error,
)
from .system import discretize, named_ss
from .trace import (
    Channel,
    ChannelTrace,
    parameter_notes,
    ekf_predict_with_law,
    resolve_channel_spec,
    trace_channel,
)
from .trace.channel_trace import (lacked_own_terms, law_estimate_of, refit_sensor_on_states,
                                  whole_inputs)
from .terms import BREAK_KINDS, term_kind
from .trace.dynamic import (DynamicLaw, SharedLaw, fit_input_lag, fit_shared_dynamic,
                             fit_sparse_dynamic)
from .trace.shared_order2 import SharedLaw2, fit_hidden_part2, fit_input_lag2, \
    fit_shared_order2
from .trace.joint import has_joint_parameters, joint_effect, refine_jointly, \
    integrators_as_positions, without_dead_states
from .trace.channels import (equation_subset, force_channel, input_channel, linked_forces,
                              output_channel,
                             relative_coordinates)
from .trace.laws import StaticLaw, direction, law_rows, one_term_law, sensor_states
from .trace.screen import screen_equations, screen_sensor_laws, screen_sensors
from .hold import LawHold
from .plant_adapter import LawPlant, LinearPlant, validation
from .update import Subsystem, UpdatedModel, delta_update
from .workflow_nonlinear import close_the_loop_nonlinear, nonlinear_update_of_linear
from .validate import (
    ModelValidation,
    describe_before_after,
    has_marginal_pole,
    estimate_initial_state,
    simulate_output,
    unstable_reason,
    validate_model,
)

__all__ = ["Effect", "EffectStep", "CandidateScore", "LoopReport", "close_the_loop"]

# Above this many states the equations are screened jointly first (cost ~ linear in n);
# the SCREEN_TOP highest-scoring equations, their pairs and the inputs are traced.
SCREEN_ABOVE = 4
SCREEN_TOP = 4
# ... and only those scoring at least this fraction of the best equation's score (the
# score grows with N and the effect's strength: two effects of one pass score alike; a
# much weaker one is left to the next pass of the several-effects loop; equations the
# model gets right score below 5, see trace/screen.py).
SCREEN_REL = 0.25
# A force traced again along its refitted direction may refit it again (a wrong first law
# moves the direction only part way: 64-state chain, positions only, -0.90 -> -0.976 ->
# -1.00); at most this many re-traces, each kept only if it is better.
_MAX_RETRACE = 3
# At most this many candidates of a choice pruned before it (besides the chosen one): each
# prune is one more trace of its channel (:meth:`_Pass._contenders_pruned`).
_MAX_PRUNED = 3
# A model with more outputs than default_channels offers sensor channels for (6) has its
# sensors offered by evidence instead: an offset that explains the innovations' mean
# (_offset_sensors), and the SENSOR_TOP outputs whose own sensor law explains most of the
# nominal simulation error (_sensor_law_candidates: a sensor error stays in its own
# output's simulation error). The criterion still chooses among them and the equations.
SENSOR_TOP = 2
# A sparse first-order law is fitted for a channel only when its unstructured dynamic
# fit beats its static law's estimation SE by this factor (evidence of dynamics).
SPARSE_IF = 0.8
# A second-order shared law extends a first-order one that is competitive: its estimation
# SE within this factor of the best candidate's (a hidden chain of two masses: the
# first-order law led, 2.2 % vs 4.8 %; a lag beside a spring: > 100 % vs 21 %, and the
# order-2 fit cost 11 s of 38 s)
ORDER2_WITHIN = 2.0
# Highest order of one subsystem shared by a group of equations (a chain of hidden parts).
MAX_SHARED_ORDER = 3
# The parallel delta baseline refines its N4SID model by output error on at most this
# many residuals (outputs x samples, like the trace's oe_window); its N4SID candidates
# and the held-out choice use the search window below.
DELTA_REFINE_RESIDUALS = 200_000
# The baseline is a comparison row; above ten states its cost is bounded (see
# _delta_baseline): its orders stop here (n + 6 up to ten states, as before) ...
DELTA_MAX_ORDER = 16
# ... its samples at DELTA_WORK / ((n + 1) x order x inputs)^2 (each candidate's Gram
# matrix then costs about DELTA_WORK flops; a 10-state model with one input keeps
# 1.6e5 samples, more than the search window) ...
DELTA_WORK = 5e9
#: Partners a one-equation law with evidence of dynamics is tried with as one shared state
#: where no pair of equations was traced (:meth:`_Pass._shared_with_linked`): a body in a
#: chain or a row has two neighbours
_LINKED_SHARED = 2
# ... and it starts no new candidate once it has taken as long as the trace before it,
# but never stops before this many seconds: below it the baseline runs whole whatever
# the machine's speed, so the reports of small models do not depend on it.
DELTA_MIN_BUDGET_S = 10.0
# The search runs on the first SEARCH_WINDOW samples of the estimation record: the
# equation screen, every candidate channel's trace and law fits, the sparse and
# higher-order dynamic fits, the estimation SEs that rank the candidates and gate the
# update (a nonlinear law is simulated sample by sample), the gate's BIC gain, and the
# parallel delta baseline. The residual (whiteness) test, the chosen channel's reported
# filter record and the validation table use the whole record. The static laws are
# refined by output error on their first ``trace.oe.oe_window`` samples (<= 1e4) anyway;
# beyond 1e5 samples the choice among channels and kinds no longer moves (issue 13: at
# 1e6 samples of a 2-state model the same channel, law and validation SE as on the whole
# record; bench/RESULTS_workflow.md).
SEARCH_WINDOW = 100_000

from .records import (  # noqa: E402,F401  (re-exported: greybox.workflow.LoopReport)
    CRITERION,
    Candidate,
    CRITERION_PE,
    CandidateScore,
    choice_note,
    Decision,
    Effect,
    EVIDENCE_DHAT,
    EVIDENCE_OE,
    EffectStep,
    LoopReport,
)


def _se(y, ysim, skip):
    """SE (eq. 42) [%] of a simulated output; inf when the simulation diverged (a
    candidate that cannot be simulated loses, it does not end the run)."""
    if not np.all(np.isfinite(ysim)):
        return np.inf
    try:
        return float(relative_error(y, ysim, skip=skip).value)
    except DataError:  # values beyond the magnitude check (1e252 from a diverged candidate)
        return np.inf


def _dynamic_formula(sub: Subsystem, ch: Channel, dt: float, x, u) -> str:
    nd = sub.order
    Ad = sub.Ad
    lam = np.linalg.eigvals(Ad)
    I = np.eye(nd)
    try:
        Gx = sub.Cd @ np.linalg.solve(I - Ad, sub.Bdx) + sub.Ddx
        Gu = sub.Cd @ np.linalg.solve(I - Ad, sub.Bdu) + sub.Ddu
    except np.linalg.LinAlgError:
        Gx, Gu = sub.Ddx, sub.Ddu
    rx = np.sqrt(np.mean(x**2, axis=1))
    ru = np.sqrt(np.mean(u**2, axis=1)) if u.size else np.zeros(0)
    tau = [(-dt / np.log(abs(v)) if 0 < abs(v) < 1 else np.inf) for v in lam]
    tau_s = ", ".join(f"{t:.3g} s" for t in sorted(set(np.round(tau, 12))))
    out = []
    for c in range(sub.Cd.shape[0]):
        contrib = np.concatenate([np.abs(Gx[c]) * rx, np.abs(Gu[c]) * ru])
        keep = contrib >= 0.05 * contrib.max() if contrib.size and contrib.max() > 0 else \
            np.zeros(contrib.size, bool)
        names = list(sub.state_labels) + list(sub.input_labels)
        coefs = np.concatenate([Gx[c], Gu[c]])
        terms = [(coefs[i], names[i]) for i in np.flatnonzero(keep)]
        body = " ".join(("- " if a < 0 else "+ ") + f"{abs(a):.3g}*{nm}" for a, nm in terms)
        body = body[2:] if body.startswith("+ ") else body
        uc = ch.units[c] if c < len(ch.units) else ""
        unit = "" if not uc else f" {uc}" if uc.startswith("[") else f" [{uc}]"
        out.append(f"{ch.labels[c]} = order-{nd} filter of ({body}){unit}, time constant(s) "
                   f"{tau_s}, poles {np.array2string(lam, precision=4)}")
    if ch.kind == "input" and ch.input in sub.input_labels:
        out.append(_actuator_line(sub, ch, tau_s))
    return "; ".join(out)


def _actuator_line(sub: Subsystem, ch: Channel, tau_s: str) -> str:
    """How the input reaches the plant: ``u + d`` as a filter of u (DC and high-frequency gain)."""
    j = list(sub.input_labels).index(ch.input)
    nd = sub.order
    try:
        h1 = float(sub.Cd[0] @ np.linalg.solve(np.eye(nd) - sub.Ad, sub.Bdu[:, j]))
    except np.linalg.LinAlgError:
        h1 = np.nan
    dc = 1.0 + h1 + float(sub.Ddu[0, j])
    hf = 1.0 + float(sub.Ddu[0, j])
    return (f"{ch.input} reaches the plant through an order-{nd} filter: DC gain {dc:.3g}, "
            f"gain at the first sample {hf:.3g}, time constant(s) {tau_s}")


def close_the_loop(sys: ct.StateSpace, y: ArrayLike, u: ArrayLike, y_val: ArrayLike,
                   u_val: ArrayLike, *, Q: ArrayLike, R: ArrayLike, dt: float | None = None,
                   channels=None, nonlinear: bool = True, max_order: int = 2,
                   alpha: float = 1e-3, lags: int = 20, delta: bool = True,
                   delta_max_order: int | None = None, parsimony: float = 1.1,
                   min_se_drop: float = 0.8, bic_factor: float = 10.0,
                   progress=None, max_effects: int = 3) -> LoopReport:
    """Find, trace and add the effect a nominal model lacks; report before and after.

    Parameters
    ----------
    sys : control.StateSpace or control.NonlinearIOSystem
        Nominal model from the measured inputs to the measured outputs, with
        named states, inputs and outputs. Continuous (then ``dt`` is needed
        and the model is ZOH-discretized together with each channel) or
        discrete. A NonlinearIOSystem (linear output map) goes through
        :func:`greybox.workflow_nonlinear.close_the_loop_nonlinear` (UKF
        residual, UI-UKF trace, static laws, RK4 simulation; ``max_order``,
        ``delta``, ``delta_max_order`` and ``max_effects`` do not apply).
    y, u : array_like, shapes (noutputs, nsteps), (ninputs, nsteps)
        Estimation record.
    y_val, u_val : array_like
        Validation record (used only for the before/after table).
    Q : array_like, shape (nstates, nstates)
        Process-noise covariance of the discrete nominal model.
    R : array_like, shape (noutputs, noutputs)
        Measurement-noise covariance.
    dt : float, optional
        Sampling period [s] (required for a continuous ``sys``).
    channels : optional
        Candidate error channels (see :func:`greybox.trace.resolve_channel_spec`);
        default every state equation, plus pairs where p allows.
    nonlinear : bool
        Offer x^3, sign(x) and |x| terms to the static laws.
    max_order : int
        Largest dynamic subsystem order tried (0: static laws only).
    alpha : float
        Significance level of the whiteness test (PAPER_NOTES §9.1: strict).
    lags : int
        Lags of the whiteness test and correlations.
    delta : bool
        Also fit the parallel delta baseline (21)-(24) for the table (a
        comparison row: the update never depends on it). False skips it (the
        CLI's ``--no-baseline``). Its cost is bounded so that it takes no
        longer than the trace (at least ``DELTA_MIN_BUDGET_S`` = 10 s): above
        ten states fewer orders and samples, then a time budget; a note says
        when it was bounded.
    delta_max_order : int, optional
        Highest order of the delta baseline; default n + 6 (that of
        :func:`greybox.update.delta_update`), at most ``DELTA_MAX_ORDER`` = 16.
    parsimony : float
        Deprecated, no effect (a value other than 1.1 warns): candidates are
        compared by one output-error criterion (``records.CRITERION``).
    min_se_drop : float
        The update must bring the estimation SE below this fraction of the
        nominal SE.
    bic_factor : float
        The BIC gain of the law on d^ must exceed this many times its penalty.
    progress : callable, optional
        Called with a :class:`greybox.progress.Progress` record (stage, k of
        K, elapsed seconds) at every stage boundary; None reports nothing.
    max_effects : int
        Most effects added (several effects): after each update the updated
        model's one-step residuals are tested again and, while some output
        rejects whiteness and the gate passes, traced again on the updated
        model. A nonlinear law ends the loop (the next pass would need a
        nonlinear base model).

    Returns
    -------
    LoopReport

    Raises
    ------
    ModelError, DimensionError, DataError, CovarianceError
        Bad model, shapes or data.

    Notes
    -----
    An unstable nominal model (open-loop unstable plants measured in closed
    loop) has no simulation error: candidates are then chosen, and the
    update gated, by the one-step prediction error PE on the estimation data
    and by the innovations' whiteness, and the before/after message compares
    PE ("SE n/a").

    Long records: the search (channel traces, law and dynamic fits, the
    candidates' estimation SE, the gate, the delta baseline) runs on the first
    ``SEARCH_WINDOW`` (1e5) samples of the estimation record; the residual
    test, the reported trace's filter record and the validation table use the
    whole record. The laws' output-error refinement uses at most 1e4 samples
    in any case, so a law and its intervals barely move; the BIC gains and
    estimation SEs in ``gate`` and ``candidates`` are the window's.
    """
    if isinstance(sys, ct.NonlinearIOSystem) and not isinstance(sys, ct.StateSpace):
        return close_the_loop_nonlinear(
            sys, y, u, y_val, u_val, Q=Q, R=R, dt=dt, channels=channels, nonlinear=nonlinear,
            alpha=alpha, lags=lags, parsimony=parsimony, min_se_drop=min_se_drop,
            bic_factor=bic_factor, progress=progress)
    P = _prepare(sys, y, u, y_val, u_val, Q=Q, R=R, dt=dt, channels=channels,
                 nonlinear=nonlinear, max_order=max_order, alpha=alpha, lags=lags, delta=delta,
                 delta_max_order=delta_max_order, parsimony=parsimony, min_se_drop=min_se_drop,
                 bic_factor=bic_factor, progress=progress, max_effects=max_effects)

    def once(sys_, nominal_, Q_, chans_, delta_) -> LoopReport:
        """One pass on the model ``sys_`` (the stages of :class:`_Pass`)."""
        return _Pass(P, sys_, nominal_, Q_, chans_, delta_).run()

    # one BLAS thread for the whole search: thousands of small-matrix products, solves and
    # expm, for which a second thread only waits (a 6x6 expm: 7.8 ms with two threads on a
    # busy machine, 0.05 ms with one; bench/workflow.py's 1e5-sample chain at load ~2.5:
    # 41 s vs 54 s wall)
    with single_thread_blas():
        rep = _loop(once, P.sys, P.nominal, P.Q, channels, P.chans, P.settings.delta,
                    P.settings.max_effects, P.dt, _JointRefit(P),
                    functools.partial(_refit_sensors, P))
        for other in (_fused, _split, _split_input, _reordered, _sensor_first):  # others
            rep = other(P, rep)
        rep = _with_record(rep, P.y, P.u, P.Q, P.R, P.sys)
        P.tick("validation", 1, 1)  # the report is complete (after every pass of the loop)
        return recommend(nonlinear_update_of_linear(rep), P.Q, P.R)


def _fused(P: Problem, rep: LoopReport) -> LoopReport:
    """Effects found in two single equations, traced again as one channel of the pair.

    The passes trace one equation at a time, so a hidden part touching two bodies (a
    thermal mass between two of them, not neighbours) is found as a law in each of the
    two equations, where no pair channel was formed (pairs are candidates only up to
    ``SCREEN_ABOVE`` states or among the screened equations, and the screen needs the
    outputs to determine every equation). When every effect of ``rep`` is a law in one
    state equation and they lie in exactly two equations, the pair is traced on the
    nominal model as the only channel (one pass, ``max_effects=1``: its static pair law,
    force and shared state of order 1 to 3 are the candidates). A hidden state of the
    pair (a dynamic law: what no law of one equation can be) replaces the effects only
    if it dominates them on the estimation record: a lower simulation error
    (:func:`validate_model` on the search window) with no more parameters; the decision
    trail says which was kept."""
    steps = rep.steps if rep.updated else ()
    eqs, npar = [], 0
    by_name = {c.name: c for c in P.chans}
    for st in steps:
        eff, ch = st.effect, by_name.get(st.channel)
        law = eff.dynamic_law if eff.dynamic_law is not None else eff.law
        if law is None or eff.nonlinear or ch is None or ch.kind != "equation" or ch.md != 1:
            return rep
        npar += int(law.npar)
        eqs += [e for e in ch.equations if e not in eqs]
    if len(steps) < 2 or len(eqs) != 2 or ct.isdtime(P.sys, strict=True) or \
            P.settings.channels is not None:  # the user's channels are the candidates
        return rep
    eqs.sort(key=list(P.sys.state_labels).index)
    P2 = replace(P, settings=replace(P.settings, channels=[tuple(eqs)], max_effects=1))
    pair = resolve_channel_spec(P.sys, [tuple(eqs)])
    try:
        alt = _loop(lambda *a: _Pass(P2, *a).run(), P.sys, P.nominal, P.Q, [tuple(eqs)],
                    pair, False, 1, P.dt, _JointRefit(P2))
    except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
        return rep.with_decision("loop", "", f"the effects' pair traced as one channel: {e}")
    eff = alt.effect if alt.updated else None
    law = None if eff is None else eff.dynamic_law
    if law is None:  # the pair's own static law says what the effects say (their sum)
        return rep
    S = P.settings

    def se(m):  # the model's simulation error on the estimation (search) record [%]
        row = validate_model(m.sys, P.ys, P.us, Q=m.Q, R=m.R, x0="estimate", name="",
                             lags=S.lags, alpha=S.alpha, skip=20)
        return row.se.value if row.se_defined else np.inf

    se_many, se_one = se(rep.model), se(alt.model)
    pair_name = pair[0].name
    what = (f"the {len(steps)} effects in eq({eqs[0]}) and eq({eqs[1]}) ({npar} parameters, "
            f"estimation SE {se_many:.3g} %) against {pair_name} traced as one channel "
            f"({eff.kind} of order {eff.order}, {law.npar} parameters, SE {se_one:.3g} %)")
    if not (se_one < se_many and law.npar <= npar):
        return rep.with_decision("loop", "", what + ": the effects kept")
    table = dict(alt.table)
    if "delta" in rep.table:
        table["delta"] = rep.table["delta"]
    kept = tuple(d for d in rep.decisions if d.stage != "validate")  # of the model replaced
    return replace(alt, table=table, decisions=kept + alt.decisions + (
        Decision("loop", "", what + ": one hidden state of the pair, a lower error with "
                             "no more parameters"),))


def _effects_npar(rep: LoopReport) -> int:
    """The parameters of every effect of an updated report (its laws' coefficients, poles,
    levels; a hidden part identified by subspace methods: its matrices, as its candidate
    was scored): the loop gives every such report its steps, one per effect."""
    laws = [next((x for x in (st.effect.dynamic_law, st.effect.law, st.effect.subsystem)
                  if x is not None), None) for st in rep.steps]
    return sum(int(law.npar) for law in laws if law is not None)


def _split(P: Problem, rep: LoopReport) -> LoopReport:
    """One effect in the state equations that may be two of different kinds fused (issue 27
    item 5): a sensor's error and a state equation's, absorbed by one law of the equations.

    When the report is one linear effect in state equations with three parameters or more,
    the pass is run again as two for the sensor the screen of sensor laws ranks first, if
    it reads one of the effect's states (:func:`_split_sensor`): first that sensor alone,
    then a linear static law of each equation of the effect's channel on the updated model
    (the two refitted jointly, as in the loop: the lag's time constant with the law).
    The one criterion (:func:`greybox.metrics.criterion_scores`, every effect's
    parameters counted) on the estimation record decides which explanation is kept; the
    decision trail says which and why."""
    if not _may_retry(P, rep) or len(rep.steps) > 1 or rep.channel is None or \
            rep.channel.kind == "output" or not rep.channel.equations or \
            _effects_npar(rep) < 3:
        return rep
    sensor = _split_sensor(P, rep.channel)
    if sensor is None:
        return rep
    return _as_two(P, rep, sensor, [(e,) for e in rep.channel.equations],
                   f"the effect in {rep.channel.name} ({_effects_npar(rep)} parameters) "
                   "tried as two of different kinds", "one effect",
                   ("the one effect kept", "the two effects, a lower criterion"))


def _as_two(P: Problem, rep: LoopReport, first: Channel, eqs: list, tried: str, name0: str,
            verdicts: tuple[str, str]) -> LoopReport:
    """``rep`` or the loop run as two passes (:func:`_two_passes`: the channel ``first``,
    then each equation of ``eqs``), whichever the one criterion prefers
    (:func:`_by_criterion`); the decision trail says which, or why there were not two
    (``tried``, ``name0``, ``verdicts``: as :func:`_by_criterion` takes them)."""
    what = f"{first.name} first, then " + ", ".join(f"eq({e})" for (e,) in eqs)
    alt = _two_passes(P, first, eqs)
    if isinstance(alt, str):
        return rep.with_decision("loop", "", f"{tried}: {what}: {alt}; {verdicts[0]}")
    return _by_criterion(P, rep, alt, tried, name0, what, verdicts)


def _split_input(P: Problem, rep: LoopReport) -> LoopReport:
    """One static law of several state equations that holds an input's gain error beside
    another effect (issue 27 item 5: two effects of different kinds fused).

    A law of the equations can stand for an actuator's error wherever the input enters:
    its terms in the input (``G Ddu``) then fall in rows of ``B[:, j]`` only, and the
    law adds a coefficient per row (zoo state_input: a damping error in eq(v5) and a
    gain of F found as one law of eq(v5), eq(v6), eq(v8), F in two rows at two
    coefficients). The loop is then run again as two passes (:func:`_two_passes`): the
    input's channel alone, then a linear static law of each equation of the effect on
    the updated model; the one criterion on the estimation record decides which
    explanation is kept (:func:`_by_criterion`, every effect's parameters counted)."""
    if not _may_retry(P, rep) or len(rep.steps) > 1 or rep.channel is None or \
            rep.channel.kind != "equation" or len(rep.channel.equations) < 2:
        return rep
    law = rep.effect.law
    if rep.effect.dynamic_law is not None or not isinstance(law, StaticLaw) or law.nonlinear \
            or law.output is not None:
        return rep
    B = np.asarray(P.sys.B, dtype=float)
    dB = np.asarray(rep.channel.G, dtype=float) @ np.asarray(law.Ddu, dtype=float)
    inputs = [j for j in range(B.shape[1]) if np.any(dB[:, j] != 0) and
              np.all((B[:, j] != 0) | (dB[:, j] == 0)) and
              np.count_nonzero(dB[:, j]) >= 2]
    if not inputs:
        return rep
    j = max(inputs, key=lambda j: np.linalg.norm(dB[:, j]) / np.linalg.norm(B[:, j]))
    return _as_two(P, rep, input_channel(P.sys, j), [(e,) for e in rep.channel.equations],
                   f"the effect in {rep.channel.name} (terms in {P.sys.input_labels[j]} where "
                   "it enters) tried as two of different kinds", "one effect",
                   ("the one effect kept", "the two effects, a lower criterion"))


def _may_retry(P: Problem, rep: LoopReport) -> bool:
    """Whether a linear update may be tried as another set of effects (:func:`_split`,
    :func:`_reordered`): greybox chose the channels, two effects are allowed, and the
    nominal model has a simulation error to compare them by."""
    S = P.settings
    return rep.updated and S.channels is None and not rep.effect.nonlinear and \
        S.max_effects >= 2 and not unstable_reason(P.nominal, P.y.shape[1])


def _by_criterion(P: Problem, rep: LoopReport, alt: LoopReport, tried: str, name0: str,
                  name1: str, verdicts: tuple[str, str]) -> LoopReport:
    """``rep`` or the alternative explanation ``alt`` of the same record, whichever the one
    criterion (:func:`greybox.metrics.criterion_scores` at ``bic_factor``, every effect's
    parameters counted, on the estimation record) prefers; the decision trail says which
    and by how much (``tried``: what was tried; ``name0``, ``name1``: the two
    explanations; ``verdicts``: the note when ``rep`` stays, when ``alt`` replaces it)."""
    reps = (rep, alt)
    fits = [_estimation_fit(P, r) for r in reps]
    npars = [_effects_npar(r) for r in reps]
    best_fit = int(np.argmin([f.se for f in fits]))
    crit = criterion_scores(fits, npars, n_eff=fits[best_fit].n_eff,
                            factor=P.settings.bic_factor)
    what = (f"{tried}, by the criterion: {name0} ({npars[0]} parameters, SE "
            f"{fits[0].se:.3g} %) 0; {name1} ({npars[1]} parameters, SE {fits[1].se:.3g} %) "
            f"{crit[1] - crit[0]:+.4g}")
    if not crit[1] < crit[0]:
        return rep.with_decision("loop", "", f"{what}: {verdicts[0]}")
    table = dict(alt.table)
    if "delta" in rep.table:
        table["delta"] = rep.table["delta"]
    kept = tuple(d for d in rep.decisions if d.stage != "validate")
    return replace(alt, table=table, decisions=kept + alt.decisions + (
        Decision("loop", "", f"{what}: {verdicts[1]}"),))


def _estimation_fit(P: Problem, rep: LoopReport):
    """How the updated model of ``rep`` follows the estimation (search) record: its
    :class:`greybox.metrics.OutputFit`; a one-effect nonlinear law simulated in full
    (:class:`greybox.plant_adapter.LawPlant` on its trace), not its linear surrogate."""
    plant = LinearPlant(rep.model.sys)
    if rep.effect.nonlinear and rep.trace is not None and len(rep.steps) <= 1:
        res = rep.trace.filter_result
        plant = LawPlant(res.sys, res.G, rep.trace.static, rep.model.sys)
    return _model_fit(P, plant)


def _model_fit(P: Problem, model):
    """The :class:`greybox.metrics.OutputFit` of ``model`` (a discrete ``StateSpace`` or a
    plant adapter) simulated on the estimation (search) record from its estimated
    initial state."""
    plant = LinearPlant(model) if isinstance(model, ct.StateSpace) else model
    with np.errstate(all="ignore"):  # a diverging simulation loses, it does not warn
        ysim = plant.simulate(P.us, plant.initial_state(P.ys, P.us))
    return output_fit(P.ys, ysim, skip=_Pass.SKIP)


def _sensor_first(P: Problem, rep: LoopReport) -> LoopReport:
    """Effects found in state equations where a sensor's law alone was an acceptable first
    effect: the loop run again with that sensor first (issue 27 item 5).

    A sensor's gain or offset makes d^ of the equations of the states near the one it
    reads look like an error there, and a law of those equations with more terms can
    beat the sensor's own law on the first pass (zoo state_sensor: a 4-term law of
    eq(v1), eq(v3) against output(p2)'s gain and offset; the damping error in eq(v5)
    then never traced, a nonlinear law ending the loop). When the first pass scored a
    sensor channel whose law alone passes the gate's SE drop, and no effect of ``rep``
    is a sensor's, that sensor is traced alone; if its law is an offset (with or without a
    gain: a linear model with an offset state, which later passes start from), the loop
    goes on from it over every channel, and the one criterion on the estimation record
    decides between the two explanations (:func:`_by_criterion`, every effect's
    parameters counted; a one-effect nonlinear law simulated in full)."""
    S = P.settings
    if not rep.updated or S.channels is not None or S.max_effects < 2 or \
            unstable_reason(P.nominal, P.y.shape[1]) or \
            (rep.effect.nonlinear and len(rep.steps) > 1):
        return rep
    sensors = {output_channel(P.sys, o).name: o for o in P.sys.output_labels}
    if any(st.channel in sensors for st in rep.steps):
        return rep
    limit = S.min_se_drop * rep.gate.get("se_estimation_nominal", np.nan)
    ok = [c for c in rep.candidates if c.channel in sensors and c.status == "ok" and
          c.kind == "static" and c.se_estimation < limit]
    if not ok:
        return rep
    sensor = output_channel(P.sys, sensors[min(ok, key=lambda c: c.se_estimation).channel])
    once = _first_then(P, replace(S, channels=[sensor]), S)
    tried = f"{sensor.name} first, then every channel"
    try:
        first = [once(P.sys, P.nominal, P.Q, (sensor,), False)]
        law = first[0].effect.law if first[0].updated else None
        if law is None or law.nonlinear or sensor_states(law) or law.output is None or \
                not any(term_kind(law.spec[j][1]).constant for j in np.flatnonzero(law.coef[0])):
            # (only an offset, with or without a gain: what a law of the equations can stand
            # for, and what the loop could not continue after before it became a state; a
            # lag on one of two outputs can stand for an input's lag, and the split and the
            # reorder try a lag)
            return rep.with_decision("loop", "", f"the effects tried with {tried}: the "
                                     "sensor's law alone is not an offset (with or without a "
                                     "gain) that passes the gate; the effects kept")
        alt = _loop(lambda *a: first.pop() if first else once(*a), P.sys, P.nominal, P.Q,
                    None, (sensor,), False, S.max_effects, P.dt,
                    _JointRefit(P), functools.partial(_refit_sensors, P))
    except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
        return rep.with_decision("loop", "", f"the effects tried with {tried}: failed ({e})")
    if not alt.updated or len(alt.steps) < 2 or alt.nonlinear is not None:
        why = ("the sensor's law alone fails the gate" if not alt.updated else
               "no second effect" if len(alt.steps) < 2 else "a nonlinear law after it")
        return rep.with_decision("loop", "", f"the effects tried with {tried}: {why}; "
                                             "the effects kept")
    return _by_criterion(P, rep, alt, f"the effects tried with {tried}", "as found", tried,
                         ("the effects kept as found", "the sensor first, a lower criterion"))


def _reordered(P: Problem, rep: LoopReport) -> LoopReport:
    """Effects in state equations found before a sensor's: the sensor tried first (issue 27).

    A sensor's error (a lag, a gain) colours d^ in the equations of the states it reads,
    and more the larger it is; a pass that traces those equations before the sensor fits
    that colour too (a filter of order 1 or 2 where an equation lacks one static term),
    and the sensor's law found after it cannot undo the choice (the joint refit refits
    the laws it was given, the re-trace redoes only the last). When the loop's effects
    are laws of state equations followed by one sensor's, the loop is run again as two
    passes (:func:`_two_passes`): that sensor's channel alone, then a linear static law
    of each of those equations on the updated model; the one criterion decides which
    explanation is kept (:func:`_by_criterion`)."""
    if not _may_retry(P, rep) or len(rep.steps) < 2:
        return rep
    by_name = {c.name: c for c in P.chans}
    chans = [by_name.get(st.channel) for st in rep.steps]
    if any(c is None for c in chans) or chans[-1].kind != "output" or \
            any(c.kind != "equation" for c in chans[:-1]) or \
            any(st.effect.nonlinear for st in rep.steps):
        return rep
    eqs = []
    for c in chans[:-1]:
        eqs += [(e,) for e in c.equations if (e,) not in eqs]
    sensor = chans[-1]
    return _as_two(P, rep, sensor, eqs,
                   f"the effects in {', '.join(c.name for c in chans[:-1])} and then "
                   f"{sensor.name} tried the other way round", "as found",
                   ("the effects kept as found", "the sensor first, a lower criterion"))


def _split_sensor(P: Problem, ch: Channel) -> Channel | None:
    """The sensor a split tries: the one whose own law explains the most of the nominal
    simulation error (:func:`greybox.trace.screen.screen_sensor_laws`), if it reads a
    state whose equation is in the channel ``ch`` (a law of the equations can reproduce a
    sensor's lag only there); None otherwise."""
    x0 = estimate_initial_state(P.nominal, P.ys, P.us)
    labels = list(P.sys.output_labels)
    scr = screen_sensor_laws(P.ys, simulate_output(P.nominal, P.us, x0), P.dt, labels)
    o = labels.index(scr.outputs[0])
    C = np.asarray(P.sys.C, dtype=float)
    states = list(P.sys.state_labels)
    if not any(C[o, states.index(e)] != 0 for e in ch.equations):
        return None
    return output_channel(P.sys, scr.outputs[0])


def _first_then(P: Problem, first: Settings, rest: Settings):
    """The ``once`` of a loop whose first pass runs with the settings ``first`` and every
    later pass with ``rest`` (a pass of one sensor, then the equations or every channel)."""
    calls: list[int] = []

    def once(sys_, nominal_, Q_, chans_, delta_) -> LoopReport:
        settings = rest if calls else first
        calls.append(1)
        return _Pass(replace(P, settings=settings), sys_, nominal_, Q_, chans_,
                     delta_).run()

    return once


def _two_passes(P: Problem, sensor: Channel, eqs: list) -> LoopReport | str:
    """The loop run as two passes: the channel ``sensor`` alone (a sensor's, an input's),
    then a linear static law of each of the equations ``eqs`` alone on the updated model
    (the one linear law they would replace is the alternative), both refitted jointly (a
    sensor lag's time constant is biased by the equation's error until then); why not, as
    a string, when it finds fewer than two effects."""
    once = _first_then(P, replace(P.settings, channels=[sensor]),
                       replace(P.settings, channels=eqs, max_order=0, nonlinear=False))
    try:
        alt = _loop(once, P.sys, P.nominal, P.Q, eqs, (sensor,),
                    False, 2, P.dt, _JointRefit(P),
                    functools.partial(_refit_sensors, P))
    except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
        return f"failed ({e})"
    if not alt.updated:
        return f"the law of {sensor.name} alone fails the gate"
    if len(alt.steps) < 2:
        return "no second effect"
    return alt


def _prepare(sys, y, u, y_val, u_val, *, Q, R, dt, channels, nonlinear, max_order, alpha,
             lags, delta, delta_max_order, parsimony, min_se_drop, bic_factor, progress,
             max_effects) -> Problem:
    """Check every argument of :func:`close_the_loop` once; the Problem and its Settings."""
    check_statespace(sys, "sys")
    lags = check_positive(lags, "lags", integer=True)
    if ct.isdtime(sys, strict=True):
        nominal = sys
        if dt is not None and abs(float(dt) - float(sys.dt)) > 1e-9 * float(sys.dt):
            raise ModelError(f"dt = {dt} disagrees with the discrete model's dt = {sys.dt}")
        dt = float(sys.dt)
    else:
        if dt is None:
            raise ModelError("sys is continuous-time; give the sampling period dt [s] of the "
                             "data so that it can be discretized (ZOH)")
        dt = check_positive(dt, "dt")
        nominal = discretize(sys, dt)
    n, m, p = nominal.nstates, nominal.ninputs, nominal.noutputs
    min_steps = max(200, 10 * (n + m) + 4 * lags)
    y, u, y_val, u_val = check_records(nominal, y, u, y_val, u_val, R, min_steps=min_steps,
                                       min_val_steps=max(100, 2 * lags + 2))
    Q = check_covariance(Q, n, "Q", definite=False)
    R = check_covariance(R, p, "R", definite=True)
    chans = resolve_channel_spec(sys, channels)
    if channels is None:  # a kinematic identity is a definition, never a candidate channel
        chans = _without_definitions(sys, chans)
    max_order = check_positive(max_order, "max_order", integer=True, allow_zero=True)
    if delta_max_order is not None:
        delta_max_order = check_positive(delta_max_order, "delta_max_order", integer=True)
    max_effects = check_positive(max_effects, "max_effects", integer=True)
    if max_order > 10 or (delta_max_order is not None and delta_max_order > 20):
        raise DataError(f"max_order = {max_order} (at most 10) and delta_max_order = "
                        f"{delta_max_order} (at most 20): higher orders cannot be identified "
                        f"reliably from one record")
    nonlinear, delta = check_flag(nonlinear, "nonlinear"), check_flag(delta, "delta")
    parsimony = check_parsimony(parsimony)
    alpha = check_positive(alpha, "alpha")
    min_se_drop = check_positive(min_se_drop, "min_se_drop")
    bic_factor = check_positive(bic_factor, "bic_factor")
    if not 0 < alpha < 1 or not 0 < min_se_drop <= 1 or not bic_factor > 0:
        raise DataError(f"need 0 < alpha < 1, 0 < min_se_drop <= 1, bic_factor > 0; found "
                        f"{alpha}, {min_se_drop}, {bic_factor}")
    ys, us = _search_record(y, u)  # the search's window of the estimation record (views)
    settings = Settings(alpha=alpha, lags=lags, parsimony=parsimony, min_se_drop=min_se_drop,
                        bic_factor=bic_factor, max_order=max_order, nonlinear=nonlinear,
                        delta=delta, delta_max_order=delta_max_order, max_effects=max_effects,
                        channels=channels)
    return Problem(sys=sys, nominal=nominal, y=y, u=u, y_val=y_val, u_val=u_val, ys=ys, us=us,
                   Q=Q, R=R, dt=dt, chans=chans, settings=settings,
                   tick=ProgressClock(progress))


def _screened_channels(P: Problem, sys, nominal, Q, chans, notes):
    """Above SCREEN_ABOVE states: the screened equations, their pairs, and the inputs; where
    the screen is not available, every equation and (first pass) the linked forces."""
    scr = screen_equations(sys, P.ys, P.us, Q=Q, R=P.R, dt=P.dt, skip=20)
    if not scr.available:
        # on the nominal model only: a later pass starts from a model holding an effect,
        # where the error left is small and each of n more candidates is one more chance
        # for a spurious effect to pass the gate (a joint-refit chain took a third effect
        # that raised its validation error)
        eqs = [c.equations[0] for c in chans if c.kind == "equation" and c.md == 1]
        forces = _traceable_linked_forces(sys, eqs) if sys is P.sys else []
        notes.append(Decision("screen", "", f"equation screen unavailable ({scr.reason}): "
                              "every single equation is traced (cost grows with n)" +
                              (f", and one force between each of the {len(forces)} pairs of "
                               "bodies the model links, along the link's direction"
                               if forces else "")))
        return tuple(chans) + tuple(forces)
    top = scr.ranked(SCREEN_TOP)
    best = max((scr.score[scr.states.index(t)] for t in top), default=0.0)
    top = [t for t in top if scr.score[scr.states.index(t)] >= SCREEN_REL * best]
    notes.append(Decision("screen", "", "equation screen (joint unknown-input filter): " +
                          ", ".join(f"eq({s}) z = {scr.score[scr.states.index(s)]:.3g}"
                                    for s in top) +
                          f"; {len(scr.states) - len(top)} other equations below"))
    keep = [c for c in chans if c.kind in ("input", "output") or
            (c.md == 1 and c.equations and c.equations[0] in top)]
    if not top and sys is P.sys:
        # no equation above the screen's threshold (positions only: its d^ is a second
        # difference of them): the inputs' own channels still, an input that enters one
        # equation included (otherwise that equation's channel stands for it), a few
        # traces where an actuator's error is the likeliest (zoo actuator_gain: a chain
        # of 9, positions only, F's gain 0.794 left unnamed at 52x the true model's error)
        B = np.asarray(sys.B, dtype=float)
        have = {c.name for c in keep}
        extra = [input_channel(sys, j) for j in range(sys.ninputs) if np.any(B[:, j] != 0)]
        keep += [c for c in extra if c.name not in have]
        notes.append(Decision("screen", "", "no equation above the screen's threshold: the "
                              "inputs' channels traced (" +
                              ", ".join(c.name for c in extra) + ")"))
    if nominal.noutputs >= 2:
        idx = sorted(list(sys.state_labels).index(s) for s in top)
        for a, i in enumerate(idx):
            for j in idx[a + 1:]:
                pair = resolve_channel_spec(sys, [(sys.state_labels[i],
                                                   sys.state_labels[j])])[0]
                # the pair, with the bodies' relative coordinates offered to its law
                # (a force between them); step 2a then traces one force along the
                # pair law's direction (the screen's own direction is too rough)
                keep.append(replace(pair, relative=relative_coordinates(sys, pair)))
                # and one force along the screen's direction, when it sees one (traced
                # after step 2a, and only when the pair law gives no force of its own)
                rows = [scr.states.index(sys.state_labels[q]) for q in (i, j)]
                g = direction(scr.coef[rows], np.ones(scr.coef.shape[1]))
                fch = force_channel(sys, pair, g) if g is not None and \
                    not _kinematic_in(sys, pair) else None
                if fch is not None and not _along_an_input(sys, fch):
                    keep.append(fch)
    if sys is P.sys:
        lone = _lone_forces(sys, top)
        if lone:
            keep += lone
            notes.append(Decision("screen", "", "an equation ranked without the bodies it is "
                                  "linked to: its force with each, along the link's direction "
                                  "(" + ", ".join(c.name for c in lone) + ")"))
    return _without_definitions(P.sys, keep)


def _lone_forces(sys: ct.StateSpace, top) -> list[Channel]:
    """The forces between each screened equation and the bodies the model links it to
    (:func:`_traceable_linked_forces`), for an equation the screen ranks without any of
    them. A force between two bodies acts on both, but the screen may see it in one only
    (the lighter or the more moving body; positions only, where d^ is a second difference):
    zoo cubic_force 20261207 #1 and #2 ranked one body of the spring's pair, and the pair
    was never traced. Each force is one more candidate, chosen or not by the criterion.
    Only towards a body whose own state no output reads: where one does, that body's d^
    enters the outputs at relative degree 1 and the screen sees it as well as the first
    body's, so its not ranking it is evidence against the force."""
    if ct.isdtime(sys, strict=True) or not top:
        return []
    A = np.asarray(sys.A, dtype=float)
    read = np.any(np.asarray(sys.C, dtype=float) != 0, axis=0)
    labels = list(sys.state_labels)
    defs = set(definitions(sys))
    out: list[Channel] = []
    for s in top:
        a = labels.index(s)
        near = set()
        for c in np.flatnonzero(A[a]):
            if labels[c] in defs:  # a position: its body's equation is the velocity's
                c = int(np.flatnonzero(A[c])[0])
            if c != a and labels[c] not in defs:
                near.add(c)
        forces = [(b, f) for b in sorted(near)
                  for f in _traceable_linked_forces(sys, [s, labels[b]])]
        if any(labels[b] in top for b, _ in forces):
            continue  # ranked with a body it is linked to: that pair is traced
        have = {o.name for o in out}
        out += [f for b, f in forces if not read[b] and f.name not in have]
    return out


def _joint(P: Problem, passes, final, Qf, always: bool = False):
    """Refit all effects at once (greybox.trace.joint); None if some cannot be, or if no
    effect has a coefficient in A or B (sensors' gains and offsets: each refitted on its
    own by :func:`_refit_sensors`).

    ``passes``: (base model, channel, effect) per effect; ``Qf`` the final Q. The
    validation row is None where the refit does not improve on ``final`` (a lower
    estimation SE, or fewer coefficients within 1 %), unless ``always`` (an alternative
    set compared with another refit by the criterion, not with its own start).
    """
    effs = [joint_effect(base, ch, eff.dynamic_law or eff.law) for base, ch, eff in passes]
    if any(e is None for e in effs) or ct.isdtime(final, strict=True) or \
            not has_joint_parameters(effs):
        return None
    x0 = estimate_initial_state(discretize(final, P.dt), P.y, P.u)
    jr = refine_jointly(effs, final, P.y, P.u, Q=Qf, R=P.R, dt=P.dt, x0=x0, k0=20)
    jr0 = _held_sensors_refitted(P, jr, passes)
    jr = without_dead_states(jr0, effs)
    alt = integrators_as_positions(jr0, effs, P.dt)
    if alt is not jr0:  # the pole at 0 against its fitted value, by the one criterion
        alt = without_dead_states(alt, effs)
        jr = alt if _JointRefit(P).prefers(alt, jr)[0] else jr
    if not always and not (jr.se_after < jr.se_before or
                           (jr.npar_after < jr.npar_before and
                            jr.se_after <= 1.01 * jr.se_before)):
        return jr, None
    S = P.settings
    row = validate_model(jr.model.sys, P.y_val, P.u_val, Q=jr.model.Q, R=jr.model.R,
                         x0="estimate", name="updated", lags=S.lags, alpha=S.alpha, skip=20)
    return jr, row


@dataclass(frozen=True)
class _JointRefit:
    """The loop's joint refit of its effects (:func:`_joint`, called as ``joint(passes,
    final, Qf)``) and the one criterion that compares two refits (:meth:`prefers`)."""

    P: Problem

    def __call__(self, passes, final, Qf, always: bool = False):
        return _joint(self.P, passes, final, Qf, always)

    def prefers(self, new, old) -> tuple[bool, str]:
        """Whether the refit ``new`` (JointRefinement) beats ``old`` by the one criterion
        (:func:`greybox.metrics.criterion_scores` at ``bic_factor``, every effect's
        parameters counted, on the estimation record), and the comparison in words: an
        equal fit with fewer terms wins (a lag the data cannot see, dropped in one refit
        and kept in the other)."""
        P = self.P
        fits = [_model_fit(P, jr.model.sys) for jr in (new, old)]
        npars = [sum(int(law.npar) for law in jr.laws) for jr in (new, old)]
        best = int(np.argmin([f.se for f in fits]))
        crit = criterion_scores(fits, npars, n_eff=fits[best].n_eff,
                                factor=P.settings.bic_factor)
        return bool(crit[0] < crit[1]), (
            f"{npars[0]} parameters, SE {fits[0].se:.3g} %, criterion {crit[0] - crit[1]:+.4g} "
            f"against {npars[1]} parameters, SE {fits[1].se:.3g} %")


def _held_sensors_refitted(P: Problem, jr, passes):
    """The joint refit ``jr`` with the static sensor laws it held (a gain, an offset: they
    act on C, not on A and B) refitted on its model's simulation, its model's rows of C
    and D with them (:func:`_sensor_refit`)."""
    laws = list(jr.laws)
    for k, (base, ch, _) in enumerate(passes):
        new = _sensor_refit(P, ch, laws[k], base, jr.model, [], "the joint refit")
        if new is laws[k]:
            continue
        laws[k] = new
        jr = replace(jr, laws=tuple(laws),
                     model=replace(jr.model, sys=_with_sensor_row(jr.model.sys, new, base)),
                     continuous=_with_sensor_row(jr.continuous, new, base))
    return jr


# --------------------------------------------------------------------------- the stages
@dataclass(frozen=True)
class Settings:
    """The options of :func:`close_the_loop`, checked once at the boundary (see there)."""

    alpha: float
    lags: int
    parsimony: float
    min_se_drop: float
    bic_factor: float
    max_order: int
    nonlinear: bool
    delta: bool
    delta_max_order: int | None
    max_effects: int
    channels: object = None  # the user's channel spec; None: every channel


@dataclass(frozen=True)
class Problem:
    """One call's checked data: the model as given and discretized, the records, noise.

    ``y, u`` (noutputs/ninputs, nsteps) are the estimation record, ``ys, us`` its
    search window (views of the first ``SEARCH_WINDOW`` samples), ``y_val, u_val``
    the validation record; ``chans`` the candidate channels of the first pass.
    """

    sys: ct.StateSpace = field(repr=False)
    nominal: ct.StateSpace = field(repr=False)
    y: np.ndarray = field(repr=False)
    u: np.ndarray = field(repr=False)
    y_val: np.ndarray = field(repr=False)
    u_val: np.ndarray = field(repr=False)
    ys: np.ndarray = field(repr=False)
    us: np.ndarray = field(repr=False)
    Q: np.ndarray = field(repr=False)
    R: np.ndarray = field(repr=False)
    dt: float
    chans: tuple = field(repr=False)
    settings: Settings
    tick: object = field(repr=False)


@dataclass(frozen=True)
class Residual:
    """Stage 1 of a pass: the nominal model's residual on the estimation record.

    ``white`` the Ljung-Box test of its one-step innovations (from sample ``k0``),
    ``x0n`` its initial state, ``se_nom`` its SE (PE when ``unstable``) on the
    search window [%], ``val_nom`` its validation row, ``crit`` the stated
    criterion, ``t_pass`` when the pass started (:func:`time.monotonic`),
    ``sensors`` the outputs whose constant offset alone explains the
    innovations' mean (:func:`_offset_sensors`).
    """

    white: WhitenessTest
    k0: int
    x0n: np.ndarray = field(repr=False)
    se_nom: float
    val_nom: ModelValidation = field(repr=False)
    unstable: str | None
    crit: str
    nominal_model: UpdatedModel = field(repr=False)
    t_pass: float
    fit: OutputFit | None = field(default=None, repr=False)
    sensors: tuple[str, ...] = ()


@dataclass(frozen=True)
class Verdict:
    """Stage 3 of a pass: the chosen candidate as an effect, its model and the gate's call."""

    effect: Effect
    model: UpdatedModel = field(repr=False)
    kind: str
    passed: bool


class _Pass:
    """One pass of close the loop on the model ``sys``: residual, trace, choose, gate,
    before/after. Stages are methods; what they decide is kept in ``cands`` (every
    candidate's score, for the report), ``scored`` (the Candidates in play) and
    ``decisions`` (the decision trail, :class:`greybox.records.Decision`)."""

    SKIP = 20  # leading samples left out of SE, PE and whiteness (the filters' transient)

    def __init__(self, P: Problem, sys, nominal, Q, chans, delta: bool):
        self.P, self.S = P, P.settings
        self.sys, self.nominal, self.Q, self.chans, self.delta = sys, nominal, Q, chans, delta
        self.cands: list[CandidateScore] = []
        self.scored: list[Candidate] = []
        self.decisions: list[Decision] = []
        self.gate: dict = {}
        self.n_eff = None  # the choice's effective samples, once it is made
        self.unstable = unstable_reason(nominal, P.y.shape[1])
        self.big = P.settings.channels is None and nominal.nstates > SCREEN_ABOVE
        self._enough = None  # (the best static candidate, whether it leaves white innovations)
        self._prune_tried: set[int] = set()  # ids of the traces pruned, or pruned from

    def run(self) -> LoopReport:
        """The stages in order."""
        r = self.residual()
        if r.white.all_white:
            self.gate["passed"] = {"whiteness": False}
            return self._no_update(r, "no significant model error: the nominal one-step "
                                      f"residuals are white and zero-mean on every output "
                                      f"(Ljung-Box, {self.S.lags} lags, and the mean's t-test; "
                                      f"all p >= {self.S.alpha:g})", False)
        self.trace_channels(r)
        self.forces()
        self.higher_orders()
        self.sparse_laws(r)
        self.input_lags(r)
        chosen = self.choose()
        if chosen is None:
            self.gate["passed"] = {"whiteness": True, "trace": False}
            return self._no_update(r, "model error detected, but no candidate channel could "
                                      "explain it (see candidates)", True,
                                   cands=self.cands)
        v = self.judge(r, chosen)
        if not v.passed:
            failed = [k for k, ok in self.gate["passed"].items() if not ok]
            return self._no_update(r, f"model error detected (residual not white), but the best "
                                      f"candidate ({chosen.trace.channel.name}, {v.kind}) failed "
                                      f"the gate: {', '.join(failed)}; model unchanged", True,
                                   cands=self.cands, tr=chosen.trace)
        table = self.validate(r, chosen.trace, v)
        return self.report(r, chosen.trace, v, table)

    # ------------------------------------------------------------------ helpers
    def fit_error(self, sys_, Q_, R_, ysim=None, ypred=None) -> OutputFit:
        """How a model follows y on the search window: its SE (or PE, for an unstable
        nominal) [%] per output and the effective samples of its error
        (:class:`greybox.metrics.OutputFit`: what the criterion reads)."""
        ys, us, plant = self.P.ys, self.P.us, LinearPlant(sys_)
        if not self.unstable:
            return output_fit(ys, ysim() if ysim is not None else plant.simulate(
                us, plant.initial_state(ys, us)), skip=self.SKIP)
        try:
            with np.errstate(all="ignore"):  # a diverging predictor loses, it does not warn
                yp = ypred() if ypred is not None else plant.filter(ys, us, Q=Q_, R=R_).y_pred
        except (GreyboxError, np.linalg.LinAlgError, ValueError, FloatingPointError):
            yp = np.full(ys.shape, np.nan)
        return output_fit(ys, yp[:, :ys.shape[1]], skip=self.SKIP)

    def _trace(self, ch, **kw):
        P = self.P
        return trace_channel(self.sys, ch, P.ys, P.us, Q=self.Q, R=P.R, dt=P.dt, **kw)

    def note(self, stage: str, subject: str, reason: str) -> None:
        """Record a decision of ``stage`` about ``subject`` (a channel, or "": the model)."""
        self.decisions.append(Decision(stage, subject, reason))

    def _no_update(self, r: Residual, msg, detected, cands=(), effect=None, tr=None,
                   ch=None) -> LoopReport:
        table = {"nominal": r.val_nom, "updated": r.val_nom}
        return LoopReport(model_error_detected=detected, updated=False, message=msg,
                          residual=r.white, effect=effect or Effect(kind="none"), channel=ch,
                          candidates=tuple(cands), gate=self.gate, criterion=r.crit,
                          nominal=self.nominal, model=r.nominal_model, table=table, trace=tr,
                          decisions=tuple(self.decisions))

    # ------------------------------------------------------------------ 1. residual
    def residual(self) -> Residual:
        """1. The nominal model's one-step residual, its SE and its validation row."""
        P, S, nominal, skip = self.P, self.S, self.nominal, self.SKIP
        t_pass = time.monotonic()  # the delta baseline's budget: this pass's time
        crit = CRITERION_PE if self.unstable else CRITERION
        P.tick("residual of the nominal model", 0, 1)
        kf = LinearPlant(nominal).filter(P.y, P.u, Q=self.Q, R=P.R)
        k0 = kf.settled(skip)
        white = innovation_test(kf.innovations[:, k0:], S.lags, alpha=S.alpha)
        sensors = _offset_sensors(nominal, kf, k0, white, S.alpha, self.decisions) \
            if S.channels is None else ()
        x0n = estimate_initial_state(nominal, P.y, P.u)
        se_nom = _se(P.ys, kf.y_pred[:, :P.ys.shape[1]], skip) if self.unstable else \
            _se(P.ys, simulate_output(nominal, P.us, x0n), skip)  # on the search window
        kf = None  # its histories (~60 MB at 1e6 samples) would stay alive through the pass
        nominal_model = UpdatedModel(sys=nominal, Q=self.Q, R=P.R, order=nominal.nstates,
                                     kind="nominal")
        val_nom = validate_model(nominal, P.y_val, P.u_val, Q=self.Q, R=P.R, x0="estimate",
                                 name="nominal", lags=S.lags, alpha=S.alpha, skip=skip)
        self.gate.update({"whiteness_pvalue": white.pvalue, "mean_pvalue": white.mean_pvalue,
                          "alpha": S.alpha, "se_estimation_nominal": se_nom,
                          "measure": "PE" if self.unstable else "SE"})
        if self.unstable:
            self.gate["measure_reason"] = f"nominal: {self.unstable}"
        P.tick("residual of the nominal model", 1, 1)
        return Residual(white=white, k0=k0, x0n=x0n, se_nom=se_nom, val_nom=val_nom,
                        unstable=self.unstable, crit=crit, nominal_model=nominal_model,
                        t_pass=t_pass, fit=None if white.all_white else
                        self.fit_error(nominal, self.Q, P.R), sensors=sensors)

    # ------------------------------------------------------------------ 2. candidates
    def score(self, tr, narrowable: bool = False) -> None:
        """Score a trace's static and dynamic laws by their estimation SE (candidates).
        A static law of several equations with a component that holds no term is the
        same as a smaller channel's and is not scored, unless ``narrowable`` (the
        criterion's prune emptied it: the step is stated as the law of the other
        equations at the end, :func:`_narrowed`)."""
        tr = _light(tr)  # every candidate's full filter record would be kept to the end
        ch, ys, us = tr.channel, self.P.ys, self.P.us
        self.decisions.extend(Decision("trace", ch.name, s) for s in tr.notes)
        dead = tr.static is not None and ch.md > 1 and bool(
            np.any(np.all(tr.static.coef == 0, axis=1))) and not (
            narrowable and _narrowable(ch, tr.static))
        if dead:  # a component explains nothing: the same as a smaller channel
            self.cands.append(CandidateScore(ch.name, "static", 0, np.inf, tr.static.npar,
                                             "redundant", "a component of d has no term"))
        elif tr.static_model is not None and tr.static.npar > 0:
            sm = tr.static_model
            if tr.static.nonlinear:
                res = tr.filter_result
                plant = LawPlant(res.sys, res.G, tr.static, sm.sys)
                x0 = plant.initial_state(ys, us)
                fit = self.fit_error(sm.sys, sm.Q, sm.R, ysim=lambda: plant.simulate(us, x0),
                                     ypred=lambda: ekf_predict_with_law(
                                         res.sys, res.G, tr.static, ys, us, x0, Q=sm.Q,
                                         R=sm.R))
            else:
                fit = self.fit_error(sm.sys, sm.Q, sm.R)
            brk = tr.static.breakpoints
            self.cands.append(CandidateScore(ch.name, "static", 0, fit.se, tr.static.npar, "ok",
                                             f"with {brk[0]}" if brk else ""))
            self.scored.append(Candidate(fit.se, tr.static.npar, tr, "static", fit=fit))
        if tr.dynamic_model is not None:
            dm, sub = tr.dynamic_model, tr.dynamic
            fit = self.fit_error(dm.sys, dm.Q, dm.R)
            self.cands.append(CandidateScore(ch.name, "dynamic", sub.order, fit.se, sub.npar,
                                             "ok"))
            self.scored.append(Candidate(fit.se, sub.npar, tr, "dynamic", fit=fit))

    def trace_channels(self, r: Residual) -> None:
        """2. Trace every candidate channel: static laws and order-1 dynamics."""
        P, S = self.P, self.S
        first_max = min(S.max_order, 1)
        if self.big:
            self.chans = _screened_channels(P, self.sys, self.nominal, self.Q, self.chans,
                                            self.decisions)
            # unstructured subsystems (driven by all n + m signals) cost O(n) each and read
            # as noise: above SCREEN_ABOVE states only the sparse first-order law is tried
            first_max = 0
        have = {c.output for c in self.chans if c.kind == "output"}
        offered = list(r.sensors)
        if not have and self.S.channels is None:  # no sensor offered by default: by evidence
            offered += [o for o in _sensor_law_candidates(
                self.nominal, self.P.ys, self.P.us, r.x0n, self.P.dt, r.white, r.unstable,
                self.decisions) if o not in offered]
        held = set(self.sys.state_labels)  # an output whose earlier sensor law has an
        # offset state gets no second law (two offsets on one output: not identifiable;
        # its law is refitted after each later effect instead, _refit_sensors)
        self.chans = tuple(self.chans) + tuple(output_channel(self.sys, o) for o in offered
                                               if o not in have and f"{o}_offset" not in held)
        defs = definitions(P.sys) if S.channels is None else []
        if defs:
            self.note("screen", "", "kinematic identities, definitions rather than candidate "
                                    "channels: " + ", ".join(f"eq({d})" for d in defs))
        self.screen_forces = [c for c in self.chans if c.kind == "force"] if self.big else \
            self._linked_forces()
        for kc, ch in enumerate(self.chans):
            P.tick("trace candidate channels", kc, len(self.chans))
            if ch in self.screen_forces:
                continue
            try:
                tr = self._trace(ch, nonlinear=S.nonlinear, max_order=first_max)
            except (GreyboxError, np.linalg.LinAlgError) as e:
                self.cands.append(CandidateScore(ch.name, "-", 0, np.inf, 0, "failed", str(e)))
                continue
            if tr.status != "ok":
                self.cands.append(CandidateScore(ch.name, "-", 0, np.inf, 0, "skipped",
                                                 tr.reason))
                continue
            self.score(tr)
            if S.nonlinear and whole_inputs(self.sys, ch):
                self.static_trace(ch, breaks=True)
        P.tick("trace candidate channels", len(self.chans), len(self.chans))

    def static_trace(self, ch_, breaks: bool = False):
        """The static trace of one channel (a force, a group), scored; or None. With
        ``breaks``: the law offered a dead zone and a saturation of the inputs whose whole
        effect the channel carries, scored only if it selects one."""
        try:
            tr_ = self._trace(ch_, nonlinear=self.S.nonlinear, max_order=0, breaks=breaks)
        except (GreyboxError, np.linalg.LinAlgError) as e:
            self.note("trace", ch_.name, str(e))
            return None
        if tr_.status != "ok":
            if tr_.reason:
                self.note("trace", ch_.name, tr_.reason)
            return None
        if breaks and not (tr_.static is not None and tr_.static.breakpoints):
            self.note("trace", ch_.name, "no input dead zone or saturation selected")
            return None
        self.score(tr_)
        return next((t.trace for t in self.scored[::-1] if t.trace.channel == ch_), None)

    def retraced(self, pick: Candidate) -> Candidate:
        """The Candidate ``pick``, or the force traced again along its refitted direction
        if that scores better by the criterion, up to _MAX_RETRACE."""
        for _ in range(_MAX_RETRACE):
            tr = pick.trace
            if not (pick.kind == "static" and tr.refined_G is not None):
                break
            # the force's law contradicts its direction (taken from a noisy pair law):
            # trace it again along the refitted one (law, filter and model then agree);
            # the new law can refit the direction again (a wrong first law moves it part
            # way)
            n_before = len(self.scored)
            try:
                rtr = self._trace(replace(tr.channel, G=tr.refined_G),
                                  nonlinear=self.S.nonlinear, max_order=0)
                if rtr.status == "ok":
                    self.score(rtr)
            except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
                # (ValueError: a direction refitted again and again can run away until
                # the filter's matrices overflow; that retrace is not taken)
                self.note("generate", tr.channel.name,
                          f"traced again along its refitted direction: {e}")
            new = [c for c in self.scored[n_before:] if c.kind == "static" and c.fit is not None]
            crit = self._criterion([pick, *new]) if new else []
            better = [c for c, k in zip(new, crit[1:]) if k < crit[0]]
            if not better:
                break
            pick = better[0]
        return pick

    def _linked_forces(self) -> list[Channel]:
        """A small model's forces between the bodies it links, along the link's direction,
        for the pairs of equations it traces (first pass, default channels): traced in 2a
        where the pair's law gives no force of its own, as the screen's forces are for a
        larger model. A pair's law in the two bodies' own states cannot hold a nonlinear
        force of their relative coordinate (a cubic spring: linear terms in p1 and p2)."""
        if self.S.channels is not None or self.sys is not self.P.sys:
            return []
        pairs = {frozenset(c.equations) for c in self.chans if c.kind == "equation" and
                 c.md == 2}
        eqs = sorted({e for p in pairs for e in p})
        return [f for f in _traceable_linked_forces(self.sys, eqs)
                if frozenset(f.equations) in pairs]

    def forces(self) -> None:
        """2a. One force inside a pair of equations: md = 1 along the law's direction, with
        the bodies' relative coordinates offered to the law (PAPER_NOTES §9.6)."""
        sys, u = self.sys, self.P.u
        for se_, tr_, kind_ in [(c.se, c.trace, c.kind) for c in self.scored]:
            if kind_ != "static" or tr_.channel.md != 2 or tr_.channel.kind != "equation":
                continue
            res_ = tr_.filter_result
            k0s, Ns = res_.settled(20), res_.d_est.shape[1] - 1
            g = tr_.static.direction(res_.x_filt[:, k0s:Ns], u[:, k0s:Ns])
            if g is None or np.min(np.abs(g)) <= 1e-9:
                # (a pair law with no term in one equation acts in the other alone: that
                # equation's own law, traced on its own, not a force between two bodies)
                continue
            if _kinematic_in(sys, tr_.channel):
                continue  # a force acts on momentum equations, not on dp/dt = v
            fch = force_channel(sys, tr_.channel, g)
            if _along_an_input(sys, fch):
                continue  # the input's own channel says the same, and names the input
            self.static_trace(fch)
        # ... and along the screen's direction (rougher) where the pair law gave no force
        for fch in self.screen_forces:
            if not any(t.trace.channel.kind == "force" and
                       set(t.trace.channel.equations) == set(fch.equations)
                       for t in self.scored):
                self.static_trace(fch)
        # ... and the best force along its refitted direction already here (not only once
        # chosen, below): above SCREEN_ABOVE states the evidence for dynamics in 2b is that
        # the best static law leaves coloured innovations, and a force along its first,
        # noisy direction leaves them coloured where the refitted one leaves them white (the
        # 32-state chain, positions measured: a 30 s sparse dynamic fit for nothing)
        forces = [t for t in self.scored if self.big and t.kind == "static" and
                  t.trace.channel.kind == "force" and np.isfinite(t.se)]
        if forces:
            self.retraced(min(forces, key=lambda t: t.se))

    def higher_orders(self) -> None:
        """2. Higher-order subsystems for the two channels that explain the data best."""
        S = self.S
        if not (S.max_order >= 2 and self.scored and not self.big):
            return
        ranked = []
        for se_, tr_ in [(c.se, c.trace) for c in sorted(self.scored, key=lambda c: c.se)]:
            if tr_.channel not in ranked and np.isfinite(se_):
                ranked.append(tr_.channel)
        for kc, ch in enumerate(ranked[:2]):
            self.P.tick("higher-order subsystems", kc, min(2, len(ranked)))
            if ch.md > 1 or ch.kind == "output":
                continue  # md = 2 already gives 2 states at order 1; a sensor law has no
                # subsystem (traced again, its notes would be listed twice)
            try:
                tr = self._trace(ch, nonlinear=False, max_order=S.max_order, min_order=2)
            except (GreyboxError, np.linalg.LinAlgError) as e:
                self.note("generate", ch.name, f"dynamic order >= 2 failed: {e}")
                continue
            tr = replace(tr, static=None, static_model=None)
            self.score(tr)

    # ------------------------------------------------------------------ 2b, 2c. sparse laws
    def sparse_laws(self, r: Residual) -> None:
        """2b. Sparse first-order laws in continuous time for the best one-component
        channels; 2c. one state shared by a pair of equations or a screened group."""
        S, sys = self.S, self.sys
        if not (S.max_order >= 1 and self.scored and not ct.isdtime(sys, strict=True)
                and not self.unstable and not (self.big and self.static_is_enough(r))):
            return
        done = set()
        for cand in sorted(self.scored, key=lambda c: c.se):
            se_, tr_ = cand.se, cand.trace
            ch = tr_.channel
            if len(done) >= (1 if self.big else 2) or ch in done or ch.md != 1 or \
                    not np.isfinite(se_) or ch.kind == "output":
                continue
            done.add(ch)
            se_static = self._best_se(ch, "static")
            se_dyn = self._best_se(ch, "dynamic")
            if not self.big and np.isfinite(se_dyn) and not se_dyn < SPARSE_IF * se_static:
                continue  # no evidence of dynamics in this channel: the static law stands
            self._sparse(tr_)
        # one state shared by a pair of equations along no fixed direction (a thermal
        # mass between two bodies): the best pair with evidence of dynamics
        self.white_shared = []  # the groups whose first-order shared law leaves white innovations
        tried = None
        for cand in sorted(self.scored, key=lambda c: c.se):
            se_, tr_, kind_ = cand.se, cand.trace, cand.kind
            ch = tr_.channel
            if self.big or ch.md != 2 or ch.kind != "equation" or not np.isfinite(se_) or \
                    kind_ != "dynamic":
                continue
            se_static = self._best_se(ch, "static")
            if not se_ < se_static:
                continue
            # the evidence rule of the screened groups below: a static law that already
            # leaves white innovations needs no hidden state (on a 2-state model missing
            # a spring, the shared fit cost 4.6 s of 10 s and returned nothing)
            if not self.static_is_enough(r):
                self._shared(tr_, r)
            tried = ch
            break
        # and the pair whose static law fits best, where no pair's unstructured fit showed
        # dynamics there (a dense fit of 2 x (n + m) drivers can miss one hidden state)
        self._shared_best_pair(r, tried)
        self._shared_with_linked(r)
        # above SCREEN_ABOVE states there is no unstructured fit to show dynamics (the
        # best static law left the innovations coloured, see _static_is_enough): the
        # screen's group of equations (a hidden body touching 2-4 bodies) and the best
        # pair's static trace
        for gtr in (_shared_groups(sys, self.chans, self.scored, self.static_trace)
                    if self.big else ()):
            if not self._shared(gtr, r):
                break

    def input_lags(self, r: Residual) -> None:
        """2d. Each input's actuator lag: its channel's first-order law driven by the input
        alone (:func:`greybox.trace.dynamic.fit_input_lag`) and, with ``max_order >= 2``,
        its second-order one (the actuator's own mode,
        :func:`greybox.trace.shared_order2.fit_input_lag2`, where the first-order lag
        passes the gate's SE drop), fitted by output error and scored with the rest. It needs no evidence of dynamics from d^ (through a delayed
        channel d^ is mostly estimation noise and the unstructured fit there diverged: a
        chain measured in part) and is one law where a one-input plant shows the same lag
        on every output. Not for an input whose column of B an earlier pass changed."""
        P, S, sys = self.P, self.S, self.sys
        if not (S.max_order >= 1 and sys.ninputs and not ct.isdtime(sys, strict=True)
                and not self.unstable):
            return
        B, B0 = np.asarray(sys.B, dtype=float), np.asarray(P.sys.B, dtype=float)
        for j in range(sys.ninputs):
            if not np.allclose(B[:B0.shape[0], j], B0[:, j], rtol=1e-9, atol=0.0):
                continue  # an earlier effect changed the input's path (a static law's
                # feedthrough of it): B[:, j] no longer names how the input reaches the plant
            # a traced channel that carries the input's whole effect (its own; or the one
            # equation it enters), else the input's channel traced here; not where a big
            # model's equation screen left that one equation out (the screen found no
            # error there, and the lag's d enters it: at n = 32 the trace and fits cost
            # 10 s of 28)
            carriers = [c.trace for c in self.scored if j in whole_inputs(sys, c.trace.channel)]
            tr_ = next((t for t in carriers if t.channel.kind == "input"),
                       carriers[0] if carriers else None)
            if tr_ is None and (S.channels is not None or self.big) and not any(
                    c.kind == "input" and c.input == sys.input_labels[j] for c in self.chans):
                continue  # (the user's channels, or a pass of one sensor: no other channel)
            ch = tr_.channel if tr_ is not None else input_channel(sys, j)
            try:
                if tr_ is None:
                    tr_ = self._trace(ch, nonlinear=False, max_order=0)
                    if tr_.status != "ok":
                        continue
                    tr_ = _light(tr_)
                res_, k0s, _, _ = _sparse_start(tr_)
                kw = dict(Q=self.Q, R=P.R, dt=P.dt, x0=res_.x_filt[:, 0], k0=k0s)
                dl = fit_input_lag(sys, ch, j, P.y, P.u, **kw)
                se1 = self._input_lag(tr_, dl, j)
                # the actuator's own mode, where the first-order lag already passes the
                # gate's SE drop (the input's path is where the error is)
                if S.max_order >= 2 and se1 < S.min_se_drop * r.se_nom:
                    self._input_lag(tr_, fit_input_lag2(
                        sys, ch, j, P.y, P.u, tau=dl.tau, **kw), j)
            except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
                self.note("generate", ch.name, f"actuator lag failed: {e}")

    def _input_lag(self, tr_, dl, j: int) -> float:
        """Score input j's lag law ``dl`` (order 1 or 2; None: nothing) on ``tr_``'s
        channel; its SE [%] (inf for None)."""
        if dl is None:
            return np.inf
        fit = self.fit_error(dl.model.sys, dl.model.Q, dl.model.R)
        order = getattr(dl, "order", 1)
        self.cands.append(CandidateScore(tr_.channel.name, "dynamic (sparse)", order, fit.se,
                                         dl.npar, "ok", f"{self.sys.input_labels[j]} alone: "
                                         f"an actuator lag of order {order}"))
        self.scored.append(Candidate(fit.se, dl.npar, tr_, "sparse", dl, fit=fit))
        return fit.se

    def _sparse(self, tr_) -> None:
        """2b for one channel: its sparse first-order law, scored."""
        P, ch = self.P, tr_.channel
        res_, k0s, Ns, pole0 = _sparse_start(tr_)
        try:
            dl = fit_sparse_dynamic(self.sys, ch, res_.x_filt[:, k0s:Ns], res_.d_est[:, k0s:Ns],
                                    P.y, P.u, Q=self.Q, R=P.R, dt=P.dt, x0=res_.x_filt[:, 0],
                                    k0=k0s, pole=pole0, d_noise=_d_noise(res_))
        except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
            self.note("generate", ch.name, f"sparse dynamic law failed: {e}")
            return
        if dl is not None:
            fit = self.fit_error(dl.model.sys, dl.model.Q, dl.model.R)
            self.cands.append(CandidateScore(ch.name, "dynamic (sparse)", 1, fit.se, dl.npar,
                                             "ok"))
            self.scored.append(Candidate(fit.se, dl.npar, tr_, "sparse", dl, fit=fit))
        if self.S.max_order >= 2 and not self.big:
            self._hidden_part(tr_, dl, res_, k0s)

    def _hidden_part(self, tr_, dl, res_, k0s) -> None:
        """2b, order 2: a hidden part attached to the body of a one-state equation, driven
        by that state alone (:func:`greybox.trace.shared_order2.fit_hidden_part2`), from
        the poles of the channel's unstructured second-order law and around the sparse
        first-order law's pole; scored."""
        P, ch = self.P, tr_.channel
        starts = []
        sub = tr_.dynamic
        if sub is not None and sub.order == 2:
            with np.errstate(all="ignore"):
                p = np.log(np.linalg.eigvals(sub.Ad).astype(complex)) / P.dt
            starts.append((p[0], p[1]))
        a = getattr(dl, "pole", None)
        if a is not None and np.isfinite(a) and a < 0:
            starts += [(a, 5.0 * a), (a * (0.3 + 0.95j), a * (0.3 - 0.95j))]
        if not starts:
            return
        try:
            dl2 = fit_hidden_part2(self.sys, ch, P.y, P.u, Q=self.Q, R=P.R, dt=P.dt,
                                   x0=res_.x_filt[:, 0], k0=k0s, poles=starts)
        except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
            self.note("generate", ch.name, f"hidden second-order part failed: {e}")
            return
        if dl2 is None:
            return
        if dl2.undetermined_pole:
            # a real pole whose interval holds 0: an integrator of a state the model holds
            # already (a Maxwell element's spring read as s/(s (s + 1)) v2), a first-order
            # law in another form, not a hidden second-order part
            self.note("generate", ch.name, "hidden second-order part not offered: a pole "
                      "the data do not determine (" + dl2.formula.split("poles ")[-1] + ")")
            return
        fit = self.fit_error(dl2.model.sys, dl2.model.Q, dl2.model.R)
        state = ch.equations[0]
        self.cands.append(CandidateScore(ch.name, "dynamic (sparse)", 2, fit.se, dl2.npar, "ok",
                                         f"{state} alone: a hidden part attached to its body"))
        self.scored.append(Candidate(fit.se, dl2.npar, replace(tr_), "sparse", dl2, fit=fit))

    def _shared_best_pair(self, r: Residual, tried) -> None:
        """2c. One state shared by the pair of equations whose static law has the lowest
        estimation error (unless it is ``tried``), when the best static law leaves
        coloured innovations."""
        pairs = [c for c in self.scored if c.kind == "static" and c.trace.channel.md == 2 and
                 c.trace.channel.kind == "equation" and np.isfinite(c.se)]
        if self.big or not pairs:
            return
        best = min(pairs, key=lambda c: c.se).trace
        if best.channel != tried and not self.static_is_enough(r):
            self._shared(best, r)

    def _shared_with_linked(self, r: Residual) -> None:
        """2c where no pair of equations was traced (the equation screen unavailable:
        single equations and the forces between linked bodies only): the best one-equation
        law with evidence of dynamics (its first-order law fits better than its static one)
        tried as one first-order state shared with each body a force links its equation to,
        driven by the two bodies' own states (a hidden body between them: drivers from
        elsewhere let it absorb another effect), the pair traced first (its static law not
        a candidate; at most ``_LINKED_SHARED`` partners, the best-fitting forces first).
        Zoo thermal_mass 270939893 #1 (a row of 9, 4 measured, a hidden mass on T3 and T4):
        eq(T4)'s first-order law fitted 9.25 % against its static law's 42 %, and no shared
        state was tried; the model kept 38 % against the true model's 0.39 %."""
        if self.static_is_enough(r) or any(
                c.trace.channel.kind == "equation" and c.trace.channel.md == 2
                for c in self.scored):
            return
        dyn = [c for c in self.scored if c.kind == "sparse" and np.isfinite(c.se) and
               c.trace.channel.kind == "equation" and c.trace.channel.md == 1]
        if not dyn:
            return
        best = min(dyn, key=lambda c: c.se)
        ch = best.trace.channel
        se_static = self._best_se(ch, "static")
        if not best.se < se_static:
            return
        x = ch.equations[0]
        forces = sorted((c for c in self.scored if c.trace.channel.kind == "force" and
                         x in c.trace.channel.equations and np.isfinite(c.se)),
                        key=lambda c: c.se)
        partners = list(dict.fromkeys(e for c in forces for e in c.trace.channel.equations
                                      if e != x))[:_LINKED_SHARED]
        for y in partners:
            pair = resolve_channel_spec(self.sys, [(x, y)])[0]
            try:
                tr = self._trace(pair, nonlinear=False, max_order=0)
            except (GreyboxError, np.linalg.LinAlgError) as e:
                self.note("trace", pair.name, str(e))
                continue
            if tr.status == "ok":  # its static law is not a candidate: the state is
                self._shared(_light(tr), r, own=True)

    def _best_se(self, ch, kind: str) -> float:
        """The lowest estimation SE [%] of the scored candidates of ``kind`` on ``ch``
        (inf without one)."""
        return min((c.se for c in self.scored if c.trace.channel == ch and c.kind == kind),
                   default=np.inf)

    def static_is_enough(self, r: Residual) -> bool:
        """:func:`_static_is_enough` on the pass's candidates: its Kalman filter over the
        whole record runs once per best static candidate (three stages ask)."""
        stat = [c for c in self.scored if c.kind == "static" and np.isfinite(c.se)]
        best = min(stat, key=lambda c: c.se) if stat else None
        if self._enough is None or self._enough[0] is not best:
            P, S = self.P, self.S
            self._enough = (best, _static_is_enough(self.scored, P.y, P.u, self.Q, P.R, r.k0,
                                                    S.lags, S.alpha))
        return self._enough[1]

    def _shared(self, tr_, r: Residual, own: bool = False) -> bool:
        """2c. Fit one shared state for the channel of ``tr_``; False if the fit failed.
        ``own``: driven by the states of the channel's equations alone (a hidden body
        between the bodies it touches), first order only."""
        P, S, ch = self.P, self.S, tr_.channel
        res_, k0s, Ns, pole0 = _sparse_start(tr_)
        try:
            dl = fit_shared_dynamic(self.sys, ch, res_.x_filt[:, k0s:Ns], res_.d_est[:, k0s:Ns],
                                    P.y, P.u, Q=self.Q, R=P.R, dt=P.dt, x0=res_.x_filt[:, 0],
                                    k0=k0s, pole=pole0, own_only=own)
            fit = None if dl is None else self.fit_error(dl.model.sys, dl.model.Q, dl.model.R)
            se = np.inf if fit is None else fit.se
        except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
            self.note("generate", ch.name, f"shared-state law failed: {e}")
            return False
        if dl is not None and dl.one_direction and any(
                t.trace.channel.kind == "force" and
                set(t.trace.channel.equations) == set(ch.equations) for t in self.scored):
            self.cands.append(CandidateScore(ch.name, "dynamic (sparse)", 1, se, dl.npar,
                                             "redundant", "one state along one direction: "
                                             "the force channel's law says the same"))
            self._force_along(dl, se, ch)
        elif dl is not None:
            self.cands.append(CandidateScore(ch.name, "dynamic (sparse)", 1, se, dl.npar, "ok"))
            self.scored.append(Candidate(se, dl.npar, tr_, "sparse", dl, fit=fit))
            # a second order only where the first leaves coloured innovations, and no
            # earlier group's shared law left white ones (on a first-order hidden
            # mass, the order-2 fits cost 18 s of 41 s)
            others = [t.se for t in self.scored[:-1] if np.isfinite(t.se)]
            if own:
                self.note("generate", ch.name, "no second-order shared law tried: the state "
                                               "of a body between two bodies is one state")
            elif others and not se <= ORDER2_WITHIN * min(others):
                self.note("generate", ch.name, f"no second-order shared law tried: the "
                                               f"first-order one ({se:.3g} %) is not within "
                                               f"{ORDER2_WITHIN:g}x of the best candidate's SE "
                                               f"({min(others):.3g} %)")
            elif self.white_shared:
                self.note("generate", ch.name, f"no second-order shared law tried: "
                                               f"{self.white_shared[0]}'s leaves white innovations")
            elif _leaves_white(dl.model, P.y, P.u, self.Q, P.R, r.k0, S.lags, S.alpha):
                self.white_shared.append(ch.name)
                self.note("generate", ch.name, "no second-order shared law tried: the "
                                               "first-order one leaves white innovations")
            else:
                self._shared_higher(tr_, dl, res_, k0s, se, r)
        return True

    def _shared_higher(self, tr_, dl, res_, k0s, se, r: Residual) -> None:
        """A subsystem one order above the shared law ``dl`` (SE ``se``), scored; then
        order 3 where order 2 fits better than order 1, leads every other candidate
        and still leaves coloured innovations (a chain of three hidden parts; a
        second-order law that another channel beats is not where the error is: on
        the lag + spring chain, seed 4, its order-3 fit cost 32 s of 77 s and
        failed)."""
        P, S, ch = self.P, self.S, tr_.channel
        word = "third" if isinstance(dl, SharedLaw2) else "second"
        try:
            dl2 = fit_shared_order2(self.sys, ch, dl, P.y, P.u, Q=self.Q, R=P.R, dt=P.dt,
                                    x0=res_.x_filt[:, 0], k0=k0s)
            fit2 = None if dl2 is None else self.fit_error(dl2.model.sys, dl2.model.Q,
                                                           dl2.model.R)
            se2 = np.inf if fit2 is None else fit2.se
        except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
            self.note("generate", ch.name, f"{word}-order shared law failed: {e}")
            return
        if dl2 is None:
            self.note("generate", ch.name, f"no {word}-order shared law (unstable, or a gain or "
                                           f"an interval the data do not determine)")
            return
        self.cands.append(CandidateScore(ch.name, "dynamic (sparse)", dl2.order, se2,
                                         dl2.npar, "ok"))
        tr2 = replace(tr_)  # its own trace (the lower order keeps tr_)
        self.scored.append(Candidate(se2, dl2.npar, tr2, "sparse", dl2, fit=fit2))
        if dl2.order >= MAX_SHARED_ORDER:
            return
        others = [t.se for t in self.scored[:-1] if np.isfinite(t.se)]
        if not se2 < se:
            self.note("generate", ch.name, f"no third-order shared law tried: the second-order "
                                           f"one ({se2:.3g} %) fits no better than the first "
                                           f"({se:.3g} %)")
        elif not se2 <= min(others, default=np.inf):
            self.note("generate", ch.name, f"no third-order shared law tried: the second-order "
                                           f"one ({se2:.3g} %) does not lead the candidates (best "
                                           f"{min(others):.3g} %)")
        elif _leaves_white(dl2.model, P.y, P.u, self.Q, P.R, r.k0, S.lags, S.alpha):
            self.note("generate", ch.name, "no third-order shared law tried: the second-order "
                                           "one leaves white innovations")
        else:
            self._shared_higher(tr2, dl2, res_, k0s, se2, r)

    def _force_along(self, dl, se, ch) -> None:
        """The force traced again along a one-direction shared law's k, if that fits better.

        The force channel's direction comes from the static pair law (a few % off
        for a dynamic effect: its law then adds compensating terms); the shared
        law's k is refitted by output error with the dynamics.
        """
        P = self.P
        fse = min((t.se for t in self.scored if t.trace.channel.kind == "force" and
                   set(t.trace.channel.equations) == set(ch.equations)), default=np.inf)
        if not se < fse:
            return
        fch = force_channel(self.sys, ch, dl.k)
        n_before = len(self.scored)
        self.static_trace(fch)
        ftr = next((t.trace for t in self.scored[n_before:] if t.kind == "static"), None)
        if ftr is None:
            return
        res_, k0s, Ns, _ = _sparse_start(ftr)
        try:
            fl = fit_sparse_dynamic(self.sys, fch, res_.x_filt[:, k0s:Ns],
                                    res_.d_est[:, k0s:Ns], P.y, P.u, Q=self.Q, R=P.R, dt=P.dt,
                                    x0=res_.x_filt[:, 0], k0=k0s,
                                    pole=float(np.exp(dl.pole * P.dt)))
        except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
            self.note("generate", fch.name, f"traced again along the shared law's direction: {e}")
            return
        if fl is None:
            return
        ffit = self.fit_error(fl.model.sys, fl.model.Q, fl.model.R)
        fse = ffit.se
        self.cands.append(CandidateScore(fch.name, "dynamic (sparse)", 1, fse, fl.npar, "ok",
                                         "along the shared-state law's direction "
                                         f"{np.array2string(dl.k, precision=3)}"))
        self.scored.append(Candidate(fse, fl.npar, ftr, "sparse", fl, fit=ffit))

    # ------------------------------------------------------------------ choose
    def choose(self) -> Candidate | None:
        """The lowest output-error criterion (:func:`greybox.metrics.criterion_scores`: each
        output's log mean squared simulation error on its effective samples, plus
        ``bic_factor log n`` per parameter: the evidence the gate asks of a law, asked of
        each parameter, since the candidates' laws are fitted on d^ or by output error,
        not for this likelihood), every candidate on the effective samples of the
        best-fitting one; ties go to the fewest parameters, then components. A force
        re-traced if it scores better; a static law's terms then kept only where the
        criterion supports them."""
        finite = [s for s in self.scored if np.isfinite(s.se) and s.fit is not None]
        if not finite:
            return None
        self.n_eff = min(finite, key=lambda s: s.se).fit.n_eff
        finite += self._contenders_pruned(finite)
        crit = self._criterion(finite)
        order = sorted(range(len(finite)), key=lambda i: (crit[i], finite[i].npar,
                                                          finite[i].trace.channel.md,
                                                          finite[i].se))
        self.note("choose", "", choice_note(
                  [f"{c.trace.channel.name} {c.kind}" for c in finite], [c.npar for c in finite],
                  [c.se for c in finite], crit, order, self.n_eff, self.S.bic_factor))
        return self.pruned(self.retraced(finite[order[0]]))

    def _criterion(self, cands) -> np.ndarray:
        """The criterion of each candidate of ``cands`` on the choice's effective samples."""
        n_eff = self.n_eff
        if n_eff is None:  # before the choice (the big model's early re-trace of a force)
            n_eff = min(cands, key=lambda s: s.se).fit.n_eff
        return criterion_scores([c.fit for c in cands], [c.npar for c in cands],
                                n_eff=n_eff, factor=self.S.bic_factor)

    def _contenders_pruned(self, cands) -> list[Candidate]:
        """Every static law among ``cands`` that pruning could make the best, pruned
        (:meth:`pruned`): the candidates are chosen as their laws would be kept, not as
        fitted (zoo static_state: eq(T2)'s 6-term law lost to a force's 2 parameters at
        the same SE; pruned, it is the one true term). A law of k terms is a contender
        when its criterion less ``k - 1`` parameters' price beats the best criterion and
        its fit alone (the criterion less all its parameters' price) is within one
        parameter's price of the best's: pruning weighs explanations that fit alike by
        their terms, it does not rescue a worse fit (the drives' rectifying sensor, 3
        parameters at SE 38 %, against a 3-term law of the speed's equation at 89 %, on 36
        effective samples). At most ``_MAX_PRUNED`` of them, the most promising first.
        Returns the pruned candidates (to be scored beside the others)."""
        crit = self._criterion(cands)
        price = self.S.bic_factor * np.log(max(float(np.sum(self.n_eff)), 2.0))
        ib = int(np.argmin(crit))
        best, fit_best = float(crit[ib]), float(crit[ib]) - price * cands[ib].npar
        hope = [(crit[i] - price * (c.npar - 1), i) for i, c in enumerate(cands)
                if c.kind == "static" and c.npar >= 2 and c.trace.static is not None and
                c.trace.static.output is None and id(c.trace) not in self._prune_tried and
                crit[i] > best and crit[i] - price * c.npar < fit_best + price]
        out = []
        for h, i in sorted(hope)[:_MAX_PRUNED]:
            if h >= best:
                break
            new = self.pruned(cands[i])
            if new is not cands[i]:
                out.append(new)
        return out

    def pruned(self, pick: Candidate) -> Candidate:
        """The chosen static law traced again with its terms pruned by the one criterion
        (:func:`greybox.trace.oe.prune_by_criterion`), a one-equation law that lacks its
        equation's own state offered it first (``own``: :func:`greybox.trace.oe.offer_terms`),
        scored; ``pick`` itself when its terms are kept as they are, the new law cannot be
        simulated, a changed law does not lower the criterion, or the law was pruned
        already (:meth:`_contenders_pruned`)."""
        law, ch = pick.trace.static, pick.trace.channel
        if pick.kind != "static" or law is None or law.output is not None or \
                id(pick.trace) in self._prune_tried or \
                not (law.npar >= 2 or
                     (law.npar == 1 and lacked_own_terms(law, ch, self.sys.state_labels))):
            return pick
        self._prune_tried.add(id(pick.trace))
        breaks = any(sp[1] in BREAK_KINDS for sp in law.spec)
        n_before = len(self.scored)
        try:
            tr = self._trace(ch, nonlinear=self.S.nonlinear, max_order=0, breaks=breaks,
                             prune=self.S.bic_factor, own=True)
        except (GreyboxError, np.linalg.LinAlgError) as e:
            self.note("choose", ch.name, f"criterion prune failed: {e}")
            return pick
        if tr.status != "ok" or tr.static is None or (
                np.array_equal(tr.static.coef != 0, law.coef != 0) and
                np.array_equal(tr.static.eps, law.eps)):  # no term dropped, no width fitted
            return pick
        self.score(tr, narrowable=True)
        new = [s for s in self.scored[n_before:] if s.kind == "static" and np.isfinite(s.se)]
        self._prune_tried.update(id(s.trace) for s in new)
        if not new:
            return pick
        if new[0].npar < law.npar:  # the same terms, fewer: the prune's own criterion chose
            return new[0]
        crit = self._criterion([pick, new[0]])
        return new[0] if crit[1] < crit[0] else pick

    # ------------------------------------------------------------------ 3. gate
    def judge(self, r: Residual, chosen: Candidate) -> Verdict:
        """3. The chosen candidate as an effect, gated on its evidence (:meth:`_evidence`)
        and its SE drop."""
        P, S, sys = self.P, self.S, self.sys
        se_c, tr, kind = chosen.se, chosen.trace, chosen.kind
        ch = tr.channel  # (the report's trace gets its whole record at the end: _with_record)
        if kind == "static":
            law = tr.static
            model = tr.static_model
            nsens = sensor_states(law)  # a lag or a drift: sensor states, not a static law
            effect = Effect(kind="sensor" if nsens else "static", order=nsens,
                            formula=law.formula, channel=ch.name,
                            equations=ch.equations, nonlinear=law.nonlinear,
                            linearized=law.nonlinear,
                            parameter_notes=parameter_notes(sys, ch, law), law=law)
        elif kind == "sparse":
            dl = chosen.law
            model = dl.model
            kind = "dynamic"
            effect = Effect(kind="dynamic", order=getattr(dl, "order", 1), formula=dl.formula,
                            channel=ch.name, equations=ch.equations, dynamic_law=dl)
        else:
            sub, res = tr.dynamic, tr.filter_result  # the formula's window: the law's
            k0f, Nf = res.settled(20), res.d_est.shape[1] - 1
            x, uu = res.x_filt[:, k0f:Nf], P.u[:, k0f:Nf]
            model = tr.dynamic_model
            effect = Effect(kind="dynamic", order=sub.order,
                            formula=_dynamic_formula(sub, ch, P.dt, x, uu), channel=ch.name,
                            equations=ch.equations, subsystem=sub)
        gain, penalty, evidence = self._evidence(r, chosen)
        passed = {"whiteness": True, "bic": gain > S.bic_factor * penalty,
                  "se_drop": se_c < S.min_se_drop * r.se_nom}
        self.gate.update({"bic_gain": gain, "bic_penalty": penalty, "bic_factor": S.bic_factor,
                          "se_estimation_updated": se_c, "min_se_drop": S.min_se_drop,
                          "passed": passed, "evidence": evidence})
        ok = passed["bic"] and passed["se_drop"]
        if ok and kind == "static" and not effect.nonlinear:
            model = _noise_by_likelihood(model, self.Q, P.ys, P.us, self.SKIP, self.decisions)
        return Verdict(effect=effect, model=model, kind=kind, passed=ok)

    def _evidence(self, r: Residual, chosen: Candidate) -> tuple[float, float, str]:
        """(gain, penalty, what) of the chosen candidate; the gate asks gain > bic_factor *
        penalty. Through a channel of relative degree 1 or 0, the likelihood ratio of its
        law against d = 0 on d^ (the BIC gain plus penalty, on the d^ samples); through a
        delayed channel (relative degree >= 2: d^ is mostly estimation noise, the law was
        fitted on y), the choice's criterion against the nominal model on the output
        error (:func:`greybox.metrics.criterion_scores`; the nominal adds no parameter,
        penalty ``npar log n`` on the choice's effective samples), as the nonlinear
        pipeline's gate reads a delayed channel; the same for a law fitted by output error
        on y (a "sparse" candidate: sparse, shared, hidden-part and actuator-lag laws),
        whatever the channel's degree: d^ is not what it was fitted to, and a lightly damped
        hidden mode's d^ can be so far from the law's (a flexible shaft's: correlation
        0.65 for the true law on the filtered states) that the likelihood ratio on d^
        rejects the true law; not for a model with a pole on the unit
        circle (:func:`greybox.validate.has_marginal_pole`: an integrator's simulation
        error drifts, its few effective samples judge nothing; EMPS, a double integrator,
        read 7)."""
        tr, kind = chosen.trace, chosen.kind
        if (tr.relative_degree >= 2 or kind == "sparse") and r.fit is not None and \
                chosen.fit is not None and not has_marginal_pole(self.nominal):
            n_eff = self.n_eff if self.n_eff is not None else chosen.fit.n_eff
            n = float(np.sum(n_eff))
            penalty = float(chosen.npar * np.log(max(n, 2.0)))
            if not np.isfinite(r.fit.se):
                return np.inf, penalty, EVIDENCE_OE.format(n=n)
            like = criterion_scores([r.fit, chosen.fit], [0, 0], n_eff=n_eff)
            return float(like[0] - like[1]), penalty, EVIDENCE_OE.format(n=n)
        res = tr.filter_result
        k0f, Nf = res.settled(20), res.d_est.shape[1] - 1
        d, x, uu = res.d_est[:, k0f:Nf], res.x_filt[:, k0f:Nf], self.P.u[:, k0f:Nf]
        Nd = d.shape[1]
        if kind == "static":
            gain = float(tr.static.bic_gain + tr.static.npar * np.log(Nd))  # before penalty
        elif kind == "sparse":
            gain = _logdet_gain(d, d - chosen.law.evaluate(x, uu))
        else:
            sub = tr.dynamic
            gain = _logdet_gain(d, d - sub.d_sim[:, -Nd:] if sub.d_sim.shape[1] >= Nd else d)
        return gain, float(chosen.npar * np.log(Nd)), EVIDENCE_DHAT

    # ------------------------------------------------------------------ 4. validate
    def validate(self, r: Residual, tr, v: Verdict) -> dict:
        """4. Before/after on the validation record (and the parallel delta baseline)."""
        P, S, skip, model = self.P, self.S, self.SKIP, v.model
        P.tick("validation", 0, 2 if self.delta else 1)
        table = {"nominal": r.val_nom}
        if v.effect.nonlinear:
            res = tr.filter_result
            table["updated"] = validation(
                LawPlant(res.sys, res.G, tr.static, model.sys, order=model.order), P.y_val,
                P.u_val, Q=model.Q, R=model.R, name="updated", lags=S.lags, alpha=S.alpha,
                skip=skip)
            table["updated (linearized)"] = validate_model(
                model.sys, P.y_val, P.u_val, Q=model.Q, R=model.R, x0="estimate",
                name="updated (linearized)", lags=S.lags, alpha=S.alpha, skip=skip)
            self.note("validate", "", "the law is nonlinear: the updated StateSpace holds its best "
                                      "linear part; the 'updated' row simulates the full law")
        else:
            table["updated"] = validate_model(model.sys, P.y_val, P.u_val, Q=model.Q,
                                              R=model.R, x0="estimate", name="updated",
                                              lags=S.lags, alpha=S.alpha, skip=skip)
        if self.delta:
            P.tick("validation", 1, 2)
            self._baseline(r, table)
        P.tick("validation", 2 if self.delta else 1, 2 if self.delta else 1)
        for name, row in table.items():
            if not row.se_defined:
                self.note("validate", name, f"SE n/a: {row.se_reason}")
        return table

    def _baseline(self, r: Residual, table: dict) -> None:
        """The parallel delta baseline's row, its cost bounded by this pass's time."""
        P, S = self.P, self.S
        try:
            dm, bound = _delta_baseline(self.nominal, P.y, P.u, self.Q, P.R, S.delta_max_order,
                                        r.x0n, max(time.monotonic() - r.t_pass,
                                                   DELTA_MIN_BUDGET_S))
            self.note("baseline", "", dm.message)
            if bound:
                self.note("baseline", "", bound)
            table["delta"] = validate_model(dm.updated.sys, P.y_val, P.u_val, Q=dm.updated.Q,
                                            R=dm.updated.R, name="delta",
                                            x0=dm.initial_state(P.y_val, P.u_val),
                                            lags=S.lags, alpha=S.alpha, skip=self.SKIP)
        except (GreyboxError, np.linalg.LinAlgError) as e:
            self.note("baseline", "", f"parallel delta baseline failed: {e}")

    # ------------------------------------------------------------------ 5. report
    def report(self, r: Residual, tr, v: Verdict, table: dict) -> LoopReport:
        """5. The pass's report: where, what, before/after."""
        ch, effect = tr.channel, v.effect
        where = _where(ch)
        if ch.kind == "force":
            g = np.asarray(ch.G)[[list(self.nominal.state_labels).index(e)
                                  for e in ch.equations], 0]
            where = (f"one force between {' and '.join(ch.equations)} (it enters {where} as "
                     f"{np.array2string(g, precision=3)})")
        what = _effect_phrase(v.kind, effect.order)
        if effect.kind == "sensor":
            what = ("sensor dynamics, a first-order lag (one sensor state)"
                    if any(term_kind(sp[1]).time_constant for sp in effect.law.spec) else
                    "a drifting sensor (offset and drift rate: two sensor states)")
        msg = f"model error found in {where}: {what}; {describe_before_after(table)}"
        return LoopReport(model_error_detected=True, updated=True, message=msg,
                          residual=r.white, effect=effect, channel=ch,
                          candidates=tuple(self.cands), gate=self.gate, criterion=r.crit,
                          nominal=self.nominal, model=v.model, table=table, trace=tr,
                          decisions=tuple(self.decisions))


def _logdet_gain(d, r) -> float:
    """``N (log det cov d - log det cov r)``: the BIC gain of a law leaving residual r."""
    _, ld0 = np.linalg.slogdet(np.atleast_2d(np.cov(d, bias=True)))
    _, ld1 = np.linalg.slogdet(np.atleast_2d(np.cov(r, bias=True)))
    return float(d.shape[1] * (ld0 - ld1))



def _noise_by_likelihood(model: UpdatedModel, Q, y, u, skip, notes) -> UpdatedModel:
    """A static law's updated model with the likelier process noise: eq. (30)'s Q or the pass's.

    Eq. (30) adds the law's residual variance G R_nu G^T to Q. With a law
    that is right, that residual is mostly d^'s own estimation error, not
    process noise, and the inflated Q makes the one-step innovations
    coloured (the next pass of the several-effects loop then traces a
    model that is already right). The Kalman filters of the updated model
    under both noise models are compared by the Gaussian log-likelihood of
    their (steady) innovations on the same estimation samples; the likelier
    Q is kept and the choice noted.
    """
    Qa = np.asarray(model.Q, dtype=float)
    Qp = np.asarray(Q, dtype=float)
    if Qa.shape != Qp.shape or np.allclose(Qa, Qp, rtol=1e-9, atol=0.0):  # Q may be ~1e-12
        return model
    kfs = [kalman_filter(model.sys, y, u, Q=Qx, R=model.R) for Qx in (Qa, Qp)]
    k0 = max(kf.settled(skip) for kf in kfs)
    ll = []
    for kf in kfs:
        S = np.atleast_2d(kf.innovation_cov)
        e = kf.innovations[:, k0:]
        ll.append(-0.5 * (e.shape[1] * np.linalg.slogdet(S)[1] +
                          float(np.sum(e * np.linalg.solve(S, e)))))
    if not ll[1] > ll[0]:
        return model
    notes.append(Decision(
        "gate", "", f"noise model: the law's residual variance (eq. 30) is left out of Q: "
        f"the innovations are likelier without it (log-likelihood {ll[0]:.6g} -> "
        f"{ll[1]:.6g}); that residual is d^'s estimation error, not process noise"))
    return replace(model, Q=Qp)


def _static_is_enough(scored, y, u, Q, R, k0, lags, alpha) -> bool:
    """True if the best static candidate leaves white one-step innovations.

    Above SCREEN_ABOVE states no unstructured subsystem is fitted, so there
    is no dynamic fit to compare with: the evidence for dynamics is then that
    the best static law leaves the innovations coloured under the user's
    noise model (Q, R) -- the law is deterministic (the sparse dynamic law
    costs hundreds of simulations of the full model).
    """
    stat = [s for s in scored if s.kind == "static" and np.isfinite(s.se)]
    if not stat:
        return False
    return _leaves_white(min(stat, key=lambda s: s.se).trace.static_model, y, u, Q, R, k0, lags,
                         alpha)


def _leaves_white(sm, y, u, Q, R, k0, lags, alpha) -> bool:
    """True if the updated model ``sm`` leaves white one-step innovations under (Q, R).

    The law's own states (a sensor lag, a hidden state) keep the law's Q.
    """
    n = np.shape(Q)[0]
    if sm.sys.nstates > n:
        Q = block_diag(Q, np.asarray(sm.Q)[n:, n:])
    kf = kalman_filter(sm.sys, y, u, Q=Q, R=R)
    return innovation_test(kf.innovations[:, k0:], lags, alpha=alpha).all_white


def _light(tr: ChannelTrace) -> ChannelTrace:
    """The trace as the choice keeps it: of its filter record only x^[k|k] and d^.

    The choice, the pair-force step, the sparse laws and the gate read only those;
    x^[k|k-1], the innovations, var(d^) and the time axis (~50 MB per channel at 1e6
    samples of a 2-state model) are dropped (zero-length), and :func:`_whole_record`
    recomputes them for the chosen channel. The delayed or smoothed estimate the
    law was fitted on (``law_estimate``, with its covariance histories) is dropped
    too: the law is already fitted, and nothing downstream reads it.
    """
    res = tr.filter_result
    if res is None:
        return tr
    tr = replace(tr, law_estimate=None)
    def none(a):  # a fresh empty array: a view would keep the whole history alive
        return np.zeros(a.shape[:-1] + (0,))

    return replace(tr, filter_result=replace(
        res, t=none(res.t), x_pred=none(res.x_pred), d_var=none(res.d_var),
        innovations=none(res.innovations), P_filt_history=None))


def _whole_record(tr: ChannelTrace, y, u, Q, R) -> ChannelTrace:
    """A :func:`_light` trace with its whole filter record again (the same filter re-run)."""
    res = tr.filter_result
    if res is None or res.t.shape[0] == y.shape[1]:
        return tr
    filt = feedthrough_uikf if tr.channel.kind == "output" else uikf  # as trace_channel ran
    return replace(tr, filter_result=filt(tr.model, y, u, unknown=list(tr.channel.labels),
                                          Q=Q, R=R))


#: Samples of the law's own estimate kept for its figure (plot_law)
_FIGURE_SAMPLES = 20_000


def _with_record(rep: LoopReport, y, u, Q, R, sys=None) -> LoopReport:
    """The report with its trace's whole filter record (:func:`_whole_record`).

    Built once, at the end: the report's trace is the first pass's (under the
    user's Q), and its histories (~130 MB at 1e6 samples of a 2-state model)
    need not live through the delta baseline and the later passes.
    """
    if rep.trace is None:
        return rep
    tr = _whole_record(rep.trace, y, u, Q, R)
    law = tr.static
    if rep.updated and rep.effect.kind == "static" and law is not None and \
            law.output is None and tr.relative_degree >= 2 and sys is not None:
        # the law's own (delayed) estimate, for its figure (plot_law): the r = 1 filter's
        # d^ of a relative-degree-2 channel is mostly amplified noise. On the first
        # _FIGURE_SAMPLES samples: the figure needs no more
        K = min(y.shape[1], _FIGURE_SAMPLES)
        try:
            tr = replace(tr, law_estimate=law_estimate_of(sys, tr, y[:, :K],
                                                          u[:, :K], Q, R))
        except (GreyboxError, np.linalg.LinAlgError):
            pass
    return replace(rep, trace=tr)


def _search_record(y, u):
    """The first ``SEARCH_WINDOW`` samples of the estimation record (views, no copy).

    A prefix: a causal filter's record on it is the prefix of its record on the
    whole, and the initial state is the same.
    """
    return y[:, :SEARCH_WINDOW], u[:, :SEARCH_WINDOW]


def _delta_baseline(nominal, y, u, Q, R, max_order, x0, budget_s: float):
    """The parallel delta baseline, its cost bounded; (DeltaModel, note on the bounds or None).

    Its N4SID candidates, residue fits and order choice cost O(samples) each: on
    the first ``SEARCH_WINDOW`` samples (at 1e6 samples of a 2-state model 12 s on
    the whole record, 2 s on 1e5 samples; validation SE 0.159 % vs 0.166 %). The
    refinement's dense Jacobian has ``noutputs x samples`` rows: on at most
    ``DELTA_REFINE_RESIDUALS`` of them (36 s and 2.4 GB on the whole estimation part).

    Above ten states its cost grows as n^4 or faster (each candidate's residue fit
    forms the Gram matrix of ``(n + 1) x order`` whitened regressors, for every
    order up to n + 6): the orders stop at ``DELTA_MAX_ORDER``, the samples at
    ``DELTA_WORK / ((n + 1) order m)^2`` (at least 2000), and no new candidate is
    started after ``budget_s`` seconds (a 32-state chain: over 17 minutes before).
    """
    n, m = nominal.nstates, max(nominal.ninputs, 1)
    cut = []
    if max_order is None:
        max_order = min(n + 6, DELTA_MAX_ORDER)
        if max_order < n + 6:
            cut.append(f"orders up to {max_order} (of n + 6 = {n + 6})")
    y, u = _search_record(y, u)  # x0: the record's first state, the same for its prefix
    keep = int(max(2000, DELTA_WORK // ((n + 1) * max_order * m) ** 2))
    if keep < y.shape[1]:
        cut.append(f"the first {keep} samples (of {y.shape[1]})")
        y, u = y[:, :keep], u[:, :keep]
    win = max(2000, DELTA_REFINE_RESIDUALS // max(y.shape[0], 1))
    deadline = time.monotonic() + budget_s
    with single_thread_blas():  # thin and small products: a second thread only stalls
        dm = delta_update(nominal, y, u, Q=Q, R=R, max_order=max_order, x0=x0,
                          refine_window=win, deadline=deadline)
    if dm.bounded:
        cut.append(f"a time budget of {budget_s:.3g} s (the trace's time, at least "
                   f"{DELTA_MIN_BUDGET_S:g} s)")
    return dm, (None if not cut else "parallel delta baseline bounded (a comparison row, "
                "never dearer than the trace): " + "; ".join(cut))


def _d_noise(res) -> float | None:
    """The variance of d^'s estimation noise (Pd) of a one-component filter, or None.

    None for a delayed or smoothed d^ (coloured noise: its variance says little
    about the law, see ``greybox.trace.channel_trace``).
    """
    if res.smoothed or res.relative_degree != 1 or res.d_cov is None:
        return None
    Pd = np.atleast_2d(res.d_cov)
    return float(Pd[0, 0]) if Pd.shape == (1, 1) else None


def _sparse_start(tr):
    """(filter result, first and end sample of d^, the unstructured fit's slowest real pole)."""
    dyn = tr.dynamic
    lam = np.linalg.eigvals(dyn.Ad) if dyn is not None and dyn.order else np.zeros(0)
    lam = lam[np.isreal(lam) & (lam.real > 0) & (lam.real < 1)].real
    res = tr.filter_result
    return (res, res.settled(20), res.d_est.shape[1] - 1,
            float(lam.max()) if lam.size else None)


def _shared_groups(sys: ct.StateSpace, chans, scored, trace):
    """Traces to fit one shared state on, above SCREEN_ABOVE states (one per group of equations).

    The equations the screen kept (the single-equation channels of ``chans``),
    when 2 to SCREEN_TOP of them, as one channel (a hidden body touching those
    bodies; its trace from ``scored``, or traced by ``trace``); where there is no
    screen (fewer outputs than equations: every equation was traced alone), the two
    equations whose single static laws have the lowest estimation error instead (zoo
    thermal_mass, a hidden mass between two bodies the model does not link, 10 of 11
    temperatures measured); then the pair
    of equations whose static law has the lowest estimation error, if it is
    not that group. A pair with a force channel is left to the force (one
    element between two bodies; a shared state there reads as one direction,
    and its fit costs simulations of the whole model: 15 of 65 s CPU on a
    16-state chain with positions only).
    """
    def static(t):
        return t.kind == "static" and t.trace.channel.kind == "equation" and np.isfinite(t.se)

    def forced(eqs):
        return len(eqs) == 2 and any(t.trace.channel.kind == "force" and
                                     set(t.trace.channel.equations) == eqs for t in scored)

    top = [c.equations[0] for c in chans if c.md == 1 and c.kind == "equation" and c.equations]
    group = set(top) if 2 <= len(top) <= SCREEN_TOP else None
    if group is None:
        # no screen (fewer outputs than equations: every equation traced alone): the two
        # equations whose single static laws fit best (a hidden body between two bodies
        # the model does not link, only some temperatures measured)
        best = list(dict.fromkeys(  # each equation once, at its best single law's rank
            t.trace.channel.equations[0] for t in sorted(scored, key=lambda t: t.se)
            if static(t) and t.trace.channel.md == 1))
        if len(best) >= 2:
            group = set(best[:2])
            top = [s for s in sys.state_labels if s in group]
    if group is not None and not forced(group):
        tr = next((t.trace for t in scored if static(t) and
                   set(t.trace.channel.equations) == group and t.trace.channel.md == len(group)),
                  None)
        tr = tr if tr is not None else trace(resolve_channel_spec(sys, [tuple(top)])[0])
        if tr is not None:
            yield tr
    pairs = sorted((t for t in scored if static(t) and t.trace.channel.md == 2),
                   key=lambda t: t.se)
    if pairs and set(pairs[0].trace.channel.equations) != group and \
            not forced(set(pairs[0].trace.channel.equations)):
        yield pairs[0].trace


def _offset_sensors(nominal: ct.StateSpace, kf, k0: int, white: WhitenessTest, alpha: float,
                    notes: list[Decision]) -> tuple[str, ...]:
    """The sensors whose constant offset explains the innovations' mean, offered as
    candidate channels (above ``_AUTO_OUTPUTS`` outputs there are none by default); the
    criterion still chooses.

    :func:`greybox.trace.screen.screen_sensors` fits one offset per sensor to the mean
    (its variance from the effective samples: a strongly coloured residual's mean says
    little). Sensor j is offered when its offset is significant (the likelihood ratio
    ``null - misfit_j`` beyond the chi-square quantile 1 - alpha on 1 degree of freedom)
    and explains the mean alone (``misfit_j`` within the quantile on noutputs - 1).
    Only when the residual test rejected."""
    if white.all_white or nominal.noutputs < 2:
        return ()
    e = kf.innovations[:, k0:]
    scr = screen_sensors(nominal, kf.K, e,
                         white.n_eff if white.n_eff is not None else effective_samples(e))
    limit, one = chi2.isf(alpha, nominal.noutputs - 1), chi2.isf(alpha, 1)
    keep = [(o, b, m) for o, b, m in zip(scr.outputs, scr.offset, scr.misfit)
            if m <= limit and scr.null - m >= one]
    if keep:
        notes.append(Decision(
            "screen", "", "sensor screen (the innovations' mean against one constant offset "
            "per sensor): " + ", ".join(f"output({o}) offset {b:.3g}, evidence "
                                        f"{scr.null - m:.3g}, misfit {m:.3g}"
                                        for o, b, m in keep)
            + f" (limits {one:.3g} and {limit:.3g})"))
    return tuple(o for o, _, _ in keep)


def _sensor_law_candidates(nominal: ct.StateSpace, ys: np.ndarray, us: np.ndarray, x0: np.ndarray,
                           dt: float, white: WhitenessTest, unstable: str | None,
                           notes: list[Decision]) -> tuple[str, ...]:
    """The ``SENSOR_TOP`` sensors whose own law (gain, offset, lag, drift) explains most of
    the nominal simulation error (:func:`greybox.trace.screen.screen_sensor_laws`),
    offered as sensor channels where none is offered by default (above ``_AUTO_OUTPUTS``
    outputs). Not for a model whose simulation is not compared (unstable: its simulation
    error grows without a sensor error)."""
    if white.all_white or nominal.noutputs < 2 or unstable:
        return ()
    scr = screen_sensor_laws(ys, simulate_output(nominal, us, x0), dt,
                             list(nominal.output_labels))
    top = list(scr.outputs[:SENSOR_TOP])
    notes.append(Decision("screen", "", "sensors offered by the share of the simulation error "
                          "their own law (gain, offset, lag, drift) explains: " + ", ".join(
                              f"output({o}) {e / max(scr.total, 1e-300):.0%}"
                              for o, e in zip(top, scr.explained))))
    return tuple(top)


def _traceable_linked_forces(sys: ct.StateSpace, equations) -> list[Channel]:
    """The forces between the bodies the model links among ``equations``
    (:func:`greybox.trace.channels.linked_forces`), less those acting on a kinematic
    identity or along an input's B column (the input's own channel says the same)."""
    return [f for f in linked_forces(sys, equations) if not _kinematic_in(sys, f) and
            not _along_an_input(sys, f)]


def _kinematic_in(sys: ct.StateSpace, ch: Channel) -> bool:
    """True if the channel enters a kinematic equation (dp/dt = v: one nonzero in A, none in B).

    Only for a continuous model (a discrete one mixes the rows).
    """
    if ct.isdtime(sys, strict=True):
        return False
    A, B = np.asarray(sys.A, dtype=float), np.asarray(sys.B, dtype=float)
    labels = list(sys.state_labels)
    for e in ch.equations:
        i = labels.index(e)
        if np.count_nonzero(A[i]) == 1 and not np.any(B[i]):
            return True
    return False


def _along_an_input(sys: ct.StateSpace, ch: Channel, tol: float = 0.02) -> bool:
    """True if a one-column channel is parallel to an input's B column (the same channel)."""
    g = np.asarray(ch.G, dtype=float)[:, 0]
    B = np.asarray(sys.B, dtype=float)
    for j in range(B.shape[1]):
        b = B[:, j]
        nb, ng = np.linalg.norm(b), np.linalg.norm(g)
        if nb > 0 and ng > 0 and 1.0 - abs(b @ g) / (nb * ng) < tol:
            return True
    return False


def _next_model(sys: ct.StateSpace, rep: LoopReport):
    """The model the next pass starts from: continuous when the law was fitted so."""
    eff = rep.effect
    if eff.dynamic_law is not None:
        return eff.dynamic_law.continuous
    law = eff.law
    if eff.kind == "static" and law is not None and law.time_base == "continuous" and \
            not ct.isdtime(sys, strict=True):
        G = np.asarray(rep.channel.G, dtype=float)
        A = np.asarray(sys.A, dtype=float) + G @ law.Ddx
        B = np.asarray(sys.B, dtype=float) + G @ law.Ddu
        return named_ss(A, B, sys.C, sys.D, 0, states=sys.state_labels,
                        inputs=sys.input_labels, outputs=sys.output_labels,
                        name=f"{sys.name or 'model'}_updated")
    if rep.channel is not None and rep.channel.kind == "output" and law is not None and \
            not ct.isdtime(sys, strict=True):
        cont = _continuous_sensor(sys, rep)
        if cont is not None:
            return cont
    return rep.model.sys


def _continuous_sensor(sys: ct.StateSpace, rep: LoopReport):
    """The continuous nominal read through the sensor law of ``rep`` (a lag: its state
    last, named as in the updated model), or None.

    A later pass on the discrete updated model would lose every channel of relative
    degree 2: a discrete G enters one state, so ``C G = 0`` when that state is read only
    through the lag (zoo state_sensor, seed 424242: the damping error in eq(v1) was
    skipped by the rank condition (17), and pass 2 named a cubic sensor law on p1). A
    continuous G spreads over the sample (ZOH), and the delayed estimate reads it; and
    the joint refit (greybox.trace.joint) refits the lag's time constant with the later
    effects."""
    law = rep.effect.law
    sel = np.flatnonzero(law.coef[0]) if law.coef.shape[0] == 1 else np.zeros(0, int)
    mats = [np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D)]
    extra = list(rep.model.sys.state_labels[sys.nstates:])
    if sel.size and not law.nonlinear and all(term_kind(law.spec[j][1]).affine for j in sel):
        aug = _affine_sensor_continuous(mats, rep.model.sys, law.output, len(extra))
    elif sel.size != 1:
        return None
    else:
        _, kind, i = law.spec[sel[0]]
        aug = term_kind(kind).continuous_sensor(*mats, int(i), float(law.coef[0, sel[0]]))
    if aug is None or aug[0].shape[0] != sys.nstates + len(extra):
        return None
    return named_ss(*aug, 0, states=list(sys.state_labels) + extra, inputs=sys.input_labels,
                    outputs=sys.output_labels, name=f"{sys.name or 'model'}_updated")


def _affine_sensor_continuous(mats, upd: ct.StateSpace, i: int, h: int):
    """The continuous ``(A, B, C, D)`` read through an affine sensor law on output ``i``
    (its gain in row i of the updated model's C and D; ``h`` constant offset states, last,
    with no dynamics: ZOH keeps them constant)."""
    A, B, C, D = mats
    n = A.shape[0]
    Aa = np.zeros((n + h, n + h))
    Aa[:n, :n] = A
    Ca = np.hstack([C, np.zeros((C.shape[0], h))])
    Ca[i] = np.asarray(upd.C, dtype=float)[i]
    Da = D.copy()
    Da[i] = np.asarray(upd.D, dtype=float)[i]
    return Aa, np.vstack([B, np.zeros((h, B.shape[1]))]), Ca, Da


def _channels_for(sys: ct.StateSpace, spec, physical, n0: int):
    """Candidate channels of a later pass: the physical states' and inputs' only."""
    if spec is not None:
        out = []
        for ch in resolve_channel_spec(physical, spec):
            G = np.vstack([ch.G, np.zeros((sys.nstates - n0, ch.md))])
            out.append(replace(ch, G=G))
        return tuple(out)
    keep = set(physical.state_labels)
    return _without_definitions(physical, tuple(
        ch for ch in resolve_channel_spec(sys, None) if set(ch.equations) <= keep))


def definitions(sys: ct.StateSpace) -> list[str]:
    """The kinematic identities of a continuous model: the state equations that only say
    dp/dt = v (one nonzero in their row of A, off the diagonal and equal to 1; no input).

    A definition is never a candidate channel of :func:`close_the_loop` (unless the
    user names it in ``channels``): an unknown input there would rewrite what a state
    means (a ball on a beam: pos' = vel became pos' = 0.023 vel). A discrete model
    mixes the rows, so it has none here.
    """
    if ct.isdtime(sys, strict=True):
        return []
    A, B = np.asarray(sys.A, dtype=float), np.asarray(sys.B, dtype=float)
    out = []
    for i, name in enumerate(sys.state_labels):
        nz = np.flatnonzero(A[i])
        if nz.size == 1 and nz[0] != i and A[i, nz[0]] == 1.0 and not np.any(B[i]):
            out.append(name)
    return out


def _without_definitions(sys: ct.StateSpace, chans) -> tuple:
    """The channels that enter no kinematic identity of ``sys`` (:func:`definitions`)."""
    defs = set(definitions(sys))
    return tuple(c for c in chans if not set(c.equations) & defs)


#: The final model's one-step residuals correlating with an input beyond this many times
#: the 99 % band get a note (Silverbox, validation record: 16.5x with the input midpoint
#: held, 0.75x with its ZOH equivalent; issue 12).
INPUT_CORR_NOTE = 5.0


def _input_correlation_note(row, inputs, outputs) -> str | None:
    """A note when ``row``'s one-step residuals still correlate with an input, else None."""
    xc = np.abs(np.asarray(row.crosscorr, dtype=float))
    if xc.size == 0 or not np.all(np.isfinite(xc)) or not xc.max() > INPUT_CORR_NOTE * row.band:
        return None
    j, i, _ = np.unravel_index(int(np.argmax(xc)), xc.shape)
    return (f"the updated model's one-step residuals still correlate with input {inputs[j]} "
            f"(output {outputs[i]}: max |r| {xc.max():.2f}, {xc.max() / row.band:.0f}x the 99 % "
            f"band {row.band:.3f}): an input path the model lacks, or how the input is fed: "
            "a band-limited input (filtered noise, multisines; not held between samples) "
            "is fed to the ZOH model as greybox.zoh_equivalent_input(sys, u, dt); on "
            "closed-loop data feedback alone correlates them")


def _loop(once, sys, nominal, Q, spec, chans, delta, max_effects, dt, joint,
          sensors=None) -> LoopReport:
    """Run ``once`` until the residual is white, the gate fails or max_effects is reached.

    With two effects or more, ``joint(passes, final)`` refits them all at once
    (see :func:`_refit_jointly`); ``sensors`` (:func:`_refit_sensors`), when given,
    refits an earlier sensor's static law after each later effect. The final model's
    residuals are checked for correlation with the inputs
    (:func:`_input_correlation_note`).
    """
    rep = _loop_passes(once, sys, nominal, Q, spec, chans, delta, max_effects, dt, joint,
                       sensors)
    row = rep.table.get("updated") if rep.updated else None
    note = None if row is None else _input_correlation_note(row, sys.input_labels,
                                                            sys.output_labels)
    return rep if note is None else rep.with_decision("validate", "", note)


def _loop_passes(once, sys, nominal, Q, spec, chans, delta, max_effects, dt,
                 joint, sensors=None) -> LoopReport:
    """The passes of :func:`_loop`."""
    first = once(sys, nominal, Q, chans, delta)
    if not first.updated:
        return first
    steps, reps, bases = [], [first], [sys]
    notes = list(first.decisions)
    cur_sys, rep = sys, first
    while True:
        tb = rep.table
        steps.append(EffectStep(effect=rep.effect, channel=rep.channel.name, message=rep.message,
                                se_before=tb["nominal"].se.value, se_after=tb["updated"].se.value,
                                model=rep.model))
        if len(steps) >= max_effects:
            break
        if rep.effect.nonlinear:
            notes.append(Decision("loop", "", "several effects: the loop stops after a nonlinear "
                                  "law (the next pass would need the law in its base model)"))
            break
        nxt = _next_model(cur_sys, rep)
        nom_next = nxt if ct.isdtime(nxt, strict=True) else discretize(nxt, dt)
        try:
            rep2 = once(nxt, nom_next, rep.model.Q,
                        _channels_for(nxt, spec, sys, sys.nstates), False)
        except (GreyboxError, np.linalg.LinAlgError) as e:
            notes.append(Decision("loop", "",
                                  f"several effects: pass {len(steps) + 1} failed: {e}"))
            break
        notes.append(Decision("loop", "", f"pass {len(steps) + 1}: {rep2.message}"))
        if not rep2.updated:
            break
        if sensors is not None:
            nxt, rep2 = _with_sensors_refitted(
                sensors, reps, bases, steps, nxt, rep2, notes,
                lambda b: once(b, b if ct.isdtime(b, strict=True) else discretize(b, dt),
                               rep.model.Q, _channels_for(b, spec, sys, sys.nstates), False))
        cur_sys, rep = nxt, rep2
        reps.append(rep2)
        bases.append(nxt)
    if len(steps) == 1:
        st, ch = _narrowed(steps[0], first.channel)
        return replace(first, steps=(st,), decisions=tuple(notes), channel=ch,
                       effect=st.effect, message=st.message)
    last = reps[-1]
    table = dict(first.table)
    for k in ("updated", "updated (linearized)"):
        table.pop(k, None)
        if k in last.table:
            table[k] = last.table[k]
    model = last.model
    by_name = {r.channel.name: r.channel for r in reps}
    if not rep.effect.nonlinear:
        passes = [(b, r.channel, r.effect) for b, r in zip(bases, reps)]
        out = _refit_jointly(joint, passes, _next_model(cur_sys, rep), rep.model.Q, notes)
        if out is not None:
            jr, row = out
            steps = _refitted_steps(steps, passes, jr, row)
            alt = _retrace_last(once, joint, jr, passes, reps[-2].model.Q, steps,
                                _channels_for(jr.partials[-1], spec, sys, sys.nstates), dt,
                                notes)
            if alt is not None:
                jr, row, steps, passes = alt
            jr, row, steps, passes = _input_gains(joint, passes, jr, row, steps, dt, notes)
            table["updated"], model = row, jr.model
            steps = _without_empty(steps)
            by_name.update({ch.name: ch for _, ch, _ in passes})
    narrowed = [_narrowed(st, by_name.get(st.channel)) for st in steps]
    steps = [st for st, _ in narrowed]
    if narrowed[0][1] is not None and steps[0].channel != first.channel.name:
        first = replace(first, channel=narrowed[0][1])
    first = replace(first, effect=steps[0].effect)
    msg = (f"{len(steps)} effects found: " +
           "; then ".join(st.message.split(";")[0].replace("model error found in ", "")
                          for st in steps) + "; " + describe_before_after(table))
    nl = None
    if last.effect.nonlinear:  # the last pass's law is nonlinear: its exact model
        nl = nonlinear_update_of_linear(last).nonlinear
    return replace(first, message=msg, model=model, table=table, steps=tuple(steps),
                   decisions=tuple(notes), nonlinear=nl)


def _with_sensors_refitted(sensors, reps, bases, steps, nxt, rep, notes, again):
    """``(nxt, rep)`` after ``sensors`` (:func:`_refit_sensors`) refitted an earlier sensor
    law on the pass ``rep`` just accepted; when it did, that pass is run again on its base
    read through the refitted sensor (``again(base) -> LoopReport``: the pass's law was
    fitted beside the sensor's bias, and what it left shows up as a spurious later effect)
    and the sensor refitted once more on it. The first refit is kept where the pass run
    again updates nothing, and the pass is not run again where every refitted coefficient
    moved less than its 95 % half-width (:func:`_within_interval`: the pass was fitted
    beside a sensor law the data cannot tell from the refitted one)."""
    before = [r.effect.law for r in reps]
    nxt2, rep2 = sensors(reps, bases, steps, nxt, rep, notes)
    if rep2 is rep:
        return nxt, rep
    if all(_within_interval(b, r.effect.law) for b, r in zip(before, reps)):
        notes.append(Decision("refit", "", "the pass not run again: every refitted sensor "
                                           "coefficient moved less than its 95 % half-width"))
        return nxt2, rep2
    try:
        rep3 = again(nxt2)
    except (GreyboxError, np.linalg.LinAlgError) as e:
        notes.append(Decision("refit", "", f"the pass run again after the sensor's refit "
                                           f"failed: {e}"))
        return nxt2, rep2
    notes.append(Decision("refit", "", "the pass run again on its model read through the "
                                       f"refitted sensor: {rep3.message}"))
    if not rep3.updated:
        return nxt2, rep2
    return sensors(reps, bases, steps, nxt2, rep3, notes)


def _within_interval(old, new) -> bool:
    """Whether every coefficient of the refitted law ``new`` is within its 95 % half-width of
    the earlier law ``old`` (same terms selected): the data cannot tell the two apart, so
    a pass fitted beside ``old`` need not run again beside ``new``. True when unchanged."""
    if new is old:
        return True
    if not isinstance(old, StaticLaw) or not isinstance(new, StaticLaw) or \
            old.coef.shape != new.coef.shape or \
            not np.array_equal(old.coef != 0, new.coef != 0) or new.ci is None:
        return False
    sel = new.coef != 0
    half = np.asarray(new.ci, dtype=float)[sel]
    return bool(np.all(np.isfinite(half)) and
                np.all(np.abs(new.coef[sel] - old.coef[sel]) < half))


def _refit_sensors(P: Problem, reps, bases, steps, nxt, rep, notes):
    """An earlier pass's static sensor law (a gain, an offset) refitted on the model of the
    pass ``rep`` just accepted: ``(nxt, rep)`` with that output's row of C and D (in the
    next pass's base ``nxt`` and in ``rep``'s model) at the refitted law, its validation
    row recomputed; ``reps`` and ``steps`` (lists) get the refitted law in place.

    A sensor law does not feed back into the states, so given the later effects its
    coefficients are least squares on the updated model's simulation
    (:func:`greybox.trace.channel_trace.refit_sensor_on_states`): a gain fitted first, with
    a state equation's error still in the residual, is biased by it (zoo state_sensor: a
    -13.7 % gain found as -19.6 %, then found again on the same output by the next pass).
    """
    for k, r in enumerate(reps):
        law, lines = r.effect.law, []
        new = _sensor_refit(P, r.channel, law, bases[k], rep.model, lines,
                            f"the model of pass {len(reps) + 1}")
        if new is law:
            continue
        nxt, model = (_with_sensor_row(m, new, bases[k]) for m in (nxt, rep.model.sys))
        eff = replace(r.effect, law=new, formula=new.formula)
        reps[k] = replace(r, effect=eff)
        steps[k] = replace(steps[k], effect=eff)
        S = P.settings
        row = validate_model(model, P.y_val, P.u_val, Q=rep.model.Q, R=rep.model.R,
                             x0="estimate", name="updated", lags=S.lags, alpha=S.alpha, skip=20)
        rep = replace(rep, model=replace(rep.model, sys=model), table={**rep.table,
                                                                        "updated": row})
        notes.append(Decision("refit", r.channel.name, f"after pass {len(reps) + 1}: " +
                              "; ".join(lines) + f": {new.formula}"))
    return nxt, rep


def _sensor_refit(P: Problem, ch, law, base: ct.StateSpace, updated, lines: list,
                  simulation: str):
    """A static sensor law of the channel ``ch`` (a gain, an offset; found on the model
    ``base``) refitted on the simulation of the discrete model of ``updated``
    (UpdatedModel: its Q colours the simulation's error, for the intervals) over the
    search window (:func:`greybox.trace.channel_trace.refit_sensor_on_states`); ``law``
    itself for any other effect or when the error does not drop. ``lines`` receives the
    refit's note."""
    if ch is None or ch.kind != "output" or law is None or not isinstance(law, StaticLaw) or \
            law.nonlinear or sensor_states(law) or law.output is None:
        return law
    model = updated.sys
    i, nb = law.output, base.nstates
    Ad, Bd = np.asarray(model.A, dtype=float), np.asarray(model.B, dtype=float)
    x = lti_states(Ad, Bd @ P.us, estimate_initial_state(model, P.ys, P.us))
    cb, db = np.asarray(base.C, dtype=float)[i], np.asarray(base.D, dtype=float)[i]
    return refit_sensor_on_states(law, x[:nb], cb, db, P.ys[i], P.us, ch.labels[0],
                                  ch.units[0] if ch.units else "", lines, simulation,
                                  prune=True, noise=(Ad, updated.Q, P.R[i, i]))


def _with_sensor_row(sys: ct.StateSpace, law, base: ct.StateSpace):
    """``sys`` with the output of the sensor ``law`` (found on ``base``) reading the
    base's row of C and D plus the law's linear part (the columns of the states after
    the base's kept: a sensor's offset)."""
    i, nb = law.output, base.nstates
    C, D = np.array(sys.C, dtype=float), np.array(sys.D, dtype=float)
    C[i, :nb] = np.asarray(base.C, dtype=float)[i] + law.Ddx[0]
    D[i] = np.asarray(base.D, dtype=float)[i] + law.Ddu[0]
    return named_ss(sys.A, sys.B, C, D, sys.dt, states=sys.state_labels,
                    inputs=sys.input_labels, outputs=sys.output_labels, name=sys.name)


def _without_empty(steps: list) -> list:
    """The steps whose effect kept a term after the joint refit (a static law whose every
    term's interval contained 0 is no effect); the last kept step carries the final
    model and error."""
    def empty(st):
        law = st.effect.law if st.effect.dynamic_law is None else None
        return law is not None and int(law.npar) == 0
    kept = [st for st in steps if not empty(st)]
    if not kept or len(kept) == len(steps):
        return steps
    kept[-1] = replace(kept[-1], se_after=steps[-1].se_after, model=steps[-1].model)
    return kept


def _where(ch: Channel) -> str:
    """Where a step's message says the error is: ``"eq(v1), eq(v7)"``, ``"input F (it
    enters eq(v1), eq(v7))"``, or the channel's name (a force's direction is the report's
    to add)."""
    where = ", ".join(f"eq({s})" for s in ch.equations) or ch.name
    return f"input {ch.input} (it enters {where})" if ch.kind == "input" else where


def _narrowable(ch, law) -> bool:
    """Whether a static law of the channel ``ch`` can be stated as the law of the equations
    where it holds terms (:func:`_narrowed`): a law of several state equations, one
    component each, not a sensor's, not along one direction, with a term."""
    return ch is not None and ch.kind == "equation" and ch.md >= 2 and \
        len(ch.equations) == ch.md and isinstance(law, StaticLaw) and law.output is None and \
        "one direction" not in law.formula and bool(np.any(law.coef))


def _narrowed(st, ch):
    """``(step, channel)``: a static law of several state equations that kept a term in
    some of them only after the joint refit, stated as the law of those equations (its
    channel narrowed, :func:`greybox.trace.channels.equation_subset`; its law's rows,
    :func:`greybox.trace.laws.law_rows`; the step's message and the effect's channel
    with them); the same numbers. ``(st, ch)`` otherwise (``ch`` None: the step's channel
    is not one of the passes')."""
    law = st.effect.law
    if st.effect.dynamic_law is not None or not _narrowable(ch, law):
        return st, ch
    keep = [k for k in range(ch.md) if np.any(law.coef[k])]
    if not keep or len(keep) == ch.md:
        return st, ch
    sub = equation_subset(ch, keep)
    new = law_rows(law, keep, sub.labels, sub.units)
    eff = replace(st.effect, law=new, formula=new.formula, channel=sub.name,
                  equations=sub.equations)
    msg = st.message.replace(_where(ch), _where(sub), 1)
    return replace(st, effect=eff, channel=sub.name, message=msg), sub


def _holding(eff, law):
    """The effect ``eff`` holding the (refitted) ``law``: its static or its dynamic law."""
    if isinstance(law, (DynamicLaw, SharedLaw, SharedLaw2)):
        return replace(eff, dynamic_law=law)
    return replace(eff, law=law)


def _one_input_terms(base, ch, law) -> tuple[int, int] | None:
    """``(j, t)``: the input j whose gain error a refitted law of several state equations
    states row by row, and its term's index t in ``law.spec``: every term of ``law`` is
    input j's, in at least two rows, each where j enters (``B[:, j]``); None otherwise."""
    if ch.kind != "equation" or ch.md < 2 or not isinstance(law, StaticLaw) or \
            law.nonlinear or law.output is not None:
        return None
    used = np.flatnonzero(np.any(law.coef != 0, axis=0))
    if len(used) != 1 or law.spec[used[0]][1] != "u":
        return None
    t = int(used[0])
    j = int(law.spec[t][2])
    rows = np.flatnonzero(np.asarray(ch.G, dtype=float) @ (law.coef[:, t] != 0))
    B = np.asarray(base.B, dtype=float)[:, j]
    return (j, t) if len(rows) >= 2 and np.all(B[rows] != 0) else None


def _input_gains(joint, passes, jr, row, steps, dt, notes):
    """``(jr, row, steps, passes)`` with each refitted law of several equations that states an
    input's gain error row by row (``d_v1 = -0.295*F; d_v7 = 0.171*F`` where F enters v1
    and v7: :func:`_one_input_terms`) tried as that input's channel (one gain, ``G =
    B[:, j]``) and kept where the one criterion prefers the set so refitted
    (``joint.prefers``: an equal fit with fewer parameters wins). Zoo state_input: an
    actuator's gain error beside a damping error was named as a law of F in two equations
    at two coefficients, each 31.7 % of B's entry (issue 27)."""
    for k, ((base, ch, eff), st, law) in enumerate(zip(passes, steps, jr.laws)):
        found = _one_input_terms(base, ch, law)
        if found is None:
            continue
        j, t = found
        ch_in = input_channel(base, j)
        b = np.asarray(base.B, dtype=float)[:, j]
        added = np.asarray(ch.G, dtype=float) @ law.Ddu[:, j]  # what the law adds to B[:, j]
        c = float(added @ b / (b @ b))
        hold = None if law.hold is None else LawHold.of(np.asarray(base.A, dtype=float),
                                                         ch_in.G, dt)
        new = one_term_law(law, t, c, ch_in.labels[0], ch_in.units[0], base.nstates,
                           base.ninputs, hold)
        jc = jr.continuous
        Bf = np.asarray(jc.B, dtype=float).copy()
        Bf[:base.nstates, j] += c * b - added
        final = named_ss(jc.A, Bf, jc.C, jc.D, 0, states=jc.state_labels,
                         inputs=jc.input_labels, outputs=jc.output_labels, name=jc.name)
        alt = [(b_, c_, _holding(e_, l_)) for (b_, c_, e_), l_ in zip(passes, jr.laws)]
        alt[k] = (base, ch_in, replace(eff, law=new, dynamic_law=None, formula=new.formula))
        what = f"{ch.name}'s law of {ch_in.input} tried as {ch_in.name} (one gain)"
        try:
            out = joint(alt, final, jr.model.Q, always=True)
        except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
            out = e
        if not isinstance(out, tuple):
            notes.append(Decision("refit", "", f"{what}: no refit ({out})"))
            continue
        better, how = joint.prefers(out[0], jr)
        notes.append(Decision("refit", "", f"{what}, by the criterion: {how}: " +
                              (f"{ch_in.name} kept" if better else f"{ch.name} kept")))
        if not better:
            continue
        st2 = replace(st, channel=ch_in.name,
                      message=st.message.replace(_where(ch), _where(ch_in), 1),
                      effect=replace(st.effect, channel=ch_in.name, equations=ch_in.equations))
        jr, row = out
        passes = alt
        steps = _refitted_steps(steps[:k] + [st2] + steps[k + 1:], passes, jr, row)
    return jr, row, steps, passes


def _refit_jointly(joint, passes, final, Qf, notes, always: bool = False):
    """Refit every effect at once by output error; ``(JointRefinement, validation row)``.

    None when an effect cannot be refitted (a discrete-time or nonlinear
    law), when the refit fails, or when it does not lower the estimation
    output error (or keep it within 1 % with fewer coefficients), unless ``always``
    (an alternative set, compared with another refit by the criterion).
    """
    try:
        out = joint(passes, final, Qf, always=always)
    except (GreyboxError, np.linalg.LinAlgError, ValueError) as e:
        notes.append(Decision("refit", "", f"joint refinement failed: {e}"))
        return None
    if out is None:
        return None
    jr, row = out
    drop = f"; dropped {', '.join(jr.dropped)}" if jr.dropped else ""
    notes.append(Decision(
        "refit", "", f"joint refinement of the {len(passes)} effects by output error: estimation "
        f"SE {jr.se_before:.3g}% -> {jr.se_after:.3g}%, {jr.npar_before} -> "
        f"{jr.npar_after} coefficients{drop}" +
        ("" if row is not None else " (not kept: no better)")))
    return None if row is None else (jr, row)


def _effect_phrase(kind: str, order: int) -> str:
    """``"static effect"`` or ``"dynamic effect of order 2"``: an effect in a message."""
    return f"{kind} effect{'' if kind == 'static' else f' of order {order}'}"


def _refitted_steps(steps, passes, jr, row):
    """The steps with their effects' laws, formulas and notes at the refitted values."""
    new = []
    for st, (base, ch, _), law in zip(steps, passes, jr.laws):
        eff = st.effect
        if isinstance(law, (DynamicLaw, SharedLaw, SharedLaw2)):
            eff = replace(eff, formula=law.formula, dynamic_law=law)
        else:
            eff = replace(eff, formula=law.formula, law=law,
                          parameter_notes=parameter_notes(base, ch, law))
            if eff.dynamic_law is not None:  # every lag dropped: the feedthrough, static
                st = replace(st, message=st.message.replace(
                    _effect_phrase(eff.kind, eff.order), _effect_phrase("static", 0), 1))
                eff = replace(eff, kind="static", order=0, dynamic_law=None, subsystem=None)
        new.append(replace(st, effect=eff))
    new[-1] = replace(new[-1], se_after=row.se.value, model=jr.model)
    return new


def _retrace_last(once, joint, jr, passes, Q, steps, chans, dt, notes):
    """Trace the last effect again on the earlier effects at their refitted values.

    An earlier pass's law can borrow part of a later effect (a static law
    fitted first absorbs some of an actuator lag); the last pass then traced
    what was left and may have picked the wrong drivers. Once the joint
    refit has dropped the borrowed terms, the last effect is traced again on
    that model and the whole set refitted; the better set by the one criterion
    (``joint.prefers``: an equal fit with fewer terms wins) is kept. Returns ``(jr, row, steps,
    passes)`` or None. Not traced again where
    the joint refit moved no coefficient by its 95 % half-width and dropped no term
    (``jr.moved`` False): the last pass then saw what it would see now.
    """
    if not jr.moved:
        notes.append(Decision("refit", "", "re-trace of the last effect skipped: the joint "
                                           "refit moved no coefficient by its 95 % "
                                           "half-width and dropped none"))
        return None
    base = jr.partials[-1]
    try:
        rep = once(base, discretize(base, dt), Q, chans, False)
    except (GreyboxError, np.linalg.LinAlgError) as e:
        notes.append(Decision("refit", "", f"re-trace of the last effect failed: {e}"))
        return None
    if not rep.updated or rep.effect.nonlinear:
        notes.append(Decision("refit", "", "re-trace of the last effect on the refitted model: "
                              + rep.message))
        return None
    earlier = [(b, ch, st.effect) for (b, ch, _), st in zip(passes[:-1], steps[:-1])]
    alt = passes[:-1] + [(base, rep.channel, rep.effect)]
    # an alternative set: the one criterion compares it with the refit at hand (its own
    # start is no yardstick; zoo two_static 270939893 #1: the re-traced static law refitted
    # to the same SE, 0.364 %, at 2 parameters against 7, was dropped as "no better")
    out = _refit_jointly(joint, earlier + [(base, rep.channel, rep.effect)],
                         _next_model(base, rep), rep.model.Q, notes, always=True)
    if out is None:
        notes.append(Decision("refit", "", "re-trace of the last effect on the refitted model: "
                              "no better"))
        return None
    better, how = joint.prefers(out[0], jr)
    if not better:
        notes.append(Decision("refit", "", "re-trace of the last effect on the refitted model: "
                              f"no better by the criterion ({how})"))
        return None
    notes.append(Decision("refit", "", f"the re-traced set by the criterion: {how}"))
    jr2, row2 = out
    tb = rep.table
    last = EffectStep(effect=rep.effect, channel=rep.channel.name, message=rep.message,
                      se_before=tb["nominal"].se.value, se_after=tb["updated"].se.value,
                      model=rep.model)
    notes.append(Decision("refit", "", "re-trace of the last effect on the refitted model: "
                          + rep.message))
    return jr2, row2, _refitted_steps(steps[:-1] + [last], alt, jr2, row2), alt
