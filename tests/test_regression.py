"""Static least squares and sparse forward selection (greybox.ident.regression).

Oracles: known coefficients with their least-squares standard errors
(``sigma^2 (W W^T)^-1``), numpy's unscaled ``lstsq``, and hand-built
selection paths (a proxy term that only backward pruning removes).
"""

from __future__ import annotations

import numpy as np
import pytest

import greybox as gb
from greybox.ident.regression import (SparseLaw, forward_selection, forward_selection_gram,
                                      static_least_squares)


@pytest.fixture
def rng():
    return np.random.default_rng(20240611)


def _ls_stderr(W: np.ndarray, sigma: float) -> np.ndarray:
    """Standard errors of least-squares coefficients for regressors W (nin, N)."""
    return sigma * np.sqrt(np.diag(np.linalg.inv(W @ W.T)))


# --------------------------------------------------------------------------- static LS
def test_static_least_squares_scaled_collinear_regressors(rng):
    N, sigma = 4000, 0.02
    a, b, c = rng.standard_normal((3, N))
    # regressors 1e3 and 1e-3 in scale, w1 and w2 correlated at ~0.995
    W = np.vstack([1e3 * a, 1e-3 * (a + 0.1 * b), c])
    coef = np.array([[2e-3, 500.0, -1.0], [0.0, -300.0, 0.5]])
    d = coef @ W + sigma * rng.standard_normal((2, N))
    fit = static_least_squares(W, d)
    assert fit.rank == 3
    se = _ls_stderr(W, sigma)
    # each coefficient within 4 of its standard errors (|z| > 4 has p ~ 6e-5)
    np.testing.assert_allclose((fit.coef - coef) / se[None, :], 0.0, atol=4.0)
    # residual covariance: sample variance of 4000 N(0, sigma^2) draws, relative
    # standard error sqrt(2/N) = 2.2 %; 10 % is > 4 of those
    np.testing.assert_allclose(np.diag(fit.residual_cov), sigma**2, rtol=0.1)
    np.testing.assert_allclose(fit.residuals, d - fit.coef @ W, rtol=0, atol=1e-12)
    # independent oracle: numpy's unscaled least squares on the same data; both are
    # exact LS solutions of a problem with cond ~ 1e7, so agree to ~1e-9 relative
    ref = np.linalg.lstsq(W.T, d.T, rcond=None)[0].T
    np.testing.assert_allclose(fit.coef, ref, rtol=1e-7, atol=1e-9 * np.abs(ref).max())


def test_static_least_squares_exact_collinearity_gives_min_norm(rng):
    N = 500
    a, b = rng.standard_normal((2, N))
    W = np.vstack([a, 2.0 * a, b])          # w2 = 2 w1: rank 2
    d = (3.0 * a + b)[None, :]
    fit = static_least_squares(W, d)
    assert fit.rank == 2
    # minimum-norm split of 3 a over (a, 2a) in the unit-RMS scaled coordinates,
    # where the two columns are equal: equal scaled coefficients, i.e. c1 = 2 c2,
    # c1 * 1 + c2 * 2 = 3 -> (1.5, 0.75); exact data, so only round-off (1e-10)
    np.testing.assert_allclose(fit.coef, [[1.5, 0.75, 1.0]], atol=1e-10)


def test_static_least_squares_errors(rng):
    w = rng.standard_normal((3, 100))
    with pytest.raises(gb.DataError, match="samples cannot fit 3 coefficients"):
        static_least_squares(w[:, :3], w[:1, :3])
    with pytest.raises(gb.DimensionError, match="different numbers of samples"):
        static_least_squares(w, w[:1, :99])
    bad = w.copy()
    bad[1, 5] = np.nan
    with pytest.raises(gb.DataError, match="NaN"):
        static_least_squares(bad, w[:1])


# --------------------------------------------------------------------------- selection
def _candidates(rng, N):
    """20 named candidate terms of 5 smooth signals: x, x^3, tanh(x/eps), |x|."""
    t = np.arange(N)
    X = np.array([np.convolve(rng.standard_normal(N + 49), np.ones(50) / np.sqrt(50),
                              "valid") for _ in range(5)])
    X[2] += 0.5 * X[0]                       # some correlation between candidates
    X *= np.array([[1.0], [0.5], [2.0], [1.0], [0.3]])
    X[3] += 0.2 * np.sin(2 * np.pi * t / 400)
    eps = 0.05 * np.sqrt(np.mean(X**2, axis=1))
    rows, names = [], []
    for i in range(5):
        rows += [X[i], X[i] ** 3, np.tanh(X[i] / eps[i]), np.abs(X[i])]
        names += [f"x{i}", f"x{i}^3", f"sign(x{i})", f"|x{i}|"]
    return np.array(rows), names


