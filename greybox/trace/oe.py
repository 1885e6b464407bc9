"""Output-error refinement and selection of linear static laws on the measured outputs."""

from __future__ import annotations

from dataclasses import replace

import control as ct
import numpy as np
from numpy.typing import NDArray

from .._lti import lti_states
from .laws import StaticLaw, _law_line, _one_direction

# Output-error refinements of static laws run on at most this many samples
# (their cost is then independent of the record length).
_OE_WINDOW = 10_000


class _OutputErrorLaw:
    """Simulation error on y of the model augmented with a linear static law.

    The law's selected terms ``sel`` (pairs (component of d, term index))
    with coefficients ``theta`` are folded into A and B; the residual is the
    output error over at most ``_OE_WINDOW`` samples after ``k0``, scaled per
    output by its RMS (PAPER_NOTES §9.3: output-error fits are unbiased on a
    noisy d^).
    """

    def __init__(self, law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray,
                 u: NDArray, x0: NDArray, k0: int):
        self.law, self.md, self.k0, self.x0 = law, md, k0, x0
        self.y, self.u = y[:, :k0 + _OE_WINDOW], u[:, :k0 + _OE_WINDOW]
        m = model.ninputs - md
        Bf = np.asarray(model.B, dtype=float)
        self.A = np.asarray(model.A, dtype=float)
        self.B, self.G = Bf[:, :m], Bf[:, m:]
        self.C = np.asarray(model.C, dtype=float)
        self.D = np.asarray(model.D, dtype=float)[:, :m]
        self.scale = np.sqrt(np.mean(self.y[:, k0:] ** 2, axis=1)) + 1e-300

    def matrices(self, sel, theta):
        """(A + G Ddx, B + G Ddu, Ddx, Ddu) for the terms ``sel`` at ``theta``."""
        Ddx = np.zeros((self.md, self.A.shape[0]))
        Ddu = np.zeros((self.md, self.B.shape[1]))
        for (c, j), t in zip(sel, theta):
            _, kind, i = self.law.spec[j]
            (Ddx if kind == "x" else Ddu)[c, i] = t
        return self.A + self.G @ Ddx, self.B + self.G @ Ddu, Ddx, Ddu

    def resid(self, theta, sel):
        """Scaled output error, flattened; a diverged simulation counts as 1e6."""
        Aa, Ba, _, _ = self.matrices(sel, theta)
        with np.errstate(all="ignore"):
            x = lti_states(Aa, Ba @ self.u, self.x0)
            r = ((self.y - self.C @ x - self.D @ self.u)[:, self.k0:]
                 / self.scale[:, None]).ravel()
        return np.clip(np.where(np.isfinite(r), r, 1e6), -1e6, 1e6)

    def se(self, theta, sel) -> float:
        """Simulation error of eq. (42) [%] on the window."""
        r = self.resid(theta, sel).reshape(self.y.shape[0], -1)
        return float(100 * np.mean(np.sqrt(np.mean(r**2, axis=1))))  # |r| <= 1e6

    def fit(self, sel, start, max_nfev=60):
        """Levenberg-Marquardt from ``start``; returns the optimizer result."""
        from scipy.optimize import least_squares

        return least_squares(self.resid, start, args=(sel,), method="lm", x_scale="jac",
                             max_nfev=max_nfev)

    def law_with(self, sel, theta, labels, units, tscale=None, **changes) -> StaticLaw:
        """The law with the terms ``sel`` at ``theta`` (all others zero)."""
        law = self.law
        _, _, Ddx, Ddu = self.matrices(sel, theta)
        coef = np.zeros_like(law.coef)
        for (c, j), t in zip(sel, theta):
            coef[c, j] = t
        lines = []
        for c in range(self.md):
            idx = [j for (cc, j) in sel if cc == c]
            lines.append(_law_line(labels[c], coef[c, idx], [law.spec[j][0] for j in idx],
                                   units[c] if c < len(units) else ""))
        if tscale is not None:
            lines += _one_direction(coef, tscale, labels)
        return replace(law, coef=coef, Ddx=Ddx, Ddu=Ddu, formula="; ".join(lines), **changes)


def _refine_static_oe(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray,
                      u: NDArray, x0: NDArray, k0: int, labels, units, tscale=None):
    """Refine a linear static law by output error on y (PAPER_NOTES §9.3).

    The law's coefficients fitted on d^ are consistent but, when C G is small
    (e.g. only positions measured), d^ is so noisy that the law can make the
    augmented model unstable. Here the selected coefficients are re-fitted to
    minimize the simulation error of the augmented model on the outputs,
    starting from the d^ fit (shrunk towards zero until the model is stable).
    Returns ``(law, se_before, se_after)``; the law is unchanged when the
    refinement does not lower the simulation error.
    """
    sel = [(c, j) for c in range(md) for j in range(len(law.spec)) if law.coef[c, j] != 0]
    if not sel:
        return law, np.nan, np.nan
    prob = _OutputErrorLaw(law, model, md, y, u, x0, k0)
    theta0 = np.array([law.coef[c, j] for c, j in sel])
    se0 = prob.se(theta0, sel)
    start = theta0.copy()
    for _ in range(30):  # shrink towards the (stable) nominal model
        if np.max(np.abs(np.linalg.eigvals(prob.matrices(sel, start)[0]))) <= 1 + 1e-9:
            break
        start *= 0.5
    sol = prob.fit(sel, start)
    se1 = prob.se(sol.x, sel)
    if not se1 < se0:
        return law, se0, se0
    return prob.law_with(sel, sol.x, labels, units, tscale), se0, se1


def _select_static_oe(law: StaticLaw, model: ct.StateSpace, md: int, y: NDArray,
                      u: NDArray, x0: NDArray, k0: int, labels, units, max_terms: int = 4):
    """Choose a linear static law by output error on y (forward selection, BIC).

    Used when d^ is mostly estimation noise (its variance barely exceeds the
    filter's Pd, e.g. when only positions are measured and C G ~ dt^2/2):
    regressions on d^ then select terms at random. Each candidate support is
    fitted by Levenberg-Marquardt on the simulation error of the augmented
    model; terms are added while the BIC of the output error drops.
    """
    prob = _OutputErrorLaw(law, model, md, y, u, x0, k0)
    lin = [j for j, (_, kind, _) in enumerate(law.spec) if kind in ("x", "u")]
    cands = [(c, j) for c in range(md) for j in lin]
    Ny = prob.y[:, k0:].size

    def bic(rss, k):
        return Ny * np.log(max(rss / Ny, 1e-300)) + k * np.log(Ny)

    sel, theta = [], np.zeros(0)
    best_bic = bic(float(np.sum(prob.resid(theta, sel) ** 2)), 0)
    while len(sel) < max_terms:
        trial = None
        for cj in cands:
            if cj in sel:
                continue
            sol = prob.fit(sel + [cj], np.r_[theta, 0.0], max_nfev=100)
            b = bic(float(np.sum(sol.fun ** 2)), len(sel) + 1)
            if trial is None or b < trial[0]:
                trial = (b, cj, sol.x)
        if trial is None or trial[0] >= best_bic:
            break
        best_bic, sel, theta = trial[0], sel + [trial[1]], trial[2]
    return prob.law_with(sel, theta, labels, units, nonlinear=False, npar=len(sel))


# --------------------------------------------------------------------------- one channel
