"""Five real measured sets (tutorials 04, 06-09): what greybox says, before/after.

Each set's tutorial runs once (a subprocess, as a user runs it; one xdist
group per set) and writes a JSON summary; the tests assert on it: the
channel named, the law's terms and their 95 % intervals, the before/after errors on each benchmark's official
test split, and that ``greybox update`` on the written MODEL.json / MODEL.py
and CSV files reaches the one call's verdict. The goals the current code does
not reach are strict xfails (they fail, as XPASS, the day they are reached,
so that the table of docs/results/real-data.md is updated). Skipped when ``../shared/data`` is
absent. The bilinear ``x*u`` law term the heat exchanger needs is tested on
a simulated plant first.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import greybox as gb
from greybox.system import named_ss

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
SETS = ("emps", "silverbox", "daisy_exchanger", "coupled_electric_drives", "cascaded_tanks")
HAVE_DATA = all((DATA / s).is_dir() for s in SETS)
needs_data = pytest.mark.skipif(not HAVE_DATA, reason=f"measured data {DATA}/{{{','.join(SETS)}}}"
                                " not present (see ../shared/data/INDEX.md)")


# --------------------------------------------------------------------- the bilinear term
def test_trace_finds_a_flow_dependent_time_constant_as_the_product_term():
    """dT/dt = -a T + b q - c q T: the nominal lag lacks -c q T; the law names T*q."""
    a, b, c, dt = 0.2, -3.0, 0.5, 1.0
    rng = np.random.default_rng(12)
    N = 3000
    q = np.repeat(rng.uniform(-0.3, 0.3, N // 5), 5)
    T = np.zeros(N)
    for k in range(N - 1):  # RK4 of the true bilinear model, q held over the sample
        f = lambda x: -a * x + b * q[k] - c * q[k] * x  # noqa: E731
        k1 = f(T[k]); k2 = f(T[k] + k1 / 2); k3 = f(T[k] + k2 / 2); k4 = f(T[k] + k3)
        T[k + 1] = T[k] + (k1 + 2 * k2 + 2 * k3 + k4) / 6
    y = T + 0.01 * rng.standard_normal(N)
    nom = named_ss([[-a]], [[b]], [[1]], [[0]], 0, states=["T"], inputs=["q"], outputs=["T"])
    rep = gb.close_the_loop(nom, y[None, :2000], q[None, :2000], y[None, 2000:],
                            q[None, 2000:], Q=[[1e-4]], R=[[1e-4]], dt=dt, max_order=0,
                            delta=False)
    assert rep.updated and rep.effect.equations == ("T",), rep.message
    law = rep.effect.law
    names = [s[0] for s in law.spec]
    j = names.index("T*q")
    # the product is the law's dominant term, its coefficient -c within its interval plus
    # 5 % (measured -0.506 +- 0.0036: d^ averages the bilinear force over a sample in which T
    # moves by ~20 %, which also brings in a small offset, checked below; a small T term
    # beside them, -0.478 T*q, is pruned at the choice's price, bic_factor)
    assert abs(law.coef[0, j] - (-c)) <= law.ci[0, j] + 0.05 * c, law.formula
    x_e = np.array([y[:2000]])
    contrib = np.abs(law.coef[0]) * law.term_scale(x_e, q[None, :2000])
    others = np.delete(contrib, j)
    # the offset's contribution is 0.10 of the product's (q*T has a nonzero mean: T
    # follows -q); the product dominates the law
    assert contrib.argmax() == j and others.max() < 0.25 * contrib[j], law.formula
    assert rep.table["updated"].se.value < 0.2 * rep.table["nominal"].se.value


# ---------------------------------------------------------------------- the real sets
def _run_tutorial(tmp_path_factory, script, name):
    """Run one real-data tutorial as a user does (a subprocess); its JSON summary."""
    out = tmp_path_factory.mktemp(name)
    env = dict(os.environ, GREYBOX_TUTORIAL_OUT=str(out), MPLBACKEND="Agg",
               PYTHONPATH=os.pathsep.join([str(ROOT)] + [p for p in
                                                         [os.environ.get("PYTHONPATH")] if p]))
    proc = subprocess.run([sys.executable, str(ROOT / "tutorials" / script)],
                          env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    s = json.loads((out / f"{name}_summary.json").read_text())
    s["_out"], s["_stdout"] = out, proc.stdout
    return s


def _tutorial_fixture(script, name):
    """A module-scoped fixture: the summary of one tutorial's run."""
    @pytest.fixture(scope="module")
    def run(tmp_path_factory):
        if not HAVE_DATA:
            pytest.skip("measured data not present")
        return _run_tutorial(tmp_path_factory, script, name)
    return run


