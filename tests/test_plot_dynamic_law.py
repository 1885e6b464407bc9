"""plot_dynamic_law: a dynamic law's frequency response with its 95 % band, and law.png.

Plant with a known truth: a mass-spring-damper (m = 2 kg, k = 4 N/m, c = 0.6 N s/m)
whose force F reaches it through an actuator lag 1/(tau s + 1), tau = 0.1 s (pole
-10 1/s). The nominal model lacks the lag, so the error entering ``G d`` is
``B (1/(tau s + 1) - 1) F``: in d's own units ``d = pinv(G) B (1/(tau s + 1) - 1) F``,
whatever channel the trace names (its G fixes the scale).
"""

from __future__ import annotations

import json
from dataclasses import replace

import control as ct
import matplotlib
import numpy as np
import pytest

import greybox as gb
from greybox.exceptions import DataError
from greybox.records import Effect
from greybox.system import named_ss
from greybox.trace.channels import Channel
from greybox.update import Subsystem

matplotlib.use("Agg")

from greybox.plotting import plot_dynamic_law  # noqa: E402

K, C, M, TAU, DT = 4.0, 0.6, 2.0, 0.1, 0.01
BANDWIDTH_HZ = 2.0  # the input's Butterworth cut-off
Q_STD = np.array([0.0, 5e-4])
R_STD = 1e-3


def _nominal():
    A = np.array([[0.0, 1.0], [-K / M, -C / M]])
    B = np.array([[0.0], [1.0 / M]])
    return named_ss(A, B, np.eye(2), np.zeros((2, 1)), 0, states=["pos", "vel"],
                    inputs=["F"], outputs=["pos", "vel"], name="msd")


def _simulate(n, rng, noise):
    """The true plant (states pos, vel, actuator force) discretized by ZOH, driven by
    low-pass noise; process noise on vel (estimation record only), 1e-3 sensor noise."""
    At = np.array([[0.0, 1.0, 0.0], [-K / M, -C / M, 1.0 / M], [0.0, 0.0, -1.0 / TAU]])
    Bt = np.array([[0.0], [0.0], [1.0 / TAU]])
    true = ct.c2d(ct.ss(At, Bt, np.eye(3)[:2], np.zeros((2, 1))), DT, "zoh")
    Ad, Bd = np.asarray(true.A), np.asarray(true.B)[:, 0]
    u = gb.lowpass_noise(n, dt=DT, bandwidth=BANDWIDTH_HZ, amplitude=2.0, rng=rng)
    x, X = np.zeros(3), np.empty((3, n))
    for i in range(n):
        X[:, i] = x
        x = Ad @ x + Bd * u[0, i] + noise * np.r_[Q_STD * rng.standard_normal(2), 0.0]
    return X[:2] + R_STD * rng.standard_normal((2, n)), u


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(0)
    y, u = _simulate(4000, rng, 1.0)
    yv, uv = _simulate(2000, rng, 0.0)
    Q, R = np.diag(Q_STD**2) + 1e-12 * np.eye(2), R_STD**2 * np.eye(2)
    rep = gb.close_the_loop(_nominal(), y, u, yv, uv, Q=Q, R=R, dt=DT, delta=False)
    assert rep.updated and rep.effect.kind == "dynamic", rep.message
    return rep, (y, u, yv, uv, Q, R)


def _truth(rep, w):
    """The true law's transfer from F to d at w [rad/s], in d's units."""
    scale = (np.linalg.pinv(np.asarray(rep.channel.G, float)) @ _nominal().B)[0, 0]
    return scale * (1.0 / (TAU * 1j * w + 1.0) - 1.0)


def _excited(w):
    """Where the record tells the law: above 1 rad/s (6 periods in the 40 s record; below,
    |d| < 0.1 |F| / m fades into the DC cancellation) up to the input's cut-off."""
    return (w >= 1.0) & (w <= 2 * np.pi * BANDWIDTH_HZ)


