"""Tests of greybox.ident.n4sid (open-loop subspace identification).

Only similarity-invariant quantities are compared: poles, Markov parameters,
frequency responses, noise covariances of outputs, predicted outputs.
Tolerances come from a 10-seed Monte Carlo run of the same set-ups (noted
at each test): the pole error of N4SID scaled linearly with the noise
standard deviation sigma, with mean ~0.07 sigma and worst ~0.17 sigma for the
4th-order SISO test system at N = 4000.
"""

from __future__ import annotations

import tracemalloc

import control as ct
import matplotlib
import numpy as np
import pytest
from scipy.linalg import solve_discrete_are
from scipy.optimize import linear_sum_assignment

from greybox.exceptions import DataError, DimensionError, GreyboxWarning
from greybox.ident import N4SIDResult, n4sid
from greybox.ident._hankel import hankel_r

matplotlib.use("Agg")

PAIR_A = [0.9 * np.exp(0.5j), 0.9 * np.exp(-0.5j)]
PAIR_B = [0.7 * np.exp(1.5j), 0.7 * np.exp(-1.5j)]
POLES = {
    0: [],
    1: [0.8],
    2: PAIR_A,
    3: PAIR_A + [0.8],
    4: PAIR_A + PAIR_B,
    5: PAIR_A + PAIR_B + [0.8],
    6: PAIR_A + PAIR_B + [0.8, -0.6],
}


def modal_system(poles, m, l, seed, *, feedthrough=True):
    """Real modal (A, B, C, D) with the given poles; every mode clearly excited/observed."""
    rng = np.random.default_rng(seed)
    n = len(poles)
    A = np.zeros((n, n))
    k = 0
    while k < n:
        p = poles[k]
        if abs(np.imag(p)) > 0:
            A[k:k + 2, k:k + 2] = [[p.real, abs(p.imag)], [-abs(p.imag), p.real]]
            k += 2
        else:
            A[k, k] = np.real(p)
            k += 1
    sign = lambda shape: rng.choice([-1.0, 1.0], size=shape)  # noqa: E731
    B = rng.uniform(0.5, 1.5, (n, m)) * sign((n, m))
    C = rng.uniform(0.5, 1.5, (l, n)) * sign((l, n))
    D = rng.standard_normal((l, m)) if feedthrough else np.zeros((l, m))
    return A, B, C, D


def simulate(A, B, C, D, K, u, e, x0=None):
    """Innovation-form simulation; u (m, N), e (l, N)."""
    l = C.shape[0]
    sysa = ct.ss(A, np.hstack([B, K]), C, np.hstack([D, np.eye(l)]), 1.0)
    return ct.forced_response(sysa, U=np.vstack([u, e]), X0=0 if x0 is None else x0).y


def pole_error(est, true):
    """Largest distance between matched poles (optimal assignment)."""
    est, true = np.atleast_1d(est), np.atleast_1d(true)
    assert est.size == true.size
    if true.size == 0:
        return 0.0
    cost = np.abs(est[:, None] - true[None, :])
    r, c = linear_sum_assignment(cost)
    return float(cost[r, c].max())


def freq_rel_error(sys_est, A, B, C, D, w=np.linspace(0.01, 3.0, 60)):
    G = ct.ss(A, B, C, D, 1.0)(np.exp(1j * w))
    Gh = sys_est(np.exp(1j * w))
    return float(np.max(np.abs(Gh - G)) / np.max(np.abs(G)))


def make_data(order, m, l, N, sigma, seed, *, ksc=0.3, feedthrough=True):
    A, B, C, D = modal_system(POLES[order], m, l, 10 + order, feedthrough=feedthrough)
    K = ksc * np.random.default_rng(20 + order).standard_normal((order, l))
    # a true innovation form needs a stable predictor A - K C (else the model
    # is not the minimum-phase spectral factor the methods estimate)
    while order and np.max(np.abs(np.linalg.eigvals(A - K @ C))) > 0.9:
        K *= 0.8
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((m, N))
    e = sigma * rng.standard_normal((l, N))
    return (A, B, C, D, K), u, simulate(A, B, C, D, K, u, e)


