"""zoh_equivalent_input: the held input under which the ZOH model responds as the
continuous model to a band-limited input (issue 12, the Silverbox's 1 mV goal).

The truth is analytic: a multisine's periodic response through the continuous
transfer function, sum_k |Hc(j w_k)| cos(w_k t + phi_k + arg Hc(j w_k)).
"""

import numpy as np
import pytest

import greybox as gb
from greybox.exceptions import DimensionError, ModelError
from greybox.system import named_ss

DT = 2**14 / 1e7                       # the Silverbox's sampling period
WN, ZETA = 2 * np.pi * 69.0, 0.044     # its resonance (data README)


def _oscillator(outputs=1):
    C = [[1, 0]] if outputs == 1 else [[1, 0], [0, 1 / WN]]
    return named_ss([[0, 1], [-WN**2, -2 * ZETA * WN]], [[0], [WN**2]], C,
                    np.zeros((outputs, 1)), 0, states=["y", "v"], inputs=["u"],
                    outputs=["y"] if outputs == 1 else ["y", "v_scaled"])


def _multisine(period, periods, rng, top=0.35):
    """Odd-line multisine up to ``top`` * fs, its sample times and its lines."""
    lines = np.arange(1, int(top * period), 2)
    phi = rng.uniform(0, 2 * np.pi, lines.size)
    n = np.arange(period * periods)
    w = 2 * np.pi * lines / period / DT                 # rad/s
    u = np.cos(np.outer(n * DT, w) + phi).sum(axis=1)
    return u, n * DT, w, phi


def _analytic(sys, t, w, phi, out=0, inp=0):
    A, B, C = (np.asarray(M) for M in (sys.A, sys.B, sys.C))
    H = np.array([(C @ np.linalg.solve(1j * wk * np.eye(2) - A, B))[out, inp] for wk in w])
    return (np.abs(H) * np.cos(np.outer(t, w) + phi + np.angle(H))).sum(axis=1)


def test_the_zoh_model_driven_by_the_equivalent_input_matches_the_continuous_response():
    sys = _oscillator()
    rng = np.random.default_rng(0)
    P = 1024
    u, t, w, phi = _multisine(P, 4, rng)
    ue = gb.zoh_equivalent_input(sys, u[None], DT)
    assert ue.shape == (1, u.size)
    sd = gb.discretize(sys, DT)
    y_eq = gb.simulate(sd, ue).y[0]
    y_raw = gb.simulate(sd, u[None]).y[0]
    truth = _analytic(sys, t, w, phi)
    last = slice(3 * P, 4 * P)            # three periods: the transient (32 samples) is gone
    scale = np.abs(truth[last]).max()
    # exact by construction on the DFT lines: float64 round-off of the FFTs and of
    # 4096 recursion steps, relative to the amplitude
    np.testing.assert_allclose(y_eq[last], truth[last], atol=1e-9 * scale)
    # the raw samples held: the hold's half-sample delay and gain error (a few %), which
    # the equivalent input removes; this is what a test without the helper would see
    assert np.abs(y_raw[last] - truth[last]).max() > 0.05 * scale


def test_two_inputs_each_get_their_own_equivalent():
    rng = np.random.default_rng(1)
    two = named_ss([[0, 1], [-WN**2, -2 * ZETA * WN]], [[0, 1], [WN**2, 0]], [[1, 0]],
                   [[0, 0]], 0, states=["y", "v"], inputs=["u1", "u2"], outputs=["y"])
    P = 512
    u1, t, w1, p1 = _multisine(P, 4, rng)
    u2, _, w2, p2 = _multisine(P, 4, rng, top=0.2)
    ue = gb.zoh_equivalent_input(two, np.vstack([u1, u2]), DT)
    y = gb.simulate(gb.discretize(two, DT), ue).y[0]
    truth = _analytic(two, t, w1, p1, inp=0) + _analytic(two, t, w2, p2, inp=1)
    last = slice(3 * P, 4 * P)
    # exact per input (one output): round-off as above
    np.testing.assert_allclose(y[last], truth[last], atol=1e-9 * np.abs(truth[last]).max())


def test_several_outputs_least_squares_and_offsets_pass_through():
    sys = _oscillator(outputs=2)
    rng = np.random.default_rng(2)
    P = 512
    u, t, w, phi = _multisine(P, 4, rng)
    ue = gb.zoh_equivalent_input(sys, u[None], DT)
    y = gb.simulate(gb.discretize(sys, DT), ue).y
    last = slice(3 * P, 4 * P)
    raw = gb.simulate(gb.discretize(sys, DT), u[None]).y
    for i in range(2):
        truth = _analytic(sys, t, w, phi, out=i)
        err, err_raw = (np.abs(s[i, last] - truth[last]).max() for s in (y, raw))
        # a least-squares match over two outputs is not exact; it must still remove
        # most of the hold's error on each (measured: 24x and 57x)
        assert err < 0.2 * err_raw, (i, err, err_raw)
    # DC gain 1: an offset passes through unchanged (ZOH holds a constant exactly), also
    # with an integrator (A singular at DC)
    integ = named_ss([[0, 1], [0, -2.0]], [[0], [1.0]], [[1, 0]], [[0]], 0, states=["q", "v"],
                     inputs=["u"], outputs=["q"])
    a = gb.zoh_equivalent_input(integ, u[None], DT)
    b = gb.zoh_equivalent_input(integ, u[None] + 3.0, DT)
    # round-off of two FFTs of a 2048-sample record
    np.testing.assert_allclose(b - a, 3.0, atol=1e-12 * np.abs(a).max() + 1e-12)


def test_bad_inputs_are_refused():
    sys = _oscillator()
    with pytest.raises(ModelError, match="continuous-time nominal model"):
        gb.zoh_equivalent_input(gb.discretize(sys, DT), np.zeros((1, 100)), DT)
    with pytest.raises(DimensionError, match=r"expected \(1, nsteps\)"):
        gb.zoh_equivalent_input(sys, np.zeros((2, 100)), DT)
    with pytest.raises(gb.GreyboxError, match="dt"):
        gb.zoh_equivalent_input(sys, np.zeros((1, 100)), -1.0)


def test_input_correlation_note_threshold():
    """close_the_loop's note on residuals that correlate with an input (workflow._loop)."""
    from types import SimpleNamespace

    from greybox.workflow import INPUT_CORR_NOTE, _input_correlation_note
    band = 0.02
    assert INPUT_CORR_NOTE < 7
    xc = np.zeros((2, 1, 41))
    xc[1, 0, 7] = -0.14                                  # input u2, output y: 7x the band
    note = _input_correlation_note(SimpleNamespace(crosscorr=xc, band=band), ("u1", "u2"), ("y",))
    assert note is not None and "input u2 (output y: max |r| 0.14, 7x" in note
    assert "zoh_equivalent_input" in note and "closed-loop" in note
    xc[1, 0, 7] = -(INPUT_CORR_NOTE - 0.5) * band      # below the threshold
    assert _input_correlation_note(SimpleNamespace(crosscorr=xc, band=band), ("u1", "u2"),
                                   ("y",)) is None
    xc[0, 0, 0] = np.nan                                 # an undefined correlation: no note
    xc[1, 0, 7] = 10 * band
    assert _input_correlation_note(SimpleNamespace(crosscorr=xc, band=band), ("u1", "u2"),
                                   ("y",)) is None
