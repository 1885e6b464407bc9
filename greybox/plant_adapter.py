"""Plant adapters: one interface over the kinds of model close the loop judges.

A stage that simulates a model, runs its one-step predictor or builds its
validation row asks the adapter, not the model's type:

- :class:`LinearPlant`: a discrete ``StateSpace``; exact LTI simulation and the
  Kalman predictor (the fast constant-gain paths of :mod:`greybox.filters`).
- :class:`LawPlant`: a discrete ``StateSpace`` plus a static law entering
  through G (the nominal and the law found); the law's own simulation and an
  extended Kalman predictor (its gain from the law's local slope).
- :class:`NonlinearPlant`: a discrete ``NonlinearIOSystem`` (a continuous one
  discretized with RK4) with a linear output map; its RK4 simulation and the
  unscented predictor.

Every adapter has ``order``, ``output_labels``, ``filter(y, u, Q=, R=)`` (its
one-step predictor's :class:`~greybox.FilterResult` on a record: the residual
stage's innovations), ``run(y, u, Q=, R=, skip=)``
(a :class:`greybox.validate.Run`: simulation and prediction, with the reason
when either is undefined), ``simulate(u, x0)`` (outputs, shape (noutputs,
nsteps)) and ``linearize(x_op, u_op)`` (a discrete ``StateSpace``).
:func:`validation` turns any adapter's run into the same
:class:`~greybox.validate.ModelValidation` row.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import control as ct
import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from ._lti import lti_states
from ._validation import MAX_MAGNITUDE
from .exceptions import GreyboxError
from .filters import FilterResult, kalman_filter, ukf
from .nonlinear import linear_output_map, linearize_at, simulate_batch, simulate_nonlinear
from .terms import term_kind
from .trace.laws import StaticLaw, ekf_predict_with_law, simulate_with_law
from .validate import (
    SENSITIVE_REASON,
    ModelValidation,
    Run,
    estimate_initial_state,
    linear_run,
    simulate_output,
    start_state,
    validation_row,
)

__all__ = ["LinearPlant", "LawPlant", "NonlinearPlant", "validation", "bounded", "SENSITIVE"]

#: A nonlinear model's simulation error is undefined when, over the record's last half,
#: its simulation started within the 95 % ellipsoid of the filter's state estimate
#: still moves by at least this fraction of that error (or of the measurement noise):
#: the error then measures where the simulation started (a chaotic or neutrally stable
#: plant), not the model, and PE compares models instead.
SENSITIVE = 0.5


def bounded(y_sim: NDArray) -> bool:
    """Finite and below the magnitude the metrics accept (else: a diverged simulation).

    A simulation that diverges slowly can stay finite (e.g. 4e215 on the cascaded
    tanks with a candidate law) and would make the metrics refuse it as bad data.
    """
    return bool(np.all(np.isfinite(y_sim)) and np.max(np.abs(y_sim), initial=0.0)
                <= MAX_MAGNITUDE)


@dataclass(frozen=True)
class LinearPlant:
    """A discrete ``StateSpace`` (its states' names kept).

    Parameters
    ----------
    sys : control.StateSpace
        Discrete model from the measured inputs to the measured outputs.
    x0 : ndarray, shape (nstates,), "estimate" or None
        Where its simulation and predictor start on a record: a given state,
        the least-squares estimate from the record's first samples
        (:func:`greybox.validate.estimate_initial_state`), or zero (None).
    """

    sys: ct.StateSpace = field(repr=False)
    x0: object = "estimate"

    @property
    def order(self) -> int:
        return self.sys.nstates

    @property
    def output_labels(self) -> tuple[str, ...]:
        return tuple(self.sys.output_labels)

    def initial_state(self, y: NDArray, u: NDArray) -> NDArray:
        """The state the record starts from, shape (nstates,)."""
        return start_state(self.sys, self.x0, y, u)

    def simulate(self, u: NDArray, x0: NDArray) -> NDArray:
        """Outputs from ``x0`` under the inputs ``u``, shape (noutputs, nsteps)."""
        return simulate_output(self.sys, u, x0)

    def filter(self, y: NDArray, u: NDArray, *, Q, R) -> FilterResult:
        """The Kalman filter on the record from its default start (zero state; the gain
        settles within the record: :meth:`greybox.FilterResult.settled`)."""
        return kalman_filter(self.sys, y, u, Q=Q, R=R)

    def run(self, y: NDArray, u: NDArray, *, Q, R, skip: int = 0) -> Run:
        """Simulation and Kalman prediction from :meth:`initial_state` (``skip`` unused: the
        simulation starts at the first sample)."""
        return linear_run(self.sys, y, u, Q=Q, R=R, x0=self.initial_state(y, u))

    def linearize(self, x_op=None, u_op=None) -> ct.StateSpace:
        """The model itself (it is linear)."""
        return self.sys


@dataclass(frozen=True)
class LawPlant:
    """A discrete ``StateSpace`` plus a static law: x+ = A x + B u + G law(x, u) (or a
    sensor law added to one output).

    Parameters
    ----------
    sys : control.StateSpace
        The discrete model the law enters (the trace's model).
    G : ndarray, shape (nstates, ncomponents)
        Where the law's components enter.
    law : StaticLaw
    linear : control.StateSpace
        The updated model's linear part: the directions its initial state is
        estimated along (:meth:`initial_state`).
    order : int, optional
        States counted in the report (default: the linear part's).
    """

    sys: ct.StateSpace = field(repr=False)
    G: NDArray = field(repr=False)
    law: StaticLaw = field(repr=False)
    linear: ct.StateSpace = field(repr=False)
    order: int | None = None

    def __post_init__(self):
        if self.order is None:
            object.__setattr__(self, "order", self.linear.nstates)

    @property
    def output_labels(self) -> tuple[str, ...]:
        return tuple(self.linear.output_labels)

    def initial_state(self, y: NDArray, u: NDArray) -> NDArray:
        """Least squares on the first samples along the linear part's directions (a short
        window: over a long one the law's nonlinearity biases x0). For an affine law
        (linear terms and a constant, an offset the linear part lacks that would
        otherwise be read as initial state) against the law's own free response from
        x0 = 0, exact then; else the better start, by the law's own simulation over the
        same window, of the linear part's estimate and least squares through C on the
        first sample: a law the linear part lacks (Coulomb friction) can make the first
        wrong, and a mass the friction holds keeps a wrong start (a zoo draw's 'updated'
        row read 4.6 % from it, 1.3 % from the second)."""
        law = self.law
        affine = all(term_kind(law.spec[j][1]).affine
                     for j in np.flatnonzero(np.any(law.coef != 0, axis=0)))
        if not affine:
            starts = [estimate_initial_state(self.linear, y, u, slow_modes=False),
                      first_sample_state(self.sys.C, self.sys.D, y, u)]
            k = min(y.shape[1], max(10 * self.sys.nstates, 50))
            with np.errstate(all="ignore"):
                sse = [float(np.sum((y[:, :k] - self.simulate(u[:, :k], x0)) ** 2))
                       for x0 in starts]
            # NaN (a diverging start) is never the better; ties keep the linear estimate
            return starts[1] if sse[1] < sse[0] or not np.isfinite(sse[0]) else starts[0]
        return estimate_initial_state(self.linear, y, u, slow_modes=False,
                                      free=lambda k: self.simulate(
                                          u[:, :k], np.zeros(self.sys.nstates)))

    def simulate(self, u: NDArray, x0: NDArray) -> NDArray:
        """Outputs of the model with its law from ``x0``, shape (noutputs, nsteps).

        A sensor law (``law.output``, G = 0, no hold) adds to one output and leaves
        the state recursion linear: its states are then one modal, vectorized LTI
        pass instead of a Python loop over the samples (~18 us each: 1.8 s per
        candidate on 1e5 samples).
        """
        law, G = self.law, np.asarray(self.G, dtype=float)
        if law.output is None or law.hold is not None or np.any(G):
            return simulate_with_law(self.sys, G, law, u, x0)
        A, B, C, D = (np.asarray(a, dtype=float)
                      for a in (self.sys.A, self.sys.B, self.sys.C, self.sys.D))
        x = lti_states(A, B @ u, np.asarray(x0, dtype=float))
        with np.errstate(over="ignore", invalid="ignore"):  # diverged: the SE is inf
            y = C @ x + D @ u
            y[law.output] += law.evaluate(x, u)[0]
        return y

    def run(self, y: NDArray, u: NDArray, *, Q, R, skip: int = 0) -> Run:
        """The law's own simulation from :meth:`initial_state` (the linearized model's
        eigenvalues say nothing about it: a friction law's linear surrogate may be
        unstable) and the extended Kalman predictor of the law; a constant gain designed
        on the law's linear stand-in diverges when its slope changes sign (a |.| sensor:
        its PE read ~1e28 %)."""
        law, G = self.law, self.G
        x0 = self.initial_state(y, u)
        se_reason = pe_reason = ""
        y_sim = simulate_with_law(self.sys, G, law, u, x0)
        if not np.all(np.isfinite(y_sim)):
            se_reason = "the simulation diverged: its simulation error is undefined"
            y_sim = np.full(y.shape, np.nan)
        y_pred = ekf_predict_with_law(self.sys, G, law, y, u, x0, Q=Q, R=R)
        if not np.all(np.isfinite(y_pred[:, skip:])):
            pe_reason = "the one-step predictor (extended Kalman filter) diverged"
            y_pred = np.full(y.shape, np.nan)
        return Run(y_sim=y_sim, y_pred=y_pred, residuals=y - y_pred, se_reason=se_reason,
                   pe_reason=pe_reason)

    def linearize(self, x_op=None, u_op=None) -> ct.StateSpace:
        """The law's best linear part folded into the model (the updated StateSpace)."""
        return self.linear


def first_sample_state(C, D, y: NDArray, u: NDArray) -> NDArray:
    """x0 from the first sample alone: least squares through ``y[0] = C x0 + D u[0]``
    (minimum norm where C does not see a state), shape (nstates,)."""
    C, D = np.asarray(C, dtype=float), np.asarray(D, dtype=float)
    return np.linalg.lstsq(C, y[:, 0] - D @ u[:, 0], rcond=None)[0]


@dataclass(frozen=True)
class NonlinearPlant:
    """A discrete ``NonlinearIOSystem`` with a linear output map y = C x + D u.

    Parameters
    ----------
    sys : control.NonlinearIOSystem
        Discrete model (a continuous one discretized with RK4 sub-steps).
    P0 : ndarray, shape (nstates, nstates)
        The unscented predictor's initial state covariance.
    order : int
        States counted in the report (the continuous model's).
    x0 : ndarray, shape (nstates,), optional
        Where the predictor starts on a record; default: least squares through
        the model's C on the first sample (:meth:`initial_state`).
    """

    sys: object = field(repr=False)
    P0: NDArray = field(repr=False)
    order: int = 0
    x0: NDArray | None = field(default=None, repr=False)

    @property
    def output_labels(self) -> tuple[str, ...]:
        return tuple(self.sys.output_labels)

    def initial_state(self, y: NDArray, u: NDArray) -> NDArray:
        """The given ``x0``, or x0 from the first sample: least squares through C."""
        if self.x0 is not None:
            return np.asarray(self.x0, dtype=float)
        return first_sample_state(*linear_output_map(self.sys), y, u)

    def filter(self, y: NDArray, u: NDArray, *, Q, R) -> FilterResult:
        """The unscented Kalman filter on the record from :meth:`initial_state` and P0."""
        return ukf(self.sys, y, u, Q=Q, R=R, x0=self.initial_state(y, u), P0=self.P0)

    def simulate(self, u: NDArray, x0: NDArray) -> NDArray:
        """Outputs from ``x0``, shape (noutputs, nsteps); raises GreyboxError (or
        FloatingPointError) when the simulation diverges."""
        C, D = linear_output_map(self.sys)
        return C @ simulate_nonlinear(self.sys, u, x0=x0).x + D @ u

    def run(self, y: NDArray, u: NDArray, *, Q, R, skip: int = 0) -> Run:
        """The unscented predictor from :meth:`initial_state`; the simulation from its
        filtered state at sample ``skip`` (the filter's own estimate before that).

        The simulation error is undefined when the simulation diverges, or when it
        is sensitive to where it starts (:data:`SENSITIVE`, :meth:`_sensitivity`).
        """
        C, D = linear_output_map(self.sys)
        kf = self.filter(y, u, Q=Q, R=R)
        y_pred = C @ kf.x_pred + D @ u
        y_sim = C @ kf.x_filt + D @ u
        se_reason = ""
        try:
            sim = simulate_nonlinear(self.sys, u[:, skip:], x0=kf.x_filt[:, skip])
            y_sim[:, skip:] = C @ sim.x + D @ u[:, skip:]
        except (GreyboxError, FloatingPointError) as ex:
            se_reason = f"the simulation diverged ({ex}): its simulation error is undefined"
        if not se_reason and not bounded(y_sim):
            se_reason = "the simulation diverged: its simulation error is undefined"
        if not se_reason:
            # P[skip|skip]: the same filter over the first skip + 1 samples (the whole
            # record's covariance history would cost n^2 N numbers)
            head = self.filter(y[:, :skip + 1], u[:, :skip + 1], Q=Q, R=R)
            se_reason = self._sensitivity(y, u, y_sim, kf.x_filt[:, skip], head.P_filt,
                                          skip, R) if _worse(y, y_sim, y_pred, skip) else ""
        if se_reason:
            y_sim = np.full(y.shape, np.nan)
        return Run(y_sim=y_sim, y_pred=y_pred, residuals=y - y_pred, se_reason=se_reason)

    def _sensitivity(self, y, u, y_sim, x_start, P_start, skip: int, R) -> str:
        """Why the simulation error says nothing of the model ("" when it does).

        The filter knows the state at sample ``skip`` to within its 95 % ellipsoid
        (covariance ``P_start``). The simulation is started at the ends of that
        ellipsoid's principal axes (2 n starts). A stable model forgets its start; a
        chaotic or neutrally stable one does not. When, over the record's last half,
        the farthest start still moves the simulation by at least :data:`SENSITIVE`
        of its error against y (or of the measurement noise, when that is larger; both
        eq. 42's relative RMS, averaged over the outputs), the error measures where the
        simulation started, not the model.
        """
        C, D = linear_output_map(self.sys)
        n, N = x_start.size, y.shape[1] - skip
        late = skip + N // 2
        w, V = np.linalg.eigh(0.5 * (P_start + P_start.T))
        axes = V * np.sqrt(np.clip(w, 0.0, None) * chi2.ppf(0.95, n))
        yl, sl, ut = y[:, late:], y_sim[:, late:], u[:, skip:]
        scale = np.sqrt(np.mean(yl ** 2, axis=1))
        if not np.all(scale > 0):
            return ""
        err = float(_relative_rms(yl, sl, scale))
        noise = float(np.mean(np.sqrt(np.clip(np.diag(np.atleast_2d(R)), 0.0, None)) / scale))
        bar = SENSITIVE * max(err, noise)
        X = simulate_batch(self.sys, ut, x_start[:, None] + np.hstack([axes, -axes]))
        with np.errstate(all="ignore"):  # a diverged start: moved inf
            alt = np.einsum("pn,nsk->psk", C, X[:, :, late - skip:]) + \
                (D @ ut[:, late - skip:])[:, None]
        moved = _relative_rms(sl, alt, scale)  # against the simulation, not y
        ok = np.isfinite(moved) & np.all(np.abs(alt) <= MAX_MAGNITUDE, axis=(0, 2))
        moved = np.where(ok, moved, np.inf)
        if float(np.max(moved)) >= bar:
            return (f"{SENSITIVE_REASON}: started within the 95 % ellipsoid of the "
                    f"filter's state estimate, over the record's last half it still "
                    f"moves by {100 * float(np.max(moved)):.3g} % of y (its error against "
                    f"y there: {100 * err:.3g} %), so its simulation error measures the "
                    f"start, not the model; PE used")
        return ""

    def linearize(self, x_op: NDArray, u_op: NDArray) -> ct.StateSpace:
        """The discrete linearization at (x_op, u_op) (:func:`greybox.linearize_at`)."""
        return linearize_at(self.sys, x_op, u_op)


def _relative_rms(y: NDArray, y_hat: NDArray, scale: NDArray) -> NDArray:
    """Eq. 42's relative RMS (a fraction) averaged over the outputs: y (p, N) against
    y_hat (p, N) or (p, S, N) for S candidates; NaN or inf where y_hat is not finite."""
    with np.errstate(all="ignore"):
        dev = np.sqrt(np.mean((y_hat - (y if y_hat.ndim == 2 else y[:, None])) ** 2,
                              axis=-1))
        return np.mean(dev / (scale if y_hat.ndim == 2 else scale[:, None]), axis=0)


def _worse(y: NDArray, y_sim: NDArray, y_pred: NDArray, skip: int) -> bool:
    """Whether the simulation follows y worse than the one-step predictor does (eq. 42's
    relative RMS after ``skip``, averaged over the outputs): only then can its error be
    inflated by where it started (a simulation as good as the predictor is not)."""
    yt = y[:, skip:]
    scale = np.sqrt(np.mean(yt ** 2, axis=1))
    return not _relative_rms(yt, y_sim[:, skip:], scale) <= _relative_rms(
        yt, y_pred[:, skip:], scale)


def validation(plant, y: NDArray, u: NDArray, *, Q, R, name: str, lags: int, alpha: float,
               skip: int) -> ModelValidation:
    """The validation row of any plant adapter on the record (y, u): SE of its simulation,
    PE of its one-step predictor, and the residual tests after ``skip`` samples.

    Parameters
    ----------
    plant : LinearPlant or LawPlant or NonlinearPlant
    y : ndarray, shape (noutputs, nsteps)
    u : ndarray, shape (ninputs, nsteps)
    Q, R : ndarray
        The predictor's process and measurement noise covariances.
    name : str
        The row's name ("nominal", "updated", ...).
    lags : int
        Lags of the residual correlations and the whiteness test.
    alpha : float
        Significance level of the whiteness test.
    skip : int
        Leading samples left out of SE, PE and the tests.
    """
    return validation_row(plant.run(y, u, Q=Q, R=R, skip=skip), y, u, name=name,
                          order=plant.order, output_labels=plant.output_labels, lags=lags,
                          alpha=alpha, skip=skip)