# ---------------------------------------------------------------------------
# accuracy
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("sigma", [0.01, 0.1, 0.5], ids=["snr-high", "snr-mid", "snr-low"])
def test_poles_and_frequency_response_vs_snr(sigma):
    (A, B, C, D, K), u, y = make_data(4, 1, 1, 4000, sigma, seed=1, ksc=0.0)
    res = n4sid(y, u, order=4, feedthrough=True)
    # Monte Carlo (10 seeds): pole error <= 0.17 sigma, relative frequency
    # response error <= 0.10 sigma. 0.5 sigma / 0.3 sigma keeps ~3x margin
    # while a bias of a few per cent (e.g. a wrong horizon handling) fails.
    assert pole_error(res.sys.poles(), POLES[4]) < 0.5 * sigma
    assert freq_rel_error(res.sys, A, B, C, D) < 0.3 * sigma
    # the output noise is white here: innovation covariance = sigma^2 (+- 3 * sqrt(2/N) relative)
    np.testing.assert_allclose(res.innovation_cov[0, 0], sigma**2, rtol=3 * np.sqrt(2 / 4000) + 0.02)


@pytest.mark.parametrize("weighting", ["N4SID", "MOESP", "CVA"])
def test_weightings_mimo_markov_parameters(weighting):
    (A, B, C, D, K), u, y = make_data(3, 2, 2, 4000, 0.05, seed=2)
    res = n4sid(y, u, order=3, feedthrough=True, weighting=weighting)
    s = res.sys
    # sigma = 0.05 against unit-variance inputs: Markov parameters are
    # estimated to ~ sigma / sqrt(N) * (gain) ~ 1e-3; 2e-2 absolute tolerance
    # is a 10x margin that still catches any structural error (~0.1-1).
    for k, (Mh, M) in enumerate([(s.D, D), (s.C @ s.B, C @ B), (s.C @ s.A @ s.B, C @ A @ B),
                                 (s.C @ s.A @ s.A @ s.B, C @ A @ A @ B)]):
        np.testing.assert_allclose(Mh, M, atol=2e-2, err_msg=f"Markov parameter {k}")
    assert pole_error(s.poles(), POLES[3]) < 1e-2
    assert res.weighting == weighting


@pytest.mark.parametrize("order", range(7), ids=[f"n{n}" for n in range(7)])
@pytest.mark.parametrize("mimo", [False, True], ids=["siso", "mimo"])
def test_order_selection(order, mimo):
    m, l = (2, 2) if mimo else (1, 1)
    _, u, y = make_data(order, m, l, 3000, 0.1, seed=3)
    res = n4sid(y, u, feedthrough=True)
    assert res.order == order, res.criterion_values
    assert res.criterion == "bic"
    assert np.nanargmin(res.criterion_values) == order


def test_innovations_white_on_validation_data():
    # Estimation record >> validation record: the Ljung-Box statistic of an
    # estimated model exceeds chi2(20) by about npar * Nval / Nest (~3 here),
    # which the 99.9 % quantile absorbs; with Nest = Nval it would not.
    (A, B, C, D, K), u, y = make_data(4, 1, 2, 20000, 0.2, seed=4, ksc=0.4)
    res = n4sid(y, u, order=4, feedthrough=True)
    # fresh validation data from the same system
    (_, _, _, _, _), uv, yv = make_data(4, 1, 2, 3000, 0.2, seed=5, ksc=0.4)
    s = res.sys
    pred = ct.ss(s.A - res.K @ s.C, np.hstack([s.B - res.K @ s.D, res.K]), -s.C,
                 np.hstack([-s.D, np.eye(2)]), 1.0)
    eps = ct.forced_response(pred, U=np.vstack([uv, yv])).y[:, 100:]
    Nv = eps.shape[1]
    # covariance of the prediction errors matches the reported innovation
    # covariance (sampling error of a variance ~ sqrt(2/N) = 2 %; 10 %)
    np.testing.assert_allclose(np.cov(eps), res.innovation_cov, rtol=0.1, atol=4e-3)
    # whiteness: Ljung-Box over 20 lags per output; chi2(20) 99.9 % quantile = 45.3
    for i in range(2):
        x = eps[i] - eps[i].mean()
        r = np.array([x[k:] @ x[:-k] for k in range(1, 21)]) / (x @ x)
        q = Nv * (Nv + 2) * np.sum(r**2 / (Nv - np.arange(1, 21)))
        assert q < 45.3, f"output {i}: Ljung-Box Q = {q:.1f}"
    # ...and the test has power: with K = 0 the residuals are coloured
    pred0 = ct.ss(s.A, np.hstack([s.B, 0 * res.K]), -s.C, np.hstack([-s.D, np.eye(2)]), 1.0)
    eps0 = ct.forced_response(pred0, U=np.vstack([uv, yv])).y[0, 100:]
    x = eps0 - eps0.mean()
    assert abs(x[1:] @ x[:-1] / (x @ x)) > 10 / np.sqrt(Nv)