# one fixture per set, each in its own xdist group: the five tutorials run in parallel
emps = _tutorial_fixture("04_emps.py", "emps")
silverbox = _tutorial_fixture("06_silverbox.py", "silverbox")
exchanger = _tutorial_fixture("07_heat_exchanger.py", "exchanger")
drives = _tutorial_fixture("08_electric_drives.py", "drives")
tanks = _tutorial_fixture("09_cascaded_tanks.py", "tanks")


def _marks(name):
    """needs the data, slow, and in the set's own xdist group (where its fixture runs)."""
    def deco(f):
        return needs_data(pytest.mark.slow(pytest.mark.xdist_group(f"real_{name}")(f)))
    return deco


# ------------------------------------------------------------------------------- EMPS
@_marks("emps")
def test_emps_friction_in_the_velocity_equation_with_the_published_coulomb_force(emps):
    assert emps["updated"] and emps["channel"] == "eq(v)" and emps["kind"] == "static"
    # the law is the Coulomb friction and the friction asymmetry, nothing else:
    # d_v = -(0.215 +- 0.0034)*sign(v) + (0.393 +- 0.034)*|v| (measured)
    assert sorted(emps["terms"]) == ["sign(v)", "|v|"], emps["formula"]
    # goal: Fc within 5 % of the published 20.39 N, with its 95 % interval (measured
    # 20.49 +- 0.32 N: the published value lies inside)
    Fc, h = emps["Fc"], emps["Fc_halfwidth"]
    assert abs(Fc - 20.39) <= 0.05 * 20.39 and abs(Fc - 20.39) <= h, (Fc, h)
    # |v| is half the friction asymmetry, (Fv- - Fv+)/2 = 36.86 N s/m published: measured
    # 0.393 * M = 37.4 +- 3.3
    c, hc = emps["terms"]["|v|"]
    assert abs(95.1089 * c - 36.86) <= 95.1089 * hc, emps["terms"]
    # goal: the offset within 1 N of -3.16 N with its interval. The selection does not keep
    # an offset beside |v| (|v| carries it: the published symmetric model's offset is the
    # mean of the asymmetry term); the published model's terms forced in by least squares on
    # the same d^: -2.92 +- 0.57 N (measured), Fc 20.57 +- 0.67 N
    off, hoff = emps["offset_fit"]["without_abs_v"]
    assert abs(off - -3.16) <= 1.0 and abs(off - -3.16) <= hoff, (off, hoff)
    assert emps["relative_degree"] == 2


@_marks("emps")
def test_emps_before_after_on_the_official_test_file(emps):
    t = emps["table"]
    # DATA_EMPS_PULSES, all 24841 samples simulated in open loop from vir: the nominal
    # (M, Fv only) drifts away, SE 109 %, RMS 163 mm; with the friction law SE 4.58 %,
    # RMS 6.8 mm (measured; 2 % covers platform rounding of the nominal's simulation, 5 %
    # the updated one's: the pure integrator accumulates any rounding of the law's force)
    np.testing.assert_allclose([t["nominal"]["se"], 1e3 * t["nominal"]["rms"]], [109.1, 162.5],
                               rtol=0.02)
    np.testing.assert_allclose([t["updated"]["se"], 1e3 * t["updated"]["rms"]], [4.58, 6.82],
                               rtol=0.05)
    # the pulses of the test record are in vir: the published inverse model's force residual
    # holds -0.054 of them (an external force would read -1)
    assert abs(emps["pulse_coef"]) < 0.2


