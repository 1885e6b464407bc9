"""greybox.trace: candidate channels, channel models, static/dynamic laws, notes.

The plant is a discrete mass-spring-damper (states p, v; force F; dt = 0.05 s)
whose true dynamics add a known error in the v equation, exactly in discrete
time, so the law greybox should find is known without a ZOH approximation:

* static: ``d[k] = -0.05 p[k]`` (a missing spring);
* dynamic: ``d[k] = -z[k]``, ``z[k+1] = 0.8 z[k] + 0.2 v[k]`` (a lagged damper).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest
import scipy.linalg as sla

import greybox as gb
from greybox.system import discretize, named_ss
from greybox.trace import (
    Channel,
    StaticLaw,
    channel_model,
    default_channels,
    law_terms,
    parameter_notes,
    predict_with_law,
    resolve_channel_spec,
    simulate_with_law,
    trace_channel,
)

DT = 0.05
AC = np.array([[0.0, 1.0], [-4.0, -0.4]])
BC = np.array([[0.0], [1.0]])
Q = np.diag([1e-10, 1e-7])
R = 1e-6 * np.eye(2)
C_SPRING = -0.05                        # static law d = C_SPRING * p [v units / sample]
A_LAG, B_LAG = 0.8, 0.2                 # dynamic law d = -z, z+ = A_LAG z + B_LAG v


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def msd(dt=0.0, measured=("p", "v")):
    C = np.eye(2)[[["p", "v"].index(s) for s in measured]]
    return named_ss(AC, BC, C, np.zeros((len(measured), 1)), dt, states=["p", "v"],
                    inputs=["F"], outputs=list(measured), name="msd")


def nominal_discrete():
    return discretize(msd(), DT)


@lru_cache(maxsize=None)
def plant_data(kind: str, N: int = 3000, seed: int = 4):
    """(y, u) of the true plant; cached, the arrays are not modified by the tests."""
    rng = np.random.default_rng(seed)
    nd = nominal_discrete()
    A, B = np.asarray(nd.A), np.asarray(nd.B)
    u = gb.lowpass_noise(N, dt=DT, bandwidth=3.0, amplitude=1.0, rng=rng)
    x, z, y = np.zeros(2), 0.0, np.zeros((2, N))
    for k in range(N):
        y[:, k] = x
        d = C_SPRING * x[0] if kind == "static" else -z
        xn = A @ x + B[:, 0] * u[0, k] + np.array([0.0, d]) \
            + np.sqrt(np.diag(Q)) * rng.standard_normal(2)
        z = A_LAG * z + B_LAG * x[1]
        x = xn
    return y + 1e-3 * rng.standard_normal((2, N)), u


# --------------------------------------------------------------------------- channels
def test_default_channels_singles_and_pairs():
    four = named_ss(np.eye(4), np.ones((4, 1)), np.eye(4)[:2], np.zeros((2, 1)), 0,
                    states=["a", "b", "c", "e"], inputs=["u"], outputs=["a", "c"])
    chans = default_channels(four)
    assert [c.name for c in chans[:4]] == ["eq(a)", "eq(b)", "eq(c)", "eq(e)"]
    # 4 singles, the input (enters 4 rows), C(4, 2) pairs, the 2 outputs' sensor channels
    assert len(chans) == 4 + 1 + 6 + 2
    assert [c.name for c in chans[-2:]] == ["output(a)", "output(c)"]
    inp = chans[4]
    assert inp.name == "input(u)" and inp.kind == "input" and inp.input == "u"
    assert inp.equations == ("a", "b", "c", "e") and inp.units == ("[u]",)
    np.testing.assert_array_equal(inp.G, np.ones((4, 1)))
    pair = chans[5]
    assert pair.name == "eq(a)+eq(b)" and pair.md == 2 and pair.equations == ("a", "b")
    np.testing.assert_array_equal(pair.G, np.eye(4)[:, :2])
    assert pair.labels == ("d_a", "d_b") and pair.units == ("[a]/s", "[b]/s")
    assert len(default_channels(four, pairs=False, outputs=False)) == 5
    assert len(default_channels(four, pairs=False, inputs=False, outputs=False)) == 4
    # one output: md = 2 cannot satisfy rank(C G) = 2, so no pairs even if asked
    one = named_ss(np.eye(2), np.ones((2, 1)), [[1.0, 0.0]], [[0.0]], 0.1,
                   states=["a", "b"], inputs=["u"], outputs=["a"])
    assert [c.name for c in default_channels(one, pairs=True)] == ["eq(a)", "eq(b)", "input(u)",
                                                                   "output(a)"]
    assert default_channels(one)[0].units == ("[a]/sample",)
    with pytest.raises(gb.DataError, match="pairs must be True, False or 'auto'"):
        default_channels(four, pairs="yes")


def test_resolve_channel_spec_names_and_G_columns():
    sys = msd()
    (v,) = resolve_channel_spec(sys, ["v"])
    assert v.name == "eq(v)" and v.equations == ("v",)
    np.testing.assert_array_equal(v.G, [[0.0], [1.0]])
    assert resolve_channel_spec(sys, "v") == (v,)            # a bare name, not letters
    (both,) = resolve_channel_spec(sys, [("p", "v")])
    assert both.md == 2 and both.equations == ("p", "v")
    named = resolve_channel_spec(sys, {"force": [0.0, 2.0], "pv": ["p", "v"],
                                       "two": [[1.0, 0.0], [0.0, 1.0]]})
    force, pv, two = named
    assert force.name == "force" and force.labels == ("force",) and force.equations == ("v",)
    np.testing.assert_array_equal(force.G, [[0.0], [2.0]])
    assert pv.name == "pv" and pv.md == 2 and pv.labels == ("d_p", "d_v")
    assert two.labels == ("two[0]", "two[1]") and two.md == 2
    assert resolve_channel_spec(sys, [v]) == (v,)             # records pass through
    assert [c.name for c in resolve_channel_spec(sys, None)] == ["eq(p)", "eq(v)", "eq(p)+eq(v)",
                                                                 "output(p)", "output(v)"]


@pytest.mark.parametrize("spec, match", [
    (["w"], r"no state named \['w'\]; states are \['p', 'v'\]"),
    ([("p", "w")], r"no state named \['w'\]"),
    ({"g": [1.0, 0.0, 0.0]}, r"channels\['g'\] has shape \(3, 1\); expected \(2,\) or \(2, md\)"),
    ({"g": [np.nan, 1.0]}, "contains NaN or inf"),
    ({"g": {"a": 1}}, "must be a G matrix or state names"),
    ([], "at least one candidate channel"),
], ids=["name", "name-in-tuple", "G-shape", "G-nan", "G-type", "empty"])
def test_resolve_channel_spec_errors(spec, match):
    with pytest.raises(gb.DimensionError, match=match):
        resolve_channel_spec(msd(), spec)


def test_channel_model_is_one_zoh_of_u_and_d():
    sys = msd()
    (ch,) = resolve_channel_spec(sys, {"force": [0.0, 2.0]})
    m = channel_model(sys, ch, DT)
    assert m.dt == DT
    assert list(m.input_labels) == ["F", "force"]
    assert list(m.state_labels) == ["p", "v"]
    # oracle: ZOH of [B, G] from the matrix exponential of the augmented generator
    M = np.zeros((4, 4))
    M[:2, :2], M[:2, 2:] = AC, np.hstack([BC, ch.G])
    E = sla.expm(M * DT)
    np.testing.assert_allclose(m.A, E[:2, :2], rtol=1e-12, atol=1e-14)   # both exact ZOH
    np.testing.assert_allclose(m.B, E[:2, 2:], rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(m.D, np.zeros((2, 2)))
    # a discrete model is used as is (its d acts per sample)
    nd = nominal_discrete()
    (vd,) = resolve_channel_spec(nd, ["v"])
    md = channel_model(nd, vd)
    np.testing.assert_array_equal(md.A, nd.A)
    np.testing.assert_array_equal(md.B, np.hstack([nd.B, [[0.0], [1.0]]]))
    assert vd.units == ("[v]/sample",) and ch.units == ("",)
    with pytest.raises(gb.ModelError, match="give the sampling period dt"):
        channel_model(sys, ch)
    with pytest.raises(gb.ModelError, match="disagrees with the discrete model's dt"):
        channel_model(nd, vd, dt=0.1)
    with pytest.raises(gb.DimensionError, match=r"has G of shape \(3, 1\)"):
        channel_model(sys, Channel("bad", np.ones((3, 1)), ("bad",)), DT)


# --------------------------------------------------------------------------- tracing
def test_trace_channel_static_law():
    y, u = plant_data("static")
    nd = nominal_discrete()
    (ch,) = resolve_channel_spec(nd, ["v"])
    tr = trace_channel(nd, ch, y, u, Q=Q, R=R, max_order=0)
    assert tr.status == "ok" and tr.dynamic is None
    law = tr.static
    assert law.npar == 1 and not law.nonlinear
    j = [s[0] for s in law.spec].index("p")
    # d^ error ~1.4e-3 per sample on p ~ 0.1 over 3000 samples: standard error of the
    # coefficient ~ 1e-3 relative; 1 % is > 5 of them
    np.testing.assert_allclose(law.coef[0, j], C_SPRING, rtol=0.01)
    np.testing.assert_allclose(law.Ddx, [[law.coef[0, j], 0.0]], rtol=0, atol=0)
    c, h = law.coef[0, j], law.ci[0, j]
    assert law.formula == f"d_v = -({abs(c):.3g} ± {h:.2g})*p [v]/sample"
    # the 95 % interval covers the truth and is not vacuous (< 1 % of the value)
    assert abs(c - C_SPRING) <= h < 0.01 * abs(C_SPRING)
    assert law.time_base == "discrete"  # a discrete nominal model: the law stays discrete
    assert law.bic_gain > 0
    # the static model folds the law into A: A[v, p] moves by the coefficient
    sm = tr.static_model.sys
    np.testing.assert_allclose(sm.A[1, 0] - nd.A[1, 0], law.coef[0, j], rtol=1e-12)


def test_trace_channel_dynamic_law_matches_true_augmented_poles():
    y, u = plant_data("dynamic")
    nd = nominal_discrete()
    (ch,) = resolve_channel_spec(nd, ["v"])
    tr = trace_channel(nd, ch, y, u, Q=Q, R=R, max_order=1)
    assert tr.dynamic is not None and tr.dynamic.order == 1
    A_true = np.block([[np.asarray(nd.A), np.array([[0.0], [-1.0]])],
                       [np.array([[0.0, B_LAG, A_LAG]])]])
    ev = np.sort_complex(np.linalg.eigvals(tr.dynamic_model.sys.A))
    ev_true = np.sort_complex(np.linalg.eigvals(A_true))
    # invariant (the subsystem's own coordinates are not unique); measured error
    # ~1e-5, 1e-3 is still 0.1 % of the pole radius
    np.testing.assert_allclose(ev, ev_true, atol=1e-3)
    # a static law cannot hold the lag: its model has no pole near the lag's (0.986) and
    # misses the others by far more (its output-error refit, a linear law in p and v, puts
    # the oscillatory pair 2e-3 off; the dynamic model's error is ~1e-5)
    ev_s = np.sort_complex(np.linalg.eigvals(tr.static_model.sys.A))
    lag = ev_true[np.argmin(np.abs(ev_true.imag))]
    assert np.min(np.abs(ev_s - lag)) > 1e-2
    miss_s = np.min(np.abs(ev_s[:, None] - ev_true[None, :]), axis=1).max()
    miss_d = np.min(np.abs(ev[:, None] - ev_true[None, :]), axis=1).max()
    assert miss_s > 10 * miss_d, (miss_s, miss_d)


def test_trace_channel_skips_unobservable_channel():
    sys = msd(measured=("p",))
    nd = discretize(sys, DT)
    y, u = plant_data("static")
    # p measured, error in both equations: rank(C G) = 1 < md = 2
    (pair,) = resolve_channel_spec(nd, [("p", "v")])
    tr = trace_channel(nd, pair, y[:1], u, Q=Q, R=R[:1, :1])
    assert tr.status == "skipped" and "rank" in tr.reason and tr.static is None
    # eq(v) with only p measured: C G = 0 for a discrete model (v reaches p a sample later)
    (v,) = resolve_channel_spec(nd, ["v"])
    tr = trace_channel(nd, v, y[:1], u, Q=Q, R=R[:1, :1])
    assert tr.status == "skipped"


def test_trace_channel_errors():
    nd = nominal_discrete()
    (ch,) = resolve_channel_spec(nd, ["v"])
    y, u = plant_data("static")
    with pytest.raises(gb.DataError, match="samples left after skipping 2990"):
        trace_channel(nd, ch, y, u, Q=Q, R=R, skip=2990, max_order=0)
    with pytest.raises(gb.DataError, match="skip must be finite and >= 0"):
        trace_channel(nd, ch, y, u, Q=Q, R=R, skip=-1)
    with pytest.raises(gb.ModelError, match="give the sampling period dt"):
        trace_channel(msd(), ch, y, u, Q=Q, R=R)


# --------------------------------------------------------------------------- laws
def _law(spec, eps, coef, n=2, m=1):
    coef = np.atleast_2d(np.asarray(coef, dtype=float))
    coef = np.pad(coef, ((0, 0), (0, len(spec) - coef.shape[1])))  # unlisted terms (offset): 0
    return StaticLaw(spec=tuple(spec), eps=eps, coef=coef, Ddx=coef[:, :n],
                     Ddu=coef[:, n:n + m], nonlinear=bool(np.any(coef[:, n + m:])),
                     residual_var=np.zeros(coef.shape[0]), bic_gain=0.0,
                     npar=int(np.count_nonzero(coef)), formula="")


def _spec(rng, N=50):
    x, u = rng.standard_normal((2, N)), rng.standard_normal((1, N))
    _, spec, eps = law_terms(x, u, ["p", "v"], ["F"])
    # the tests below list coefficients by position in the library before the signed
    # square v*|v| joined it
    return [s for s in spec if s[1] != "x|x|"], eps


def test_law_terms_names_and_values(rng):
    x, u = rng.standard_normal((2, 40)), rng.standard_normal((1, 40))
    T, spec, eps = law_terms(x, u, ["p", "v"], ["F"])
    names = [s[0] for s in spec]
    assert names == ["p", "v", "F", "p^3", "sign(p)", "|p|", "p*|p|", "v^3", "sign(v)", "|v|",
                     "v*|v|", "p*F", "v*F", "1"]
    np.testing.assert_allclose(eps, 0.05 * np.sqrt(np.mean(x**2, axis=1)), rtol=1e-12)
    # the cube is two products (v*v*v, 10x faster than pow at a simulation's column
    # counts): within 2 roundings of the correctly rounded cube
    np.testing.assert_allclose(T[names.index("p^3")], x[0] ** 3, rtol=3e-16, atol=0)
    np.testing.assert_array_equal(T[names.index("sign(v)")], np.tanh(x[1] / eps[1]))
    np.testing.assert_array_equal(T[names.index("|p|")], np.abs(x[0]))
    np.testing.assert_array_equal(T[names.index("v*|v|")], x[1] * np.abs(x[1]))
    np.testing.assert_array_equal(T[names.index("1")], 1.0)  # the offset term
    np.testing.assert_array_equal(T[names.index("v*F")], x[1] * u[0])  # bilinear product
    T2, spec2, _ = law_terms(x, u, ["p", "v"], ["F"], nonlinear=False)
    assert [s[0] for s in spec2] == ["p", "v", "F"] and T2.shape == (3, 40)


def test_parameter_notes_right_parameter_and_percentage(rng):
    nd = nominal_discrete()
    spec, eps = _spec(rng)
    (v,) = resolve_channel_spec(nd, ["v"])
    a_vp, b_vf = float(nd.A[1, 0]), float(nd.B[1, 0])
    # p term: re-scales A[v, p] by -0.05 / a_vp; F term: re-scales B[v, F] by +10 %
    law = _law(spec, eps, [[-0.05, 0.0, 0.1 * b_vf] + [0.0] * 6])
    notes = parameter_notes(nd, v, law)
    assert len(notes) == 2
    assert notes[0].startswith("A[v; p] = ") and notes[1].startswith("B[v; F] = ")
    assert f"({100 * -0.05 / a_vp:+.1f}%)" in notes[0]
    assert "(+10.0%)" in notes[1]
    # p's column of A is zero in the p equation: a missing term, not a re-scaling
    (p,) = resolve_channel_spec(nd, {"pch": [1.0, 0.0]})
    law_v = _law(spec, eps, [[0.0, 0.0, 0.0] + [0.0] * 6])
    assert parameter_notes(nd, p, law_v) == ()
    cont = msd()
    (pc,) = resolve_channel_spec(cont, ["p"])
    notes = parameter_notes(cont, pc, _law(spec, eps, [[0.3, 0.0, 0.0] + [0.0] * 6]))
    assert notes == ("A[p; p] is 0 in the model; the data want 0.3 (a missing term)",)
    # nonlinear terms say nothing about A, B
    assert parameter_notes(nd, v, _law(spec, eps, [[0.0] * 3 + [1.0] + [0.0] * 5])) == ()


def _loop(A, B, C, D, G, f, u, x0, K=None, y=None):
    """Plain reference loop: x+ = A x + B u + G f(x, u) (filtered if K is given)."""
    x, out = np.array(x0, dtype=float), []
    for k in range(u.shape[1]):
        yk = C @ x + D @ u[:, k]
        out.append(yk)
        if K is not None:
            x = x + K @ (y[:, k] - yk)
        x = A @ x + B @ u[:, k] + G @ f(x, u[:, k])
    return np.array(out).T


def test_simulate_and_predict_with_law_match_a_plain_loop(rng):
    nd = nominal_discrete()
    A, B, C, D = (np.asarray(a) for a in (nd.A, nd.B, nd.C, nd.D))
    G = np.array([[0.0], [1.0]])
    spec, eps = _spec(rng)
    law = _law(spec, eps, [[-0.05, 0.0, 0.0, -0.3, 0.0, 0.0, 0.0, 0.01, 0.0]])

    def f(x, u):
        return np.array([-0.05 * x[0] - 0.3 * x[0] ** 3 + 0.01 * np.tanh(x[1] / eps[1])])

    u = rng.standard_normal((1, 300))
    x0 = [0.5, -0.2]
    ys = simulate_with_law(nd, G, law, u, x0)
    # same arithmetic in a different order: agreement to round-off
    np.testing.assert_allclose(ys, _loop(A, B, C, D, G, f, u, x0), rtol=1e-10, atol=1e-13)
    y = ys + 0.01 * rng.standard_normal(ys.shape)
    K = np.array([[0.3, 0.05], [0.1, 0.4]])
    yp = predict_with_law(nd, G, law, y, u, K, x0)
    np.testing.assert_allclose(yp, _loop(A, B, C, D, G, f, u, x0, K=K, y=y),
                               rtol=1e-10, atol=1e-13)
    # reduction: with K = 0 the one-step predictor is the simulation
    np.testing.assert_allclose(predict_with_law(nd, G, law, y, u, np.zeros((2, 2)), x0), ys,
                               rtol=1e-12, atol=1e-15)


def test_simulate_and_predict_with_law_stop_at_divergence(rng):
    nd = nominal_discrete()
    G = np.array([[0.0], [1.0]])
    spec, eps = _spec(rng)
    law = _law(spec, eps, [[0.0, 0.0, 0.0, 50.0, 0.0, 0.0, 0.0, 0.0, 0.0]])  # +50 p^3
    u = np.zeros((1, 200))
    x0 = [1.0, 0.0]
    with np.errstate(all="raise"):      # no overflow on the way
        ys = simulate_with_law(nd, G, law, u, x0)
        yp = predict_with_law(nd, G, law, ys * 0, u, np.zeros((2, 2)), x0)
    k = int(np.argmax(np.isnan(ys[0])))
    assert 0 < k < 200 and np.all(np.isnan(ys[:, k:]))
    np.testing.assert_array_equal(np.isnan(yp), np.isnan(ys))
