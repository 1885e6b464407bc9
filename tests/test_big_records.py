"""Memory and time of long records (issue 13, item 5) without changing any result.

* ``hac_covariance`` pads its FFTs to a fast length and forms the long-run
  covariance one pair of terms at a time: it must equal the Newey-West sum
  written out lag by lag, also when 2T has a large prime factor.
* ``close_the_loop`` keeps of a non-chosen channel's filter record only x^
  and d^ (``workflow._light``) and re-filters the chosen one whole
  (``workflow._whole_record``): the report's record equals the filter's.
* ``delta_update(refine_window=...)``: a window that covers the estimation
  part changes nothing; a bad one is refused.
* ``close_the_loop`` searches on the first ``SEARCH_WINDOW`` samples of the
  estimation record (``workflow._search_record``): on a record twice the
  window the same channel and law as on the whole record, and the report's
  trace still has the whole record (``workflow._with_record``).
* ``plant_adapter.LawPlant.simulate``: a sensor law's simulation in one LTI pass equals
  ``simulate_with_law``'s sample loop.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import greybox as gb
from greybox.system import named_ss
from greybox.trace import resolve_channel_spec, trace_channel
from greybox.trace.intervals import hac_covariance
from greybox.update import delta_update
from greybox.workflow import _light, _whole_record, close_the_loop

DT = 0.01


def _osc(k=4.0):
    A = np.array([[0.0, 1.0], [-k, -0.8]])
    return named_ss(A, [[0.0], [1.0]], np.eye(2), np.zeros((2, 1)), 0, states=["x", "v"],
                    inputs=["F"], outputs=["x", "v"], name="osc")


def _records(N, seed=0):
    """Estimation and validation records of the oscillator whose spring is 6 (model: 4)."""
    rng = np.random.default_rng(seed)
    truth = gb.discretize(_osc(6.0), DT)
    Q, R = np.diag([0.0, 1e-8]), 1e-6 * np.eye(2)
    u = gb.lowpass_noise(N, dt=DT, bandwidth=1.0, amplitude=2.0, rng=rng)
    uv = gb.lowpass_noise(2000, dt=DT, bandwidth=1.0, amplitude=2.0, rng=rng)
    y = gb.simulate(truth, u, Q=Q, R=R, rng=rng).y
    yv = gb.simulate(truth, uv, R=R, rng=rng).y
    return y, u, yv, uv, Q + 1e-12 * np.eye(2), R


def _hac_by_lags(jac, resid, nout):
    """Newey-West covariance written out: every lag's Gamma_l by a direct sum."""
    k = jac.shape[1]
    T = resid.size // nout
    r = resid.reshape(nout, T)
    s = np.zeros((T, k))
    for o in range(nout):
        s += jac[o * T:(o + 1) * T] * r[o][:, None]
    rc = r - r.mean(axis=1, keepdims=True)
    acf = np.zeros(T // 4)
    for o in range(nout):
        full = np.array([rc[o, l:] @ rc[o, :T - l] for l in range(T // 4)])
        acf += full / full[0] / nout
    above = np.flatnonzero(np.abs(acf) >= 0.05)
    L = int(min(max(2 * (above[-1] if above.size else 1), 1), T // 4))
    Om = s.T @ s
    for lag in range(1, L + 1):
        gam = s[lag:].T @ s[:T - lag]          # sum_t s[t+l] s[t]^T
        Om += (1.0 - lag / (L + 1.0)) * (gam + gam.T)
    Ji = np.linalg.pinv(jac.T @ jac)
    return Ji @ Om @ Ji, L


@pytest.mark.parametrize("T", [1009, 1200])  # 2T = 2 x prime (the slow FFT length) / smooth
def test_hac_covariance_equals_the_lag_by_lag_sum(T):
    rng = np.random.default_rng(3)
    nout, k = 2, 3
    jac = rng.standard_normal((nout * T, k))
    # coloured residual: a moving average of 7, so the bandwidth is well above 1
    e = rng.standard_normal(nout * T + 6)
    resid = np.convolve(e, np.ones(7) / 7, mode="valid")
    ref, L = _hac_by_lags(jac, resid, nout)
    assert L >= 8  # the lag sum really is exercised (MA(7): acf >= 0.05 up to lag ~6)
    # same sums in a different order (FFT vs direct): round-off only
    np.testing.assert_allclose(hac_covariance(jac, resid, nout), ref, rtol=1e-9, atol=1e-15)


def test_light_trace_is_rebuilt_to_the_same_filter_record():
    y, u, _, _, Q, R = _records(3000)
    sys = gb.discretize(_osc(), DT)
    ch = resolve_channel_spec(sys, None)[1]
    tr = trace_channel(sys, ch, y, u, Q=Q, R=R)
    light = _light(tr)
    res, lres = tr.filter_result, light.filter_result
    # what the choice reads is kept, the rest is gone (no view on the old arrays either)
    assert lres.x_filt is res.x_filt and lres.d_est is res.d_est
    for name in ("t", "x_pred", "d_var", "innovations"):
        assert getattr(lres, name).shape[-1] == 0 and getattr(lres, name).base is None
    whole = _whole_record(light, y, u, Q, R).filter_result
    for f in dataclasses.fields(res):
        a = getattr(res, f.name)
        if isinstance(a, np.ndarray):  # the same filter on the same data: bit for bit
            np.testing.assert_array_equal(getattr(whole, f.name), a, err_msg=f.name)
    assert _whole_record(tr, y, u, Q, R) is tr  # a whole record is left as it is


def test_report_trace_has_the_whole_filter_record():
    y, u, yv, uv, Q, R = _records(3000)
    rep = close_the_loop(_osc(), y, u, yv, uv, Q=Q, R=R, dt=DT, delta=False, max_effects=1)
    assert rep.updated and rep.channel.name == "eq(v)"
    res = rep.trace.filter_result
    assert res.t.shape == (3000,) and res.x_pred.shape == (2, 3000)
    assert res.innovations.shape == (2, 3000) and res.d_var.shape == (1, 3000)
    ref = gb.uikf(rep.trace.model, y, u, unknown=list(rep.trace.channel.labels), Q=Q, R=R)
    np.testing.assert_array_equal(res.d_var, ref.d_var)  # same filter, same data


def test_delta_refine_window_covering_the_record_changes_nothing():
    y, u, _, _, Q, R = _records(2000, seed=1)
    sys = gb.discretize(_osc(), DT)
    a = delta_update(sys, y, u, Q=Q, R=R)
    b = delta_update(sys, y, u, Q=Q, R=R, refine_window=10**6)
    assert a.message == b.message and a.refined == b.refined
    np.testing.assert_array_equal(np.asarray(a.updated.sys.A), np.asarray(b.updated.sys.A))


def test_delta_refine_window_is_checked():
    y, u, _, _, Q, R = _records(400)
    sys = gb.discretize(_osc(), DT)
    with pytest.raises(gb.DataError, match="refine_window must be finite and > 0"):
        delta_update(sys, y, u, Q=Q, R=R, refine_window=0)
    with pytest.raises(gb.DimensionError, match="refine_window must be an integer"):
        delta_update(sys, y, u, Q=Q, R=R, refine_window=2.5)


def test_close_the_loop_refines_the_delta_baseline_on_a_window(monkeypatch):
    import greybox.workflow as wf

    seen = {}
    real = wf.delta_update

    def spy(*args, **kw):
        seen.update(kw)
        return real(*args, **kw)

    monkeypatch.setattr(wf, "delta_update", spy)
    y, u, yv, uv, Q, R = _records(3000)
    rep = close_the_loop(_osc(), y, u, yv, uv, Q=Q, R=R, dt=DT, max_effects=1)
    # 2 outputs: at most 2e5 residuals = 1e5 samples (the record here is shorter: no effect)
    assert seen["refine_window"] == wf.DELTA_REFINE_RESIDUALS // 2 == 100_000
    assert "delta" in rep.table


def test_light_output_channel_is_rebuilt_with_its_own_filter():
    """A sensor channel is traced with the feedthrough filter: its record is rebuilt with
    that filter (the plain one would treat d as a state-equation input)."""
    from greybox.trace.channels import output_channel

    y, u, _, _, Q, R = _records(3000)
    sys = gb.discretize(_osc(), DT)
    tr = trace_channel(sys, output_channel(sys, 0), y, u, Q=Q, R=R)
    whole = _whole_record(_light(tr), y, u, Q, R).filter_result
    for f in dataclasses.fields(tr.filter_result):
        a = getattr(tr.filter_result, f.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(getattr(whole, f.name), a, err_msg=f.name)


def test_search_window_gives_the_same_channel_and_law(monkeypatch):
    """A record twice the search window: the same channel, law and validation SE.

    The window is set to 3000 samples here (1e5 in the library); the gate's BIC
    penalty says which d^ it was computed on (npar log Nd, Nd = samples used).
    """
    import greybox.workflow as wf

    y, u, yv, uv, Q, R = _records(6000, seed=2)
    whole = close_the_loop(_osc(), y, u, yv, uv, Q=Q, R=R, dt=DT, delta=False, max_effects=1)
    monkeypatch.setattr(wf, "SEARCH_WINDOW", 3000)
    win = close_the_loop(_osc(), y, u, yv, uv, Q=Q, R=R, dt=DT, delta=False, max_effects=1)
    for rep in (whole, win):
        assert rep.updated and rep.channel.name == "eq(v)" and rep.effect.kind == "static"
        assert rep.effect.law.npar == 1  # one spring term
    # Nd = N - 1 - k0 samples of d^ (k0: the filter's transient, the same on a prefix)
    nd = [np.exp(r.gate["bic_penalty"] / r.effect.law.npar) for r in (whole, win)]
    assert round(nd[0] - nd[1]) == 3000, nd
    # the law is refined by output error on the first oe_window samples in both: the same
    # terms and, within a part in 1e4 (the least-squares starts differ), the same values
    np.testing.assert_array_equal(win.effect.law.coef != 0, whole.effect.law.coef != 0)
    np.testing.assert_allclose(win.effect.law.coef, whole.effect.law.coef, rtol=1e-4)
    # the same verdict; the validation SE within the coefficients' part in 1e4 (the
    # message prints the SE ratio to 4 digits: 376.5x vs 376.6x is that difference)
    import re

    def words(msg):
        return re.sub(r"[0-9.]+", "#", msg)

    assert words(win.message) == words(whole.message)
    np.testing.assert_allclose(win.table["updated"].se.value, whole.table["updated"].se.value,
                               rtol=1e-3)
    # the report's trace is the whole record's (built at the end)
    assert win.trace.filter_result.t.shape == (6000,)
    assert win.trace.filter_result.innovations.shape == (2, 6000)


def test_sensor_law_simulation_in_one_pass_equals_the_sample_loop():
    from greybox.trace import simulate_with_law
    from greybox.trace.channels import output_channel
    from greybox.plant_adapter import LawPlant

    y, u, _, _, Q, R = _records(3000)
    sys = gb.discretize(_osc(), DT)
    tr = trace_channel(sys, output_channel(sys, 0), y, u, Q=Q, R=R)
    res, law = tr.filter_result, tr.static
    assert law.output == 0 and not np.any(res.G)  # the fast path applies
    x0 = res.x_filt[:, 0]
    ref = simulate_with_law(res.sys, res.G, law, u, x0)
    # a modal recursion vs the sample loop: round-off only
    np.testing.assert_allclose(LawPlant(res.sys, res.G, law, sys).simulate(u, x0), ref,
                               rtol=1e-10,
                               atol=1e-12 * np.abs(ref).max())
    # a law in a state equation feeds back: the sample loop itself
    tr2 = trace_channel(sys, resolve_channel_spec(sys, None)[1], y, u, Q=Q, R=R, max_order=0)
    r2 = tr2.filter_result
    np.testing.assert_array_equal(LawPlant(r2.sys, r2.G, tr2.static, sys).simulate(u, x0),
                                  simulate_with_law(r2.sys, r2.G, tr2.static, u, x0))


def test_delta_baseline_runs_on_the_search_window(monkeypatch):
    import greybox.workflow as wf

    seen = {}
    real = wf.delta_update

    def spy(sys, y, u, **kw):
        seen["shapes"] = (y.shape, u.shape)
        seen["x0"] = kw["x0"]
        return real(sys, y, u, **kw)

    monkeypatch.setattr(wf, "delta_update", spy)
    monkeypatch.setattr(wf, "SEARCH_WINDOW", 2500)
    y, u, yv, uv, Q, R = _records(3000)
    rep = close_the_loop(_osc(), y, u, yv, uv, Q=Q, R=R, dt=DT, max_effects=1)
    assert seen["shapes"] == ((2, 2500), (1, 2500))
    # the initial state of its simulation is the whole record's (a prefix starts alike)
    x0 = gb.estimate_initial_state(gb.discretize(_osc(), DT), y, u)
    np.testing.assert_array_equal(seen["x0"], x0)
    assert "delta" in rep.table and rep.table["delta"].y_sim.shape == (2, 2000)


def test_delta_update_past_its_deadline_fits_nothing_and_says_so():
    """A deadline already passed: no N4SID order, score or refinement is started, and the
    model says what was cut (the report's note), never a half-fitted candidate."""
    import time

    y, u, _, _, Q, R = _records(2000, seed=1)
    dm = delta_update(gb.discretize(_osc(), DT), y, u, Q=Q, R=R, deadline=time.monotonic())
    assert not dm.improved and dm.order == 0
    assert dm.bounded.startswith("stopped at its time budget") and "N4SID" in dm.bounded
    assert dm.message.endswith(dm.bounded)
    # no deadline: nothing cut (the same model as before the deadline existed)
    assert delta_update(gb.discretize(_osc(), DT), y, u, Q=Q, R=R).bounded == ""


def test_default_horizons_keep_the_hankel_factor_small():
    from greybox.update import _MAX_HANKEL_ROWS, _default_horizons

    assert _default_horizons(3) == [10, 40]      # small models: both default horizons
    for width in (11, 33, 65, 129):              # outputs + inputs of 10 to 128-state chains
        hs = _default_horizons(width)
        assert all(2 * h * width <= max(_MAX_HANKEL_ROWS, 4 * width) for h in hs), (width, hs)
        assert hs and min(hs) >= 2


def test_close_the_loop_bounds_the_baseline_and_says_so(monkeypatch):
    """Orders above DELTA_MAX_ORDER and samples above DELTA_WORK's share are cut, and
    the report's note says which; the update itself does not depend on the baseline."""
    import greybox.workflow as wf

    seen = {}
    real = wf.delta_update

    def spy(sys, y, u, **kw):
        seen.update(kw, steps=y.shape[1])
        return real(sys, y, u, **kw)

    monkeypatch.setattr(wf, "delta_update", spy)
    monkeypatch.setattr(wf, "DELTA_MAX_ORDER", 3)   # n + 6 = 8 for the oscillator
    monkeypatch.setattr(wf, "DELTA_WORK", 81 * 2500.0)  # ((n+1) order m)^2 = 81: 2500 steps
    y, u, yv, uv, Q, R = _records(3000)
    rep = close_the_loop(_osc(), y, u, yv, uv, Q=Q, R=R, dt=DT, max_effects=1)
    assert seen["max_order"] == 3 and seen["steps"] == 2500 and seen["deadline"] is not None
    note = [s for s in rep.notes if s.startswith("parallel delta baseline bounded")]
    assert len(note) == 1 and "orders up to 3 (of n + 6 = 8)" in note[0], rep.notes
    assert "the first 2500 samples (of 3000)" in note[0]
    skip = close_the_loop(_osc(), y, u, yv, uv, Q=Q, R=R, dt=DT, max_effects=1, delta=False)
    assert "delta" in rep.table and "delta" not in skip.table
    assert skip.message == rep.message  # the verdict never depends on the baseline


def test_a_diverged_candidate_scores_inf_and_does_not_end_the_run():
    """A candidate's simulation at 1e252 (finite, beyond the magnitude check) is an
    infinite SE, not a DataError out of close_the_loop (found on a fleet unit)."""
    from greybox.workflow import _se

    y = np.ones((1, 100))
    assert _se(y, 1e252 * np.ones((1, 100)), 20) == np.inf
    assert _se(y, np.full((1, 100), np.nan), 20) == np.inf
    assert _se(y, y, 20) == 0.0