# -------------------------------------------------------------------------- Silverbox
@_marks("silverbox")
def test_silverbox_cubic_stiffness_in_the_velocity_equation(silverbox):
    sb = silverbox
    assert sb["updated"] and sb["channel"] == "eq(v)" and sb["relative_degree"] == 2
    k3, h3 = sb["terms"]["y^3"]
    # a hardening spring: negative in d_v, its interval far from 0 (measured
    # -7.68e5 +- 0.011e5 1/(V^2 s^2)), the dominant term on the arrow's amplitudes
    assert k3 < 0 and abs(k3) > 20 * h3, sb["formula"]
    # the Duffing law (y, v, y^3) on the same d^: k3 -7.47e5 +- 0.035e5, within 5 %
    k3d, h3d = sb["duffing_on_dhat"]["coef"][2], sb["duffing_on_dhat"]["halfwidth"][2]
    assert abs(k3d / k3 - 1) < 0.05 and abs(k3d) > 20 * h3d
    # and, simulated alone on the arrow test, under the goal too (measured 0.396 mV against
    # greybox's six-term law's 0.304 mV)
    assert sb["duffing_on_dhat"]["rms_mV"] < 1.0, sb["duffing_on_dhat"]
    # three effects in one law (measured -(7.68e5 +- 0.011e5)*y^3 + (777 +- 45)*|y| -
    # (2.63e-4 +- 0.38e-4)*v^3, beside small corrections of the linear part y, v, u):
    # the cubic hardening spring, an asymmetric (even) stiffness and a cubic damping,
    # each with an interval excluding 0. With the midpoint input held (before
    # zoh_equivalent_input) only y^3 mattered: |y| and v^3 lowered the arrow RMS by 0.01 mV
    # (bench/silverbox_structures.py: the hold's error masked them, Duffing floor 1.48 mV
    # held against 0.357 mV with the band-limited input; the two terms gain 0.09 mV).
    # The damping is one odd shape of v: v^3 until the signed square v*|v| joined the
    # library, v*|v| since (the two are alternatives: never both in one law)
    terms = sb["terms"]
    damping = [t for t in ("v^3", "v*|v|") if t in terms]
    assert len(damping) == 1, sb["formula"]
    for term, sign in (("y^3", -1), ("|y|", 1), (damping[0], -1)):
        assert term in terms and sign * terms[term][0] > terms[term][1] > 0, (term,
                                                                             sb["formula"])
    # the same structure as a continuous ODE with the band-limited input, by output error
    # (bench/silverbox_structures.py): k3/m = -7.37e5, |y| 662; the discrete law (ZOH-
    # equivalent input, the law integrated over each sample by ETDRK4): measured -7.367e5
    # and 710, 0.04 % and 7 % off (4 % and 8 % when the Heun step integrated it)
    np.testing.assert_allclose(terms["y^3"][0], -7.37e5, rtol=0.1)
    np.testing.assert_allclose(terms["|y|"][0], 662, rtol=0.3)
    # the final model's residuals no longer correlate with the input (0.75x the 99 % band)
    assert not any("correlate with input" in n for n in sb["notes"]), sb["notes"]


@_marks("silverbox")
def test_silverbox_arrow_test_goal(silverbox):
    rms = silverbox["rms_mV"]
    # the official test (the arrow without extrapolation, [100:32100]): linear models 10+ mV
    # published, ours 12.4 mV (measured); goal <= 1 mV, measured 0.246 mV (0.265 mV when the
    # law was integrated by the Heun step of its first-order hold, 0.304 mV with a -v^3
    # damping before the signed square v*|v| joined the library)
    assert rms["nominal"] > 10 and rms["updated"] <= 1.0, rms
    # (deterministic code and data; 5 % covers BLAS/platform rounding in the law's
    # output-error refit, whose arrow simulation runs 32000 samples)
    np.testing.assert_allclose(rms["updated"], 0.246, rtol=0.05)