def test_pole_error_shrinks_with_n():
    errs = []
    for N in (1000, 4000, 16000):
        e = [pole_error(n4sid(y, u, order=2, feedthrough=True).sys.poles(), POLES[2])
             for _, u, y in (make_data(2, 1, 1, N, 0.3, seed=s, ksc=0.0) for s in range(3))]
        errs.append(np.mean(e))
    # consistency: error ~ 1/sqrt(N), so x16 samples should give ~4x smaller
    # errors; require 2x per 16x (mean of 3 seeds) and monotone decrease
    assert errs[0] > errs[1] > errs[2], errs
    assert errs[2] < errs[0] / 2, errs


# ---------------------------------------------------------------------------
# special cases
# ---------------------------------------------------------------------------


def test_order_zero_static_map():
    rng = np.random.default_rng(6)
    D = np.array([[1.5, -0.7], [0.3, 2.0]])
    u = rng.standard_normal((2, 3000))
    y = D @ u + 0.1 * rng.standard_normal((2, 3000))
    res = n4sid(y, u, order=0, feedthrough=True)
    assert res.order == 0 and res.sys.nstates == 0
    # OLS on N = 3000, noise 0.1: std of D entries ~ 0.1/sqrt(3000) = 2e-3; 1e-2 = 5 std
    np.testing.assert_allclose(res.sys.D, D, atol=1e-2)
    np.testing.assert_allclose(res.innovation_cov, 0.01 * np.eye(2), atol=2e-3)
    assert res.K.shape == (0, 2) and res.x0.shape == (0,)
    # automatic selection finds the static map as well
    assert n4sid(y, u, feedthrough=True).order == 0


def test_order_zero_without_feedthrough_is_noise():
    rng = np.random.default_rng(7)
    y = 2.0 * rng.standard_normal((1, 2000))
    res = n4sid(y, rng.standard_normal((1, 2000)), order=0)
    np.testing.assert_allclose(res.sys.D, 0.0)
    np.testing.assert_allclose(res.innovation_cov, [[4.0]], rtol=0.1)  # 2000 samples: ~3 % std


def test_pure_stochastic_model():
    # ARMA-like: y = e filtered by the innovation model (A, K, C); poles of A recovered
    A, _, C, _ = modal_system(PAIR_A, 1, 1, 8)
    # a Kalman gain (stable predictor: the minimum-phase factor is identifiable)
    P = solve_discrete_are(A.T, C.T, 0.5 * np.eye(2), np.eye(1))
    K = A @ P @ C.T @ np.linalg.inv(C @ P @ C.T + 1)
    rng = np.random.default_rng(8)
    y = simulate(A, np.zeros((2, 0)), C, np.zeros((1, 0)), K, np.zeros((0, 8000)),
                 rng.standard_normal((1, 8000)))
    res = n4sid(y, None, order=2)
    assert res.sys.ninputs == 0
    # stochastic poles converge slower (variance ~ 1/N with weaker SNR): 0.05
    assert pole_error(res.sys.poles(), PAIR_A) < 0.05
    # first Markov parameter of the noise model C K (invariant)
    np.testing.assert_allclose(res.sys.C @ res.K, C @ K, atol=0.1)
    np.testing.assert_allclose(res.innovation_cov, [[1.0]], rtol=0.1)


def test_labels_and_record():
    (_, _, _, _, _), u, y = make_data(2, 2, 1, 2000, 0.1, seed=9)
    res = n4sid(y, u, order=2, dt=0.01, input_labels=["a", "b"], output_labels=["d"],
                state_prefix="w")
    assert isinstance(res, N4SIDResult)
    assert res.sys.dt == 0.01 and res.dt == 0.01
    assert res.sys.input_labels == ["a", "b"] and res.sys.output_labels == ["d"]
    assert res.sys.state_labels == ["w[0]", "w[1]"]
    assert res.Q.shape == (2, 2) and res.S.shape == (2, 1) and res.R.shape == (1, 1)
    assert res.K.shape == (2, 1) and res.horizon == 10 and res.criterion is None
    with pytest.raises(AttributeError):
        res.order = 3  # frozen


