"""Updated models are ordinary python-control systems: they go straight into
``control.dlqr``, ``control.dlqe``, ``control.feedback`` and
``control.forced_response``; and the claim of tutorial 2 holds.

The models are built once per module from Table II's filter run, the same
calls as :func:`greybox.reproduce.reproduce_table3` (without its validation
step, to keep the module fast): static (order 0), dynamic (order >= 1) and the
parallel delta baseline.
"""

from __future__ import annotations

import runpy
import warnings
from pathlib import Path

import control as ct
import numpy as np
import pytest

import greybox as gb
from greybox.reproduce import reproduce_table2
from greybox.update import augment_model, delta_update, identify_subsystem

PHYSICAL = ("I1", "I2", "p1", "p2", "w1", "w2")
TUTORIAL2 = Path(__file__).resolve().parents[1] / "tutorials" / "02_controller_design.py"


@pytest.fixture(scope="module")
def updated_models():
    """{"static", "dynamic", "delta"}: UpdatedModel of the tape drive."""
    t2 = reproduce_table2()
    Q, R = gb.TAPE_DRIVE_Q, gb.TAPE_DRIVE_R
    nominal = gb.tape_drive_nominal(dt=gb.TAPE_DRIVE_DT)
    base = gb.split_inputs(nominal, "T").sys
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", gb.GreyboxWarning)
        static = identify_subsystem(t2.uif, order=0)
        dynamic = identify_subsystem(t2.uif, order=1)  # orders 2-3 (output-error) take minutes
        # a small delta order search: the full one (1..12) is reproduce_table3's
        # job; any delta model exercises the same code paths here
        delta = delta_update(base, t2.uif.y, t2.uif.u, Q=Q, R=R, max_order=5)
        assert delta.improved, delta.message
    return {
        "static": augment_model(nominal, static, unknown="T", Q=Q, R=R),
        "dynamic": augment_model(nominal, dynamic, unknown="T", Q=Q, R=R),
        "delta": delta.updated,
    }


KINDS = ["static", "dynamic", "delta"]


@pytest.mark.parametrize("kind", KINDS, ids=KINDS)
def test_signal_names_and_shapes(updated_models, kind):
    m = updated_models[kind]
    sys = m.sys
    n = sys.nstates
    assert m.order == n
    assert m.kind == kind
    assert sys.isdtime(strict=True) and sys.dt == gb.TAPE_DRIVE_DT
    assert tuple(sys.state_labels[:6]) == PHYSICAL
    prefix = "delta" if kind == "delta" else "z"
    assert list(sys.state_labels[6:]) == [f"{prefix}[{i}]" for i in range(n - 6)]
    assert tuple(sys.input_labels) == ("V1", "V2")
    assert tuple(sys.output_labels) == PHYSICAL
    assert m.Q.shape == (n, n) and m.R.shape == (6, 6)
    if kind == "static":
        assert n == 6
    else:
        assert n > 6


@pytest.mark.parametrize("kind", KINDS, ids=KINDS)
def test_dlqr_gives_stabilizing_gain(updated_models, kind):
    sys = updated_models[kind].sys
    n = sys.nstates
    # weight the outputs (all physical states) and, lightly, the new states
    Qx = np.asarray(sys.C).T @ np.diag([1, 1, 1e4, 1e4, 1e-2, 1e-2]) @ np.asarray(sys.C)
    Qx = Qx + 1e-6 * np.eye(n)
    # scipy's DARE: the slycot path of python-control escalates SlycotResultWarning
    # ("poor scaling / eigenvalues near the unit circle") for these 1e-4 s models
    K, S, E = ct.dlqr(sys, Qx, np.eye(2), method="scipy")
    assert K.shape == (2, n) and S.shape == (n, n) and E.shape == (n,)
    assert np.max(np.abs(E)) < 1.0
    cl = np.linalg.eigvals(np.asarray(sys.A) - np.asarray(sys.B) @ K)
    # E are the closed-loop eigenvalues; same set up to round-off of the sort
    np.testing.assert_allclose(np.sort(np.abs(cl)), np.sort(np.abs(E)), atol=1e-8)


