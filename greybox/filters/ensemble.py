"""Ensemble unknown-input filter (section IV: "an approach similar to the particle filter").

For strong or non-smooth nonlinearities (Coulomb friction, saturation) the
paper suggests propagating an ensemble instead of sigma points. Each step:

1. every member goes through F with the unknown input held at its previous
   estimate, plus a process-noise draw w ~ N(0, Q): the ensemble mean and
   sample covariance are x^[k|k-1] and P[k|k-1];
2. (8)-(10) with the linear C exactly as in :func:`greybox.uikf` give d^[k-1]
   (its correction ``M e``), K and the combined gain ``L = G M + K - K F M``;
3. the mean is updated deterministically, ``x^[k|k] = x^[k|k-1] + L e``, and
   the members with perturbed observations,
   ``x_i <- x_i + L (y + v_i - C x_i)`` with centred draws v_i ~ N(0, R),
   whose sample covariance is then ``(I - L C) P (I - L C)^T + L R L^T``,
   the unknown-input filter's P[k|k] (``(I - L C) G = 0``: the members carry
   no memory of d).

The record is the same :class:`FilterResult` as :func:`greybox.uikf`'s; its
``P_filt`` is the sample covariance of the final ensemble. The run is
reproducible: all draws come from ``rng``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validation import check_positive
from ..exceptions import DataError
from ..signals import as_generator
from .kernels import FilterResult, _check_options, _measurement_gains, check_rank_condition
from .ukf import _check_d, _initial_G, _linearized_record_sys, _prepare_nl, _propagate

__all__ = ["ensemble_uikf"]


def _draws(S, shape, g):
    """Zero-mean Gaussian draws with covariance S (PSD), shape (n, nmembers)."""
    w, V = np.linalg.eigh(S)
    return (V * np.sqrt(np.clip(w, 0, None))) @ g.standard_normal(shape)


def ensemble_uikf(sys, y: ArrayLike, u: ArrayLike | None = None, *,
                  unknown: int | str | Sequence[int | str], Q: ArrayLike, R: ArrayLike,
                  x0: ArrayLike | None = None, P0: ArrayLike | None = None,
                  G: ArrayLike | None = None, nmembers: int = 100, rng=None,
                  level: float = 0.95, store_covariances: bool = False) -> FilterResult:
    """Ensemble (Monte Carlo) unknown-input filter for non-smooth nonlinear models.

    Parameters
    ----------
    sys : control.NonlinearIOSystem or control.StateSpace
        Discrete-time model with inputs ``[u, d]`` and a linear output map.
    y : array_like, shape (noutputs, nsteps)
        Measured outputs.
    u : array_like, shape (ninputs_known, nsteps), optional
        Measured known inputs.
    unknown : label(s) or index(es)
        Which inputs of ``sys`` are unknown (md >= 1).
    Q : array_like, shape (nstates, nstates)
        Process-noise covariance (PSD).
    R : array_like, shape (noutputs, noutputs)
        Measurement-noise covariance (PD).
    x0 : array_like, shape (nstates,), optional
        Prior mean (zero by default).
    P0 : array_like, shape (nstates, nstates), optional
        Prior covariance (identity by default).
    G : array_like, shape (nstates, md), optional
        Constant unknown-input matrix; by default the Jacobian dF/dd of the
        discrete model at the ensemble mean, at every step.
    nmembers : int
        Ensemble size (>= 2; 100 by default). The Monte Carlo error of the
        covariance falls as ``1/sqrt(nmembers)``.
    rng : numpy.random.Generator or int, optional
        Source of the ensemble draws (seed it for a reproducible run).
    level : float
        Confidence level of ``d_lower``/``d_upper``.
    store_covariances : bool
        Keep every ``P[k|k]`` (the formula's, from the ensemble's ``P[k|k-1]``).

    Returns
    -------
    FilterResult
        Same record and alignment as :func:`greybox.uikf`.

    Raises
    ------
    ModelError
        As :func:`greybox.ui_ukf` (f failing or non-finite names the state and step).
    RankConditionError
        rank(C G) = md (17) fails at the prior.
    DataError, DimensionError, CovarianceError
        Bad data, shapes or covariances; non-finite d estimate.

    Examples
    --------
    >>> import numpy as np, greybox as gb
    >>> sys = gb.tape_drive_nominal(dt=1e-4)
    >>> sim = gb.simulate(gb.tape_drive_true(dt=1e-4), np.ones((2, 100)), rng=0)
    >>> res = gb.ensemble_uikf(sys, sim.y, sim.u, unknown="T", Q=gb.TAPE_DRIVE_Q,
    ...                        R=gb.TAPE_DRIVE_R, nmembers=50, rng=1)
    >>> res.d_est.shape
    (1, 100)
    """
    level, _, _ = _check_options(level, "auto", 1.0)
    ne = _check_members(nmembers)
    g = as_generator(rng)
    pb = _prepare_nl(sys, y, u, unknown, Q, R, x0, P0, G, allow_no_unknown=False,
                     check_rank=True)
    Gk = _initial_G(pb)
    check_rank_condition(pb.C, Gk, pb.labels)
    n, N = pb.x0.size, pb.y.shape[1]
    C, D, Rm, yv, uv = pb.C, pb.D, pb.R, pb.y, pb.u
    p, m, md = C.shape[0], uv.shape[0], len(pb.unknown)
    has_D = m > 0 and bool(np.any(D))
    rec = _Record.empty(n, p, md, N, store_covariances)
    jac = pb.G is None
    scale = 1.0 / (ne - 1)
    centred = functools.partial(_centred_draws, ne=ne, g=g)
    # k = 0: members from the prior, perturbed-observation update
    yk = yv[:, 0] - D @ uv[:, 0] if has_D else yv[:, 0]
    s0 = _ensemble_prior(pb, yk, centred)
    E, A, xf, K, Rt, Pf = s0.E, s0.A, s0.xf, s0.K, s0.Rt, s0.Pf
    rec.store(0, pb.x0, s0.e, xf, Pf)
    M, Pd, Pp = np.zeros((md, p)), np.zeros((md, md)), pb.P0
    dlin = np.zeros(md)
    for k in range(1, N):
        fc = _forecast(pb, k, E, uv[:, k - 1], dlin, xf, jac, centred, scale)
        if fc.G is not None:
            Gk = fc.G
        xp, A, Pp = fc.xp, fc.A, fc.Pp
        K, M, Pd, Rt, Pf = _measurement_gains(Pp, C, Gk, Rm)
        F = C @ Gk
        L = Gk @ M + K - K @ F @ M
        yk = yv[:, k] - D @ uv[:, k] if has_D else yv[:, k]
        e = yk - C @ xp
        with np.errstate(over="ignore", invalid="ignore"):
            dd = M @ e
            dh = dlin + dd
        _check_d(dh, k, pb.labels)
        rec.d_est[:, k - 1] = dh
        rec.d_var[:, k - 1] = Pd.diagonal()
        xf = xp + L @ e
        A = A + L @ (centred(Rm) - C @ A)
        E = xf[:, None] + A
        x0pred = xp - Gk @ dlin
        rec.store(k, x0pred, yk - C @ x0pred, xf, Pf)
        dlin = dh
    Pens = scale * (A @ A.T)
    return FilterResult(
        t=np.arange(N) * pb.dt, x_filt=rec.x_filt, x_pred=rec.x_pred, d_est=rec.d_est,
        d_var=rec.d_var, d_cov=Pd, level=level, innovations=rec.innov, innovation_cov=Rt,
        P_filt=0.5 * (Pens + Pens.T), P_pred=Pp, P_filt_history=rec.Phist, K=K, M=M,
        converged=False, period_converged=None, sys=_linearized_record_sys(pb, xf), G=Gk,
        unknown_labels=tuple(pb.labels), u=uv, y=yv)


def _check_members(nmembers) -> int:
    """The ensemble size, an integer >= 2 (DataError otherwise)."""
    ne = check_positive(nmembers, "nmembers", integer=True)
    if ne < 2:
        raise DataError(f"nmembers must be at least 2 (a sample covariance needs two "
                        f"members); found {ne}")
    return ne


def _centred_draws(S, *, ne: int, g):
    """``ne`` draws of covariance S with their sample mean removed, shape (n, ne)."""
    V = _draws(S, (S.shape[0], ne), g)
    return V - V.mean(axis=1, keepdims=True)


@dataclass(frozen=True)
class _Record:
    """The per-step outputs of :func:`ensemble_uikf` (arrays filled in place)."""

    x_filt: NDArray[np.float64]
    x_pred: NDArray[np.float64]
    innov: NDArray[np.float64]
    d_est: NDArray[np.float64]
    d_var: NDArray[np.float64]
    Phist: NDArray[np.float64] | None

    @classmethod
    def empty(cls, n: int, p: int, md: int, N: int, store_covariances: bool) -> _Record:
        """Buffers for N steps (d^ NaN until estimated; P[k|k] kept if asked)."""
        return cls(x_filt=np.empty((n, N)), x_pred=np.empty((n, N)), innov=np.empty((p, N)),
                   d_est=np.full((md, N), np.nan), d_var=np.full((md, N), np.nan),
                   Phist=np.empty((n, n, N)) if store_covariances else None)

    def store(self, k: int, x_pred, innov, x_filt, Pf) -> None:
        """Step k's predicted state (without d), innovation, filtered state and P[k|k]."""
        self.x_pred[:, k] = x_pred
        self.innov[:, k] = innov
        self.x_filt[:, k] = x_filt
        if self.Phist is not None:
            self.Phist[:, :, k] = Pf