def test_feedthrough_subset_by_label():
    (A, B, C, D, K), u, y = make_data(1, 2, 1, 3000, 0.05, seed=10)
    D[:, 1] = 0.0
    y = simulate(A, B, C, D, K, u, 0.05 * np.random.default_rng(99).standard_normal((1, 3000)))
    res = n4sid(y, u, order=1, feedthrough=["a"], input_labels=["a", "b"])
    assert res.feedthrough == (0,)
    assert res.sys.D[0, 1] == 0.0
    np.testing.assert_allclose(res.sys.D[0, 0], D[0, 0], atol=1e-2)  # ~5 std of OLS


def test_initial_state_estimate():
    A, B, C, D = modal_system(PAIR_A + [0.8], 1, 1, 11)
    x0 = np.array([5.0, -3.0, 4.0])
    rng = np.random.default_rng(11)
    u = rng.standard_normal((1, 3000))
    y = simulate(A, B, C, D, np.zeros((3, 1)), u, 0.01 * rng.standard_normal((1, 3000)), x0=x0)
    res = n4sid(y, u, order=3, feedthrough=True)
    s = res.sys
    # free response C A^k x0 is invariant; compare the first 20 samples
    free = np.array([C @ np.linalg.matrix_power(A, k) @ x0 for k in range(20)])
    free_h = np.array([s.C @ np.linalg.matrix_power(s.A, k) @ res.x0 for k in range(20)])
    # noise 0.01 vs free response amplitude ~ 10: 0.1 absolute is ~1 %
    np.testing.assert_allclose(free_h, free, atol=0.1)


def test_several_experiments_match_one_record():
    (_, _, _, _, _), u, y = make_data(2, 1, 1, 6000, 0.1, seed=12)
    whole = n4sid(y, u, order=2, feedthrough=True)
    parts = n4sid([y[:, :3000], y[:, 3000:]], [u[:, :3000], u[:, 3000:]], order=2,
                  feedthrough=True)
    assert parts.x0_experiments.shape == (2, 2)
    assert parts.nsamples == whole.nsamples - 19  # one Hankel window lost at the split
    # both are estimates from the same data: differ by far less than their error (~0.02)
    assert pole_error(parts.sys.poles(), whole.sys.poles()) < 5e-3


def test_chunk_size_does_not_change_result():
    (_, _, _, _, _), u, y = make_data(2, 1, 1, 3000, 0.1, seed=13)
    a = n4sid(y, u, order=2, chunk_size=257)
    b = n4sid(y, u, order=2)
    # same data, different floating point summation order only
    np.testing.assert_allclose(np.sort_complex(a.sys.poles()), np.sort_complex(b.sys.poles()),
                               rtol=1e-9)
    np.testing.assert_allclose(a.singular_values, b.singular_values, rtol=1e-9)


def test_hankel_factor_gram_equals_qr_and_direct():
    rng = np.random.default_rng(14)
    y, u = rng.standard_normal((1, 1500)), rng.standard_normal((2, 1500))
    nb = 6
    H = np.vstack([np.concatenate([u[:, t:1501 - nb + t], y[:, t:1501 - nb + t]])
                   for t in range(nb)])
    direct = H @ H.T / H.shape[1]
    for method in ("gram", "qr"):
        h = hankel_r([y], [u], np.ones(1), np.ones(2), nb, chunk_size=100, method=method)
        np.testing.assert_allclose(h.L @ h.L.T, direct, atol=1e-12)  # rounding only


def test_memory_does_not_grow_with_n():
    def peak(N):
        (_, _, _, _, _), u, y = make_data(2, 1, 1, N, 0.1, seed=15, ksc=0.0)
        tracemalloc.start()
        n4sid(y, u, order=2, chunk_size=1000)
        p = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return p

    small, large = peak(20_000), peak(200_000)
    # the data grow by 3.2 MB; the working memory must not (chunks are fixed size):
    # allow 1 MB of variation, far below the 2 x 2.9 MB a copy of the data would add
    assert large < small + 1_000_000, (small, large)


