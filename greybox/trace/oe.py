"""Output-error refinement and selection of linear static laws on the measured outputs."""

from __future__ import annotations

from dataclasses import replace
from functools import cached_property

from scipy.linalg import expm

import control as ct
import numpy as np
from numpy.typing import NDArray

from .._blas import single_thread_blas
from .._lti import lti_output, lti_states, spectral_radius
from ..filters.kernels import predicted_covariance
from ..hold import as_hold
from ..lawsim import compiled_terms, simulate_columns
from ..metrics import effective_samples, oe_criterion
from ..terms import evaluator, term_kind
from .intervals import hac_covariance, residual_colour, undetermined
from .laws import (BREAK_KINDS, LINEAR_KINDS, StaticLaw, law_line, _one_direction,
                   linear_part, siblings, step_matrix)

# Output-error refinements of static laws run on at most this many samples
# (their cost is then independent of the record length).
_OE_WINDOW = 10_000
# ... a nonlinear law's on at most this many (its simulation is a loop over samples)
_NL_OE_WINDOW = 2_000
# ... and at most this many residuals (outputs x samples, but >= 2000 samples): with many
# outputs every evaluation simulates a large model and the Jacobian grows with p.
_OE_RESIDUALS = 200_000


def oe_window(noutputs: int) -> int:
    """Samples in an output-error window for ``noutputs`` outputs."""
    return int(max(2000, min(_OE_WINDOW, _OE_RESIDUALS // max(noutputs, 1))))


def zoh(A: NDArray, B: NDArray, dt: float) -> tuple[NDArray, NDArray]:
    """Exact zero-order-hold discretization ``(Ad, Bd)`` of ``dx/dt = A x + B u``."""
    n, m = B.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n], M[:n, n:] = A * dt, B * dt
    with np.errstate(all="ignore"):  # an optimizer's wild trial: non-finite, caught by callers
        E = expm(M) if np.all(np.isfinite(M)) else np.full(M.shape, np.nan)
    return E[:n, :n], E[:n, n:]


def noise_covariance(A: NDArray, C: NDArray, jac: NDArray, scale: NDArray, k0: int,
                     Q: NDArray, R: NDArray) -> NDArray[np.float64]:
    """Covariance of ``J^T r`` when r is the output error of the right model under (Q, R).

    The scaled output error of the right model is ``r[t] = S^-1 (C x_w[t] + v[t])``
    for ``t >= k0``, where ``x_w[t+1] = A x_w[t] + w[t]`` is the response to
    the process noise (covariance Q) from t = 0 and v the measurement noise
    (covariance R), S = diag(scale). Then ``Cov(J^T r) = sum_t J_t^T S^-1 R
    S^-1 J_t + sum_s lam_s^T Q lam_s`` with the adjoint recursion
    ``lam_s = A^T lam_{s+1} + C^T S^-1 J_{s+1}`` run backwards in time.

    Parameters
    ----------
    A : ndarray, shape (n, n)
        Discrete state matrix of the fitted (augmented) model.
    C : ndarray, shape (p, n)
    jac : ndarray, shape (p * T, k)
        Jacobian of the scaled residual over the window t = k0 .. k0 + T - 1.
    scale : ndarray, shape (p,)
    k0 : int
    Q : ndarray, shape (n, n)
    R : ndarray, shape (p, p)
    """
    p, n = C.shape
    k = jac.shape[1]
    T = jac.shape[0] // p
    J = jac.reshape(p, T, k)                      # J[o, t, :]
    Js = J / scale[:, None, None]                 # S^-1 J_t
    # sum_t J_t^T S^-1 R S^-1 J_t, as matrix products (a 3-operand einsum loops in C)
    RJ = ((R / np.outer(scale, scale)) @ J.reshape(p, T * k)).reshape(p, T, k)
    M1 = J.reshape(p * T, k).T @ RJ.reshape(p * T, k)
    h = (C.T @ Js.reshape(p, T * k)).reshape(n, T, k).transpose(1, 2, 0)  # h_t = C^T S^-1 J_t
    # backward: lam_s = A^T lam_{s+1} + h_{s+1}; lam over s = 0 .. k0+T-2
    hr = h[::-1]                                  # hr[i] = h at t = end - i
    lams = np.empty((k, n, T + k0))
    for j in range(k):
        back = lti_states(A.T, hr[:, j, :].T, np.zeros(n))  # lam_s for s = end .. k0
        if k0:  # then s = k0 - 1 .. 0, where h = 0
            start = A.T @ back[:, -1] + hr[-1, j, :]
            back = np.hstack([back, lti_states(A.T, np.zeros((n, k0)), start)])
        lams[j] = back
    QL = np.matmul(Q, lams)                       # Q lam_s for every s, (k, n, T + k0)
    M2 = lams.reshape(k, -1) @ QL.reshape(k, -1).T
    return M1 + M2


def scaled_output_error(Ad: NDArray, Bd: NDArray, C: NDArray, D: NDArray, y: NDArray,
                        u: NDArray, x0: NDArray, k0: int, scale: NDArray) -> NDArray:
    """Output error of ``(Ad, Bd, C, D)`` from ``x0`` on y after ``k0``, per-output scaled, flat.

    A non-finite model (an optimizer's wild trial) or simulation counts as 1e6.
    """
    if not (np.all(np.isfinite(Ad)) and np.all(np.isfinite(Bd))):
        return np.full(y[:, k0:].size, 1e6)
    with np.errstate(all="ignore"):
        r = ((y - lti_output(Ad, Bd, C, D, u, x0))[:, k0:] / scale[:, None]).ravel()
    return np.clip(np.where(np.isfinite(r), r, 1e6), -1e6, 1e6)


def robust_halfwidths(sol, nout: int, Ad: NDArray, C: NDArray, scale: NDArray, k0: int,
                      Q: NDArray | None, R: NDArray | None) -> NDArray[np.float64]:
    """95 % half-widths of an output-error fit: the larger of two variances per coefficient.

    The sandwich covariance under the noise model (Q, R) of the discrete model
    (:func:`noise_covariance`; calibrated when Q and R are right; skipped when
    Q is None) and the data-driven one robust to autocorrelation
    (:func:`hac_covariance`; guards against an understated Q). NaN when the
    fit diverged.
    """
    jac = np.asarray(sol.jac)
    if not np.all(np.isfinite(jac)) or np.max(np.abs(sol.fun)) >= 1e6:
        return np.full(sol.x.size, np.nan)
    var = np.diag(hac_covariance(jac, np.asarray(sol.fun), nout))
    if Q is not None:
        Ji = np.linalg.pinv(jac.T @ jac)
        vm = np.diag(Ji @ noise_covariance(Ad, C, jac, scale, k0, Q, R) @ Ji)
        var = np.maximum(var, vm)
    return 1.96 * np.sqrt(np.clip(var, 0, None))


class OutputError:
    """The output error of a linear model whose matrices depend on parameters: the one
    engine of every linear law's output-error fit (a static law folded into A and B, a
    first-order or order-q subsystem, a shared state, the joint refit of several effects).

    ``matrices(theta, *args) -> (A, B)``: continuous when ``dt`` is given (discretized
    exactly by the zero-order hold, :func:`zoh`), discrete otherwise; ``args`` (a
    selection of terms, the active parameters) pass through :meth:`resid`, :meth:`se`,
    :meth:`fit` and :meth:`halfwidths`. The residual is the output error over at most
    ``oe_window(noutputs)`` samples after ``k0``, scaled per output by its RMS there
    (PAPER_NOTES §9.3: output-error fits are unbiased on a noisy d^), flat (output-major);
    a diverged simulation counts as 1e6.

    Parameters
    ----------
    matrices : callable
    C : ndarray, shape (p, n)
    D : ndarray, shape (p, m)
    y : ndarray, shape (p, N)
    u : ndarray, shape (m, N)
    x0 : ndarray, shape (n,)
        Initial state of the simulation (not fitted).
    k0 : int
        First compared sample.
    dt : float, optional
        Sampling period [s] of a continuous ``matrices``.
    """

    def __init__(self, matrices, C: NDArray, D: NDArray, y: NDArray, u: NDArray,
                 x0: NDArray, k0: int, dt: float | None = None):
        win = oe_window(y.shape[0])
        self.matrices, self.C, self.D, self.x0, self.k0, self.dt = matrices, C, D, x0, k0, dt
        self.y, self.u = y[:, :k0 + win], u[:, :k0 + win]
        self.scale = np.sqrt(np.mean(self.y[:, k0:] ** 2, axis=1)) + 1e-300

    def model(self, theta, *args) -> tuple[NDArray, NDArray]:
        """The discrete ``(Ad, Bd)`` at ``theta``."""
        A, B = self.matrices(theta, *args)
        return (A, B) if self.dt is None else zoh(A, B, self.dt)

    def resid(self, theta, *args) -> NDArray[np.float64]:
        """Scaled output error, flat; 1e6 where the simulation diverged."""
        Ad, Bd = self.model(theta, *args)
        return scaled_output_error(Ad, Bd, self.C, self.D, self.y, self.u, self.x0, self.k0,
                                   self.scale)

    def se(self, theta, *args) -> float:
        """Simulation error of eq. (42) [%] on the window."""
        r = self.resid(theta, *args).reshape(self.y.shape[0], -1)
        return float(100 * np.mean(np.sqrt(np.mean(r**2, axis=1))))  # |r| <= 1e6

    def fit(self, theta0, *args, max_nfev: int = 60, tol: float = 1e-8):
        """Levenberg-Marquardt from ``theta0`` (forward-difference Jacobian); the result.
        ``tol``: MINPACK's ftol and xtol (relative changes of the sum of squares and of
        the parameters at which it stops)."""
        from scipy.optimize import least_squares

        with single_thread_blas():  # thin products: threads only cost (150x for a 6x6 expm)
            return least_squares(self.resid, theta0, args=args, method="lm", x_scale="jac",
                                 max_nfev=max_nfev, ftol=tol, xtol=tol)

    def halfwidths(self, sol, Q: NDArray | None, R: NDArray | None,
                   *args) -> NDArray[np.float64]:
        """95 % half-widths of ``sol.x`` (:func:`robust_halfwidths`; Q sized as the model)."""
        with single_thread_blas():
            return robust_halfwidths(sol, self.y.shape[0], self.model(sol.x, *args)[0], self.C,
                                     self.scale, self.k0, Q, R)


def _refine_static_pe(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray,
                      u: NDArray, x0: NDArray, k0: int, labels, units, tscale=None, cont=None,
                      noise=None):
    """Refine a linear static law by one-step prediction error on y, for a model whose
    simulation diverges (:class:`PredictionError`; ``noise = (Q, R)`` of the discrete
    model required): the d^ fit's terms from its coefficients, then terms whose 95 %
    interval contains 0 dropped one at a time (as :func:`_refine_static_oe`). Returns
    ``(law, pe_before, pe_after)`` [% RMS of the whitened innovations]; the law unchanged
    where the prediction error does not drop or no predictor exists."""
    sel, theta0 = _selected(law)
    if not sel or noise is None:
        return law, np.nan, np.nan
    try:
        prob = _OutputErrorLaw(law, model, md, y, u, x0, k0, cont, noise, predictor=True)
    except np.linalg.LinAlgError:
        return law, np.nan, np.nan
    pe0 = prob.se(theta0, sel)
    sel1, sol, hw = _prune(prob, sel, prob.fit(sel, theta0))
    theta = sol.x if sol is not None else np.zeros(0)
    pe1 = prob.se(theta, sel1)
    if not pe1 < pe0:
        return law, pe0, pe0
    return (prob.law_with(sel1, theta, labels, units, tscale, ci=hw, npar=len(sel1)),
            pe0, pe1)


class PredictionError(OutputError):
    """The one-step prediction error of a linear model whose matrices depend on parameters:
    :class:`OutputError` for a model whose simulation diverges (an unstable plant measured
    in closed loop), where the simulation error means nothing.

    The residual is the innovation ``y[t] - C x^[t|t-1] - D u[t]`` of the model's
    steady-state Kalman predictor under the discrete model's noise ``(Q, R)`` (stable
    for a detectable model, whatever the model's own poles), whitened by the innovation
    covariance of the reference model ``A_ref`` (fixed, so that every trial's residual is
    on one scale); the prediction-error method's estimate is consistent and its
    intervals those of least squares on white residuals (Ljung, System Identification,
    ch. 9), where a static law's regression on d^ is biased by the state estimate's
    error (its interval then misses the truth). A trial whose predictor cannot be
    formed (no stabilizing Riccati solution) counts as 1e6, as a diverged simulation.

    Parameters
    ----------
    matrices, C, D, y, u, x0, k0, dt
        As :class:`OutputError`.
    Q : ndarray, shape (n, n)
    R : ndarray, shape (p, p)
        Process and measurement noise covariances of the discrete model.
    A_ref : ndarray, shape (n, n)
        Discrete state matrix whose innovation covariance whitens the residual.
    """

    def __init__(self, matrices, C: NDArray, D: NDArray, y: NDArray, u: NDArray,
                 x0: NDArray, k0: int, Q: NDArray, R: NDArray, A_ref: NDArray,
                 dt: float | None = None):
        super().__init__(matrices, C, D, y, u, x0, k0, dt)
        self.Q, self.R = np.asarray(Q, dtype=float), np.asarray(R, dtype=float)
        gain = self._gain(np.asarray(A_ref, dtype=float))
        if gain is None:
            raise np.linalg.LinAlgError("no steady-state Kalman predictor of the model")
        self.white = np.linalg.inv(np.linalg.cholesky(gain[1]))
        self.yu = np.vstack([self.u, self.y])

    def _gain(self, Ad: NDArray):
        """(K (n, p), S (p, p)): the predictor's gain and innovation covariance, or None."""
        C, R = self.C, self.R
        P = predicted_covariance(Ad, C, self.Q, R)
        if P is None:
            return None
        S = C @ P @ C.T + R
        with np.errstate(all="ignore"):
            K = Ad @ P @ C.T @ np.linalg.inv(S)
        ok = np.all(np.isfinite(K)) and np.max(np.abs(np.linalg.eigvals(Ad - K @ C))) < 1.0
        return (K, S) if ok else None

    def resid(self, theta, *args) -> NDArray[np.float64]:
        """Whitened innovations after ``k0``, flat (output-major); 1e6 where there is no
        predictor."""
        size = self.y[:, self.k0:].size
        Ad, Bd = self.model(theta, *args)
        if not (np.all(np.isfinite(Ad)) and np.all(np.isfinite(Bd))):
            return np.full(size, 1e6)
        gain = self._gain(Ad)
        if gain is None:
            return np.full(size, 1e6)
        K = gain[0]
        p = self.C.shape[0]
        Bp = np.hstack([Bd - K @ self.D, K])
        Dp = np.hstack([self.D, np.zeros((p, p))])
        with np.errstate(all="ignore"):
            e = self.y - lti_output(Ad - K @ self.C, Bp, self.C, Dp, self.yu, self.x0)
            r = (self.white @ e[:, self.k0:]).ravel()
        return np.clip(np.where(np.isfinite(r), r, 1e6), -1e6, 1e6)

    def halfwidths(self, sol, Q: NDArray | None, R: NDArray | None,
                   *args) -> NDArray[np.float64]:
        """95 % half-widths of ``sol.x``: :func:`robust_halfwidths` without the output-error
        noise model (``Q``, ``R`` unused: the residual is whitened; the covariance robust to
        its autocorrelation is least squares' for the right model's white innovations)."""
        return super().halfwidths(sol, None, None, *args)


class _OutputErrorLaw:
    """Simulation error on y of the model augmented with a linear static law.

    The law's selected terms ``sel`` (pairs (component of d, term index))
    with coefficients ``theta`` are folded into A and B, and the augmented model's
    output error is :class:`OutputError`'s.

    With ``cont = (Ac, Bc, Gc, dt)`` (a continuous nominal model) the law is
    parametrized in continuous time, ``dx/dt = (Ac + Gc Dx) x + (Bc + Gc Du) u``,
    and the augmented model is discretized exactly (ZOH) at every evaluation
    (PAPER_NOTES §9.5): the coefficients are then physical, without the
    half-sample terms a discrete-time law carries.
    """

    def __init__(self, law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray,
                 u: NDArray, x0: NDArray, k0: int, cont=None, noise=None,
                 predictor: bool = False):
        self.law, self.md, self.k0, self.x0 = law, md, k0, x0
        self.noise = noise  # (Q, R) of the discrete model, for the intervals
        m = model.ninputs - md
        Bf = np.asarray(model.B, dtype=float)
        self.A = np.asarray(model.A, dtype=float)
        self.B, self.G = Bf[:, :m], Bf[:, m:]
        self.C = np.asarray(model.C, dtype=float)
        self.D = np.asarray(model.D, dtype=float)[:, :m]
        self.cont = cont
        # with a direction dG (continuous models only), theta carries one more entry r
        # after the law's coefficients and d enters through Gc + r dG (a force's direction)
        self.dG = None
        dt = None if cont is None else cont[3]
        if predictor:  # one-step prediction error (``noise`` required): an unstable model
            self.engine = PredictionError(self._folded, self.C, self.D, y, u, x0, k0,
                                          *noise, self.A, dt=dt)
        else:
            self.engine = OutputError(self._folded, self.C, self.D, y, u, x0, k0, dt=dt)
        self.y, self.u, self.scale = self.engine.y, self.engine.u, self.engine.scale

    @property
    def nextra(self) -> int:
        """Entries of theta after the law's coefficients (1 with a free direction)."""
        return 0 if self.dG is None else 1

    def _linear(self, sel, theta):
        """The law's (Ddx, Ddu) for the terms ``sel`` at ``theta`` (the law's time base)."""
        coef = np.zeros((self.md, len(self.law.spec)))
        for (c, j), t in zip(sel, theta):
            coef[c, j] = t
        return linear_part(self.law.spec, coef, self.A.shape[0], self.B.shape[1])

    def _folded(self, theta, sel):
        """(A, B) with the law folded in, before discretization (the engine's map)."""
        Ddx, Ddu = self._linear(sel, theta)
        if self.cont is None:
            return self.A + self.G @ Ddx, self.B + self.G @ Ddu
        Ac, Bc, Gc, _ = self.cont
        if self.dG is not None:
            Gc = Gc + theta[-1] * self.dG
        return Ac + Gc @ Ddx, Bc + Gc @ Ddu

    def matrices(self, sel, theta):
        """Discrete (A_aug, B_aug) and the law's (Ddx, Ddu) for the terms ``sel`` at ``theta``.

        Ddx, Ddu are in the law's time base (continuous when ``cont`` is given).
        """
        return (*self.engine.model(theta, sel), *self._linear(sel, theta))

    def resid(self, theta, sel):
        """Scaled output error, flattened; a diverged simulation counts as 1e6."""
        return self.engine.resid(theta, sel)

    def se(self, theta, sel) -> float:
        """Simulation error of eq. (42) [%] on the window."""
        return self.engine.se(theta, sel)

    def fit(self, sel, start, max_nfev=60, trial: bool = False):
        """Levenberg-Marquardt from ``start``; returns the optimizer result. ``trial``: a
        fit only compared by its residual sum of squares (a selection's trial), stopped at
        ``TRIAL_TOL``."""
        return self.engine.fit(start, sel, max_nfev=max_nfev,
                               tol=TRIAL_TOL if trial else 1e-8)

    def halfwidths(self, sol, sel) -> NDArray[np.float64]:
        """95 % half-widths of the coefficients of the last fit (inf: not determined).

        The larger of two variances per coefficient: the sandwich covariance
        under the given noise model (Q, R) of the discrete model
        (:func:`noise_covariance`; calibrated when Q and R are right) and the
        data-driven one robust to autocorrelation (:func:`hac_covariance`;
        guards against an understated Q).
        """
        if sol.jac is None:
            return np.full(sol.x.size, np.nan)
        Q, R = self.noise if self.noise is not None else (None, None)
        h = self.engine.halfwidths(sol, Q, R, sel)
        # a coefficient the data do not determine (collinear terms): "not determined" (inf),
        # never the half-width of a singular covariance; the prune drops it first
        h[undetermined(np.asarray(sol.jac))[:h.size]] = np.inf
        return h

    def law_with(self, sel, theta, labels, units, tscale=None, ci=None, **changes) -> StaticLaw:
        """The law with the terms ``sel`` at ``theta`` (all others zero), 95 % half-widths ``ci``."""
        law = self.law
        _, _, Ddx, Ddu = self.matrices(sel, theta)
        coef = np.zeros_like(law.coef)
        half = np.full_like(law.coef, np.nan)
        for q, ((c, j), t) in enumerate(zip(sel, theta)):
            coef[c, j] = t
            if ci is not None:
                half[c, j] = ci[q]
        lines = []
        for c in range(self.md):
            idx = [j for (cc, j) in sel if cc == c]
            lines.append(law_line(labels[c], coef[c, idx], [law.spec[j][0] for j in idx],
                                   units[c] if c < len(units) else "", half[c, idx]))
        if tscale is not None:
            lines += _one_direction(coef, tscale, labels)
        return replace(law, coef=coef, Ddx=Ddx, Ddu=Ddu, formula="; ".join(lines), ci=half,
                       time_base="continuous" if self.cont is not None else "discrete",
                       **changes)


def _selected(law: StaticLaw):
    """The law's nonzero terms as (component, term) pairs and their coefficients."""
    sel = [(c, j) for c, j in zip(*np.nonzero(law.coef))]
    return [(int(c), int(j)) for c, j in sel], np.array([law.coef[c, j] for c, j in sel])


def _prune(prob: _OutputErrorLaw, sel, sol):
    """Drop terms whose 95 % interval contains 0 (the weakest, or the weaker half of many); refit."""
    hw = prob.halfwidths(sol, sel)
    while sel:
        k = len(sel)  # theta's entries after the k coefficients (a direction) are kept
        t = np.abs(sol.x[:k]) / np.where(np.isfinite(hw[:k]) & (hw[:k] > 0), hw[:k], np.inf)
        weak = np.flatnonzero(t < 1.0)
        if not weak.size:
            break
        # drop the weakest; with many weak terms (a proxy-laden law) the weaker half at once
        drop = np.argsort(t)[:max(1, weak.size // 2)]
        keep = [q for q in range(k) if q not in set(drop.tolist())]
        sel = [sel[q] for q in keep]
        if not sel:
            return [], None, np.zeros(0)
        sol = prob.fit(sel, np.r_[sol.x[keep], sol.x[k:]])
        hw = prob.halfwidths(sol, sel)
    return sel, sol, hw


def _refine_static_oe(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray,
                      u: NDArray, x0: NDArray, k0: int, labels, units, tscale=None, cont=None,
                      noise=None):
    """Refine a linear static law by output error on y (PAPER_NOTES §9.3, §9.5).

    The law's coefficients fitted on d^ are consistent but biased by the
    discretization (a half-sample shift) and, when C G is small (e.g. only
    positions measured), so noisy that the law can make the augmented model
    unstable. Here the selected coefficients are re-fitted to minimize the
    simulation error of the augmented model on the outputs (in continuous
    time when ``cont`` is given), starting from the d^ fit (shrunk towards
    zero until the model is stable); every term is then checked by the
    output-error selection's rule (the BIC on the residual's independent samples,
    :func:`_backward`: a term the d^ regression took where the simulation does
    not want it is dropped), and terms whose 95 % interval contains 0
    are then dropped one at a time. Returns ``(law, se_before, se_after)``
    with the law's ``ci`` set; the law is unchanged (no intervals) when the
    refinement does not lower the simulation error.
    """
    sel, theta0 = _selected(law)
    if not sel:
        return law, np.nan, np.nan
    prob = _OutputErrorLaw(law, model, md, y, u, x0, k0, cont, noise)
    se0 = prob.se(theta0, sel)
    start = theta0.copy()
    for _ in range(30):  # shrink towards the (stable) nominal model
        if np.max(np.abs(np.linalg.eigvals(prob.matrices(sel, start)[0]))) <= 1 + 1e-9:
            break
        start *= 0.5
    sol = prob.fit(sel, start)
    se1 = prob.se(sol.x, sel)
    if not se1 < se0 and cont is None:
        return law, se0, se0
    if len(sel) >= 2:  # terms chosen on d^ kept only where the output error supports them
        p = prob.y.shape[0]
        sel2, theta2 = _backward(prob, sel, sol.x, sol.fun, prob.y[:, k0:].size,
                                 lambda r: residual_colour(np.asarray(r).reshape(p, -1)),
                                 len, 1.0, 60)
        if len(sel2) < len(sel):
            sel, sol = sel2, prob.fit(sel2, theta2)
    sel, sol, hw = _prune(prob, sel, sol)
    theta = sol.x if sol is not None else np.zeros(0)
    se1 = prob.se(theta, sel)
    return (prob.law_with(sel, theta, labels, units, tscale, ci=hw, npar=len(sel)), se0, se1)



class _OutputErrorNonlinearLaw:
    """Simulation error on y of the model with a nonlinear static law, for output error.

    ``x[k+1] = A x + B u + G law(x, u)`` (or the law integrated over each sample by its
    hold, as :func:`greybox.trace.simulate_with_law` does), the law restricted
    to the terms ``sel`` (pairs (component of d, term index)) at the
    coefficients theta. Several coefficient vectors are simulated at once,
    one per column of the state (the Jacobian's forward differences cost one
    simulation). The coefficients are scaled by their starting values (they
    differ by decades: y^3 vs v). Residual: the output error over at most
    ``_NL_OE_WINDOW`` samples after ``k0``, scaled per output by its RMS.
    """

    def __init__(self, law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray, u: NDArray,
                 x0: NDArray, k0: int, sel, theta0: NDArray, noise=None, window=None):
        self.law, self.md, self.k0, self.sel, self.noise = law, md, k0, list(sel), noise
        win = min(_NL_OE_WINDOW, oe_window(y.shape[0])) if window is None else window
        self.y, self.u = y[:, :k0 + win], u[:, :k0 + win]
        m = model.ninputs - md
        Bf = np.asarray(model.B, dtype=float)
        self.A, self.G = np.asarray(model.A, dtype=float), Bf[:, m:]
        self.C = np.asarray(model.C, dtype=float)
        D = np.asarray(model.D, dtype=float)[:, :m]
        self.Bu, self.Du = Bf[:, :m] @ self.u, D @ self.u
        self.x0 = np.asarray(x0, dtype=float)
        self.scale_y = np.sqrt(np.mean(self.y[:, k0:] ** 2, axis=1)) + 1e-300
        self.theta_scale = np.where(np.abs(theta0) > 0, np.abs(theta0), 1.0)
        self.spec = [law.spec[j] for _, j in self.sel]
        self._terms = evaluator(self.spec, law.eps)  # kinds looked up once, not per sample
        self._compiled = compiled_terms(self.spec, law.eps)  # None: the numpy loop
        self.comp = np.array([c for c, _ in self.sel], dtype=np.int64)
        self.mask = np.zeros((md, len(self.sel)))  # which component each term feeds
        for q, (c, _) in enumerate(self.sel):
            self.mask[c, q] = 1.0

    @cached_property
    def A_lin(self) -> NDArray[np.float64]:
        """The noise model's state matrix: the law's linear stand-in; where that is unstable
        (a stiffening law whose fitted directions are not quite action and reaction is
        circulatory: a lightly damped mode can grow) the process noise would grow over the
        window, and the model without the law stands in. Built on first use (only a noise
        model reads it; a matrix logarithm for a law with a hold)."""
        A_lin = step_matrix(self.A, self.G, self.law)
        return A_lin if spectral_radius(A_lin) < 1.0 else self.A

    def _law(self, X, uk, TH):
        return self.mask @ (TH * self._terms(X, uk))

    def simulate(self, TH: NDArray, isolate: bool = False) -> NDArray:
        """Outputs (K, noutputs, nsteps) for the coefficient columns TH (nsel, K).

        A diverging column stops the whole simulation (NaN from there on: the columns of
        a fit's Jacobian share their fate); with ``isolate`` (independent trials, a
        screen) only that column is NaN from where it diverged and the others go on.
        Compiled (:func:`greybox.lawsim.simulate_columns`) where numba is installed and
        knows every kind of the law; else the same recursion in numpy."""
        xs = simulate_columns(self.A, self.G, self.law.hold, self.Bu, self.u, self.x0,
                              TH, self._compiled, self.comp, isolate)
        if xs is None:
            xs = self._states(TH, isolate)
        return np.einsum("pn,knK->Kpk", self.C, xs) + self.Du[None]

    def _states(self, TH: NDArray, isolate: bool) -> NDArray:
        """States (N, nstates, K) of :meth:`simulate`, in numpy."""
        A, G, hold = self.A, self.G, as_hold(self.law.hold)
        K, N = TH.shape[1], self.u.shape[1]
        X = np.repeat(self.x0[:, None], K, axis=1)
        xs = np.full((N, A.shape[0], K), np.nan)
        dead = np.full(K, N)  # the first sample each column no longer holds
        with np.errstate(all="ignore"):  # a wild trial diverges: NaN, counted as 1e6 below
            for k in range(N):
                xs[k] = X
                uk = self.u[:, k:k + 1]
                if hold is None:
                    X = A @ X + self.Bu[:, k:k + 1] + G @ self._law(X, uk, TH)
                else:
                    X = hold.step(A, X, self.Bu[:, k:k + 1], lambda Z: self._law(Z, uk, TH))
                # one reduction, no wrapper (per sample): NaN and inf fail the comparison
                if not np.abs(X).max() <= 1e100:
                    if not isolate:
                        break
                    bad = ~(np.abs(X).max(axis=0) <= 1e100)
                    dead[bad & (dead == N)] = k + 1
                    X[:, bad] = 0.0  # a dead column idles at the origin, its law off
                    TH = np.where(bad[None], 0.0, TH)
                    if np.all(dead < N):
                        break
            for c in np.flatnonzero(dead < N):
                xs[dead[c]:, :, c] = np.nan
        return xs

    def _resid(self, Y):
        """Scaled output errors after k0, one flat row per simulated column."""
        r = (self.y[None] - Y)[:, :, self.k0:] / self.scale_y[None, :, None]
        r = r.reshape(Y.shape[0], -1)
        return np.clip(np.where(np.isfinite(r), r, 1e6), -1e6, 1e6)

    def resid(self, z):
        """Scaled output error at the scaled coefficients z (theta / theta_scale)."""
        return self._resid(self.simulate((z * self.theta_scale)[:, None]))[0]

    def jac(self, z):
        """Forward differences of :meth:`resid`, all columns in one simulation."""
        h = 1e-6 * np.maximum(np.abs(z), 1.0)
        Z = np.c_[z, z[:, None] + np.diag(h)]
        R = self._resid(self.simulate(Z * self.theta_scale[:, None]))
        return ((R[1:] - R[0]) / h[:, None]).T

    def se(self, theta) -> float:
        """Simulation error of eq. (42) [%] on the window."""
        r = self.resid(np.asarray(theta) / self.theta_scale).reshape(self.y.shape[0], -1)
        return float(100 * np.mean(np.sqrt(np.mean(r**2, axis=1))))

    def fit(self, keep, theta_start, max_nfev=10):
        """Levenberg-Marquardt on the terms ``keep`` (indices into sel); (theta, half-widths, cov).

        The covariance of theta is the larger (per coefficient) of two, as
        :func:`robust_halfwidths`: the sandwich under the noise model
        ``self.noise = (Q, R)`` of the model linearized with the law's linear
        stand-in (``self.A_lin``; output error is not efficient under process
        noise, and this says by how much) and the one robust to the
        residual's autocorrelation (:func:`greybox.trace.intervals.hac_covariance`).
        Half-widths: 95 %.
        """
        from scipy.optimize import least_squares

        sub = _OutputErrorNonlinearLaw.__new__(_OutputErrorNonlinearLaw)
        sub.__dict__.update(self.__dict__)
        sub.sel = [self.sel[q] for q in keep]
        sub.spec = [self.spec[q] for q in keep]
        sub._terms = evaluator(sub.spec, self.law.eps)
        sub._compiled = compiled_terms(sub.spec, self.law.eps)
        sub.comp = self.comp[keep]
        sub.mask = self.mask[:, keep]
        sub.theta_scale = self.theta_scale[keep]
        with single_thread_blas():
            sol = least_squares(sub.resid, theta_start / sub.theta_scale, jac=sub.jac,
                                method="lm", max_nfev=max_nfev, ftol=1e-6, xtol=1e-6)
        return sol.x * sub.theta_scale, *sub._covariance(np.asarray(sol.jac), sol.fun)

    def _covariance(self, jac, fun):
        """(95 % half-widths, covariance) of theta from the scaled Jacobian and residual."""
        k = jac.shape[1]
        if not np.all(np.isfinite(jac)) or np.max(np.abs(fun)) >= 1e6:
            return np.full(k, np.nan), np.full((k, k), np.nan)
        with single_thread_blas():
            cov = hac_covariance(jac, np.asarray(fun), self.y.shape[0])
            if self.noise is not None:
                Ji = np.linalg.pinv(jac.T @ jac)
                Q, R = self.noise
                cn = Ji @ noise_covariance(self.A_lin, self.C, jac, self.scale_y, self.k0, Q,
                                           R) @ Ji
                vh, vn = np.diag(cov), np.diag(cn)
                if np.all(vn > 0):  # the noise model's correlations, the larger variances
                    g = np.sqrt(np.maximum(vh, vn) / vn)
                    cov = cn * np.outer(g, g)
        cov = cov * np.outer(self.theta_scale, self.theta_scale)
        half = 1.96 * np.sqrt(np.clip(np.diag(cov), 0, None))
        return half, cov


# Where process noise dominates the noise floor (_process_noise_dominates), a nonlinear law
# fitted on d^ is refitted by output error only when its simulation's mean squared error is
# above this many times what the noise model alone gives (noise_floor): 10x in RMS.
# Measured ratios: a right cubic law under process noise 0.7-44 (20 records of
# tests/test_trace_delayed.py; the floor leaves out the initial state's error and the law's
# nonlinearity), EMPS 0.8, Silverbox 344, a static law for a lagged damper 2e4 (windows of
# 4000 samples; the right-law records are 2000 samples long).
_FLOOR_FACTOR = 100.0


def noise_floor(A: NDArray, C: NDArray, Q: NDArray, R: NDArray, k0: int,
                 W: int) -> NDArray[np.float64]:
    """Mean squared output error of the right model's simulation under (Q, R), per output.

    ``mean_k diag(C P_k C^T) + diag(R)`` over k = k0 .. k0 + W - 1, with
    ``P_{k+1} = A P_k A^T + Q`` from P_0 = 0: the simulation's state error
    driven by process noise (finite horizon, so a marginal or unstable A
    gives a finite, large floor).
    """
    n = A.shape[0]
    P = np.zeros((n, n))
    acc = np.zeros(C.shape[0])
    with np.errstate(all="ignore"):
        for k in range(k0 + W):
            if k >= k0:
                acc += np.einsum("ij,jk,ik->i", C, P, C)
            P = A @ P @ A.T + Q
    out = acc / W + np.diag(np.atleast_2d(R))
    return np.where(np.isfinite(out), out, np.inf)


# At most this many prune-and-refit rounds (each drops the weakest or the weaker half)
_MAX_PRUNE = 4
# Laws with more terms are left as fitted on d^: not a sparse physical law (forward selection
# kept noise proxies, 10-24 terms on the channels of tests/test_trace_actuator.py), and each
# output-error iteration costs a simulation of npar + 1 columns
_NL_OE_MAX_TERMS = 8


def _wald(dth: NDArray, cov: NDArray) -> float:
    """``dth^T cov^-1 dth`` (inf when cov is singular or not finite)."""
    if not np.all(np.isfinite(cov)):
        return np.inf
    try:
        return float(dth @ np.linalg.solve(cov, dth))
    except np.linalg.LinAlgError:
        return np.inf


def _refine_nonlinear_oe(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray,
                         u: NDArray, x0: NDArray, k0: int, labels, units, tscale=None,
                         noise=None):
    """Refine a nonlinear static law by output error on y, pruning terms with no support.

    The law selected on d^ (a noisy, coloured estimate: GLS with an AR(4)
    prewhitening) keeps small terms beside the main one whose intervals on
    d^ exclude 0 (on the Silverbox: y, |y|, v, v^3, u beside y^3); some only
    make up for the d^ fit's bias. Here the selected terms' coefficients are
    refitted to minimize the simulation error of the model with the law on
    the outputs (PAPER_NOTES §9.3: output error is consistent on a noisy d^;
    the simulation integrates the law as :func:`simulate_with_law` does).

    The d^ fit is kept, and nothing is fitted, where process noise makes up
    most of the noise floor (:func:`_process_noise_dominates`: only there is
    the d^ fit the more efficient estimate) and its simulation's mean
    squared error on y is within ``_FLOOR_FACTOR`` times what the noise
    model ``noise = (Q, R)`` alone gives (:func:`noise_floor`): the law
    already simulates as well as the noise allows. It is kept too when it
    agrees with the output-error fit: the Wald
    statistic of their difference under the output-error covariance (noise
    model ``noise = (Q, R)`` and autocorrelation-robust, see
    :meth:`_OutputErrorNonlinearLaw.fit`) below the 99 % chi-square
    quantile (a Hausman-type test: under process noise the d^ fit, which
    the filter weighs, is the more efficient one; output error wins only
    where the d^ fit is significantly off). Otherwise the output-error
    coefficients are used, terms whose 95 % output-error interval contains 0
    are dropped (the weakest, or the weaker half of many) and the rest
    refitted, as :func:`_refine_static_oe` does for linear laws. The fit
    uses the first half of the estimation samples (at most
    ``_NL_OE_WINDOW``); the output-error law replaces the d^ law only if it
    simulates better on the next, held-out samples (the simulation runs on
    through both): with process noise a lightly damped nonlinear simulation
    is so sensitive to its coefficients that output error fits the noise's
    phase drift and lowers the fitted window's error without a better law.
    Returns ``(law, se_before, se_after)`` (estimation SE [%] on the
    held-out samples); the law is unchanged when the refit does not lower
    it, and always for a sensor law (refitted by the output trace) or a law
    with a lag term.
    """
    from scipy.stats import chi2

    sel, theta0 = _selected(law)
    if not sel or law.output is not None or any(not term_kind(law.spec[j][1]).static
                                                for _, j in sel) \
            or len(sel) > _NL_OE_MAX_TERMS:
        return law, np.nan, np.nan
    W = min(_NL_OE_WINDOW, oe_window(y.shape[0]), (y.shape[1] - k0) // 2)
    if W < 10 * len(sel):
        return law, np.nan, np.nan
    prob = _OutputErrorNonlinearLaw(law, model, md, y, u, x0, k0, sel, theta0, noise, W)
    held = _OutputErrorNonlinearLaw(law, model, md, y, u, x0, k0, sel, theta0, None, 2 * W)

    def se_held(thetas):  # SE [%] on samples k0 + W .. k0 + 2W of each column of thetas
        r = held._resid(held.simulate(thetas, isolate=True))
        r = r.reshape(r.shape[0], held.y.shape[0], -1)[:, :, W:]
        return 100 * np.mean(np.sqrt(np.mean(r**2, axis=2)), axis=1)

    se0 = prob.se(theta0)
    start = theta0
    for _ in range(30):  # a d^ law that diverges: shrunk towards the nominal model until
        if np.isfinite(se0) and se0 < 1e6:  # it simulates (the linear refine's start)
            break
        start = 0.5 * start
        se0 = prob.se(start)
    if not np.isfinite(se0) or se0 >= 1e6:
        return law, se0, se0
    if start is not theta0:
        se0 = np.inf  # the d^ law itself does not simulate: any fit that does is better
    elif noise is not None:  # the d^ law already simulates as well as the noise model allows
        floor = noise_floor(prob.A_lin, prob.C, noise[0], noise[1], k0, W)
        if _process_noise_dominates(floor, noise[1]):  # else the simulation is not needed
            r0 = prob.resid(theta0 / prob.theta_scale).reshape(prob.y.shape[0], -1)
            ms = np.mean(r0**2, axis=1) * prob.scale_y**2
            if np.all(ms <= _FLOOR_FACTOR * floor):
                return law, se0, se0
    keep = list(range(len(sel)))
    theta, half, cov = prob.fit(keep, start)
    if start is theta0 and _wald(theta0 - theta, cov) <= chi2.ppf(0.99, len(sel)):
        return law, se0, se0  # the d^ fit agrees with the simulation's
    for _ in range(_MAX_PRUNE):
        t = np.abs(theta) / np.where(np.isfinite(half) & (half > 0), half, np.inf)
        weak = np.flatnonzero(t < 1.0)
        if not weak.size:
            break
        drop = set(np.argsort(t)[:max(1, weak.size // 2)].tolist())
        kept = [q for q in range(len(keep)) if q not in drop]
        keep = [keep[q] for q in kept]
        if not keep:
            return law, se0, se0
        theta, half, _ = prob.fit(keep, theta[kept])
    sub_theta = np.zeros(len(sel))
    sub_theta[keep] = theta
    se0, se1 = se_held(np.c_[theta0, sub_theta])
    if not se1 < se0:
        return law, se0, se0
    return _nl_law_with(law, sel, keep, theta, half, labels, units, tscale), se0, se1


def _process_noise_dominates(floor: NDArray, R: NDArray) -> bool:
    """Whether process noise makes up more than half of the noise floor on some output.

    Only there is the d^ fit (which the filter weighs against the process noise) the more
    efficient estimate; where the measurement noise dominates every output, output error is
    nearly the maximum-likelihood criterion and the d^ fit's bias (the delayed d^ averages
    the law over a few samples; the state estimate's error enters a nonlinear term) is the
    larger error. Measured shares: 0.79-0.81 on tests/test_trace_delayed.py's process-noise
    records, where output error spreads 7x wider than the d^ fit; 0.001-0.26 on zoo
    cubic_force 20261204 #0 (its d^ fit 1.8 % off, 2.2 half-widths; output error 0.8 %) and
    quadratic_drag 90210 #0-#2."""
    meas = np.diag(np.atleast_2d(R))
    return bool(np.any(floor - meas > meas))


#: An output-error interval is kept only where the simulated cost rises at its ends by at
#: least this share of what the fit's Jacobian predicts (:func:`checked_intervals`)
_CURVATURE_SHARE = 0.1


def checked_intervals(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray, u: NDArray,
                      x0: NDArray, k0: int, labels, units, tscale=None,
                      ) -> tuple[StaticLaw, list[str]]:
    """A nonlinear law's output-error intervals checked against its own simulation.

    The half-widths come from the fit's Jacobian (forward differences of the
    simulation). Where the simulation is not smooth at that scale (a friction's
    sign integrated once per sample beyond its step's stability limit chatters
    around zero speed: zoo coulomb seed 361028620, ``± 7.9e-07`` on 0.379), the
    Jacobian is noise and the intervals are orders of magnitude too narrow. Here
    the sum of squares is simulated at each coefficient's interval ends: where
    it rises by less than ``_CURVATURE_SHARE`` of what the Jacobian predicts
    (``|J delta|^2``), the interval says nothing and is reported as not
    determined (an infinite half-width: "interval not determined" in the
    formula). Returns ``(law, notes)``, the law unchanged when every interval
    holds (or it cannot be checked: a sensor law, a lag, no intervals).
    """
    sel, theta = _selected(law)
    if not sel or law.ci is None or law.output is not None or len(sel) > _NL_OE_MAX_TERMS \
            or any(not term_kind(law.spec[j][1]).static for _, j in sel):
        return law, []
    half = np.array([law.ci[c, j] for c, j in sel], dtype=float)
    ok = np.isfinite(half) & (half > 0)
    if not np.any(ok):
        return law, []
    prob = _OutputErrorNonlinearLaw(law, model, md, y, u, x0, k0, sel, theta, None,
                                    _nl_window(y, k0))
    z, hz = theta / prob.theta_scale, half / prob.theta_scale
    cols = [z]
    for q in range(len(sel)):
        for sgn in (1.0, -1.0):
            zq = z.copy()
            zq[q] += sgn * (hz[q] if ok[q] else 0.0)
            cols.append(zq)
    R = prob._resid(prob.simulate((np.array(cols) * prob.theta_scale).T, isolate=True))
    S = np.sum(R ** 2, axis=1)
    J = prob.jac(z)
    bad = []
    for q in np.flatnonzero(ok):
        pred = float(np.sum((J[:, q] * hz[q]) ** 2))
        rise = 0.5 * (S[1 + 2 * q] + S[2 + 2 * q]) - S[0]
        if not (np.isfinite(rise) and np.isfinite(pred) and rise >= _CURVATURE_SHARE * pred):
            bad.append(q)
    if not bad:
        return law, []
    half[bad] = np.inf
    out = _nl_law_with(law, sel, list(range(len(sel))), theta, half, labels, units, tscale)
    out = replace(out, npar=law.npar)
    names = ", ".join(law.spec[sel[q][1]][0] for q in bad)
    return out, [f"intervals not determined for {names}: at the interval's ends the "
                 f"simulated output error rises by less than {100 * _CURVATURE_SHARE:g} % of "
                 f"what the fit's Jacobian predicts (the simulation is not smooth at that "
                 f"scale: a law too fast for one step per sample chatters)"]


def _nl_law_with(law: StaticLaw, sel, keep, theta, half, labels, units, tscale=None):
    """The law with only the terms ``sel[q]`` for q in keep, at theta (95 % half-widths half)."""
    md = law.coef.shape[0]
    coef = np.zeros_like(law.coef)
    ci = np.full_like(law.coef, np.nan)
    for q, th, h in zip(keep, theta, half):
        c, j = sel[q]
        coef[c, j], ci[c, j] = th, h
    lines = []
    for c in range(md):
        idx = [j for j in range(coef.shape[1]) if coef[c, j] != 0]
        lines.append(law_line(labels[c], coef[c, idx], [law.spec[j][0] for j in idx],
                               units[c] if c < len(units) else "", ci[c, idx]))
    if tscale is not None:
        lines += _one_direction(coef, tscale, labels)
    nlin = {j for j, sp in enumerate(law.spec) if sp[1] in LINEAR_KINDS}
    nonlinear = any(j not in nlin for c, j in zip(*np.nonzero(coef)))
    changes = {}
    if not nonlinear:  # only linear terms survived: the law is its own linear part
        changes["Ddx"], changes["Ddu"] = linear_part(law.spec, coef, law.Ddx.shape[1],
                                                     law.Ddu.shape[1])
    npar = len(keep) + sum(1 for q in keep if law.spec[sel[q][1]][1] in BREAK_KINDS)
    return replace(law, coef=coef, ci=ci, npar=npar, formula="; ".join(lines),
                   nonlinear=nonlinear, **changes)


def refine_force_direction(law: StaticLaw, model: ct.StateSpace, y: NDArray, u: NDArray,
                           x0: NDArray, k0: int, labels, units, cont, noise, dG: NDArray):
    """Refit a force's linear law with its direction free (PAPER_NOTES §9.6).

    A force channel acts along the direction its pair law suggested (a ratio
    a few per cent off when d^ is noisy, e.g. positions only); a law held to
    a wrong direction needs extra terms to make up for it. Here d enters
    ``dx/dt`` through ``Gc + r dG`` with r refitted by output error together
    with the law's coefficients; terms whose 95 % interval then contains 0
    are dropped. Returns ``(law, r, r_halfwidth, se_before, se_after)``;
    the law is returned unchanged with r = 0 when the refit does not lower
    the estimation SE or r's 95 % interval contains 0 (the data do not
    contradict the given direction).

    Parameters
    ----------
    law : StaticLaw
        The force's linear law (md = 1), continuous time.
    model : control.StateSpace
        The channel model (discrete; d the last input).
    y, u : ndarray, shapes (noutputs, nsteps), (ninputs, nsteps)
    x0 : ndarray, shape (nstates,)
    k0 : int
        Samples skipped before the residual.
    labels, units : sequence of str
        Names and units of d.
    cont : tuple
        ``(Ac, Bc, Gc, dt)`` of the continuous nominal model and channel.
    noise : tuple
        ``(Q, R)`` of the discrete model, for the intervals.
    dG : ndarray, shape (nstates,)
        The direction's free part (continuous time).
    """
    sel, theta0 = _selected(law)
    if not sel or cont is None:
        return law, 0.0, np.nan, np.nan, np.nan
    prob = _OutputErrorLaw(law, model, 1, y, u, x0, k0, cont, noise)
    se0 = prob.se(theta0, sel)
    prob.dG = np.asarray(dG, dtype=float).reshape(-1, 1)
    sel1, sol, hw = _prune(prob, sel, prob.fit(sel, np.r_[theta0, 0.0], max_nfev=100))
    if sol is None:
        return law, 0.0, np.nan, se0, se0
    r, hr = float(sol.x[-1]), float(hw[-1])
    se1 = prob.se(sol.x, sel1)
    if not (se1 < se0 and np.isfinite(hr) and abs(r) > hr):
        return law, 0.0, hr, se0, se0
    new = prob.law_with(sel1, sol.x, labels, units, ci=hw, npar=len(sel1))
    return new, r, hr, se0, se1


# Above this many states, forward selection by output error fits only _SCORE_TOP
# candidates per step: the ones whose one-step (Gauss-Newton) score ranks highest
# (below it every candidate is fitted: the score's ranking is first-order only, and a
# different first law can change what the later passes of several effects find).
_SCORE_ABOVE = 8
_SCORE_TOP = 3


def _by_score(prob: _OutputErrorLaw, sel, theta, cands) -> list:
    """The ``_SCORE_TOP`` candidates that would lower the output error most, to first order.

    For each candidate term c the residual's derivative j_c at the current
    law (one simulation each, a forward difference) gives the RSS drop of a
    Gauss-Newton step in c alone, ``(j_c^T r)^2 / j_c^T j_c`` (the score
    test, :func:`_scores`). Fitting only the best few by Levenberg-Marquardt
    costs a few simulations per candidate instead of an optimization each.
    """
    if len(cands) <= _SCORE_TOP or prob.A.shape[0] <= _SCORE_ABOVE:
        return list(cands)
    order = np.argsort(_scores(prob, sel, theta, cands))[::-1][:_SCORE_TOP]
    return [cands[q] for q in order]


def _scores(prob, sel, theta, cands) -> list[float]:
    """Each candidate term's first-order drop of the output error's sum of squares beside
    the terms ``sel`` at ``theta``: ``(j^T r)^2 / j^T j``, j its sensitivity
    (:func:`_sensitivities`). ``prob``: any problem with ``resid(theta, sel)``."""
    r0, J = _sensitivities(prob, sel, theta, cands)
    out = []
    for j in J:
        jj = float(j @ j)
        out.append(float(j @ r0) ** 2 / jj if jj > 0 and np.isfinite(jj) else 0.0)
    return out


def _sensitivities(prob, sel, theta, cands, own: bool = False):
    """``(r0, J)``: the output error at the terms ``sel`` and ``theta``, and each
    candidate's forward difference of it in a new coefficient (one simulation each; the
    step grows from 1e-4 until the residual moves); with ``own``, first the chosen
    terms' own, in the order of ``sel``."""
    with single_thread_blas():
        r0 = prob.resid(theta, sel)
        scale = 1e-9 * (np.max(np.abs(r0)) + 1e-300)
        J = []
        trials = ([(q, None) for q in range(len(sel))] if own else []) + \
            [(None, c) for c in cands]
        for q, cj in trials:
            for h in (1e-4, 1e-2, 1.0):
                if cj is None:  # the chosen term's own coefficient, a step of its size
                    step = h * max(abs(float(theta[q])), 1e-300)
                    t = np.array(theta, dtype=float)
                    t[q] += step
                    diff = prob.resid(t, sel) - r0
                else:
                    step = h
                    diff = prob.resid(np.r_[theta, h], sel + [cj]) - r0
                if np.max(np.abs(diff)) > scale:
                    break
            J.append(diff / step)
    return r0, J


def _select_static_oe(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray,
                      u: NDArray, x0: NDArray, k0: int, labels, units, max_terms: int = 4,
                      cont=None, noise=None, only=None):
    """Choose a linear static law by output error on y (forward selection, BIC).

    Used when d^ is mostly estimation noise (its variance barely exceeds the
    filter's Pd, e.g. when only positions are measured and C G ~ dt^2/2):
    regressions on d^ then select terms at random. Each candidate support is
    fitted by Levenberg-Marquardt on the simulation error of the augmented
    model (continuous-time law when ``cont`` is given); terms are added while
    the BIC of the output error drops, then terms whose 95 % interval
    contains 0 are dropped. The BIC counts the residual's independent samples,
    ``nres / c`` with c its colour (:func:`greybox.trace.intervals.residual_colour`),
    as the nonlinear pipeline's selection does: the output error integrates the
    process noise, and a BIC on every sample takes terms that only fit its colour
    (a damping term of 1 % beside a missing spring, 64-state chain, positions
    measured). ``only`` restricts the candidates to these term indices.
    """
    prob = _OutputErrorLaw(law, model, md, y, u, x0, k0, cont, noise)
    lin = [j for j, (_, kind, _) in enumerate(law.spec) if kind in LINEAR_KINDS]
    if only is not None:  # a pre-ranked subset of the terms
        lin = [j for j in lin if j in set(only)]
    cands = [(c, j) for c in range(md) for j in lin]
    p = prob.y.shape[0]
    sel, theta, hw = forward_select_oe(
        prob, cands, max_terms, prob.y[:, k0:].size,
        rank=lambda sel, theta, cs: _by_score(prob, sel, theta, cs),
        colour=lambda r: residual_colour(np.asarray(r).reshape(p, -1)))
    return prob.law_with(sel, theta, labels, units, ci=hw, nonlinear=False, npar=len(sel))


#: Tolerance (MINPACK ftol, xtol) of a selection's trial fits, compared only by their residual
#: sum of squares: a sum of squares 1e-6 (relative) above its minimum moves the BIC of
#: ``n log(RSS)`` by n * 1e-6 (0.02 at n = 2e4 samples, 0.1 at 1e5), far below one
#: parameter's penalty log(n) ~ 10; the chosen law is refitted at 1e-8. Measured on
#: tests/test_trace_scale.py's two-effect plant (3 seeds): 38 % of the trial fits'
#: simulations came after the sum of squares was within 1e-6 of where 1e-8 stopped.
TRIAL_TOL = 1e-6


def forward_select_oe(prob, cands, max_terms: int, nres: int, rank=None, colour=None,
                      max_nfev: int = 100, start=None, cost=None, factor: float = 1.0,
                      exchange: bool = True):
    """Forward selection of a static law's terms by output error, BIC stop, then pruning.

    Shared by the linear trace (:func:`_select_static_oe`) and the nonlinear
    pipeline (:mod:`greybox.workflow_nonlinear`). Each step fits every
    candidate term that ``rank`` keeps (all when None) beside the terms
    already chosen, by ``prob.fit`` (Levenberg-Marquardt on the output
    error), and adds the one with the lowest residual sum of squares while
    the BIC of the output error drops, ``n log(RSS / nres) + k log(n)``;
    then each chosen term is swapped for a left-out one that fits better
    (:func:`_exchange`: greedy steps on correlated terms take a proxy first);
    then every term is checked by the same rule the other way (a term whose
    removal it accepts is dropped, :func:`_backward`: the greedy order can
    take a term that a later one makes redundant); then terms whose 95 %
    interval (``prob.halfwidths``) contains 0 are dropped (:func:`_prune`).

    n is the number of residuals ``nres``, or with ``colour`` (a function of
    a residual returning its colour c >= 1, the long-run variance over the
    variance) ``nres / c``, c the trial's colour for the first term (as a
    gate weighs a law against none), then the larger of the two models'
    compared (the trials of a step are ranked with the current model's): an
    output-error
    residual is coloured
    (the simulation error integrates the process noise), so its ``nres``
    samples carry about ``nres / c`` independent ones, and a BIC on nres
    would accept terms that only fit the colour.

    Parameters
    ----------
    prob : object
        The output-error problem: ``resid(theta, sel)`` (flat residual),
        ``fit(sel, start, max_nfev, trial)`` (a result with ``x``, ``fun`` and
        ``jac``; ``trial=True``: a fit only compared by its residual, which may stop
        earlier, :data:`TRIAL_TOL`) and ``halfwidths(sol, sel)``.
    cands : list of tuple
        Candidate terms (component of d, term index).
    max_terms : int
        At most this many terms.
    nres : int
        Residuals in the output error (outputs x samples).
    rank : callable, optional
        ``rank(sel, theta, cands)`` -> the candidates worth fitting this step.
    colour : callable, optional
        The residual's colour (see above); None: n = nres.
    max_nfev : int
        Evaluations per fit.
    start : callable, optional
        ``start(sel, theta, cand)`` -> the new term's starting coefficient
        (default 0).
    cost : callable, optional
        ``cost(cand)`` -> the parameters a term counts in the BIC (default 1;
        e.g. 2 for a saturation hinge whose level is searched too).
    factor : float
        A term is added only if the likelihood ratio exceeds ``factor`` times
        its BIC penalty (1: the BIC itself).
    exchange : bool
        After the forward steps, swap chosen terms for left-out ones that fit
        better (:func:`_exchange`), before the backward check.

    Returns
    -------
    tuple
        ``(sel, theta, halfwidths)``; halfwidths None when no term is chosen.
    """
    bic = _bic(nres)

    def npar(terms):
        return sum(1 if cost is None else cost(t) for t in terms)

    sel, theta = [], np.zeros(0)
    fun = prob.resid(theta, sel)
    rss_best = float(np.sum(fun ** 2))
    while len(sel) < max_terms:
        trial = None
        left = [c for c in cands if c not in sel]
        n0 = nres / colour(fun) if colour is not None else nres  # the trials ranked on it
        for cj in (rank(sel, theta, left) if rank is not None else left):
            t0 = 0.0 if start is None else start(sel, theta, cj)
            sol = prob.fit(sel + [cj], np.r_[theta, t0], max_nfev=max_nfev, trial=True)
            rss = float(np.sum(sol.fun ** 2))
            b = bic(rss, npar(sel + [cj]), n0)
            if trial is None or b < trial[4]:
                trial = (rss, cj, sol.x, sol.fun, b)
        if trial is None:
            break
        # the residual's colour: the trial's for the first term (against no law, as the
        # gate weighs a law), then the larger of the two models' (a term can lower the
        # colour estimate without a better law: the smaller n is the cautious one)
        n = nres if colour is None else nres / (colour(trial[3]) if not sel else
                                                 max(colour(fun), colour(trial[3])))
        lr = n * np.log(max(rss_best / nres, 1e-300)) - n * np.log(max(trial[0] / nres, 1e-300))
        if factor == 1.0:
            if bic(trial[0], npar(sel + [trial[1]]), n) >= bic(rss_best, npar(sel), n):
                break
        elif not lr > factor * (npar(sel + [trial[1]]) - npar(sel)) * np.log(n):
            break
        rss_best, sel, theta, fun = trial[0], sel + [trial[1]], trial[2], trial[3]
    if exchange:
        sel, theta, fun = _exchange(prob, sel, theta, fun, cands, npar, max_nfev)
    sel, theta = _backward(prob, sel, theta, fun, nres, colour, npar, factor, max_nfev)
    hw = None
    if sel:
        sel, sol, hw = _prune(prob, sel, prob.fit(sel, theta, max_nfev=max_nfev))
        theta = sol.x if sol is not None else np.zeros(0)
    return sel, theta, hw


# --------------------------------------------------------------------------- the criterion
def backward_by_criterion(n: int, theta: NDArray, refit, resid, nout: int, weight=None,
                          factor: float = 1.0):
    """Drop terms while the output-error criterion falls (:func:`greybox.metrics.oe_criterion`).

    ``refit(keep, start) -> theta`` fits the terms ``keep`` (indices 0..n-1);
    ``resid(keep, theta)`` is their output error, flat, output by output
    (nout outputs). The effective samples are taken once, from the residual of
    all n terms, so every subset is scored on the same count. Each round
    refits the law without each term in turn and drops the one whose removal
    lowers the criterion most; it stops when none does. ``weight[q]``: the
    parameters term q carries (2 for a breakpoint term: its coefficient and
    its level; default 1). ``factor``: the criterion's price per parameter in units
    of the BIC penalty (close the loop passes its ``bic_factor``, the price its choice
    of candidates pays). Returns ``(keep, theta)``.
    """
    w = np.ones(n, dtype=int) if weight is None else np.asarray(weight, dtype=int)
    keep, theta = list(range(n)), np.asarray(theta, dtype=float)
    r0 = np.asarray(resid(keep, theta)).reshape(nout, -1)
    if not np.all(np.abs(r0) < 1e6):
        return keep, theta
    neff = effective_samples(r0)
    cur = oe_criterion(r0, int(w[keep].sum()), neff, factor)
    while len(keep) > 1:
        best = None
        for q in range(len(keep)):
            sub = keep[:q] + keep[q + 1:]
            th = np.asarray(refit(sub, np.delete(theta, q)), dtype=float)
            r = np.asarray(resid(sub, th)).reshape(nout, -1)
            c = (oe_criterion(r, int(w[sub].sum()), neff, factor)
                 if np.all(np.abs(r) < 1e6) else np.inf)
            if best is None or c < best[0]:
                best = (c, sub, th)
        if not best[0] < cur:
            break
        cur, keep, theta = best
    return keep, theta


def prune_by_criterion(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray, u: NDArray,
                       x0: NDArray, k0: int, labels, units, tscale=None, cont=None,
                       noise=None, factor: float = 1.0) -> tuple[StaticLaw, list[str]]:
    """A static law's terms kept only where the data support them, by the one criterion.

    The law's selected terms are refitted by output error on y (the linear
    law folded into the model, in continuous time with ``cont``; a nonlinear
    law simulated), then dropped one at a time while
    :func:`greybox.metrics.oe_criterion` falls (:func:`backward_by_criterion`).
    A term beside the right one that only makes up for noise or for a
    mismatch elsewhere lowers the output error by less than its price.
    Returns ``(law, notes)``: the law unchanged (and no note) when every term
    is kept, or for a sensor law, a law with a lag or a drift term, or one of
    over ``_NL_OE_MAX_TERMS`` terms.
    """
    sel, theta0 = _selected(law)
    if len(sel) < 2 or len(sel) > _NL_OE_MAX_TERMS or law.output is not None or any(
            not term_kind(law.spec[j][1]).static for _, j in sel):
        return law, []
    weight = [2 if law.spec[j][1] in BREAK_KINDS else 1 for _, j in sel]
    p = y.shape[0]
    if law.nonlinear:
        W = _nl_window(y, k0)
        prob = _OutputErrorNonlinearLaw(law, model, md, y, u, x0, k0, sel, theta0, noise, W)

        def resid(keep, th):
            full = np.zeros(len(sel))
            full[keep] = th
            return prob.resid(full / prob.theta_scale)

        def refit(keep, start):
            return prob.fit(keep, start)[0]
    else:
        prob = _OutputErrorLaw(law, model, md, y, u, x0, k0, cont, noise)

        def resid(keep, th):
            return prob.resid(th, [sel[q] for q in keep])

        def refit(keep, start):
            return prob.fit([sel[q] for q in keep], start).x
    theta_all = refit(list(range(len(sel))), theta0)
    keep, theta = backward_by_criterion(len(sel), theta_all, refit, resid, p, weight, factor)
    if len(keep) == len(sel):
        return law, []
    dropped = [law.spec[sel[q][1]][0] for q in range(len(sel)) if q not in keep]
    note = (f"terms without support by the output-error criterion (BIC on effective "
            f"samples) dropped: {', '.join(dropped)}")
    if law.nonlinear:
        theta, half, _ = prob.fit(keep, theta)
        return _nl_law_with(law, sel, keep, theta, half, labels, units, tscale), [note]
    ssel = [sel[q] for q in keep]
    sol = prob.fit(ssel, theta)
    return prob.law_with(ssel, sol.x, labels, units, tscale, ci=prob.halfwidths(sol, ssel),
                         npar=len(ssel)), [note]


#: The search range of a smoothed sign's width, in multiples of its default (5 % of its
#: variable's RMS over the record, :func:`greybox.terms.law_terms`), and the search's
#: tolerance on the factor's logarithm (:func:`fit_smoothing`)
_EPS_FACTORS = (0.1, 10.0)
_EPS_XATOL = 0.05


def _smoothed_slots(law: StaticLaw, sel) -> list[int]:
    """The entries of ``law.eps`` the selected terms' smoothed signs read."""
    slots = {term_kind(law.spec[j][1]).eps_slot(law.spec[j][2]) for _, j in sel}
    return sorted(s for s in slots if s is not None)


def fit_smoothing(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray, u: NDArray,
                  x0: NDArray, k0: int, labels, units, tscale=None, noise=None,
                  factor: float = 1.0) -> tuple[StaticLaw, list[str]]:
    """The width of a nonlinear law's smoothed signs fitted by output error, where the
    one criterion pays for it.

    ``sign(v)`` is simulated as ``tanh(v / eps)``, eps 5 % of v's RMS by default. Real
    friction reverses over a width of its own (a Stribeck curve, a compliant contact); a
    width off by a factor of two leaves a shape error that other terms make up for (zoo
    coulomb 20261208 #0: the truth's width 8.3 % of v's RMS; at 5 % the law took a
    damping term beside the sign, ``-0.032 v``, validation SE 1.44 % against the true
    model's 0.28 %). One factor on the widths of every smoothed term of the law is
    searched (bounded, on its logarithm, within :data:`_EPS_FACTORS`; the coefficients
    refitted by output error at each trial) and kept only where
    :func:`greybox.metrics.oe_criterion` (``factor``: its price per parameter) pays for
    it as one more parameter. Returns ``(law, notes)``: the law unchanged and no note
    where it holds no smoothed term (or is a sensor law, or holds a lag or over
    ``_NL_OE_MAX_TERMS`` terms) or the default width wins.
    """
    from scipy.optimize import minimize_scalar

    sel, theta0 = _selected(law)
    if not sel or not law.nonlinear or len(sel) > _NL_OE_MAX_TERMS or law.output is not None \
            or any(not term_kind(law.spec[j][1]).static for _, j in sel):
        return law, []
    slots = _smoothed_slots(law, sel)
    if not slots:
        return law, []
    W, p, everything = _nl_window(y, k0), y.shape[0], list(range(len(sel)))
    trials: dict[float, tuple] = {}

    def trial(logf: float):
        """(problem, theta, residual (p, W)) with the widths times exp(logf)."""
        key = round(float(logf), 12)
        if key not in trials:
            eps = np.array(law.eps, dtype=float, copy=True)
            eps[slots] *= np.exp(logf)
            prob = _OutputErrorNonlinearLaw(replace(law, eps=eps), model, md, y, u, x0, k0,
                                            sel, theta0, noise, W)
            theta = prob.fit(everything, theta0)[0]
            r = prob.resid(theta / prob.theta_scale).reshape(p, -1)
            trials[key] = (prob, theta, r)
        return trials[key]

    r0 = trial(0.0)[2]
    if not np.all(np.abs(r0) < 1e6):
        return law, []
    neff = effective_samples(r0)

    def crit(logf: float, npar: int) -> float:
        r = trial(logf)[2]
        return oe_criterion(r, npar, neff, factor) if np.all(np.abs(r) < 1e6) else np.inf

    lo, hi = np.log(_EPS_FACTORS[0]), np.log(_EPS_FACTORS[1])
    best = minimize_scalar(lambda z: crit(z, len(sel)), bounds=(lo, hi), method="bounded",
                           options={"xatol": _EPS_XATOL})
    c0, c1 = crit(0.0, len(sel)), crit(float(best.x), len(sel) + 1)
    if not c1 < c0:
        return law, []
    prob, theta, _ = trial(float(best.x))
    theta, half, _ = prob.fit(everything, theta)
    out = _nl_law_with(prob.law, sel, everything, theta, half, labels, units, tscale)
    out = replace(out, npar=out.npar + 1)
    f = float(np.exp(best.x))
    widths = ", ".join(f"{law.eps[s] * f:.3g}" for s in slots)
    return out, [f"smoothing width of the law's sign terms fitted by output error: "
                 f"{f:.3g} x the default (5 % of the variable's RMS), eps = {widths}; "
                 f"output-error criterion {c1 - c0:+.1f} with it counted as a parameter"]


def exchange_siblings(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray, u: NDArray,
                      x0: NDArray, k0: int, labels, units, tscale: NDArray,
                      noise=None, family: str | None = None) -> tuple[StaticLaw, list[str]]:
    """Each term of a static law swapped for the form of its variable the output error prefers.

    A law chosen on a delayed d^ (an equation measured only through others)
    takes the form of each variable by a regression on an estimate that is
    mostly noise, where v and sign(v) (Coulomb friction on a mass whose speed
    is not measured), or v and v^3, fit nearly alike. Here each chosen
    term's siblings (:func:`greybox.trace.laws.siblings`) are weighed in its
    place on the output error of y, every law simulated with the same
    integrator (:class:`_OutputErrorNonlinearLaw`):

    1. Screen (a few batched simulations): each sibling in its term's place, and where its
       component of d has several terms as that component's whole law, at a few guessed
       coefficients, the
       best refined (:func:`_sibling_screen`); the ``_SIBLING_FITS`` best that simulate
       better than the law go on.
    2. Where a sibling already simulates better than the law, the law with the swap (from
       the screen's size) and the law as it is are refitted by output error and the swap
       is taken if it
       lowers the output-error criterion (:func:`greybox.metrics.oe_criterion`
       on the effective samples of the current law's residual, each law's parameters
       counted) and keeps the coefficient's sign (a damping stays a damping, only its
       shape may change: on the Silverbox a -v^3 damping would become a +sign(v)
       anti-friction).

    ``tscale``: each term's RMS on the aligned data (:meth:`StaticLaw.term_scale`),
    which sizes the screen's steps and the swapped term's starting coefficient.
    ``family``: only the terms of this :attr:`~greybox.terms.TermKind.family` weighed
    (None: every term). Returns ``(law, notes)``: the law unchanged and no note when no
    swap wins.
    """
    sel, theta0 = _selected(law)
    sibs = [(q, j2) for q, (_, j) in enumerate(sel) for j2 in siblings(law.spec, j)
            if family is None or term_kind(law.spec[j][1]).family == family]
    if not sibs or len(sel) > _NL_OE_MAX_TERMS or law.output is not None:
        return law, []
    p = y.shape[0]
    W = _nl_window(y, k0)
    promising = _sibling_screen(law, model, md, y, u, x0, k0, sel, theta0, sibs, tscale,
                                noise, W)
    shared = _shared_swaps(sel, sibs)
    if not promising and not shared:
        return law, []

    def fitted(s, start):
        prob = _OutputErrorNonlinearLaw(law, model, md, y, u, x0, k0, s, start, noise, W)
        theta, half, _ = prob.fit(list(range(len(s))), start)
        r = prob.resid(theta / prob.theta_scale).reshape(p, -1)
        return theta, half, r

    theta, half, r = fitted(sel, theta0)
    if not np.all(np.abs(r) < 1e6):
        return law, []
    neff = effective_samples(r)
    cur, best = oe_criterion(r, len(sel), neff), None
    for q, j2, guess, alone in promising:
        if alone:  # the sibling as its component's whole law
            rest = [k for k in range(len(sel)) if sel[k][0] != sel[q][0]]
            s2 = [sel[k] for k in rest] + [(sel[q][0], j2)]
            start, at = np.r_[theta[rest], guess], len(rest)
        else:
            s2, start, at = sel[:q] + [(sel[q][0], j2)] + sel[q + 1:], theta.copy(), q
            start[q] = guess  # the screen's refined size (the fit is not convex in it)
        th, hf, r2 = fitted(s2, start)
        if np.all(np.abs(r2) < 1e6) and np.sign(th[at]) == np.sign(theta[q]):
            crit = oe_criterion(r2, len(s2), neff)
            if crit < cur and (best is None or crit < best[0]):
                old = " + ".join(law.spec[j][0] for c, j in sel if c == sel[q][0]) \
                    if alone else law.spec[sel[q][1]][0]
                best = (crit, s2, th, hf, (old, law.spec[j2][0] + (" alone" if alone else "")))
    for qs, j2 in shared:  # one shape for a variable in every component that holds it
        s2 = [(c, j2) if k in qs else (c, j) for k, (c, j) in enumerate(sel)]
        start = theta.copy()
        for k in qs:
            start[k] = _same_size(theta[k], tscale, sel[k][1], j2)
        th, hf, r2 = fitted(s2, start)
        if np.all(np.abs(r2) < 1e6) and all(np.sign(th[k]) == np.sign(theta[k]) for k in qs):
            crit = oe_criterion(r2, len(s2), neff)
            if crit < cur and (best is None or crit < best[0]):
                best = (crit, s2, th, hf, (law.spec[sel[qs[0]][1]][0],
                                           f"{law.spec[j2][0]} in {len(qs)} components"))
    if best is None:
        return law, []
    _, sel, theta, half, (a, b) = best
    note = (f"term form chosen by output error (the output-error criterion on effective "
            f"samples): {b} for {a}")
    return _nl_law_with(law, sel, list(range(len(sel))), theta, half, labels, units,
                        tscale), [note]


def _shared_swaps(sel, sibs) -> list[tuple[list[int], int]]:
    """``(positions in sel, sibling term)`` for each term that several components of d hold
    (a force's relative coordinate in both bodies' equations) and each of its siblings in
    ``sibs`` ((position, sibling) pairs): the swap :func:`exchange_siblings` weighs in every
    such component at once (swapped in one of them only, the two bodies' forces disagree
    and neither trial simulates better: zoo cubic_force, seed 53736598 #0)."""
    held: dict[int, list[int]] = {}
    for q, (_, j) in enumerate(sel):
        held.setdefault(j, []).append(q)
    out = []
    for j, qs in held.items():
        if len(qs) > 1:
            out += [(qs, j2) for q, j2 in sibs if q == qs[0]]
    return out


def offer_terms(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray, u: NDArray,
                x0: NDArray, k0: int, labels, units, tscale: NDArray, offers, guesses,
                cont=None, noise=None, factor: float = 1.0) -> tuple[StaticLaw, list[str]]:
    """A static law with the one offered term that the output-error criterion wants most.

    The terms a law is chosen among on d^ can miss the one the plant has (an equation
    measured only through others: d^ is delayed and mostly noise, and a law of five
    neighbours' states stands in for the equation's own loss; Coulomb friction on a mass
    whose speed is not measured found as a damping of its neighbour's). Each of
    ``offers`` ((component of d, term index) pairs, the law lacks them) is fitted beside
    the law's terms by output error from 0 (``guesses``: its scale), and in their place
    (its component's whole law: several terms can stand in for it together and fit as
    well as it does beside them); the trial that lowers
    :func:`greybox.metrics.oe_criterion` most (each parameter priced at ``factor`` times
    its BIC penalty, on the effective samples of the law's own residual, the law refitted
    the same way: a linear trial as the linear law, a nonlinear one simulated) is taken;
    the caller's prune (:func:`prune_by_criterion`) then drops the terms it makes
    redundant. Returns ``(law, notes)``: the law unchanged
    and no note when no offer lowers the criterion.
    """
    sel, theta0 = _selected(law)
    todo = [(o, g) for o, g in zip(offers, guesses) if o not in sel and np.isfinite(g)]
    if not todo or not sel or len(sel) + 1 > _NL_OE_MAX_TERMS or law.output is not None:
        return law, []
    p, W = y.shape[0], _nl_window(y, k0)
    bases: dict = {}
    lin = _OutputErrorLaw(law, model, md, y, u, x0, k0, cont, noise)

    def fitted(s, start, nonlinear, scale=None):
        if nonlinear:  # (``scale``: the coefficients' scales, where ``start`` holds a 0)
            prob = _OutputErrorNonlinearLaw(law, model, md, y, u, x0, k0, s,
                                            start if scale is None else scale, noise, W)
            theta, half, _ = prob.fit(list(range(len(s))), start)
            return theta, half, prob.resid(theta / prob.theta_scale).reshape(p, -1), None
        prob = lin
        sol = prob.fit(s, start)
        return sol.x, prob.halfwidths(sol, s), np.asarray(prob.resid(sol.x, s)).reshape(
            p, -1), prob

    best = None
    for (c, j), g in todo:
        nl = law.nonlinear or not term_kind(law.spec[j][1]).linear
        if nl not in bases:
            th0, _, r0, _ = fitted(sel, theta0, nl)
            ok = bool(np.all(np.abs(r0) < 1e6))
            neff = effective_samples(r0) if ok else None
            bases[nl] = (oe_criterion(r0, len(sel), neff, factor) if ok else None, neff, th0)
        cur, neff, th0 = bases[nl]
        if cur is None:
            continue
        # beside the law, and as its component's whole law (terms that stand in for it
        # together fit as well as it does beside them); from 0 (the law as it is: the
        # guess on d^ can be far off, even in sign, where d^ could not pick the term), at
        # the guess's scale
        rest = [q for q in range(len(sel)) if sel[q][0] != c]
        trials = [(sel + [(c, j)], th0)]
        if len(rest) < len(sel):  # (else "in its place" is the same trial)
            trials.append(([sel[q] for q in rest] + [(c, j)], th0[rest]))
        for s2, th_s in trials:
            th, hf, r2, prob = fitted(s2, np.r_[th_s, 0.0], nl, np.r_[th_s, g])
            if not np.all(np.abs(r2) < 1e6):
                continue
            crit = oe_criterion(r2, len(s2), neff, factor)
            if crit < cur and (best is None or crit - cur < best[0]):
                best = (crit - cur, s2, th, hf, prob, len(s2) <= len(sel))
    if best is None:
        return law, []
    gain, s2, th, hf, prob, alone = best
    note = (f"term offered by output error: {law.spec[s2[-1][1]][0]} "
            f"{'in place of the law' if alone else 'added'} (the output-error criterion "
            f"{gain:+.4g})")
    if prob is None:
        return _nl_law_with(law, s2, list(range(len(s2))), th, hf, labels, units, tscale), \
            [note]
    return prob.law_with(s2, th, labels, units, tscale, ci=hf, npar=len(s2)), [note]


def simulates_better(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray, u: NDArray,
                     x0: NDArray, k0: int) -> bool:
    """Whether the model with ``law`` at its coefficients simulates y better (a lower,
    finite SE on the output-error window) than the model without it."""
    sel, theta0 = _selected(law)
    if not sel:
        return False
    prob = _OutputErrorNonlinearLaw(law, model, md, y, u, x0, k0, sel, theta0, None,
                                    _nl_window(y, k0))
    with np.errstate(all="ignore"):  # a diverging law loses, it does not warn
        se, se0 = prob.se(theta0), prob.se(np.zeros_like(theta0))
    return bool(np.isfinite(se) and se < se0)


def _nl_window(y: NDArray, k0: int) -> int:
    """Samples after k0 a whole-law output-error fit of a nonlinear law uses (the criterion's
    prune and the siblings' exchange): at most ``_NL_OE_WINDOW`` and ``oe_window(p)``."""
    return min(_NL_OE_WINDOW, oe_window(y.shape[0]), y.shape[1] - k0)


def _same_size(coef: float, tscale: NDArray, j: int, j2: int) -> float:
    """The coefficient of term j2 whose contribution has the RMS of term j's at ``coef``."""
    return coef * tscale[j] / max(tscale[j2], 1e-300)


def _sibling_screen(law, model, md, y, u, x0, k0, sel, theta0, sibs, tscale, noise, W):
    """The swaps ``(q, sibling term, coefficient, alone)`` that already simulate better than
    the law as it is at a guessed coefficient, best first: the sibling in its term's place
    (``alone`` False) and, where its component of d has several terms, the sibling as that
    component's whole law (``alone`` True: linear terms chosen together can mimic one odd
    form, a relative deflection and velocity for a cubic spring); its size the term's own
    of the same RMS times ``_SCREEN_FACTORS``, the best refined by halving steps
    (``_SCREEN_REFINE``); each round one simulation of every trial, the trials independent (see
    :func:`exchange_siblings`). A first-order screen (the derivative at 0, as
    :func:`_by_score`) missed Coulomb friction for the linear damping it was named as: the
    friction's effect on the motion is far from linear in its size."""
    ext = sel + [(sel[q][0], j2) for q, j2 in sibs]
    th = np.r_[theta0, np.zeros(len(sibs))]
    prob = _OutputErrorNonlinearLaw(law, model, md, y, u, x0, k0, ext, th, noise, W)
    size = np.array([_same_size(theta0[q], tscale, sel[q][1], j2) for q, j2 in sibs])
    comp = np.array([c for c, _ in sel])
    trials = [(s, False) for s in range(len(sibs))]
    trials += [(s, True) for s, (q, _) in enumerate(sibs) if np.sum(comp == comp[q]) > 1]

    def rss_at(fac):  # fac (ntrials, k): each trial at these sizes
        cols = [th]  # and the law as it is (its rss first)
        for t, (s, alone) in enumerate(trials):
            q = sibs[s][0]
            for f in fac[t]:
                col = th.copy()
                col[q] = 0.0
                if alone:  # the other terms of its component of d out
                    col[:len(sel)][comp == comp[q]] = 0.0
                col[len(sel) + s] = f * size[s]
                cols.append(col)
        with np.errstate(all="ignore"):  # trials independent: one diverging voids only itself
            R = prob._resid(prob.simulate(np.array(cols).T, isolate=True))
        r = np.sum(R ** 2, axis=1)  # _resid counts a diverged sample as 1e6: finite
        return r[0], r[1:].reshape(fac.shape)

    fac = np.tile(np.array(_SCREEN_FACTORS), (len(trials), 1))
    base, rss = rss_at(fac)
    rows = np.arange(len(trials))
    f_best, r_best = fac[rows, rss.argmin(1)], rss.min(1)
    for step in _SCREEN_REFINE:  # each trial's best size, refined around the grid's
        fac = f_best[:, None] * 2.0 ** np.array([-step, step])
        rss = rss_at(fac)[1]
        better = rss.min(1) < r_best
        f_best = np.where(better, fac[rows, rss.argmin(1)], f_best)
        r_best = np.minimum(r_best, rss.min(1))
    order = [t for t in np.argsort(r_best) if r_best[t] < base][:_SIBLING_FITS]
    return [(*sibs[trials[t][0]], float(f_best[t] * size[trials[t][0]]), trials[t][1])
            for t in order]


#: Sizes of a sibling in its term's place, relative to the term's own of the same RMS: a
#: factor 4 apart from 1/16 to 1024. An output-error fit of a wrong form shrinks it
#: towards 0 where it cannot mimic the law (a linear spring for a cubic one: on zoo
#: cubic_force seed 20261205 draw 14 the cube's right size was 32x the linear fit's of the
#: same RMS, and 560x on seed 20261206 draw 0), so the range reaches far above 1.
_SCREEN_FACTORS = tuple(4.0 ** np.arange(-2, 6))
#: Refinement of each sibling's best size on the grid: steps of 2^+-1, 2^+-1/2, 2^+-1/4,
#: 2^+-1/8 (one batched simulation each). A friction's output error is sharply peaked in
#: its size: on zoo coulomb seed 1627726626 draw 1, sign(v1) simulated worse than the law
#: at every grid size (61.7 at 1x against 48.2) and better only within x0.77-0.92 (31.9 at
#: 0.84x).
_SCREEN_REFINE = (1.0, 0.5, 0.25, 0.125)
#: Swaps refitted by output error: the screen's best few. Each is a nonlinear simulation
#: fitted by Levenberg-Marquardt (~1 s at 2000 samples); a second-order actuator lag's
#: static side law (tests/test_zoo.py draw 1) had 7 and 8 promising swaps, 21 of the
#: test's 37 s, and the swap taken was each time the screen's first.
_SIBLING_FITS = 3


def _bic(nres):
    """``bic(rss, k, n) = n log(RSS / nres) + k log(n)``."""
    def bic(rss, k, n):
        return n * np.log(max(rss / nres, 1e-300)) + k * np.log(n)
    return bic


def _exchange(prob, sel, theta, fun, cands, npar, max_nfev):
    """The forward selection's terms, each swapped for a left-out candidate that fits better.

    Greedy forward selection on correlated terms takes a proxy first (a
    thermal row's T4 for the loss of T3 beside it: alone it fits a little
    better, and every later term is then chosen around it). A proxy is a term
    whose effect on y resembles the right one's, so each round tries, for
    every chosen term, the ``_EXCHANGE_TRIALS`` candidates left out (with its
    parameter count) whose sensitivities of the output error correlate with
    its own most (:func:`_sensitivities`, one simulation each), each in its
    place, refitted from the other terms' coefficients by at most
    ``_EXCHANGE_NFEV`` evaluations; it takes the swap with the lowest
    residual sum of squares if, refitted in full, it is lower than the
    current one; at most ``len(sel)`` rounds. The parameter count does not
    change, so the criterion is the residual sum of squares itself. With one
    term there is nothing to do: the first forward step is the best single
    term. (A first-order screen of the swaps by their score, as
    :func:`_by_score` ranks the forward steps, missed the thermal row's swap:
    the proxy's neighbours make up for the term taken out.)
    """
    rss = float(np.sum(np.asarray(fun) ** 2))
    for _ in range(len(sel) if len(sel) >= 2 else 0):
        left = [c for c in cands if c not in sel]
        _, J = _sensitivities(prob, sel, theta, left, own=True)
        Jn = [j / (np.linalg.norm(j) + 1e-300) for j in J]
        best = None
        for q in range(len(sel)):
            rest, th = sel[:q] + sel[q + 1:], np.delete(theta, q)
            ok = [k for k, c in enumerate(left) if npar([c]) == npar([sel[q]])]
            ok.sort(key=lambda k: -abs(float(Jn[q] @ Jn[len(sel) + k])))
            for k in ok[:_EXCHANGE_TRIALS]:
                sol = prob.fit(rest + [left[k]], np.r_[th, 0.0], max_nfev=_EXCHANGE_NFEV,
                               trial=True)
                r2 = float(np.sum(sol.fun ** 2))
                if r2 < rss * (1 - 1e-6) and (best is None or r2 < best[0]):
                    best = (r2, rest + [left[k]], sol.x)
        if best is None:
            break
        sol = prob.fit(best[1], best[2], max_nfev=max_nfev, trial=True)
        r2 = float(np.sum(sol.fun ** 2))
        if not r2 < rss * (1 - 1e-6):
            break
        rss, sel, theta, fun = r2, best[1], sol.x, sol.fun
    return sel, theta, fun


_EXCHANGE_TRIALS = 2  # swaps refitted per chosen term and round: its two likeliest proxies
_EXCHANGE_NFEV = 20  # evaluations of a trial swap's fit (the winner is refitted in full)


def _backward(prob, sel, theta, fun, nres, colour, npar, factor, max_nfev):
    """The forward selection's terms, each dropped while the same criterion prefers without.

    A greedy first term can be made redundant by a later one (a damping term
    taken before the spring that explains the data: alone it fits a little,
    beside the spring nothing). Each round ranks the removals by the residual
    sum of squares each is expected to add (:func:`_removal_order`), refits
    the law without the cheapest (then the next, at most ``_BACKWARD_TRIALS``)
    and drops the first whose removal the stopping rule of
    :func:`forward_select_oe` accepts (the BIC on n = nres / c, c the larger
    colour of the two residuals; with ``factor`` the likelihood ratio against
    ``factor`` times the penalty); then again, until none of them is accepted.
    Refitting every removal each round cost 24 s of the 35 s a 7-state thermal
    row took to close the loop (10 000 samples); the ranked trials 2.3 s, the
    same verdict.
    """
    bic = _bic(nres)
    rss = float(np.sum(np.asarray(fun) ** 2))
    while len(sel) >= 2:
        worst = None
        for q in _removal_order(prob, sel, theta, fun)[:_BACKWARD_TRIALS]:
            s2 = sel[:q] + sel[q + 1:]
            sol = prob.fit(s2, np.delete(theta, q), max_nfev=max_nfev, trial=True)
            r2 = float(np.sum(sol.fun ** 2))
            n = nres if colour is None else nres / max(colour(fun), colour(sol.fun))
            if factor == 1.0:
                ok = bic(r2, npar(s2), n) <= bic(rss, npar(sel), n)
            else:
                lr = n * np.log(max(r2 / nres, 1e-300)) - n * np.log(max(rss / nres, 1e-300))
                ok = not lr > factor * (npar(sel) - npar(s2)) * np.log(n)
            if ok:
                worst = (r2, s2, sol.x, sol.fun)
                break
        if worst is None:
            break
        rss, sel, theta, fun = worst
    return sel, theta


_BACKWARD_TRIALS = 3  # removals refitted per round, in the order their quadratic cost ranks


def _removal_order(prob, sel, theta, fun) -> list[int]:
    """The terms of ``sel`` ordered by the residual sum of squares their removal is
    expected to add: ``theta_q^2 / [(J^T J)^-1]_qq`` (the Gauss-Newton quadratic model
    at the fit, J by forward differences: len(sel) + 1 simulations, where refitting
    every removal costs len(sel) fits of tens). Cheapest first; an undetermined
    coefficient (a singular J^T J) costs nothing to drop."""
    theta = np.asarray(theta, dtype=float)
    k = theta.size
    if hasattr(prob, "jacobian"):  # the problem's own (a batched simulation)
        J = np.asarray(prob.jacobian(theta, sel), dtype=float)
    else:
        f0 = np.asarray(fun, dtype=float).ravel()
        J = np.empty((f0.size, k))
        floor = 1e-3 * float(np.max(np.abs(theta), initial=0.0)) + 1e-12
        for q in range(k):
            h = 1e-6 * max(abs(theta[q]), floor)
            t = theta.copy()
            t[q] += h
            J[:, q] = (np.asarray(prob.resid(t, sel), dtype=float).ravel() - f0) / h
    if J.shape != (J.shape[0], k) or not np.all(np.isfinite(J)):
        return list(range(k))
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.diag(np.linalg.pinv(J.T @ J))
        cost = np.where(d > 0, theta ** 2 / d, 0.0)
    return [int(q) for q in np.argsort(cost, kind="stable")]


def lowest_start(resid, starts):
    """The start of ``starts`` (parameter vectors) whose residual ``resid(theta)`` has the
    lowest finite sum of squares, or None when none is finite."""
    best = None
    for theta in starts:
        rss = float(np.sum(resid(theta) ** 2))
        if np.isfinite(rss) and (best is None or rss < best[0]):
            best = (rss, theta)
    return None if best is None else best[1]