def test_forward_selection_finds_true_sparse_support(rng):
    N, sigma = 5000, 0.05
    T, names = _candidates(rng, N)
    true = {"x1": 1.5, "x0^3": -0.8, "sign(x3)": 0.3}
    idx = [names.index(k) for k in true]
    c_true = np.array(list(true.values()))
    d = c_true @ T[idx] + sigma * rng.standard_normal(N)
    law = forward_selection(T, d, names)
    assert isinstance(law, SparseLaw)
    assert set(law.names) == set(true)
    assert law.pruned == ()
    order = [law.names.index(k) for k in true]
    se = _ls_stderr(T[idx], sigma)
    # each coefficient within 4 standard errors of its least-squares estimate
    np.testing.assert_allclose((law.coef[order] - c_true) / se, 0.0, atol=4.0)
    # oracle: the Gram-matrix solve equals lstsq on the selected support
    # (well-conditioned 3-column problem: agreement to ~1e-12, 1e-8 leaves margin)
    ref = static_least_squares(T[list(law.index)], d).coef[0]
    np.testing.assert_allclose(law.coef, ref, rtol=1e-8)
    # residual variance = sigma^2 within 10 % (> 4 relative standard errors sqrt(2/N))
    np.testing.assert_allclose(law.residual_var, sigma**2, rtol=0.1)
    assert law.bic_path.shape == (4,)
    assert np.all(np.diff(law.bic_path) < 0)
    assert law.bic_gain == pytest.approx(law.bic_path[0] - law.bic_path[-1])


def test_forward_selection_adds_nothing_on_pure_noise(rng):
    N = 5000
    T, names = _candidates(rng, N)
    d = 0.1 * rng.standard_normal(N)
    law = forward_selection(T, d, names)
    assert law.names == () and law.index == ()
    assert law.coef.shape == (0,)
    assert law.bic_path.shape == (1,)
    # no term: the residual is d itself (exact)
    np.testing.assert_allclose(law.residual_var, np.mean(d**2), rtol=1e-12)


def test_forward_selection_stops_at_an_exact_fit(rng):
    # noise-free data: once the true terms are in, the RSS is round-off; the
    # rounding floor must stop the selection there instead of chasing it
    N = 2000
    T, names = _candidates(rng, N)
    d = 2.0 * T[names.index("x2")] - 0.1 * T[names.index("|x4|")]
    law = forward_selection(T, d, names)
    assert set(law.names) == {"x2", "|x4|"}
    # exact data: coefficients to round-off of the normal equations (cond ~ 1e2)
    np.testing.assert_allclose(sorted(law.coef), [-0.1, 2.0], rtol=1e-8)


def test_forward_selection_backward_pruning_removes_a_proxy(rng):
    N = 3000
    a, b, c = rng.standard_normal((3, N))
    proxy = a + b + 0.3 * c                 # c is not a candidate
    T = np.vstack([proxy, a, b])
    names = ["proxy", "a", "b"]
    d = a + b + 0.01 * rng.standard_normal(N)
    greedy = forward_selection(T, d, names, min_drop=1e-4)
    # the proxy correlates best with d and enters first; a and b follow
    assert greedy.names[0] == "proxy" and set(greedy.names) == set(names)
    law = forward_selection(T, d, names, min_drop=1e-4, prune=True)
    assert law.names == ("a", "b") and law.pruned == ("proxy",)
    # noise 0.01 on 3000 samples: standard errors ~2e-4; 2e-3 is 10 of them
    np.testing.assert_allclose(law.coef, [1.0, 1.0], atol=2e-3)
    assert law.bic_path.shape == (3,)


def test_forward_selection_options_limit_the_law(rng):
    N = 2000
    T, names = _candidates(rng, N)
    d = T[names.index("x1")] + 0.5 * T[names.index("x3")] + 0.01 * rng.standard_normal(N)
    # plain BIC over 20 candidates admits a third, negligible term on this draw (the
    # best of 18 chi2(1) variables beats log N); requiring 0.1 % of sum(d^2) per term
    # keeps the two true ones
    assert len(forward_selection(T, d, names).names) == 3
    full = forward_selection(T, d, names, min_drop=1e-3)
    assert full.names == ("x1", "x3")
    assert forward_selection(T, d, names, max_terms=1).names == ("x1",)
    assert forward_selection(T, d, names, max_terms=0).names == ()
    # a BIC gain requirement above the whole gain admits nothing
    assert forward_selection(T, d, names, min_gain=full.bic_gain).names == ()
    # the second term removes ~ 0.25 / 1.25 of sum(d^2): min_drop 0.5 refuses it
    assert forward_selection(T, d, names, min_drop=0.5).names == ("x1",)


