"""Validation of a model on data: simulation error, prediction error, residual tests.

Works for any discrete python-control ``StateSpace``, not only greybox's own.
SE and PE are eq. (42) with the simulated output and with the one-step
prediction of a Kalman predictor built from the model's own noise
covariances (PAPER_NOTES §5, §8.8).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import control as ct
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._lti import lti_output
from ._validation import (
    check_discrete,
    check_positive,
    check_same_length,
    check_signal,
    check_vector,
)
from .exceptions import DimensionError
from .filters import kalman_filter
from .metrics import (
    RelativeError,
    WhitenessTest,
    autocorrelation,
    correlation_band,
    cross_correlation,
    relative_error,
    whiteness_test,
)

__all__ = ["ModelValidation", "Run", "validate_model", "validation_row", "linear_run",
           "start_state",
           "simulate_output", "estimate_initial_state",
           "unstable_reason", "undefined_error", "UNSTABLE_TOL", "before_after",
           "describe_before_after", "has_marginal_pole", "MARGINAL_TOL", "SENSITIVE_REASON"]

#: How the reason of an undefined simulation error starts when the simulation depends on
#: where it starts more than on the model (:class:`greybox.plant_adapter.NonlinearPlant`).
SENSITIVE_REASON = "the simulation is sensitive to where it starts"

#: A discrete model whose spectral radius exceeds ``1 + UNSTABLE_TOL`` is unstable:
#: its simulation error is undefined (the simulation diverges from any error in x0).
UNSTABLE_TOL = 1e-6
#: Over a record of N samples, an unstable mode counts only if it grows by more
#: than this factor (rho**N): a radius of 1 + 1e-5 over 8000 samples (+8 %) is as
#: harmless as an integrator.
UNSTABLE_GROWTH = 10.0


#: A discrete pole whose modulus is above ``1 - MARGINAL_TOL`` counts as on the unit
#: circle (an integrator discretized: exactly 1; a lightly damped mode stays below).
MARGINAL_TOL = 1e-9


def has_marginal_pole(sys: ct.StateSpace) -> bool:
    """True when a discrete model has a pole on or outside the unit circle (an integrator:
    a position driven by a velocity) among the states the inputs reach; its simulation
    error drifts with the initial state and the noise, so it neither judges nor chooses
    between models (PE does).

    States no input reaches (through B, or through A from a reached state) run from their
    initial state alone, so a simulation of them has no input error to accumulate: a
    sensor's constant offset or drift (poles at 1) is estimated with the initial state
    and does not make the model marginal. Reach is read from the sparsity of A and B;
    the poles are those of A on the reached states (A is block triangular there).

    Parameters
    ----------
    sys : control.StateSpace
        Discrete model.

    Returns
    -------
    bool
    """
    A = np.asarray(sys.A, dtype=float)
    if not A.size:
        return False
    reached = np.any(np.asarray(sys.B, dtype=float) != 0, axis=1)
    while True:
        more = reached | np.any(A[:, reached] != 0, axis=1)
        if np.array_equal(more, reached):
            break
        reached = more
    Ar = A[np.ix_(reached, reached)]
    return bool(Ar.size) and bool(np.max(np.abs(np.linalg.eigvals(Ar))) > 1.0 - MARGINAL_TOL)


def unstable_reason(sys: ct.StateSpace, nsteps: int | None = None) -> str:
    """Why a discrete model's simulation error is undefined, or "" when it is defined.

    A model with an eigenvalue outside the unit circle (spectral radius
    above ``1 + UNSTABLE_TOL``, growing by more than ``UNSTABLE_GROWTH``
    over ``nsteps`` samples) amplifies any initial-state or input error
    without bound, so its simulated output says nothing about the model:
    judge it by the one-step prediction error (PE) and the innovations.
    Marginal modes (eigenvalues on the unit circle, e.g. integrators) keep
    SE defined.

    Parameters
    ----------
    sys : control.StateSpace
        Discrete model.
    nsteps : int, optional
        Length of the record the model is simulated over.

    Returns
    -------
    str
    """
    A = np.asarray(sys.A, dtype=float)
    if A.size == 0:
        return ""
    rho = float(np.max(np.abs(np.linalg.eigvals(A))))
    if rho <= 1.0 + UNSTABLE_TOL or (
            nsteps is not None and nsteps * np.log(rho) <= np.log(UNSTABLE_GROWTH)):
        return ""
    return (f"the model is unstable (spectral radius {rho:.6g} > 1): its simulation error is "
            f"undefined; PE used")


def undefined_error(noutputs: int) -> RelativeError:
    """A :class:`RelativeError` that could not be computed: NaN value and per-output values.

    Parameters
    ----------
    noutputs : int
        Number of outputs.

    Returns
    -------
    RelativeError
    """
    return RelativeError(value=float("nan"), per_output=np.full(noutputs, np.nan),
                         squared=False)


@dataclass(frozen=True)
class ModelValidation:
    """Validation of one model on one data record.

    Attributes
    ----------
    name : str
        Model name.
    order : int
        Number of states.
    se : RelativeError
        Simulation error (eq. 42, relative RMS) [%]; NaN when undefined
        (see ``se_reason``).
    pe : RelativeError
        One-step prediction error [%]; NaN when undefined (see ``pe_reason``).
    whiteness : WhitenessTest
        Ljung-Box test of the one-step prediction residuals.
    autocorr : ndarray, shape (noutputs, lags + 1)
        Autocorrelation of the prediction residuals.
    crosscorr : ndarray, shape (ninputs, noutputs, 2 lags + 1)
        Input-residual cross-correlation, lags -lags..lags.
    band : float
        Half-width of the 99 % band of both correlations.
    y_sim : ndarray, shape (noutputs, nsteps)
        Simulated output (NaN when the simulation is undefined).
    y_pred : ndarray, shape (noutputs, nsteps)
        One-step predicted output.
    residuals : ndarray, shape (noutputs, nsteps)
        One-step prediction residuals.
    output_labels : tuple of str
    se_reason : str
        Why ``se`` is undefined (an unstable model, a diverged simulation),
        or "".
    pe_reason : str
        Why ``pe`` is undefined (the one-step predictor diverged), or "".
    """

    name: str
    order: int
    se: RelativeError
    pe: RelativeError
    whiteness: WhitenessTest
    autocorr: NDArray[np.float64] = field(repr=False)
    crosscorr: NDArray[np.float64] = field(repr=False)
    band: float = field(repr=False)
    y_sim: NDArray[np.float64] = field(repr=False)
    y_pred: NDArray[np.float64] = field(repr=False)
    residuals: NDArray[np.float64] = field(repr=False)
    output_labels: tuple[str, ...] = ()
    se_reason: str = ""
    pe_reason: str = ""

    @property
    def se_defined(self) -> bool:
        """The simulation error is defined (stable model, finite simulation)."""
        return not self.se_reason

    @property
    def pe_defined(self) -> bool:
        """The one-step prediction error is defined (the predictor did not diverge)."""
        return not self.pe_reason

    def as_dict(self) -> dict:
        """JSON-ready summary (an undefined SE is None, with ``se_reason``)."""
        out = {"order": self.order,
               "se": self.se.value if self.se_defined else None,
               "pe": self.pe.value if self.pe_defined else None,
               "se_per_output": self.se.per_output.tolist() if self.se_defined else None,
               "pe_per_output": self.pe.per_output.tolist() if self.pe_defined else None,
               "whiteness_pvalue": self.whiteness.pvalue.tolist()}
        if not self.se_defined:
            out["se_reason"] = self.se_reason
        if not self.pe_defined:
            out["pe_reason"] = self.pe_reason
        return out


def simulate_output(sys: ct.StateSpace, u: NDArray, x0: NDArray | None = None) -> NDArray:
    """Noise-free output of a discrete model, shape (noutputs, nsteps)."""
    A, B, C, D = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D))
    x0 = np.zeros(A.shape[0]) if x0 is None else x0
    with np.errstate(over="ignore", invalid="ignore"):  # diverged: callers check
        return lti_output(A, B, C, D, u, x0)


def estimate_initial_state(sys: ct.StateSpace, y: NDArray, u: NDArray, *,
                           nsamples: int | None = None, slow_modes: bool = True,
                           free=None) -> NDArray[np.float64]:
    """Least-squares initial state from the first samples (PAPER_NOTES §9.7).

    Solves ``y[k] - y0[k] = C A^k x0`` for k < nsamples, with ``y0`` the
    response from x0 = 0. ``nsamples`` defaults to ``max(10 n, 50)``, or to 3
    time constants of the slowest stable mode if longer (at most 2000): a slow
    hidden state is barely observed in 50 samples, and its noisy initial value
    then costs more simulation error than a wrong law.
    Directions of x0 that the window does not observe are set to zero
    (minimum-norm solution).

    Parameters
    ----------
    sys : control.StateSpace
        Discrete model.
    y : ndarray, shape (noutputs, nsteps)
        Measured outputs.
    u : ndarray, shape (ninputs, nsteps)
        Inputs.
    nsamples : int, optional
        Length of the window.
    slow_modes : bool
        Lengthen the default window to cover the slowest stable mode (above).
        False for the linear part of a model with a nonlinear law: over a long
        window the law's nonlinearity, which ``sys`` lacks, biases x0.
    free : callable, optional
        ``free(nw) -> ndarray (noutputs, nw)``: the model's response from
        x0 = 0 to the first nw inputs, when the model is more than ``sys``
        (``sys`` plus a law: an offset or a nonlinearity that ``sys`` lacks
        would otherwise be read as initial state). Default: ``sys``'s own.

    Returns
    -------
    ndarray, shape (nstates,)
    """
    check_discrete(sys)
    y = check_signal(y, sys.noutputs, "y", min_steps=1)
    u = check_signal(u, sys.ninputs, "u")
    check_same_length(("y", y), ("u", u))
    A, C = np.asarray(sys.A, dtype=float), np.asarray(sys.C, dtype=float)
    n = A.shape[0]
    if n == 0:
        return np.zeros(0)
    if nsamples is not None:
        nsamples = check_positive(nsamples, "nsamples", integer=True)
    lam = np.linalg.eigvals(A)
    mags = np.abs(lam)
    Nw = min(y.shape[1], nsamples or (_x0_window(mags, n) if slow_modes else max(10 * n, 50)))
    if nsamples is None and slow_modes and \
            has_free_ramp(A, np.asarray(sys.B, dtype=float), eigenvalues=lam):
        Nw = min(y.shape[1], max(Nw, X0_WINDOW_MAX))
    if np.max(mags) > 1.0 + 1e-6 and Nw > 0:
        # an unstable model: keep the window short enough not to overflow
        Nw = min(Nw, max(n, int(300 / np.log(np.max(mags)))))
    y0 = None if free is None else np.asarray(free(Nw), dtype=float)
    if y0 is None or not np.all(np.isfinite(y0)):  # sys's own free response
        y0 = simulate_output(sys, u[:, :Nw])
    O = np.empty((Nw * C.shape[0], n))
    Ak = np.eye(n)
    for k in range(Nw):
        O[k * C.shape[0]:(k + 1) * C.shape[0]] = C @ Ak
        Ak = A @ Ak
    r = (y[:, :Nw] - y0).T.reshape(-1)
    scale = np.sqrt(np.mean(y[:, :Nw] ** 2, axis=1)) + 1e-300
    W = np.tile(1.0 / scale, Nw)
    x0, *_ = np.linalg.lstsq(O * W[:, None], r * W, rcond=1e-10)
    return x0


# The initial-state window covers this many time constants of the slowest stable mode, at
# most X0_WINDOW_MAX samples: a 25 s hidden thermal mass sampled at 0.05 s is barely
# observed in 50 samples, and its noisy initial state then costs more simulation error than
# a wrong law (a third-order hidden chain lost to a second-order law whose estimation SE
# was 0.87 % against the right law's 1.02 %; 0.73 % from a 1000-sample window).
X0_WINDOW_TAUS = 3.0
X0_WINDOW_MAX = 2000


def has_free_ramp(A: NDArray, B: NDArray, tol: float = 1e-9, eigenvalues=None) -> bool:
    """Whether the free response of ``x[k+1] = A x + B u`` holds a ramp no input drives.

    A Jordan block at eigenvalue 1 whose chain the inputs do not reach: a drifting sensor's
    offset and drift rate (two states, ``[[1, dt], [0, 1]]``). Its rate is seen only over
    a long record (its estimate's spread falls as N^1.5), so the initial-state window is
    the longest one (:data:`X0_WINDOW_MAX`): from the default 60 samples, zoo sensor_drift
    2020699907 #1's rate came out 1.2e-5 instead of 6.6e-5 /s and the right drift law
    simulated at 3.14 % against 0.38 % (and lost to a wrong law). A double integrator an
    input drives (a mass without spring or damper) is not one: its start is seen early.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    tol : float
        Relative rank tolerance.
    eigenvalues : ndarray, optional
        A's eigenvalues where the caller has them (not computed again).
    """
    n = A.shape[0]
    lam = np.linalg.eigvals(A) if eigenvalues is None and n >= 2 else eigenvalues
    if n < 2 or not np.any(np.abs(lam - 1.0) < 1e-6):
        return False

    def basis(X):  # orthonormal basis of the range of X
        if X.size == 0:
            return np.zeros((n, 0))
        u_, sv, _ = np.linalg.svd(X, full_matrices=False)
        return u_[:, :int(np.sum(sv > tol * max(sv.max(initial=0.0), 1.0)))]

    Qc = basis(B)  # the reachable subspace (Krylov, orthonormalized at each step)
    while 0 < Qc.shape[1] < n:
        nxt = basis(np.hstack([Qc, A @ Qc]))
        if nxt.shape[1] == Qc.shape[1]:
            break
        Qc = nxt
    u_, _, _ = np.linalg.svd(Qc, full_matrices=True) if Qc.shape[1] else (np.eye(n), 0, 0)
    Qu = u_[:, Qc.shape[1]:]  # its complement: the part of the state no input reaches
    if Qu.shape[1] < 2:
        return False
    M = Qu.T @ A @ Qu - np.eye(Qu.shape[1])  # the unreached dynamics, less the identity

    def nullity(X):
        sv = np.linalg.svd(X, compute_uv=False)
        return int(np.sum(sv <= tol * max(np.abs(A).max(), 1.0)))

    return nullity(M @ M) > nullity(M)  # a Jordan chain at 1 there: a ramp


def _x0_window(mags, n: int) -> int:
    """Default initial-state window: max(10 n, 50) samples, longer for a slow stable mode."""
    base = max(10 * n, 50)
    stable = mags[mags < 1.0 - 1e-9]
    rho = float(np.max(stable, initial=0.0))
    if rho <= 0.0:
        return base
    tau = -1.0 / np.log(rho)  # the slowest stable mode's time constant [samples]
    return max(base, min(int(np.ceil(X0_WINDOW_TAUS * tau)), X0_WINDOW_MAX))


def validate_model(sys: ct.StateSpace, y: ArrayLike, u: ArrayLike, *, Q: ArrayLike,
                   R: ArrayLike, x0: ArrayLike | str | None = None, name: str | None = None,
                   lags: int = 20, alpha: float = 1e-3, skip: int = 0) -> ModelValidation:
    """Simulation error, prediction error and residual tests of a model on data.

    Parameters
    ----------
    sys : control.StateSpace
        Discrete model from the measured inputs to the measured outputs.
    y : array_like, shape (noutputs, nsteps)
        Measured outputs of the validation record.
    u : array_like, shape (ninputs, nsteps)
        Measured inputs.
    Q : array_like, shape (nstates, nstates)
        The model's process-noise covariance, used by its Kalman predictor.
    R : array_like, shape (noutputs, noutputs)
        The model's measurement-noise covariance.
    x0 : array_like, "estimate" or None
        Initial state for the simulation and the predictor: zero (None), a
        given vector, or a least-squares estimate from the first samples.
    name : str, optional
    lags : int
        Lags of the correlations and of the whiteness test.
    alpha : float
        Significance level of the whiteness test.
    skip : int
        Leading samples left out of SE and PE (initial transients).

    Returns
    -------
    ModelValidation
        For an unstable model (:func:`unstable_reason`) SE is undefined:
        ``se`` is NaN, ``y_sim`` NaN and ``se_reason`` says why; PE and the
        residual tests are computed as usual.
    """
    check_discrete(sys)
    lags = check_positive(lags, "lags", integer=True)
    skip = check_positive(skip, "skip", integer=True, allow_zero=True)
    y = check_signal(y, sys.noutputs, "y", min_steps=2 * lags + 2)
    u = check_signal(u, sys.ninputs, "u")
    check_same_length(("y", y), ("u", u))
    x0v = start_state(sys, x0, y, u)
    return validation_row(linear_run(sys, y, u, Q=Q, R=R, x0=x0v), y, u,
                          name=name or (sys.name or "model"), order=sys.nstates,
                          output_labels=tuple(sys.output_labels), lags=lags, alpha=alpha,
                          skip=skip)


def start_state(sys: ct.StateSpace, x0, y: NDArray, u: NDArray) -> NDArray:
    """The state a record starts from, shape (nstates,): ``x0`` itself (checked), zero
    (None), or "estimate": least squares on the record's first samples
    (:func:`estimate_initial_state`)."""
    if isinstance(x0, str):
        if x0 != "estimate":
            raise DimensionError(f"x0 must be an array, None or 'estimate'; found {x0!r}")
        return estimate_initial_state(sys, y, u)
    if x0 is None:
        return np.zeros(sys.nstates)
    return check_vector(x0, sys.nstates, "x0")


@dataclass(frozen=True)
class Run:
    """What a model does on a record: its simulation and its one-step prediction.

    Attributes
    ----------
    y_sim : ndarray, shape (noutputs, nsteps)
        Simulated outputs (NaN where ``se_reason`` says the simulation is undefined).
    y_pred : ndarray, shape (noutputs, nsteps)
        One-step predicted outputs of the model's predictor.
    residuals : ndarray, shape (noutputs, nsteps)
        The predictor's innovations, y - y_pred.
    se_reason, pe_reason : str
        Why the simulation (prediction) error is undefined ("" when defined).
    """

    y_sim: NDArray = field(repr=False)
    y_pred: NDArray = field(repr=False)
    residuals: NDArray = field(repr=False)
    se_reason: str = ""
    pe_reason: str = ""


def linear_run(sys: ct.StateSpace, y: NDArray, u: NDArray, *, Q, R, x0: NDArray) -> Run:
    """The :class:`Run` of a discrete StateSpace from the state ``x0``: its exact simulation
    (undefined when the model is unstable or the simulation diverges) and its Kalman
    predictor started at x0 with zero initial covariance."""
    se_reason = unstable_reason(sys, y.shape[1])
    if se_reason:
        y_sim = np.full(y.shape, np.nan)
    else:
        y_sim = simulate_output(sys, u, x0)
        if not np.all(np.isfinite(y_sim)):
            se_reason = "the simulation diverged: its simulation error is undefined; PE used"
            y_sim = np.full(y.shape, np.nan)
    kf = kalman_filter(sys, y, u, Q=Q, R=R, x0=x0, P0=np.zeros((sys.nstates, sys.nstates)))
    return Run(y_sim=y_sim, y_pred=kf.y_pred, residuals=kf.innovations, se_reason=se_reason)


def validation_row(run: Run, y: NDArray, u: NDArray, *, name: str, order: int,
                   output_labels: tuple, lags: int, alpha: float, skip: int) -> ModelValidation:
    """The :class:`ModelValidation` row of a model's :class:`Run` on the record (y, u): SE,
    PE and the residual tests after ``skip`` samples, the same for every kind of model
    (``greybox.plant_adapter`` makes the run of each kind)."""
    e, p = run.residuals, y.shape[0]
    if run.pe_reason:  # no residual: its statistics are undefined too
        nan = np.full(p, np.nan)
        white = WhitenessTest(statistic=nan, pvalue=nan, lags=lags, alpha=alpha,
                              white=np.zeros(p, bool))
        acf = np.full((p, lags + 1), np.nan)
        xcf = np.full((u.shape[0], p, 2 * lags + 1), np.nan)
    else:
        white = whiteness_test(e[:, skip:], lags, alpha=alpha)
        acf = autocorrelation(e[:, skip:], lags)
        xcf = cross_correlation(u[:, skip:], e[:, skip:], lags) if u.shape[0] else \
            np.zeros((0, p, 2 * lags + 1))
    return ModelValidation(
        name=name, order=order,
        se=undefined_error(p) if run.se_reason else relative_error(y, run.y_sim, skip=skip),
        pe=undefined_error(p) if run.pe_reason else relative_error(y, run.y_pred, skip=skip),
        whiteness=white, autocorr=acf, crosscorr=xcf,
        band=correlation_band(y.shape[1] - skip, 0.99), y_sim=run.y_sim, y_pred=run.y_pred,
        residuals=e, output_labels=tuple(output_labels), se_reason=run.se_reason,
        pe_reason=run.pe_reason)


def before_after(table: dict) -> tuple[str, float, float]:
    """``(measure, nominal, updated)`` of a validation table: SE when both are defined, else PE.

    Never builds a ratio from a diverged simulation: when the nominal or the
    updated model is unstable (SE undefined) the one-step prediction error
    is compared instead.

    Parameters
    ----------
    table : dict of str -> ModelValidation
        Rows "nominal" and "updated".

    Returns
    -------
    tuple of (str, float, float)
        "SE" or "PE", and the nominal and updated values [%].
    """
    a, b = table["nominal"], table["updated"]
    if a.se_defined and b.se_defined:
        return "SE", float(a.se.value), float(b.se.value)
    return "PE", float(a.pe.value), float(b.pe.value)


def describe_before_after(table: dict) -> str:
    """One phrase: "validation SE 5% -> 1% (5.0x)", or with PE and why SE is n/a.

    Parameters
    ----------
    table : dict of str -> ModelValidation
        Rows "nominal" and "updated".

    Returns
    -------
    str
    """
    what, v0, v1 = before_after(table)
    ratio = v0 / max(v1, 1e-300)
    txt = f"validation {what} {v0:.3g}% -> {v1:.3g}% ({ratio:.1f}x)"
    if what == "PE":
        which = "nominal" if not table["nominal"].se_defined else "updated"
        why = "'s simulation is sensitive to its start" if \
            table[which].se_reason.startswith(SENSITIVE_REASON) else " is unstable"
        txt = f"validation SE n/a (the {which} model{why}); " + txt
    return txt