# ---------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------


def test_horizon_too_long():
    rng = np.random.default_rng(16)
    with pytest.raises(DataError, match=r"horizon=40 is too long .* reduce horizon to at most 30"):
        n4sid(rng.standard_normal((1, 300)), rng.standard_normal((1, 300)), horizon=40)


def test_too_few_samples():
    rng = np.random.default_rng(17)
    with pytest.raises(DataError, match="too few samples"):
        n4sid(rng.standard_normal((1, 10)), rng.standard_normal((1, 10)), order=2)


def test_nan_in_data():
    y = np.ones((1, 500))
    y[0, 123] = np.nan
    with pytest.raises(DataError, match=r"y contains NaN or inf .*sample 123"):
        n4sid(y, np.ones((1, 500)))


def test_mismatched_lengths():
    with pytest.raises(DimensionError, match="different numbers of samples"):
        n4sid(np.zeros((1, 500)) + 1, np.ones((1, 499)))


def test_time_must_be_last_axis():
    rng = np.random.default_rng(18)
    with pytest.raises(DimensionError, match="time must be the last axis"):
        n4sid(rng.standard_normal((1, 500)), rng.standard_normal((500, 2)))


@pytest.mark.parametrize(
    "u_kind", ["constant", "sinusoid", "collinear"], ids=["constant", "sinusoid", "collinear"]
)
def test_not_persistently_exciting_warns(u_kind):
    rng = np.random.default_rng(19)
    N = 2000
    k = np.arange(N)
    if u_kind == "constant":
        u, match = np.ones((1, N)), r"input\(s\) \['u\[0\]'\] are not persistently exciting"
    elif u_kind == "sinusoid":
        u, match = np.sin(0.3 * k)[None], r"not persistently exciting of order 20"
    else:
        a = rng.standard_normal(N)
        u, match = np.vstack([a, 2 * a]), "jointly"
    y = np.vstack([np.convolve(u.sum(0), [0, 1, 0.5])[:N]]) + 0.01 * rng.standard_normal((1, N))
    with pytest.warns(GreyboxWarning, match=match):
        res = n4sid(y, u, order=1)
    assert np.all(np.isfinite(res.sys.A))


def test_order_too_large_for_horizon():
    rng = np.random.default_rng(20)
    with pytest.raises(DimensionError, match=r"order=12 .*horizon"):
        n4sid(rng.standard_normal((1, 2000)), rng.standard_normal((1, 2000)), order=12,
              horizon=5)


def test_bad_options():
    rng = np.random.default_rng(21)
    y, u = rng.standard_normal((1, 500)), rng.standard_normal((1, 500))
    with pytest.raises(DimensionError, match="weighting='foo' is unknown"):
        n4sid(y, u, weighting="foo")
    with pytest.raises(DimensionError, match="input_labels has 2 entries; expected ninputs = 1"):
        n4sid(y, u, input_labels=["a", "b"])
    with pytest.raises(DataError, match="identically zero"):
        n4sid(np.zeros((1, 500)), u)
    with pytest.raises(DimensionError, match="y is a list of 2 experiments but u"):
        n4sid([y, y], u)
    with pytest.raises(TypeError):
        n4sid(y, u, nblock=3)  # unknown keyword


# ---------------------------------------------------------------------------
# plot
# ---------------------------------------------------------------------------


def test_plot_singular_values():
    import matplotlib.pyplot as plt

    from greybox.plotting import plot_singular_values

    (_, _, _, _, _), u, y = make_data(2, 1, 1, 2000, 0.1, seed=22)
    res = n4sid(y, u, feedthrough=True)
    out = plot_singular_values(res)
    try:
        xs, ys = out["singular_values"].get_data()
        np.testing.assert_array_equal(xs, np.arange(1, res.singular_values.size + 1))
        np.testing.assert_allclose(ys, res.singular_values)
        assert out["order"].get_xdata()[0] == res.order + 0.5
        assert out["ax"].get_yscale() == "log"
        fig, ax = plt.subplots()
        out2 = res.plot(ax=ax)
        assert out2["ax"] is ax and out2["figure"] is fig
    finally:
        plt.close("all")
