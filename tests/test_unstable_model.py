"""Open-loop unstable plants measured in closed loop (issue 13, item 2), and progress.

The plant ``x'' = k x - c x' + F`` with k = 2 (poles +1.0 and -1.5 rad/s) is
stabilized by a state feedback on the measured outputs; the nominal model
has k = 4 (the missing effect is a restoring spring of -2 N/m on eq(v)).
The simulation error of either model is undefined: greybox must say so,
choose and gate by the prediction error, find the spring, and never print a
ratio built from a diverged simulation.
"""

from __future__ import annotations

import json
import re
from functools import lru_cache

import numpy as np
import pytest
import scipy.linalg as sla

import greybox as gb
from greybox.io import dumps_json
from greybox.progress import Progress, TerminalProgress
from greybox.system import named_ss
from greybox.workflow import close_the_loop

DT = 0.01


def _closed_loop(A, N, rng):
    M = sla.expm(np.block([[A, np.array([[0.0], [1.0]])], [np.zeros((1, 3))]]) * DT)
    Ad, Bd = M[:2, :2], M[:2, 2:]
    K = np.array([30.0, 8.0])
    r = np.repeat(rng.standard_normal(N // 50 + 1), 50)[:N]
    x, y, u = np.zeros(2), np.empty((2, N)), np.empty((1, N))
    for k in range(N):
        y[:, k] = x + 1e-3 * rng.standard_normal(2)
        u[0, k] = -K @ y[:, k] + 10 * r[k]
        x = Ad @ x + Bd[:, 0] * u[0, k] + np.array([0.0, 1e-4]) * rng.standard_normal()
    return y, u


@lru_cache(maxsize=1)
def _report():
    rng = np.random.default_rng(11)
    truth = np.array([[0.0, 1.0], [2.0, -0.5]])
    y, u = _closed_loop(truth, 4000, rng)
    yv, uv = _closed_loop(truth, 2000, rng)
    nominal = named_ss([[0.0, 1.0], [4.0, -0.5]], [[0.0], [1.0]], np.eye(2), np.zeros((2, 1)),
                       0, states=["p", "v"], inputs=["F"], outputs=["p", "v"], name="pend")
    records = []
    rep = close_the_loop(nominal, y, u, yv, uv, Q=np.diag([1e-10, 1e-8]), R=1e-6 * np.eye(2),
                         dt=DT, progress=records.append)
    return rep, records


def test_unstable_nominal_se_na_pe_used_spring_found():
    rep, _ = _report()
    assert rep.updated and rep.effect.kind == "static" and rep.effect.channel == "eq(v)"
    # the data want A[v, p] = 2 (truth): 4000 samples at 1 mm noise pin the least-squares
    # law to well under 1 %; 2 % allows for the feedback's excitation being narrow-band
    want = float(re.search(r"A\[v; p\] = 4 in the model; the data want ([-\d.]+)",
                           " ".join(rep.effect.parameter_notes)).group(1))
    assert want == pytest.approx(2.0, rel=0.02)
    nom, upd = rep.table["nominal"], rep.table["updated"]
    assert not nom.se_defined and "unstable" in nom.se_reason
    assert np.isnan(nom.se.value) and np.all(np.isnan(nom.y_sim))
    assert np.isnan(rep.se_ratio())
    assert "SE n/a" in rep.message and "PE" in rep.message
    assert "nan" not in rep.message and "inf" not in rep.message
    assert rep.gate["measure"] == "PE" and "prediction error" in rep.criterion
    # the updated model explains the closed-loop data: PE drops by 5x or more and the
    # innovations turn white (the nominal ones are not)
    assert upd.pe.value < nom.pe.value / 5
    assert upd.whiteness.all_white and not nom.whiteness.all_white
    s = json.loads(dumps_json(rep.as_dict()),
                   parse_constant=lambda c: pytest.fail(f"non-standard JSON {c}"))
    assert s["table"]["nominal"]["se"] is None and s["table"]["nominal"]["se_reason"]


def test_progress_records():
    _, records = _report()
    assert records and all(isinstance(r, Progress) for r in records)
    stages = [r.stage for r in records]
    assert "trace candidate channels" in stages and "validation" in stages
    assert all(0 <= r.k <= r.K for r in records)
    assert all(b.elapsed >= a.elapsed for a, b in zip(records, records[1:]))
    last = records[-1]
    assert last.stage == "validation" and last.k == last.K


def test_terminal_progress_waits_then_rewrites_one_line():
    import io

    buf = io.StringIO()
    tp = TerminalProgress(buf, delay=1.0)
    tp(Progress("trace", 0, 4, 0.5))
    assert buf.getvalue() == ""  # quiet during the first second
    tp(Progress("trace", 2, 4, 1.5))
    assert "trace: 2 of 4" in buf.getvalue() and "\n" not in buf.getvalue()
    tp.close()
    assert buf.getvalue().endswith("\r\x1b[K")


def test_progress_must_be_callable():
    with pytest.raises(gb.DimensionError, match="progress must be a callable"):
        close_the_loop(named_ss([[0.5]], [[1.0]], [[1.0]], [[0.0]], 0.1, states=["x"],
                                inputs=["u"], outputs=["y"]),
                       np.ones((1, 300)), np.ones((1, 300)), np.ones((1, 300)),
                       np.ones((1, 300)), Q=[[1e-4]], R=[[1e-2]], progress="yes")


@pytest.mark.slow
def test_an_unstable_plant_s_law_has_an_interval_that_covers_the_truth_over_draws():
    """Twelve zoo draws of an open-loop unstable plant in closed loop (a chain of 1-3
    bodies, LQR; one damping or actuator gain wrong): the law is refined by one-step
    prediction error (the model's simulation diverges, so not by output error) and its
    95 % interval covers the true coefficient. The d^ regression's own interval, which
    the law kept before, covered it in 6 of these 12 draws (15 of 30 on seed 424201):
    d^ and the state estimate its terms are formed from err together, a bias of ~0.1 %
    the interval (~0.02 %) does not hold.

    At least 10 of 12: the prediction-error interval covered 12 of 12 here, 28 of 30 on
    seed 424201 and 20 of 20 on seeds 5191 and 777001 (`python bench/zoo.py --draws 30
    --seed 424201 --classes unstable_closed_loop`); 10 of 12 or fewer has probability
    ~2 % at the nominal 95 %."""
    from greybox import zoo

    covered = total = 0
    for i in range(12):
        d = zoo.draw_class("unstable_closed_loop", 20261128, i)
        rep = close_the_loop(d.nominal, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                             delta=False)
        sc = zoo.score(d, rep)
        assert sc.right, (i, sc.description, sc.found, sc.why)
        assert sc.error_updated <= 1.5 * sc.error_true, (i, sc.error_updated, sc.error_true)
        covered, total = covered + sc.covered, total + sc.n_coefficients
    assert total == 12 and covered >= 10, (covered, total)
