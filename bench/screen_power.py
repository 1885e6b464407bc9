"""How strongly the equation screen sees the missing spring of a chain, per size (issue 29).

``python bench/screen_power.py [nsteps] [n_masses ...]`` (default 20000 and 16 32 64):
the chain of ``bench/workflow.py chains`` (n_masses masses, the spring between the two
middle ones missing from the model, all positions and velocities measured, and positions
only), screened by :func:`greybox.trace.screen.screen_equations`. One row per case: the
z-scores of the two equations the spring enters, the best other equation's, and the
threshold the pass uses (``EquationScreen.ranked``'s 5). Where the targets fall below
the threshold the pass traces nothing (the 64-mass, positions-only row of
``bench/workflow.py chains``: "nothing traced").

Beside the screen's dense statistic (all n + m + 1 regressors, ``(N_b R^2 - k) /
sqrt(2 k)``), the table measures a sparse alternative that is not in the library: the
best s <= 3 regressors of each equation chosen greedily on the same block means, their
LM statistic's chi-square tail on s degrees of freedom times the number of s-subsets
C(k, s) and the 3 sizes tried (Bonferroni: conservative for a greedy choice), as the
normal quantile of that p-value (capped near 37 where the p-value underflows). The
"right model" rows are the same chains with the spring in the model: the null.
"""

import sys
import time
from pathlib import Path

import numpy as np
from scipy import stats
from scipy.special import gammaln

sys.path.insert(0, str(Path(__file__).resolve().parent))

from workflow import chain_data  # noqa: E402  (bench/workflow.py: the same chain cases)

import greybox.trace.screen as screen  # noqa: E402

SPARSE_MAX = 3


def _rss(X, d):
    """Residual sum of squares of the least-squares fit of d on the columns of X."""
    return float(np.sum((d - X @ np.linalg.lstsq(X, d, rcond=None)[0]) ** 2))


def sparse_z(W, D, smax=SPARSE_MAX):
    """Per column of D (N_b, neq): the sparse statistic's z on the regressors W (N_b, k)."""
    nb, k = W.shape
    out = []
    for d in D.T:
        tss, sel, logp = d @ d, [], 0.0
        for s in range(1, smax + 1):  # greedy: the regressor that lowers the RSS most
            rss, j = min((_rss(W[:, sel + [j]], d), j) for j in range(k) if j not in sel)
            sel.append(j)
            log_subsets = gammaln(k + 1) - gammaln(s + 1) - gammaln(k - s + 1)
            logp = min(logp, stats.chi2.logsf(nb * (1 - rss / tss), s) + log_subsets
                       + np.log(smax))
        out.append(stats.norm.isf(np.exp(max(logp, -700.0))))
    return np.array(out)


def _screen(nom, d):
    """The screen and the block means it regressed (captured from its one lstsq call)."""
    seen, lstsq = {}, np.linalg.lstsq

    def spy(a, b, rcond=None):
        seen["W"], seen["D"] = a, b
        return lstsq(a, b, rcond=rcond)
    np.linalg.lstsq = spy
    try:
        s = screen.screen_equations(nom, d.y, d.u, Q=d.Q, R=d.R, dt=d.dt)
    finally:
        np.linalg.lstsq = lstsq
    return s, seen


def row(n_masses: int, measured: str, N: int, right_model: bool = False) -> str:
    nom, d, i, meas = chain_data(n_masses, measured, N)
    if right_model:  # the same record, the spring in the model
        from plantlib import chain  # on the path chain_data put it on
        nom = chain(n_masses, k=20.0, measured=meas)
    t = time.perf_counter()
    s, seen = _screen(nom, d)
    el = time.perf_counter() - t
    case = f"| {2 * n_masses} | {measured} | {'right' if right_model else 'spring missing'} "
    if not s.available:
        return case + f"| unavailable: {s.reason} | | | | | {el:.1f} |"
    zs = sparse_z(seen["W"], seen["D"])
    tg = [] if right_model else [s.states.index(f"v{i + 1}"), s.states.index(f"v{i + 2}")]
    oth = [j for j in range(len(s.states)) if j not in tg]
    z = ", ".join(f"{s.states[j]} {s.score[j]:.3g}" for j in tg) or "-"
    zsp = ", ".join(f"{s.states[j]} {zs[j]:.3g}" for j in tg) or "-"
    return (case + f"| {z} | {max(s.score[oth]):.3g} | {zsp} | {max(zs[oth]):.3g} | 5 | "
            f"{el:.1f} |")


def main(argv):
    N = int(argv[0]) if argv else 20000
    sizes = [int(a) for a in argv[1:]] or [16, 32, 64]
    print(f"N = {N:.0e} estimation samples")
    print("| states | measured | model | target equations' z | best other z | sparse z of "
          "the targets | best other sparse z | threshold | time [s] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for nm in sizes:
        for meas in ("all", "positions"):
            for right in (False, True):
                print(row(nm, meas, N, right), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