@_marks("exchanger")
def test_exchanger_law_contains_the_bilinear_q_T_term(exchanger):
    hx = exchanger
    assert hx["detected"]
    coef, half = hx["eq_terms"]["T*q"]
    # negative (more flow: faster, smaller response) and its 95 % interval excludes 0
    # (measured -0.164 +- 0.020 per s and flow unit, the only term left after the
    # output-error refit of the d^ law, which had q, T, an offset and |T| beside it and
    # -0.141 +- 0.075)
    assert coef < 0 and abs(coef) > half > 0, hx["eq_law"]
    assert list(hx["eq_terms"]) == ["T*q"], hx["eq_law"]


@_marks("exchanger")
def test_exchanger_before_after(exchanger):
    hx = exchanger
    t = hx["table"]
    # the nominal lag on the test split (deterministic code and data): SE 35.1 %,
    # RMS 0.545 degC; 2 % covers BLAS/platform rounding in the filter's initial state
    np.testing.assert_allclose([t["nominal"]["se"], t["nominal"]["rms"]], [35.1, 0.545],
                               rtol=0.02)
    # greybox leaves the model unchanged: the best candidate (eq(T), order-1 subsystem)
    # lowers the estimation SE only to 0.84 of the nominal (gate: 0.8)
    assert not hx["updated"] and hx["passed"] == {"whiteness": True, "bic": True,
                                                  "se_drop": False}
    assert t["updated"]["se"] == t["nominal"]["se"]
    # the static law (T*q alone), added anyway: 35.8 % on the test split, no gain (the d^
    # law with five terms gave 34.1 %): within 5 % of the nominal either way
    assert abs(hx["forced_static"]["se"] / t["nominal"]["se"] - 1) < 0.05, hx["forced_static"]


@_marks("drives")
def test_drives_error_is_named_on_the_sensor_side_with_a_rectifier(drives):
    low = drives["low"]
    assert low["updated"] and low["channel"] == "output(z)" and low["kind"] == "output"
    coef, half = low["terms"]["|z_model|"]
    # |.| of the model's own speed, positive, its 95 % interval excluding 0; a pure
    # rectifier is d = |z| - z (+1 and -1): measured +0.86 +- 0.28 and -0.82 +- 0.10
    # (refit by least squares on the nominal simulation; the d^ fit gave 0.48 and -0.94)
    assert coef > half > 0 and abs(coef - 1.0) <= half
    c_lin, h_lin = low["terms"]["z_model"]
    assert c_lin < 0 and abs(c_lin) > h_lin


@_marks("drives")
def test_drives_before_after(drives):
    t = drives["low"]["table"]
    # nominal (reference linear part, gain rescaled on the estimation data): SE 50.0 %,
    # RMS 0.218 sensor units; with the sensor law: SE 26.2 %, RMS 0.114; 2 %: rounding
    np.testing.assert_allclose([t["nominal"]["se"], t["nominal"]["rms"]], [50.0, 0.218],
                               rtol=0.02)
    np.testing.assert_allclose([t["updated"]["se"], t["updated"]["rms"]], [26.2, 0.114],
                               rtol=0.02)
    # PE: the updated row's one-step predictor is an extended Kalman filter on the |.| law
    # (it read ~1e28 % with a constant gain from the law's linear stand-in, which diverged):
    # measured 10.9 % -> 9.55 %; 2 %: rounding
    np.testing.assert_allclose([t["nominal"]["pe"], t["updated"]["pe"]], [10.9, 9.55],
                               rtol=0.02)
    # high-amplitude record: only 13 % of its model speed samples are < 0; unchanged. The
    # sensor law fits best (4 terms, estimation SE 29.3 %) but the criterion, on the 25
    # effective samples of 400 that this record's slow error holds, does not pay its 3
    # terms more than eq(w)'s 1-term law (39 %) at the gate's factor 10; that law fails
    # the gate (BIC gain and SE drop). Under the SE-parsimony rule the sensor law was
    # chosen and failed on its BIC gain alone: either way the model stays unchanged.
    high = drives["high"]
    assert high["detected"] and not high["updated"]
    assert "(eq(w), static) failed the gate" in high["message"], high["message"]
    assert high["passed"] == {"whiteness": True, "bic": False, "se_drop": False}
    sensor = [c for c in high["candidates"] if c["channel"] == "output(z)"]
    assert sensor and sensor[0]["npar"] > 1 and sensor[0]["se_estimation"] < min(
        c["se_estimation"] for c in high["candidates"] if c["channel"] == "eq(w)")


