"""Tests of the excitation signals, the seeded simulator, model plumbing and the tape drive."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.signal as sps
from scipy.stats import chi2

import greybox as gb
from greybox import DataError, DimensionError, ModelError
from greybox.plants import TAPE_DRIVE_INPUTS, TAPE_DRIVE_STATES

ALPHA = 1e-3  # two-sided significance of the statistical checks (fixed seeds)


# --------------------------------------------------------------------------- random_binary
@pytest.mark.parametrize("nsteps,hold,amplitude", [(1000, 1, 1.0), (1003, 7, 2.5), (50, 50, 0.1)],
                         ids=["hold1", "hold7-ragged", "one-block"])
def test_random_binary_levels_and_hold(nsteps, hold, amplitude, rng):
    x = gb.random_binary(nsteps, nsignals=3, amplitude=amplitude, hold=hold, rng=rng)
    assert x.shape == (3, nsteps)
    assert set(np.unique(x)) <= {-amplitude, amplitude}
    nblk = -(-nsteps // hold)
    padded = np.concatenate([x, np.repeat(x[:, -1:], nblk * hold - nsteps, axis=1)], axis=1)
    blocks = padded.reshape(3, nblk, hold)
    # constant inside every clock period
    np.testing.assert_array_equal(blocks, np.repeat(blocks[:, :, :1], hold, axis=2))


def test_random_binary_is_balanced_and_switches(rng):
    """Levels are equally likely and the level is redrawn every hold samples."""
    hold, nblk = 5, 4000
    x = gb.random_binary(hold * nblk, nsignals=2, hold=hold, rng=rng)
    lv = x[:, ::hold]
    # binomial(4000, 1/2): SD 0.0079; 4.5 SD
    np.testing.assert_allclose(np.mean(lv > 0, axis=1), 0.5, atol=0.036)
    switch = np.mean(lv[:, 1:] != lv[:, :-1], axis=1)
    np.testing.assert_allclose(switch, 0.5, atol=0.036)  # independent draws: same binomial
    # channels are independent: correlation ~ N(0, 1/4000), 4.5 SD = 0.07
    assert abs(np.corrcoef(lv)[0, 1]) < 0.07


@pytest.mark.parametrize("kw,exc,match", [
    (dict(nsteps=10, hold=0), DataError, r"hold must be finite and > 0"),
    (dict(nsteps=10, hold=1.5), DimensionError, r"hold must be an integer"),
    (dict(nsteps=0), DataError, r"nsteps must be finite and > 0"),
], ids=["hold-zero", "hold-fraction", "nsteps-zero"])
def test_random_binary_errors(kw, exc, match):
    n = kw.pop("nsteps")
    with pytest.raises(exc, match=match):
        gb.random_binary(n, **kw)


# --------------------------------------------------------------------------- multisine
def test_multisine_rms_and_band(rng):
    dt, N, fmin, fmax, nf = 1e-3, 20000, 5.0, 50.0, 15
    x = gb.multisine(N, dt=dt, nsignals=2, amplitude=2.0, fmin=fmin, fmax=fmax, nfreq=nf,
                     rng=rng)
    assert x.shape == (2, N)
    # the normalization makes the RMS exact up to rounding
    np.testing.assert_allclose(np.sqrt(np.mean(x**2, axis=1)), 2.0, rtol=1e-12)
    f = np.fft.rfftfreq(N, dt)
    X = np.abs(np.fft.rfft(x * np.hanning(N), axis=1)) ** 2
    band = (f >= 0.9 * fmin) & (f <= 1.1 * fmax)
    # Hann leakage 10 % outside the band is < -100 dB here (measured 1e-11)
    assert np.all(X[:, band].sum(axis=1) / X.sum(axis=1) > 1 - 1e-6)
    # one line at each log-spaced frequency, both band edges included
    for i in range(2):
        pk = sps.find_peaks(X[i], height=0.05 * X[i].max())[0]
        # within one FFT bin (resolution 1/(N dt) = 0.05 Hz)
        np.testing.assert_allclose(f[pk], np.geomspace(fmin, fmax, nf), atol=1 / (N * dt))
    assert not np.allclose(x[0], x[1])  # independent phases


def test_multisine_default_band(rng):
    """Defaults: lowest resolvable frequency up to fs/4."""
    dt, N = 1e-2, 4000
    x = gb.multisine(N, dt=dt, rng=rng)
    f = np.fft.rfftfreq(N, dt)
    X = np.abs(np.fft.rfft(x[0] * np.hanning(N))) ** 2
    assert X[f > 1.1 * 25.0].sum() / X.sum() < 1e-6  # fs/4 = 25 Hz
    assert X[f > 20.0].sum() / X.sum() > 1e-3  # ... and it reaches up there


@pytest.mark.parametrize("kw", [dict(fmin=10.0, fmax=5.0), dict(fmax=60.0), dict(fmin=0.0)],
                         ids=["inverted", "above-nyquist", "zero"])
def test_multisine_bad_band(kw):
    with pytest.raises(DataError, match=r"need 0 < fmin < fmax <= fs/2 = 50 Hz"):
        gb.multisine(100, dt=1e-2, **kw)


# --------------------------------------------------------------------------- lowpass_noise
def test_lowpass_noise_std_and_bandwidth(rng):
    """Welch PSD follows the 4th-order Butterworth shape with half power at the cut-off."""
    dt, N, bw, a = 1e-3, 200_000, 20.0, 0.7
    y = gb.lowpass_noise(N, dt=dt, bandwidth=bw, nsignals=2, amplitude=a, rng=rng)
    np.testing.assert_allclose(y.std(axis=1), a, rtol=1e-12)  # normalized exactly
    fw, P = sps.welch(y, fs=1 / dt, nperseg=4096, axis=1)
    lo = (fw >= 1) & (fw <= 5)
    cut = (fw >= 19) & (fw <= 21)
    # |H(fc)|^2 = 1/2; a band average over ~9 bins x ~97 segments has a relative
    # SD of ~4 %: ±20 % is about 5 SD
    np.testing.assert_allclose(P[:, cut].mean(axis=1) / P[:, lo].mean(axis=1), 0.5, rtol=0.2)
    # 4th order: -24 dB/octave; above 3 bw almost nothing is left
    assert np.all(P[:, fw > 3 * bw].sum(axis=1) / P.sum(axis=1) < 1e-3)
    # level: one-sided PSD of std a through |H|^2, normalized to total power a^2
    sos = sps.butter(4, bw, fs=1 / dt, output="sos")
    H2 = np.abs(sps.sosfreqz(sos, worN=fw, fs=1 / dt)[1]) ** 2
    S = a**2 * H2 / np.trapezoid(H2, fw)
    for band in [(1, 10), (15, 25), (30, 50)]:
        m = (fw >= band[0]) & (fw <= band[1])
        # band averages of >= 40 bins: relative SD ~ 2 %; ±10 % is 5 SD
        np.testing.assert_allclose(P[:, m].mean(axis=1) / S[m].mean(), 1.0, rtol=0.1)


def test_lowpass_noise_above_nyquist():
    with pytest.raises(DataError, match=r"bandwidth 600 Hz must be below the Nyquist"):
        gb.lowpass_noise(100, dt=1e-3, bandwidth=600)


# --------------------------------------------------------------------------- reproducibility
@pytest.mark.parametrize("make", [
    lambda r: gb.random_binary(200, nsignals=2, hold=3, rng=r),
    lambda r: gb.multisine(200, dt=0.01, nsignals=2, rng=r),
    lambda r: gb.lowpass_noise(200, dt=0.01, bandwidth=5, nsignals=2, rng=r),
    lambda r: gb.simulate(gb.tape_drive_true(dt=1e-4), np.ones((2, 200)), Q=gb.TAPE_DRIVE_Q,
                          R=gb.TAPE_DRIVE_R, rng=r).y,
], ids=["random_binary", "multisine", "lowpass_noise", "simulate"])
def test_seeded_reproducibility(make):
    a, b = make(123), make(123)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(make(np.random.default_rng(123)), a)  # int seed == Generator
    assert not np.array_equal(make(124), a)


# --------------------------------------------------------------------------- simulate
def _plain_loop(A, B, C, D, u, x0):
    x = np.empty((A.shape[0], u.shape[1]))
    x[:, 0] = x0
    for k in range(u.shape[1] - 1):
        x[:, k + 1] = A @ x[:, k] + B @ u[:, k]
    return x, C @ x + D @ u


def _sim_model(kind, rng):
    n, m, p = 3, 2, 2
    if kind == "diagonal":  # lti_states' diagonal branch
        A = np.diag([0.9, -0.5, 0.99])
    elif kind == "jordan":  # not diagonalizable
        A = np.array([[0.9, 1.0, 0.0], [0.0, 0.9, 1.0], [0.0, 0.0, 0.9]])
    elif kind == "rotation":  # complex eigenvalues, |lambda| = 0.98
        c, s = 0.98 * np.cos(0.3), 0.98 * np.sin(0.3)
        A = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 0.5]])
    else:
        A = rng.standard_normal((n, n))
        A *= 0.95 / np.max(np.abs(np.linalg.eigvals(A)))
    return gb.named_ss(A, rng.standard_normal((n, m)), rng.standard_normal((p, n)),
                       rng.standard_normal((p, m)), 0.1, states=["a", "b", "c"],
                       inputs=["u0", "u1"], outputs=["y0", "y1"])


@pytest.mark.parametrize("kind", ["diagonal", "jordan", "rotation", "random", "tape-drive"])
def test_simulate_reproduces_plain_loop(kind, rng):
    """Noise-free simulate equals x[k+1] = A x + B u, y = C x + D u in a plain loop.

    Only rounding differs (Schur transform and lfilter vs sequential products);
    over 400 steps of these stable/marginal systems that stays below 1e-10 of
    the signal scale (measured ~1e-14).
    """
    if kind == "tape-drive":
        sys = gb.tape_drive_true(dt=1e-4)  # common-mode integrator: eigenvalue 1
    else:
        sys = _sim_model(kind, rng)
    N = 400
    u = rng.standard_normal((sys.ninputs, N))
    x0 = rng.standard_normal(sys.nstates)
    sim = gb.simulate(sys, u, x0=x0)
    x, y = _plain_loop(*(np.asarray(M) for M in (sys.A, sys.B, sys.C, sys.D)), u, x0)
    np.testing.assert_allclose(sim.x, x, rtol=0, atol=1e-10 * np.max(np.abs(x)))
    np.testing.assert_allclose(sim.y, y, rtol=0, atol=1e-10 * np.max(np.abs(y)))
    np.testing.assert_array_equal(sim.y, sim.y_clean)  # no R: no measurement noise
    np.testing.assert_array_equal(sim.u, u)
    np.testing.assert_allclose(sim.t, np.arange(N) * float(sys.dt), rtol=1e-15)


def test_simulate_noise_statistics(rng):
    """With A = 0: x[k+1] = w[k] ~ N(0, Q) and y - y_clean = v ~ N(0, R), independent."""
    n, p, N = 3, 2, 20_000
    W = rng.standard_normal((n, n))
    Q = W @ W.T + 0.1 * np.eye(n)
    V = rng.standard_normal((p, p))
    R = V @ V.T + 0.1 * np.eye(p)
    sys = gb.named_ss(np.zeros((n, n)), np.zeros((n, 1)), rng.standard_normal((p, n)),
                      np.zeros((p, 1)), 1.0, states=["a", "b", "c"], inputs=["u"],
                      outputs=["y0", "y1"])
    sim = gb.simulate(sys, np.zeros((1, N + 1)), Q=Q, R=R, rng=rng)
    w, v = sim.x[:, 1:], (sim.y - sim.y_clean)[:, 1:]
    for e, S in ((w, Q), (v, R)):
        q = np.sum(e * np.linalg.solve(S, e))
        lo, hi = chi2.ppf([ALPHA / 2, 1 - ALPHA / 2], e.size)
        assert lo < q < hi
        Lw = np.linalg.cholesky(S)
        z = np.linalg.solve(Lw, e)
        # whitened sample covariance: entries have SD <= sqrt(2/N) = 0.01; 5 SD
        np.testing.assert_allclose(z @ z.T / N, np.eye(S.shape[0]), atol=0.05)
    # w and v independent: normalized cross-covariance entries have SD 1/sqrt(N)
    zw = np.linalg.solve(np.linalg.cholesky(Q), w)
    zv = np.linalg.solve(np.linalg.cholesky(R), v)
    np.testing.assert_allclose(zw @ zv.T / N, 0.0, atol=5 / np.sqrt(N))


def test_simulate_singular_Q_leaves_unexcited_states(rng):
    """Q may be singular: a state with zero process noise stays deterministic."""
    sys = gb.named_ss(np.diag([0.5, 0.5]), np.zeros((2, 1)), np.eye(2), np.zeros((2, 1)), 1.0,
                      states=["a", "b"], inputs=["u"], outputs=["y0", "y1"])
    sim = gb.simulate(sys, np.zeros((1, 100)), Q=np.diag([1.0, 0.0]), rng=rng)
    np.testing.assert_array_equal(sim.x[1], 0.0)
    assert np.std(sim.x[0]) > 0.5


def test_simulate_without_inputs(rng):
    sys = gb.named_ss([[0.5]], [[0.0]], [[1.0]], [[0.0]], 1.0, states=["a"], inputs=["u"],
                      outputs=["y"])
    with pytest.raises(DataError, match=r"sys has 1 inputs; pass u with shape \(1, nsteps\)"):
        gb.simulate(sys, nsteps=10)
    auto = gb.named_ss(np.diag([0.5, 0.9]), np.zeros((2, 0)), np.eye(2), np.zeros((2, 0)), 1.0,
                       states=["a", "b"], inputs=[], outputs=["y0", "y1"])
    sim = gb.simulate(auto, x0=[1.0, 1.0], nsteps=5)
    np.testing.assert_allclose(sim.x[1], 0.9 ** np.arange(5), rtol=1e-14)  # a few products


def test_simulate_rejects_bad_input(rng):
    sys = _sim_model("random", rng)
    with pytest.raises(DimensionError, match=r"u has shape \(3, 10\); expected \(2, nsteps\)"):
        gb.simulate(sys, np.ones((3, 10)))
    with pytest.raises(DataError, match=r"u contains NaN"):
        gb.simulate(sys, np.full((2, 10), np.nan))
    with pytest.raises(ModelError, match=r"continuous-time"):
        gb.simulate(gb.tape_drive_true(), np.ones((2, 10)))


# --------------------------------------------------------------------------- tape drive
@pytest.fixture
def tape():
    p = gb.TapeDriveParams()
    true_c = gb.tape_drive_true()
    nom_c = gb.tape_drive_nominal()
    return p, true_c, nom_c


def test_tape_drive_true_is_nominal_plus_tension(tape):
    """A_true = A_nom + g c_T with c_T the tension law (39), T in newtons."""
    p, true_c, nom_c = tape
    cT = gb.tape_drive_tension(p)
    # T = K/2 (p2 - p1) + D/2 r (w2 - w1), by hand
    x = np.array([0.3, -0.2, 1e-3, 3e-3, 10.0, 12.0])
    T = p.K / 2 * (x[3] - x[2]) + p.D / 2 * p.r * (x[5] - x[4])
    np.testing.assert_allclose(cT @ x, [T], rtol=1e-14)  # a few flops
    g = np.asarray(nom_c.B)[:, 2:3]
    np.testing.assert_allclose(g.ravel(), [0, 0, 0, 0, p.r / p.J, -p.r / p.J], rtol=1e-14)
    np.testing.assert_allclose(true_c.A, np.asarray(nom_c.A) + g @ cT, rtol=1e-14)
    np.testing.assert_array_equal(true_c.B, np.asarray(nom_c.B)[:, :2])
    np.testing.assert_array_equal(true_c.C, np.eye(6))


def test_tape_drive_eigenvalues_differ_and_tension_restores(tape):
    p, true_c, nom_c = tape
    ev_true = np.linalg.eigvals(true_c.A)
    ev_nom = np.linalg.eigvals(nom_c.A)
    # nominal: two integrators (p1, p2); true: only the common mode is left
    assert np.sum(np.abs(ev_nom) < 1e-9) == 2
    assert np.sum(np.abs(ev_true) < 1e-9) == 1
    # the sets differ by far more than rounding: some true eigenvalue is >= 50 rad/s
    # away from every nominal one
    dist = np.min(np.abs(ev_true[:, None] - ev_nom[None, :]), axis=1)
    assert np.max(dist) > 50
    # stable apart from the common-mode integrator, whose direction is p1 = p2
    assert np.all(np.sort(ev_true.real)[:-1] < -100)
    common = np.array([0, 0, 1.0, 1.0, 0, 0])
    np.testing.assert_allclose(true_c.A @ common, 0.0, atol=1e-12)  # exact cancellation
    # restoring: a stretch p2 - p1 = s > 0 gives d^2 s/dt^2 = -(r^2 K / J) s
    s = 1e-3
    x = np.array([0, 0, -s / 2, s / 2, 0, 0])
    dx = true_c.A @ x
    assert dx[4] > 0 > dx[5]  # wheel 1 pulled forward, wheel 2 back
    acc = p.r * (dx[5] - dx[4])
    np.testing.assert_allclose(acc / s, -(p.r**2 * p.K / p.J), rtol=1e-12)  # (500 rad/s)^2
    # the printed sign (-r T on both wheels) would cancel from the stretch: nominal spectrum
    printed = np.asarray(nom_c.A) + np.array([[0, 0, 0, 0, -p.r / p.J, -p.r / p.J]]).T \
        @ gb.tape_drive_tension(p)
    ev_printed = np.linalg.eigvals(printed)
    # match each to the nearest nominal eigenvalue (sorting fails on repeated ones). The
    # double zero becomes defective (a Jordan block), so it splits by ~sqrt(eps |A|)
    # (measured 5e-6): tolerance 1e-6 of the spectral radius, i.e. ~1e-3 rad/s
    d_printed = np.min(np.abs(ev_printed[:, None] - ev_nom[None, :]), axis=1)
    assert np.max(d_printed) < 1e-6 * np.max(np.abs(ev_nom)), d_printed


def test_tape_drive_discrete_true_model_marginal():
    ev = np.linalg.eigvals(gb.tape_drive_true(dt=gb.TAPE_DRIVE_DT).A)
    mags = np.sort(np.abs(ev))
    np.testing.assert_allclose(mags[-1], 1.0, rtol=1e-12)  # exp(0 * dt)
    assert mags[-2] < 1 - 1e-3


def test_tape_drive_zoh_G_in_newtons(tape):
    """Discrete G = int_0^dt expm(A s) ds g (ZOH of the tension channel): d stays in N.

    Checked against 20-point Gauss-Legendre quadrature of the matrix
    exponential, independent of the augmented-exponential trick ZOH uses. The
    integrand is entire and ||A|| dt = 0.13, so the quadrature error
    ~ (||A|| dt)^40 / 40! is negligible: rtol 1e-9 leaves room for expm rounding.
    First order, G ~ g dt: a 1 N tension held one sample changes w1 by ~ r/J dt.
    """
    p, _, nom_c = tape
    dt = gb.TAPE_DRIVE_DT
    sp = gb.split_inputs(gb.tape_drive_nominal(p, dt=dt), "T")
    A = np.asarray(nom_c.A)
    g = np.asarray(nom_c.B)[:, 2]
    nodes, weights = np.polynomial.legendre.leggauss(20)
    s_k, w_k = dt / 2 * (nodes + 1), dt / 2 * weights

    def integral_of(Bcols):
        return sum(w * sla.expm(A * s) @ Bcols for s, w in zip(s_k, w_k))

    integral = integral_of(g)
    np.testing.assert_allclose(sp.G[:, 0], integral, rtol=1e-9, atol=1e-18)
    # first-order check of the units; the neglected term is ~|A| dt / 2 ~ 10 % here
    np.testing.assert_allclose(sp.G[4:, 0], [p.r / p.J * dt, -p.r / p.J * dt], rtol=0.15)
    # known inputs discretized the same way (one ZOH for [u, d])
    np.testing.assert_allclose(sp.sys.B, integral_of(np.asarray(nom_c.B)[:, :2]), rtol=1e-9,
                               atol=1e-18)
    np.testing.assert_allclose(sp.sys.A, sla.expm(A * dt), rtol=1e-12, atol=1e-15)


def test_labels_kept_through_discretize_and_split(tape):
    _, true_c, nom_c = tape
    dt = gb.TAPE_DRIVE_DT
    nom_d = gb.discretize(nom_c, dt)
    assert list(nom_d.state_labels) == list(TAPE_DRIVE_STATES)
    assert list(nom_d.input_labels) == list(TAPE_DRIVE_INPUTS) + ["T"]
    assert list(nom_d.output_labels) == list(TAPE_DRIVE_STATES)
    assert nom_d.dt == dt and nom_d.name == nom_c.name
    np.testing.assert_array_equal(nom_d.A, gb.tape_drive_nominal(dt=dt).A)  # same ZOH
    sp = gb.split_inputs(nom_d, "T")
    assert list(sp.sys.state_labels) == list(TAPE_DRIVE_STATES)
    assert list(sp.sys.input_labels) == list(TAPE_DRIVE_INPUTS)
    assert list(sp.sys.output_labels) == list(TAPE_DRIVE_STATES)
    assert sp.unknown_labels == ("T",) and sp.unknown_index == (2,)
    assert sp.sys.dt == dt
    np.testing.assert_array_equal(sp.H, np.zeros((6, 1)))
    np.testing.assert_array_equal(sp.G, np.asarray(nom_d.B)[:, 2:])
    np.testing.assert_array_equal(sp.sys.B, np.asarray(nom_d.B)[:, :2])
    # by index, and with the unknown channel first
    assert gb.split_inputs(nom_d, 2).unknown_labels == ("T",)
    sp0 = gb.split_inputs(nom_d, ["V1"])
    assert list(sp0.sys.input_labels) == ["V2", "T"] and sp0.unknown_index == (0,)
    tr = gb.tape_drive_true(dt=dt)
    assert list(tr.state_labels) == list(TAPE_DRIVE_STATES)
    assert list(tr.input_labels) == list(TAPE_DRIVE_INPUTS)


@pytest.mark.parametrize("call,exc,match", [
    (lambda: gb.discretize(gb.tape_drive_true(dt=1e-4), 1e-4), ModelError, r"already discrete"),
    (lambda: gb.discretize(gb.tape_drive_true(), 0.0), DataError, r"dt must be finite and > 0"),
    (lambda: gb.split_inputs(gb.tape_drive_nominal(), "T"), ModelError, r"continuous-time"),
    (lambda: gb.split_inputs(gb.tape_drive_nominal(dt=1e-4), "F"), DimensionError,
     r"unknown: no signal named 'F'; available: \['V1', 'V2', 'T'\]"),
    (lambda: gb.split_inputs(gb.tape_drive_nominal(dt=1e-4), []), DimensionError,
     r"at least one unknown-input channel"),
], ids=["discretize-discrete", "discretize-dt0", "split-continuous", "split-label", "split-empty"])
def test_plumbing_errors(call, exc, match):
    with pytest.raises(exc, match=match):
        call()


def test_nominal_without_tension_input():
    nom = gb.tape_drive_nominal(dt=1e-4, with_tension_input=False)
    assert list(nom.input_labels) == list(TAPE_DRIVE_INPUTS)
    # ZOH columns do not depend on each other; only the size of the augmented
    # exponential differs: rounding, rtol 1e-12
    np.testing.assert_allclose(nom.B, np.asarray(gb.tape_drive_nominal(dt=1e-4).B)[:, :2],
                               rtol=1e-12, atol=1e-20)