@dataclass(frozen=True)
class _Prior:
    """The k = 0 update of :func:`ensemble_uikf`: members ``E = xf + A``, gains, innovation."""

    E: NDArray[np.float64]
    A: NDArray[np.float64]
    xf: NDArray[np.float64]
    e: NDArray[np.float64]
    K: NDArray[np.float64]
    Rt: NDArray[np.float64]
    Pf: NDArray[np.float64]


def _ensemble_prior(pb, yk, centred) -> _Prior:
    """Members drawn from the prior, then the perturbed-observation update with y[0]."""
    n, C, Rm = pb.x0.size, pb.C, pb.R
    E = pb.x0[:, None] + centred(pb.P0)
    K, _, _, Rt, Pf = _measurement_gains(pb.P0, C, np.zeros((n, 0)), Rm)
    e = yk - C @ pb.x0
    xf = pb.x0 + K @ e
    A = E - pb.x0[:, None]
    A = A + K @ (centred(Rm) - C @ A)
    return _Prior(E=xf[:, None] + A, A=A, xf=xf, e=e, K=K, Rt=Rt, Pf=Pf)


@dataclass(frozen=True)
class _Forecast:
    """The members propagated to step k with process noise: dF/dd (None unless
    linearized), mean, deviations ``A`` and sample covariance ``Pp``."""

    G: NDArray[np.float64] | None
    xp: NDArray[np.float64]
    A: NDArray[np.float64]
    Pp: NDArray[np.float64]


def _forecast(pb, k: int, E, uk, dlin, xf, jac: bool, centred, scale: float) -> _Forecast:
    """Every member through F with d at ``dlin``, plus a process-noise draw."""
    FE, Gn = _propagate(pb, k, E, uk, dlin, xf, jac)
    FE = FE + centred(pb.Q)
    xp = FE.mean(axis=1)
    A = FE - xp[:, None]
    Pp = scale * (A @ A.T)
    return _Forecast(G=Gn, xp=xp, A=A, Pp=0.5 * (Pp + Pp.T))