@_marks("tanks")
def test_tanks_the_trace_names_the_upper_tank_saturation_but_the_gate_refuses_it(tanks):
    tk = tanks
    assert tk["detected"] and not tk["updated"]
    t = tk["table"]
    # Torricelli nominal with the sensor's offset on the test split: RMS 0.667 V from sample
    # 20 (0.661 V over all 1024 samples from the fitted initial state; without the offset
    # 0.700 and 0.694 V); 3 %: the UKF's initial state, rounding
    np.testing.assert_allclose(t["nominal"]["rms"], 0.667, rtol=0.03)
    np.testing.assert_allclose(tk["rms_nominal_all_samples"], 0.661, rtol=0.03)
    assert -1.0 < tk["k"][6] < -0.75  # the sensor's offset [V], measured -0.874
    # the initial state is not where the 0.17 V to the goal goes: the README's "same initial
    # state for both records" (the estimation fit's x(0) reused) is as good as x(0) fitted
    # on the whole test output (a floor; measured 0.661 vs 0.660 V, bench/tanks_floors.py),
    # and greybox's UKF start at sample 20 from the test record alone is within 0.01 V
    assert tk["rms_nominal_all_samples"] - tk["rms_nominal_x0_floor"] < 0.005
    assert abs(t["nominal"]["rms"] - tk["rms_nominal_x0_floor"]) < 0.01
    # only the lower tank is measured: eq(x1) has relative degree 2 and is traced by the
    # delayed unscented filter; the best candidate is the upper tank's level saturating
    up = [c for c in tk["candidates"] if c["channel"] == "eq(x1)"]
    assert up and all(c["status"] == "ok" for c in up), up
    best = tk["best"]
    assert best["channel"] == "eq(x1)" and best["relative_degree"] == 2, best
    assert len(best["terms"]) == 1 and best["terms"][0][1] == "x_hi", best["formula"]
    assert best["terms"][0][2] < 0  # a loss of inflow above the level
    # MODEL.py declares k1, k2, k3 and the sensor offset as params (k4 pins the scale of the
    # unmeasured upper level): greybox refits them with the law by output error (stage 2c).
    # The joint refit (hinge, its level, its spill into eq(x2), the parameters) lowers the
    # estimation SE 9.8 % -> 6.5 % (measured; the parameters refitted alone: 9.5 %) ...
    assert tk["passed"] == {"whiteness": True, "bic": False, "se_drop": True}
    g = tk["gate"]
    assert tk["evidence"].startswith("output error: likelihood ratio of the law (nominal "
                                     "parameters refitted with it)"), tk["evidence"]
    assert g["se_estimation_updated"] / g["se_estimation_nominal"] < 0.8
    assert g["se_estimation_parameters_only"] > 0.9 * g["se_estimation_nominal"]
    # ... but its likelihood ratio against the parameters refitted alone, over the residual's
    # colour (11), is 69.6 against the 10 x 13.5 the gate needs (measured): refused
    assert g["bic_gain"] < g["bic_factor"] * g["bic_penalty"]
    assert g["bic_gain"] > g["bic_penalty"]  # plain BIC would take it: the factor 10 refuses
    # what the joint refit says, refused or not: the overflow spills into the lower tank
    # (ratio -0.37 +- 0.11 of the law: the data README's "partly into the lower tank") ...
    (state, ratio, hw), = best["spill"]
    assert state == "x2" and -1.0 < ratio < 0 and abs(ratio) > hw, best["spill"]
    # ... and the parameter that moves most is the level sensor's offset, -0.87 -> -1.87 V
    # (+- 0.26): its interval excludes the nominal fit's value (fitted where y < 9.9 V)
    off = next(p for p in best["parameters"] if p["name"] == "off")
    assert abs(off["refitted"] - off["nominal"]) > off["halfwidth"], off
    assert -2.5 < off["refitted"] < -1.3, off
    # made anyway, the joint update's test RMS is 0.486 V (measured; nominal 0.667 V): inside
    # the published 0.3-0.5 V, where the gate does not let greybox go by default
    assert best["rms_forced"] < 0.52 < 0.6 < t["nominal"]["rms"], best["rms_forced"]