@pytest.mark.parametrize("kind", KINDS, ids=KINDS)
def test_dlqe_with_model_covariances(updated_models, kind):
    m = updated_models[kind]
    n = m.sys.nstates
    A, C = np.asarray(m.sys.A), np.asarray(m.sys.C)
    # process noise enters every state (G = I): dlqe(sys, ...) would take G = B
    L, P, E = ct.dlqe(A, np.eye(n), C, m.Q, m.R)
    assert L.shape == (n, 6) and P.shape == (n, n)
    # the estimator error dynamics A - A L C must be stable ...
    assert np.max(np.abs(np.linalg.eigvals(A - A @ L @ C))) < 1.0
    assert np.max(np.abs(E)) < 1.0
    # ... and P a covariance (symmetric, PSD up to round-off relative to its size)
    np.testing.assert_allclose(P, P.T, rtol=1e-8, atol=1e-12 * np.max(np.abs(P)))
    assert np.min(np.linalg.eigvalsh(0.5 * (P + P.T))) > -1e-9 * np.max(np.abs(P))


@pytest.mark.parametrize("kind", KINDS, ids=KINDS)
def test_feedback_and_forced_response(updated_models, kind):
    sys = updated_models[kind].sys
    n = sys.nstates
    # proportional speed loop: V_i = -k w_i  (a static gain 2 x 6 on the outputs)
    k = np.zeros((2, 6))
    k[0, 4] = k[1, 5] = 0.05
    cl = ct.feedback(sys, ct.ss([], [], [], k, dt=sys.dt))
    assert (cl.ninputs, cl.noutputs, cl.nstates) == (2, 6, n)
    assert cl.isdtime(strict=True)
    N = 200
    t = np.arange(N) * sys.dt
    u = np.vstack([np.ones(N), -np.ones(N)])
    resp = ct.forced_response(cl, T=t, U=u)
    assert resp.y.shape == (6, N) and resp.x.shape == (n, N)
    assert np.all(np.isfinite(resp.y))
    # python-control 0.10.2's feedback() itself drops every signal name (states x[i],
    # outputs y[i], inputs u[i]); what greybox guarantees survives is the order: the
    # closed loop's states are the model's states (physical first), same C
    np.testing.assert_array_equal(np.asarray(cl.C), np.asarray(sys.C))
    np.testing.assert_allclose(np.asarray(cl.A),
                               np.asarray(sys.A) - np.asarray(sys.B) @ k @ np.asarray(sys.C),
                               rtol=1e-12, atol=1e-12)
    # open loop: same shapes, and simulation with the greybox simulator agrees
    ol = ct.forced_response(sys, T=t, U=u)
    sim = gb.simulate(sys, u)
    # same difference equation, different summation orders: observed differences up
    # to ~1e-7 of the signal after 200 steps (poles near 1 accumulate round-off)
    scale = np.max(np.abs(sim.y), axis=1, keepdims=True) + 1e-300
    np.testing.assert_allclose(ol.y / scale, sim.y / scale, rtol=0, atol=1e-6)


def test_updated_controller_beats_nominal_on_true_plant(tmp_path, monkeypatch):
    """Tutorial 2's claim. Margin: the updated controller's cost must be at least
    3x lower than the nominal one's (observed ~24x) and within 50 % of the
    true-model yardstick (observed ~20 % above it); its tension ripple at least 3x
    lower (observed ~10x). The margins leave room for other seeds and BLAS round-off
    while still failing if the update stopped carrying the tension's torque."""
    monkeypatch.setenv("GREYBOX_TUTORIAL_OUT", str(tmp_path))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    ns = runpy.run_path(str(TUTORIAL2), run_name="tutorial2")
    res = ns["results"][5.0]
    nom, upd, true = (res[k] for k in ("nominal", "updated (static)", "true (yardstick)"))
    assert upd["cost"] * 3 < nom["cost"]
    assert upd["cost"] < 1.5 * true["cost"]
    assert upd["T_rms"] * 3 < nom["T_rms"]
    # every design is stable on the true plant
    for d in ns["designs"].values():
        assert d["rho_true"] < 1.0