def test_magnitude_matches_the_true_lag_and_the_band_covers_it(case):
    rep, _ = case
    arts = plot_dynamic_law(rep)
    # the curve from F (a fit may add a weak driver, e.g. vel, on another draw: its own curve)
    j = arts["names"].index((rep.channel.labels[0], "F"))
    w, H = arts["frequency"], arts["response"][j]
    truth, sel = _truth(rep, w), _excited(w)
    assert sel.sum() > 50
    # the pole is marked at the fitted pole, within 6 % of the true -1/tau (its 95 %
    # interval is ~4 %; 8 draws: at most 4 % off), with the record's half-width
    (p, h), = arts["poles"]
    assert abs(p.real + 1 / TAU) < 0.06 / TAU and h == rep.effect.dynamic_law.ci[0]
    # magnitude: d ln|H| / d ln tau = 1/(1 + (tau w)^2) <= 1 and the feedthrough enters
    # |H| at most 1:1, so the law's 95 % intervals (tau ~4 %, e ~2 %) bound the error near
    # 4-5 % (8 draws: at most 2.2 %); 6 % fails a pole 20 % off, or d read in F's units
    # instead of d_vel's (F / m: a factor 2)
    rel = np.abs(np.abs(H[sel]) - np.abs(truth[sel])) / np.abs(truth[sel])
    assert rel.max() < 0.06, rel.max()
    # phase: the same intervals, a few degrees (8 draws: at most 3.5 deg)
    dph = np.degrees(np.angle(H[sel] / truth[sel]))
    assert np.abs(dph).max() < 6.0, np.abs(dph).max()
    # the band (independent draws: conservative) covers the truth over >= 90 % of the
    # excited frequencies, and is informative there: at the pole narrower than 20 % of
    # |H| (intervals of ~4 % on a and b, 2 % on e; 8 draws: 5.4 - 6.7 %)
    lo, hi = arts["band"][:, j]
    covered = (np.abs(truth) >= lo) & (np.abs(truth) <= hi)
    assert covered[sel].mean() >= 0.9, covered[sel].mean()
    at_pole = np.argmin(np.abs(w - 1 / TAU))
    assert (hi - lo)[at_pole] < 0.2 * np.abs(H[at_pole]), (lo[at_pole], hi[at_pole])
    assert "rad/s" in arts["axes"][1].get_xlabel()
    assert "no band" not in arts["axes"][0].get_title()
    arts["figure"].clf()


def test_a_discrete_subsystem_is_drawn_without_band(case):
    """The same law as an update.Subsystem (ZOH-discretized; no intervals): the response is
    the discrete transfer at z = exp(j w dt) (python-control's, to rounding), which stays
    within 6 % of the continuous law below the input's cut-off (the hold delays the filtered
    part half a sample against the feedthrough: ~(dt / 2) / tau = 5 % where the two nearly
    cancel, at low w); no band, and the title says so."""
    rep, _ = case
    dl = rep.effect.dynamic_law
    phi = np.exp(dl.pole * DT)
    sub = Subsystem(
        order=1, Ad=np.array([[phi]]), Bdu=np.array([[dl.b[0] * (phi - 1) / dl.pole]]),
        Bdx=np.zeros((1, 2)), Cd=np.eye(1), Ddu=np.array([[dl.e[0]]]), Ddx=np.zeros((1, 2)),
        K=np.zeros((1, 1)), innovation_cov=np.eye(1), noise_cov=np.eye(1), criterion={},
        method="output-error", feedthrough=True, d_sim=np.zeros((1, 1)),
        input_labels=("F",), state_labels=("pos", "vel"), unknown_labels=("d_vel",))
    rep2 = replace(rep, effect=replace(rep.effect, dynamic_law=None, subsystem=sub))
    arts = plot_dynamic_law(rep2)
    ref = plot_dynamic_law(rep)
    assert arts["names"] == [("d_vel", "F")] and arts["band"] is None
    assert "no band" in arts["axes"][0].get_title()
    w = arts["frequency"]
    assert w.max() <= np.pi / DT * (1 + 1e-9)
    sel = _excited(w)
    H = arts["response"][0]
    Hc = dl.e[0] + dl.b[0] / (1j * w - dl.pole)
    disc = ct.ss(sub.Ad, sub.Bdu, sub.Cd, sub.Ddu, DT)
    np.testing.assert_allclose(H, np.ravel(disc(np.exp(1j * w * DT))), rtol=1e-9)
    np.testing.assert_allclose(np.abs(H[sel]), np.abs(Hc[sel]), rtol=0.06)
    np.testing.assert_allclose(ref["frequency"], w)  # the same pole, the same grid
    (p, h), = arts["poles"]
    assert abs(p.real - dl.pole) < 1e-9 * abs(dl.pole) and np.isnan(h)


def _steady_gain(law, col, w, n_x=2, dt=1e-3, T=12.0):
    """Complex gain from [x; u] column ``col`` to each component of d, read off
    ``law.evaluate`` driven by sin(w t) after its transient (d = Re H sin + Im H cos)."""
    t = np.arange(0, T, dt)
    xu = np.zeros((n_x + 1, t.size))
    xu[col] = np.sin(w * t)
    d = law.evaluate(xu[:n_x], xu[n_x:])
    keep = t > T / 2
    basis = np.vstack([np.sin(w * t[keep]), np.cos(w * t[keep])]).T
    coef = np.linalg.lstsq(basis, d[:, keep].T, rcond=None)[0]
    return coef[0] + 1j * coef[1]


def _report(law):
    ch = Channel(name="pair", G=np.zeros((2, 2)), labels=("d_1", "d_2"), units=("W", "W"))
    eff = Effect(kind="dynamic", order=1, channel="pair", dynamic_law=law)
    return type("R", (), {"effect": eff, "channel": ch, "nominal": None})()


