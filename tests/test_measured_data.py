"""Real measured data (../shared/data): EMPS's omitted Coulomb friction, Silverbox's cubic.

Skipped when the data folder is absent. Nominal models and choices as in
tutorials/04_emps.py and 06_silverbox.py (EMPS: published M, Fv, gtau; R from the
encoder step; Q_vv from the nominal force residual; estimation
DATA_EMPS[0:8000]. Silverbox: linear parameters by output error on the
low-amplitude arrow, the input's ZOH equivalent (zoh_equivalent_input: the
input is band-limited, not held), R from the noise floor).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import greybox as gb
from greybox import forward_selection
from greybox.system import named_ss
from greybox.trace import (
    aligned,
    law_terms,
    resolve_channel_spec,
    trace_channel,
)
from greybox.trace.intervals import hac_covariance

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "emps"
SILVER = DATA.parent / "silverbox" / "SNLS80mV.csv"
pytestmark = pytest.mark.skipif(not (DATA / "DATA_EMPS.npz").is_file(),
                                reason="measured data ../shared/data/emps not present")

M, FV, FC_PUBLISHED = 95.1089, 203.5034, 20.3935
DT = 1e-3


@pytest.fixture(scope="module")
def emps():
    z = np.load(DATA / "DATA_EMPS.npz")
    q, vir, gtau = z["qm"], z["vir"], float(z["gtau"])
    steps = np.diff(np.unique(q))
    R = np.array([[steps[steps > 1e-12].min() ** 2 / 12]])
    v = np.gradient(q, DT)
    res = M * np.gradient(v, DT) + FV * v - gtau * vir
    Q = np.diag([0.0, np.var(res / M * DT)])
    sys = named_ss([[0, 1], [0, -FV / M]], [[0], [gtau / M]], [[1, 0]], [[0]], 0,
                   states=["q", "v"], inputs=["vir"], outputs=["q"])
    return sys, q, vir, gtau, Q, R


def test_nominal_model_error_is_detected(emps):
    sys, q, vir, _, Q, R = emps
    est, val = slice(0, 8000), slice(12000, 20000)
    rep = gb.close_the_loop(sys, q[None, est], vir[None, est], q[None, val], vir[None, val],
                            Q=Q, R=R, dt=DT, max_order=0, delta=False)
    # the linear model misses ~20 N of friction on a ~680 N-RMS drive force: the
    # one-step residual is far from white (p << alpha)
    assert rep.model_error_detected
    assert rep.residual.pvalue[0] < 1e-6


def test_coulomb_friction_from_averaged_d_hat(emps):
    sys, q, vir, gtau, Q, R = emps
    est = slice(0, 8000)
    ch = [c for c in resolve_channel_spec(sys, None) if c.name == "eq(v)"][0]
    tr = trace_channel(sys, ch, q[None, est], vir[None, est], Q=Q, R=R, dt=DT, max_order=0)
    d = tr.filter_result.d_est[0, 50:-1]
    x = tr.filter_result.x_filt[:, 50:-1]
    # d^ of a position-only, relative-degree-2 channel alternates at Nyquist
    assert np.corrcoef(d[1:], d[:-1])[0, 1] < -0.9
    d2, x2 = 0.5 * (d[1:] + d[:-1]), 0.5 * (x[:, 1:] + x[:, :-1])
    terms, spec, _ = law_terms(x2, vir[None, 51:est.stop - 1], ["q", "v"], ["vir"])
    law = forward_selection(terms, d2, [s[0] for s in spec], min_drop=1e-4, prune=True)
    coef = dict(zip(law.names, law.coef))
    # the first (strongest) term is the Coulomb friction, with the published magnitude:
    # published IDIM-LS values are 20.14 / 20.63 N (asymmetric model) and 20.39 N
    # (symmetric); 15 % covers that spread plus the tanh smoothing of sign(v)
    assert law.names[0] == "sign(v)"
    Fc = -M * coef["sign(v)"]
    assert abs(Fc - FC_PUBLISHED) < 0.15 * FC_PUBLISHED, Fc
    # friction asymmetry (Fv- - Fv+)/2 = 36.86 N s/m published: the |v| term
    assert "|v|" in coef and 25 < M * coef["|v|"] < 50


def test_delayed_smoothed_d_hat_gives_fc_and_offset_with_intervals(emps):
    """eq(v) with only q measured: relative degree 2, no alternating d^, Fc with its interval."""
    sys, q, vir, gtau, Q, R = emps
    est = slice(0, 8000)
    ch = [c for c in resolve_channel_spec(sys, None) if c.name == "eq(v)"][0]
    tr = trace_channel(sys, ch, q[None, est], vir[None, est], Q=Q, R=R, dt=DT, max_order=0)
    assert tr.relative_degree == 2 and tr.law_estimate.smoothed
    assert not any("alternates" in s for s in tr.notes)
    law = tr.static
    names = [s[0] for s in law.spec]
    j = names.index("sign(v)")
    fc, hfc = -M * law.coef[0, j], M * law.ci[0, j]
    # measured 20.49 +- 0.32 N: the published 20.39 N (symmetric IDIM-LS) lies inside
    assert abs(fc - FC_PUBLISHED) <= hfc, (fc, hfc)
    assert 0 < hfc < 1.0
    # the friction asymmetry (|v| term, published (Fv- - Fv+)/2 = 36.86 N s/m) inside its
    # interval too (measured 37.4 +- 3.3)
    j = names.index("|v|")
    assert abs(M * law.coef[0, j] - 36.86) <= M * law.ci[0, j]
    # the offset: the published model (Fc sign(v) + offset, no |v|) on the same d^ and
    # aligned terms, with HAC intervals: -2.92 +- 0.57 N against the published -3.16 N
    res = tr.law_estimate
    w, _ = gb.input_weights(tr.model, unknown=list(ch.labels), r=2,
                            continuous=(np.asarray(sys.A), ch.G))
    k0, K = 50, 7000
    xs = res.x_filt[:, k0:k0 + K + len(w) - 1]
    X = aligned(np.vstack([np.tanh(xs[1] / law.eps[1]), np.ones(xs.shape[1])]), w[:, 0, 0])
    d = res.d_est[0, k0:k0 + K]
    th = np.linalg.lstsq(X.T, d, rcond=None)[0]
    half = 1.96 * np.sqrt(np.diag(hac_covariance(X.T, d - th @ X, 1)))
    assert abs(-M * th[1] - (-3.16)) <= M * half[1], (-M * th[1], M * half[1])
    assert abs(-M * th[0] - FC_PUBLISHED) <= M * half[0]
    # why the trace names |v| and not the offset: without |v| the constant absorbs the mean
    # of the friction asymmetry term. The law's |v| term averaged over the same samples is
    # -2.9 N, the forced offset's value to within its interval (published: -(Fv- - Fv+)/2
    # mean|v| + (Fc+ - Fc-)/2 = -2.92 - 0.24 = -3.16 N, the symmetric model's offset)
    v_abs = float(np.mean(np.abs(aligned(xs[1:2], w[:, 0, 0])[0])))
    as_offset = -M * law.coef[0, names.index("|v|")] * v_abs
    assert abs(as_offset - (-M * th[1])) <= M * half[1], (as_offset, -M * th[1], M * half[1])


def test_close_the_loop_finds_the_coulomb_friction(emps):
    """The one call finds eq(v), a static law with sign(v), Fc near the published value."""
    sys, q, vir, _, Q, R = emps
    est, val = slice(0, 8000), slice(12000, 20000)
    rep = gb.close_the_loop(sys, q[None, est], vir[None, est], q[None, val], vir[None, val],
                            Q=Q, R=R, dt=DT, max_order=1, delta=False)
    assert rep.updated and rep.effect.equations == ("v",) and rep.effect.kind == "static"
    law = rep.effect.law
    names = [s[0] for s in law.spec]
    fc = -law.coef[0, names.index("sign(v)")] * M
    # published 20.14-20.63 N; tanh smoothing of sign(v) and the co-selected
    # |v| and v^3 terms move it by a few percent: +-15 %
    assert abs(fc - FC_PUBLISHED) < 0.15 * FC_PUBLISHED, fc
    se0, se1 = rep.table["nominal"].se.value, rep.table["updated"].se.value
    assert se0 / se1 >= 3.0, (se0, se1)  # measured 74 % -> 4.0 %


@pytest.fixture(scope="module")
def silverbox():
    from scipy.optimize import least_squares
    from scipy.signal import lfilter, welch
    if not SILVER.is_file():
        pytest.skip("silverbox data not present")
    u_raw, y = np.loadtxt(SILVER, delimiter=",", skiprows=1, usecols=(0, 1)).T
    dt = 2**14 / 1e7
    u_mid = np.r_[0.5 * (u_raw[:-1] + u_raw[1:]), u_raw[-1]]

    def oe_linear(p, uu):
        w2, c, b, off = p
        sd = gb.discretize(named_ss([[0, 1], [-w2, -c]], [[0], [b]], [[1, 0]], [[0]], 0,
                                    states=["y", "v"], inputs=["u"], outputs=["y"]), dt)
        A, B = np.asarray(sd.A), np.asarray(sd.B)[:, 0]
        num = np.r_[0, B[0], A[0, 1] * B[1] - A[1, 1] * B[0]]
        return lfilter(num, np.poly(A), uu - off)

    lo = slice(100, 8100)
    w0 = 2 * np.pi * 69.0
    p0 = [w0**2, 2 * 0.044 * w0, w0**2, float(np.mean(u_raw))]
    def nominal(p):
        return named_ss([[0, 1], [-p[0], -p[1]]], [[0], [p[2]]], [[1, 0]], [[0]], 0,
                        states=["y", "v"], inputs=["u"], outputs=["y"])

    p = least_squares(lambda p: (oe_linear(p, u_mid[lo]) - y[lo])[200:], p0, x_scale="jac").x
    # the input is band-limited (README: filtered noise, multisines), not held: the
    # held input under which the ZOH model responds as the continuous one, then the
    # nominal refitted with it (a fixed point after this one step: 1e-6 relative)
    u_eq = gb.zoh_equivalent_input(nominal(p), u_raw, dt)[0]
    w2, c_d, b_in, off = least_squares(lambda q: (oe_linear(q, u_eq[lo]) - y[lo])[200:], p,
                                       x_scale="jac").x
    f, Py = welch(y[40650:127400], 1 / dt, nperseg=4096)
    R = np.array([[Py[(f > 210) & (f < 260)].mean() * f[-1]]])
    return (nominal((w2, c_d, b_in)), y, u_eq - off, np.diag([0.0, 1e-3]), R, dt,
            u_mid - off)


def test_silverbox_midpoint_held_input_is_flagged(silverbox):
    """The same nominal fed the midpoint held instead of the ZOH equivalent: the law still
    takes y^3, but the updated model's residuals correlate with u (16.5x the band, measured)
    and the report says how the input may be fed."""
    sys, y, _, Q, R, dt, u_mid = silverbox
    est, val = slice(40650, 48650), slice(49050, 57050)
    rep = gb.close_the_loop(sys, y[None, est], u_mid[None, est], y[None, val],
                            u_mid[None, val], Q=Q, R=R, dt=dt, max_order=1, delta=False)
    assert rep.updated and rep.effect.equations == ("v",), rep.message
    note = [n for n in rep.notes if "correlate with input u" in n]
    assert len(note) == 1 and "zoh_equivalent_input" in note[0], rep.notes


def test_close_the_loop_parallel_row_is_no_worse_than_the_nominal(emps):
    """Issue 9 (a): the delta row on closed-loop EMPS data beats the nominal row, or
    says "no improvement found" and shows the nominal; and close_the_loop's call (the
    nominal's estimated x0) picks the model the direct call (from rest) picks."""
    sys, q, vir, _, Q, R = emps
    est, val = slice(0, 8000), slice(12000, 20000)
    y, u, yv, uv = q[None, est], vir[None, est], q[None, val], vir[None, val]
    rep = gb.close_the_loop(sys, y, u, yv, uv, Q=Q, R=R, dt=DT, max_order=0, delta=True)
    lines = [s for s in rep.notes if s.startswith("parallel model:")]
    assert len(lines) == 1, rep.notes
    se_nom, se_delta = rep.table["nominal"].se.value, rep.table["delta"].se.value
    if "no improvement found" in lines[0]:
        assert se_delta == se_nom
    else:
        # measured 74.0 % -> 13.4 % (was 161 %: an estimated x0's start-up spike in the
        # whitened errors set N_eff = N and BIC chose order 6; and the delta row's x0
        # was estimated with its slow delta modes from 80 samples); 74 % is the
        # nominal's level, so a row that does not beat it fails
        assert se_delta < se_nom, (se_delta, se_nom)
    # the cause, pinned: the same candidate with the nominal's estimated x0 as from rest
    nominal = gb.discretize(sys, DT)
    x0 = gb.estimate_initial_state(nominal, y, u)
    d_rest = gb.delta_update(nominal, y, u, Q=Q, R=R)
    d_x0 = gb.delta_update(nominal, y, u, Q=Q, R=R, x0=x0)
    assert (d_rest.improved, d_rest.order, d_rest.marginal) == \
        (d_x0.improved, d_x0.order, d_x0.marginal)