def test_forward_selection_never_selects_zero_or_duplicate_terms(rng):
    N = 1000
    a, b = rng.standard_normal((2, N))
    T = np.vstack([np.zeros(N), a, a, b])
    d = a + 0.5 * b + 0.01 * rng.standard_normal(N)
    law = forward_selection(T, d, ["zero", "a", "a_copy", "b"])
    assert "zero" not in law.names
    assert len({"a", "a_copy"} & set(law.names)) == 1 and "b" in law.names


def test_forward_selection_errors(rng):
    T = rng.standard_normal((3, 200))
    d = rng.standard_normal(200)
    names = ["a", "b", "c"]
    with pytest.raises(gb.DimensionError, match="names has 2 entries; expected nterms = 3"):
        forward_selection(T, d, names[:2])
    with pytest.raises(gb.DimensionError, match="different numbers of samples"):
        forward_selection(T, d[:150], names)
    with pytest.raises(gb.DimensionError, match="d has shape"):
        forward_selection(T, np.vstack([d, d]), names)
    bad = d.copy()
    bad[3] = np.inf
    with pytest.raises(gb.DataError, match="NaN or inf"):
        forward_selection(T, bad, names)
    with pytest.raises(gb.DataError, match="max_terms must be finite and >= 0"):
        forward_selection(T, d, names, max_terms=-1)
    with pytest.raises(gb.DimensionError, match="max_terms must be an integer"):
        forward_selection(T, d, names, max_terms=1.5)
    with pytest.raises(gb.DataError, match="min_gain must be finite and >= 0"):
        forward_selection(T, d, names, min_gain=-1.0)
    with pytest.raises(gb.DataError, match="min_drop must be below 1"):
        forward_selection(T, d, names, min_drop=1.0)


# --------------------------------------------------------------------------- from products
def test_forward_selection_gram_selects_as_forward_selection_on_the_terms(rng):
    """The products X X^T, X d, d^T d carry everything the selection needs: the same
    terms, coefficients and BIC path as on X (pruning included), and the normal
    equations' RSS as the residual variance."""
    N = 3000
    T, names = _candidates(rng, N)
    a, b, c = rng.standard_normal((3, N))
    T = np.vstack([T, a + b + 0.3 * c, a, b])  # with the pruning case's proxy
    names = names + ["proxy", "a", "b"]
    d = (T[names.index("x1")] - 0.5 * T[names.index("x3")] + a + b
         + 0.01 * rng.standard_normal(N))
    ref = forward_selection(T, d, names, min_drop=1e-4, prune=True)
    law = forward_selection_gram(T @ T.T, T @ d, float(d @ d), N, names, min_drop=1e-4,
                                 prune=True)
    assert law.names == ref.names and law.pruned == ref.pruned and "proxy" not in law.names
    # both solve the same normal equations: agreement to rounding (1e-10)
    np.testing.assert_allclose(law.coef, ref.coef, rtol=1e-10)
    np.testing.assert_allclose(law.bic_path, ref.bic_path, rtol=1e-10)
    np.testing.assert_allclose(law.residual_var, ref.residual_var, rtol=1e-6)


def test_forward_selection_gram_errors(rng):
    T = rng.standard_normal((3, 200))
    d = rng.standard_normal(200)
    G, b, names = T @ T.T, T @ d, ["a", "b", "c"]
    with pytest.raises(gb.DimensionError, match=r"gram has shape \(3, 2\)"):
        forward_selection_gram(G[:, :2], b, float(d @ d), 200, names)
    with pytest.raises(gb.DimensionError, match="cross has 2 entries; expected nterms = 3"):
        forward_selection_gram(G, b[:2], float(d @ d), 200, names)
    with pytest.raises(gb.DimensionError, match="names has 2 entries"):
        forward_selection_gram(G, b, float(d @ d), 200, names[:2])
    with pytest.raises(gb.DataError, match="must be finite"):
        forward_selection_gram(G, b, np.nan, 200, names)
    with pytest.raises(gb.DataError, match="nsteps"):
        forward_selection_gram(G, b, float(d @ d), 0, names)