def _shared(ci):
    from greybox.trace.dynamic import SharedLaw

    # z' = -5 z + 2 F; d_1 = z; d_2 = 0.5 z - 0.3 x1 (states x1, x2; input F)
    return SharedLaw(pole=-5.0, tau=0.2, state="z[0]", drivers=("F",), b=np.array([2.0]),
                     k=np.array([1.0, 0.5]), reference=0, feedthrough=((1, "x1", -0.3),),
                     Bz=np.array([0.0, 0.0, 2.0]), E=np.array([[0, 0, 0], [-0.3, 0, 0.0]]),
                     ci=np.asarray(ci, float), npar=4, formula="", model=None,
                     se_estimation=0.0, continuous=None, dt=1e-3)


def _shared2(ci):
    from greybox.trace.shared_order2 import SharedLaw2

    # z_1 = (s + 3) / (s^2 + 8 s + 12) F (poles -2, -6); d_1 = z_1 + 0.4 x2; d_2 = -0.7 z_1
    return SharedLaw2(order=2, poles=np.array([-2.0, -6.0]), pole_ci=np.array([0.1, 0.2]),
                      taus=np.array([0.5, 1 / 6]), alpha=np.array([8.0, 12.0]),
                      states=("z[0]", "z[1]"), drivers=("F",), beta=np.array([[1.0], [3.0]]),
                      k=np.array([1.0, -0.7]), reference=0, feedthrough=((0, "x2", 0.4),),
                      Bz=np.array([[0, 0, 1.0], [0, 0, 3.0]]),
                      E=np.array([[0, 0.4, 0], [0, 0, 0.0]]), ci=np.asarray(ci, float), npar=6,
                      formula="", model=None, se_estimation=0.0, continuous=None, dt=1e-3)


@pytest.mark.parametrize("make, cols, band_on", [
    # SharedLaw ci = (a, b, k_2, e): only k_2 uncertain -> only d_2 / F has a band
    (lambda: _shared([0, 0, 0.1, 0]), {("d_1", "F"): 2, ("d_2", "F"): 2, ("d_2", "x1"): 0},
     ("d_2", "F")),
    # SharedLaw2 ci = (alpha_1, alpha_0, beta_1, beta_0, k_2, e): only e -> only d_1 / x2
    (lambda: _shared2([0, 0, 0, 0, 0, 0.1]),
     {("d_1", "F"): 2, ("d_1", "x2"): 1, ("d_2", "F"): 2}, ("d_1", "x2")),
], ids=["SharedLaw", "SharedLaw2"])
def test_shared_laws_transfer_and_band_follow_their_records(make, cols, band_on):
    """Each curve is the law's own steady-state gain (evaluate driven by a sinusoid, within
    1 %: the hold's half-sample delay is w dt / 2 <= 5e-3 rad up to 10 rad/s), and the band
    sits where the record's one nonzero half-width is (the ci order is read right)."""
    law = make()
    arts = plot_dynamic_law(_report(law), n_freq=60)
    assert sorted(arts["names"]) == sorted(cols)
    w = arts["frequency"]
    for f in [int(np.argmin(np.abs(w - wf))) for wf in (0.7, 3.0, 10.0)]:
        for i, (dn, drv) in enumerate(arts["names"]):
            g = _steady_gain(law, cols[(dn, drv)], w[f])[int(dn[-1]) - 1]
            np.testing.assert_allclose(arts["response"][i, f], g, rtol=0.01, atol=1e-9)
    lo, hi = arts["band"]
    for i, name in enumerate(arts["names"]):
        width = np.max(hi[i] - lo[i])
        assert (width > 1e-3) if name == band_on else (width < 1e-12), (name, width)


def test_a_static_effect_is_refused(case):
    rep, _ = case
    with pytest.raises(DataError, match="not a dynamic law"):
        plot_dynamic_law(replace(rep, effect=replace(rep.effect, kind="static")))


def test_update_cli_writes_the_frequency_response_as_law_png(case, tmp_path, capsys):
    from greybox.cli import main
    from greybox.model_io import model_to_dict

    _, (y, u, yv, uv, Q, R) = case
    model = tmp_path / "model.json"
    model.write_text(json.dumps(model_to_dict(_nominal(), Q, R, Ts=DT)))

    def csv(path, y, u):
        rows = np.vstack([u, y]).T
        path.write_text("F,pos,vel\n" + "\n".join(",".join(f"{v:.12g}" for v in r)
                                                   for r in rows) + "\n")
        return path

    out = tmp_path / "report"
    code = main(["update", str(model), str(csv(tmp_path / "e.csv", y, u)), "--validate",
                 str(csv(tmp_path / "v.csv", yv, uv)), "--out", str(out), "--json"])
    s = json.loads(capsys.readouterr().out)
    assert code == 0 and s["effect"]["kind"] == "dynamic"
    assert list(s["figures"])[0] == "law" and (out / "law.png").stat().st_size > 1000
    assert "![law](law.png)" in (out / "report.md").read_text()