@_marks("tanks")
@pytest.mark.xfail(strict=True, reason="the trace names the upper tank's saturation (eq(x1), "
                   "a max(x1 - c, 0) hinge) and, with the nominal's k1..k3 and sensor offset "
                   "refitted jointly, its spill into the lower tank: estimation SE 9.8 -> "
                   "6.5 % and a test RMS of 0.486 V if made, but its evidence against the "
                   "parameters refitted alone (69.6) is below the gate's 10 x 13.5: the model "
                   "stays unchanged at 0.667 V (goal <= 0.5 V)")
def test_tanks_goal_test_rms(tanks):
    tk = tanks
    assert tk["updated"] and tk["table"]["updated"]["rms"] <= 0.5


def _cli_check(one, out, name, model):
    """``greybox update`` on the files the tutorial wrote: exit 0, the one call's verdict."""
    cli = one["cli"]
    assert cli["exit_code"] == 0
    assert cli["message"] == one["message"] and cli["updated"] == one["updated"]
    for f in (model, f"{name}_estimation.csv", f"{name}_test.csv",
              f"{name}_report/summary.json", f"{name}_report/updated_model.json"):
        assert (out / f).is_file(), f


@_marks("emps")
def test_emps_cli_and_figure(emps):
    _cli_check(emps, emps["_out"], "emps", "emps_MODEL.json")
    assert "model error found in eq(v): static effect" in emps["_stdout"]
    assert "Coulomb friction Fc =" in emps["_stdout"]
    assert (emps["_out"] / "fig6_emps.png").stat().st_size > 1000


@_marks("silverbox")
def test_silverbox_cli_and_figure(silverbox):
    _cli_check(silverbox, silverbox["_out"], "silverbox", "silverbox_MODEL.json")
    assert "model error found in eq(v): static effect" in silverbox["_stdout"]
    assert (silverbox["_out"] / "fig7_silverbox.png").stat().st_size > 1000


@_marks("exchanger")
def test_exchanger_cli_and_figure(exchanger):
    _cli_check(exchanger, exchanger["_out"], "exchanger", "exchanger_MODEL.json")
    assert (exchanger["_out"] / "fig9_exchanger.png").stat().st_size > 1000


@_marks("drives")
def test_drives_cli_and_figures(drives):
    _cli_check(drives["low"], drives["_out"], "drives", "drives_MODEL.json")
    for name in ("fig10_drives_low.png", "fig10_drives_high.png"):
        assert (drives["_out"] / name).stat().st_size > 1000, name


@_marks("tanks")
def test_tanks_cli_and_figure(tanks):
    _cli_check(tanks, tanks["_out"], "tanks", "tanks_MODEL.py")
    assert (tanks["_out"] / "fig11_tanks.png").stat().st_size > 1000
