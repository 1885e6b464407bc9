"""A worse model is never handed over as a success (greybox.recommend).

The trace's update is judged last on the validation record: when it predicts
those data worse than the nominal model, the report keeps the nominal model
and says "not recommended" first, with both figures; the CLI exits 4.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import greybox as gb
from greybox.cli import NOT_RECOMMENDED, main
from greybox.model_io import model_to_dict
from greybox.recommend import judged_measure, recommend
from test_workflow import DT, N_EST, N_VAL, QD, R_STD, _simulate, chain, run_case, true_dynamics


def _changed_plant_records():
    """Estimation data of the chain with its missing 15 N/m spring, validation data of
    the chain without it (the nominal model): the machine changed between the records,
    so the update that explains the estimation record is wrong on the validation one."""
    rng = np.random.default_rng(31)
    nom = chain()
    C = np.asarray(nom.C, dtype=float)
    u = gb.lowpass_noise(N_EST, dt=DT, bandwidth=1.0, amplitude=2.0, rng=rng)
    uv = gb.lowpass_noise(N_VAL, dt=DT, bandwidth=1.0, amplitude=2.0, rng=rng)
    f_spring, _ = true_dynamics("spring")
    f_right, _ = true_dynamics("right")
    _simulate.extra = 0
    y = _simulate(f_spring, C, u, noise_q=True, rng=rng)
    yv = _simulate(f_right, C, uv, noise_q=False, rng=rng)
    return nom, y, u, yv, uv, QD + 1e-12 * np.eye(4), R_STD**2 * np.eye(4)


def test_an_update_worse_on_validation_is_not_recommended():
    nom, y, u, yv, uv, Q, R = _changed_plant_records()
    rep = gb.close_the_loop(nom, y, u, yv, uv, Q=Q, R=R, dt=DT, delta=False)
    assert rep.model_error_detected
    assert not rep.updated and not rep.recommended
    assert rep.message.startswith("not recommended: "), rep.message
    # both figures in the first line, the refused row kept beside the nominal's
    refused, nominal = rep.table["not recommended"], rep.table["nominal"]
    assert refused.se.value > nominal.se.value
    assert f"{nominal.se.value:.3g}% -> {refused.se.value:.3g}%" in rep.message
    assert rep.table["updated"] is nominal            # what is handed over: the nominal
    assert rep.model.kind == "nominal" and rep.model.sys is rep.nominal
    np.testing.assert_array_equal(rep.model.Q, Q)
    # what the trace proposed is still said: the spring on mass 2
    assert rep.effect.equations == ("v2",) and "p2" in rep.effect.formula
    d = rep.as_dict()
    assert d["updated"] is False and d["recommended"] is False


def test_a_better_update_is_left_as_it_is():
    rep, _ = run_case("spring")
    assert rep.updated and rep.recommended
    assert recommend(rep, rep.model.Q, rep.model.R) is rep
    measure, before, after = judged_measure(rep)
    assert measure == "SE" and after < before


def test_the_judgement_reads_the_rows_it_is_given():
    """The same report with its rows swapped (the update now the worse one) is refused:
    the rule is the comparison itself, no margin."""
    rep, _ = run_case("spring")
    table = dict(rep.table, nominal=rep.table["updated"], updated=rep.table["nominal"])
    out = recommend(rep.__class__(**{**rep.__dict__, "table": table}), np.eye(4), np.eye(4))
    assert not out.updated and not out.recommended and out.message.startswith("not recommended")


def test_a_marginal_nominal_is_judged_by_its_prediction_error():
    """A double integrator (poles at 1) drifts in simulation: PE is the measure."""
    di = gb.discretize(gb.named_ss([[0, 1], [0, 0]], [[0], [1]], np.eye(2), np.zeros((2, 1)), 0,
                                   states=["x", "v"], inputs=["a"], outputs=["x", "v"]), DT)
    rep, _ = run_case("spring")
    assert judged_measure(rep)[0] == "SE"
    assert judged_measure(rep.__class__(**{**rep.__dict__, "nominal": di}))[0] == "PE"


def test_cli_exits_4_and_writes_the_nominal_model(tmp_path, capsys):
    nom, y, u, yv, uv, Q, R = _changed_plant_records()
    model = tmp_path / "model.json"
    model.write_text(json.dumps(model_to_dict(nom, Q, R, Ts=DT)))

    def csv(path, y, u):
        data = np.vstack([u, y])
        lines = ["F," + ",".join(nom.output_labels)]
        lines += [",".join(f"{v:.10g}" for v in row) for row in data.T]
        path.write_text("\n".join(lines) + "\n")
        return str(path)

    out = tmp_path / "report"
    code = main(["update", str(model), csv(tmp_path / "e.csv", y, u), "--validate",
                 csv(tmp_path / "v.csv", yv, uv), "--out", str(out), "--json", "--no-plots",
                 "--no-baseline"])
    assert code == NOT_RECOMMENDED == 4
    s = json.loads(capsys.readouterr().out)
    assert s["updated"] is False and s["recommended"] is False
    assert s["message"].startswith("not recommended")
    written = json.loads((out / "updated_model.json").read_text())
    # the nominal (discretized, as any report without an update writes it)
    np.testing.assert_allclose(written["A"], np.asarray(gb.discretize(nom, DT).A), rtol=1e-12)


def test_the_json_explains_the_effect_as_data():
    """``explanation``: channel (kind, equations, direction) and law terms with their
    coefficient and interval, for a program to read (the spring k2 = 15 N/m on mass 2)."""
    rep, _ = run_case("spring")
    ex = rep.as_dict()["explanation"]
    assert len(ex) == 1
    ch, law = ex[0]["channel"], ex[0]["law"]
    assert ch["kind"] == "equation" and ch["equations"] == ["v2"] and ch["direction"] == [1.0]
    assert law["kind"] == "static" and law["order"] == 0 and law["formula"] == rep.effect.formula
    terms = {t["expression"]: t for t in law["terms"]}
    assert "p2" in terms, terms
    t = terms["p2"]
    assert t["determined"] and t["ci95"] > 0
    # the truth, -15 N/m on a 1 kg mass: within two 95 % half-widths (about 4 sigma; one
    # draw: coverage over seeds is asserted in test_nonlinear_intervals, test_sensor_*)
    assert abs(t["coefficient"] + 15.0) <= 2 * t["ci95"], t
    json.dumps(ex, allow_nan=False)  # strict JSON
    # a correct model explains nothing
    right, _ = run_case("right")
    assert right.as_dict()["explanation"] == []


def test_report_md_opens_with_the_answer(tmp_path):
    """The verdict, the effect in one line and the before/after table come before the
    residual test and the decision trail (candidates, notes)."""
    from greybox.cli import _report_markdown

    rep, _ = run_case("spring")
    md = _report_markdown(rep, {"outputs": str(tmp_path / "outputs.png")})
    heads = [ln for ln in md.splitlines() if ln.startswith("## ")]
    assert heads[:3] == ["## Effects", "## Validation data: before and after (eq. 42, "
                         "relative RMS)", "## Figures"], heads
    assert heads.index("## Decision trail") > heads.index("## Figures")
    assert md.splitlines()[2].startswith("**model error found in eq(v2)")
    assert f"`{rep.effect.formula}`" in md.split("## Validation")[0]
    assert all(f"| {c.channel} |" in md for c in rep.candidates)


# --------------------------------------------------------------------------- definitions
BALLBEAM = Path(__file__).resolve().parents[2] / "shared" / "data" / "daisy_ballbeam" / \
    "ballbeam.csv"


def test_a_kinematic_identity_is_a_definition_not_a_channel():
    from greybox.workflow import definitions

    chain4 = chain()
    assert definitions(chain4) == ["p1", "p2"]          # dp/dt = v: definitions
    assert definitions(gb.discretize(chain4, DT)) == []  # a discrete model mixes the rows
    # a first-order decay (one nonzero, on the diagonal) is physics, not a definition
    tank = gb.named_ss([[-0.5]], [[1.0]], [[1.0]], [[0.0]], 0, states=["h"], inputs=["q"],
                       outputs=["h"])
    assert definitions(tank) == []
    rep, _ = run_case("spring")
    assert not any(set(c.channel.replace("eq(", "").replace(")", "").split("+")) & {"p1", "p2"}
                   for c in rep.candidates if c.channel.startswith("eq("))
    assert any("kinematic identities" in s for s in rep.notes)


@pytest.mark.skipif(not BALLBEAM.exists(), reason="../shared/data/daisy_ballbeam not present")
def test_ball_and_beam_is_not_made_worse():
    """The real ball-and-beam record (DaISy 96-004, closed loop), nominal x'' = 7 theta, a
    double integrator: the update once rewrote pos' = vel as pos' = 0.023 vel and took the
    one-step prediction error on the last 300 samples from 2.93 % to 30.9 %. Now the
    kinematic identity is no channel, and the model handed over predicts no worse (PE:
    the nominal has poles at 1)."""
    d = np.loadtxt(BALLBEAM, delimiter=",", skiprows=1)
    u, y = d[:, 0][None], d[:, 1][None]
    nom = gb.named_ss([[0, 1], [0, 0]], [[0], [7.0]], [[1, 0]], [[0]], 0,
                      states=["pos", "vel"], inputs=["theta"], outputs=["pos"])
    rep = gb.close_the_loop(nom, y[:, :700], u[:, :700], y[:, 700:], u[:, 700:],
                            Q=np.diag([1e-8, 1e-4]), R=[[1e-6]], dt=0.1, delta=False)
    assert not any(c.channel.startswith("eq(pos") for c in rep.candidates), rep.candidates
    measure, before, after = judged_measure(rep)
    assert measure == "PE"
    assert after <= before, rep.message
    assert rep.recommended or not rep.updated
