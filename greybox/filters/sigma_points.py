"""Sigma-point strategies of the unscented transform (Julier & Uhlmann; van der Merwe).

A strategy is a small frozen object: the unscented filters take it as a
parameter (``points=``), as filterpy's ``UnscentedKalmanFilter`` does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.lapack import dpotrf as _dpotrf

from .._validation import check_positive
from ..exceptions import CovarianceError, DimensionError

__all__ = ["MerweScaledSigmaPoints", "robust_cholesky"]


def robust_cholesky(P: NDArray, name: str = "P", *, max_tries: int = 8) -> NDArray[np.float64]:
    """Lower Cholesky factor of a covariance that rounding may have made indefinite.

    Symmetrize, try Cholesky; on failure add a jitter ``eps * 10^j * mean(diag P)``
    to the diagonal (j = 0, 1, ...) until it succeeds. The jitter is far below
    any physical variance (it starts at 2.2e-16 of the mean variance); a matrix
    that needs more than ``10^(max_tries-1)`` times that is truly indefinite
    and raises.

    Parameters
    ----------
    P : ndarray, shape (n, n)
        Covariance.
    name : str
        Name used in the error message.
    max_tries : int
        Number of jitter levels tried.

    Returns
    -------
    ndarray, shape (n, n)
        Lower-triangular S with ``S S^T = P + jitter I``.

    Raises
    ------
    CovarianceError
        If P is not positive semidefinite up to rounding.
    """
    P = 0.5 * (P + P.T)
    S, info = _dpotrf(P, lower=1, clean=1)  # LAPACK directly: numpy's wrapper costs ~5 us
    if info == 0:
        return S
    scale = float(np.mean(np.abs(np.diag(P)))) or 1.0
    for j in range(max_tries):
        try:
            return np.linalg.cholesky(P + (np.finfo(float).eps * 10.0**j * scale)
                                      * np.eye(P.shape[0]))
        except np.linalg.LinAlgError:
            continue
    w = np.linalg.eigvalsh(P)
    raise CovarianceError(
        f"{name} is not positive semidefinite (smallest eigenvalue {w.min():.3g}, largest "
        f"{w.max():.3g}); the filter lost positive definiteness. Increase Q or check that "
        f"the model is finite and smooth near the estimate")


@dataclass(frozen=True)
class MerweScaledSigmaPoints:
    """Van der Merwe's scaled sigma points: 2n + 1 points, spread ``alpha``.

    Parameters
    ----------
    alpha : float
        Spread of the points around the mean, in (0, 1]. The default 1.0 puts
        the points at ``sqrt(n + kappa)`` standard deviations with
        non-negative weights (well conditioned); small values (1e-3, the
        textbook choice) give a large negative centre weight.
    beta : float
        Prior knowledge of the distribution (2 is optimal for a Gaussian).
    kappa : float
        Secondary scaling; 0 by default (``3 - n`` is Julier's choice).

    Notes
    -----
    With ``lambda = alpha^2 (n + kappa) - n`` the points are
    ``x``, ``x + sqrt(n + lambda) S[:, i]``, ``x - sqrt(n + lambda) S[:, i]``
    with S the lower Cholesky factor of P (see :func:`robust_cholesky`), and

    .. math::

        W^m_0 = \\frac{\\lambda}{n+\\lambda},\\quad
        W^c_0 = W^m_0 + 1 - \\alpha^2 + \\beta,\\quad
        W^m_i = W^c_i = \\frac{1}{2(n+\\lambda)}.

    The unscented transform is exact for linear maps whatever the spread.

    References
    ----------
    R. van der Merwe, "Sigma-point Kalman filters for probabilistic inference
    in dynamic state-space models", PhD thesis, OGI, 2004, eqs. (3.107)-(3.109).

    Examples
    --------
    >>> import numpy as np
    >>> pts = MerweScaledSigmaPoints(alpha=1.0)
    >>> X = pts.points(np.zeros(2), np.eye(2))
    >>> X.shape
    (2, 5)
    >>> wm, wc = pts.weights(2)
    >>> float(wm.sum())
    1.0
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0

    def __post_init__(self):
        check_positive(self.alpha, "alpha")
        if self.alpha > 1:
            raise DimensionError(f"alpha must be in (0, 1]; found {self.alpha}")
        try:
            float(self.beta), float(self.kappa)
        except (TypeError, ValueError) as e:
            raise DimensionError(f"beta and kappa must be numbers; found {self.beta!r}, "
                                 f"{self.kappa!r}") from e

    def lam(self, n: int) -> float:
        """``lambda = alpha^2 (n + kappa) - n``."""
        lam = self.alpha**2 * (n + self.kappa) - n
        if n + lam <= 0:
            raise DimensionError(f"n + lambda = {n + lam:g} <= 0 for n = {n}; increase "
                                 f"alpha or kappa")
        return lam

    def num_points(self, n: int) -> int:
        """Number of points, 2n + 1."""
        return 2 * n + 1

    def weights(self, n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Mean and covariance weights, each shape (2n + 1,)."""
        lam = self.lam(n)
        wm = np.full(2 * n + 1, 0.5 / (n + lam))
        wc = wm.copy()
        wm[0] = lam / (n + lam)
        wc[0] = wm[0] + 1 - self.alpha**2 + self.beta
        return wm, wc

    def offsets(self, n: int) -> NDArray[np.float64]:
        """Offsets of the points in units of the Cholesky factor, shape (n, 2n + 1).

        ``points(x, P) == x[:, None] + robust_cholesky(P) @ offsets(n)``:
        the columns are 0, ``sqrt(n + lambda) e_i`` and ``-sqrt(n + lambda) e_i``
        (products with exact zeros and +-1 multiples, so the two forms agree to
        the last bit). The filters precompute it once per run.
        """
        c = np.sqrt(n + self.lam(n))
        E = np.zeros((n, 2 * n + 1))
        E[:, 1:n + 1] = c * np.eye(n)
        E[:, n + 1:] = -c * np.eye(n)
        return E

    def points(self, x: NDArray, P: NDArray) -> NDArray[np.float64]:
        """Sigma points of (x, P), shape (n, 2n + 1) (column 0 is the mean)."""
        n = x.shape[0]
        S = robust_cholesky(P) * np.sqrt(n + self.lam(n))
        return np.concatenate((x[:, None], x[:, None] + S, x[:, None] - S), axis=1)
