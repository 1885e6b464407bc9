"""A hidden state shared by two state equations (issue 8, item 2).

Two masses (the nominal model's chain of two, all states measured) joined by a
Maxwell element the model lacks: a spring km = 10 N/m in series with a damper,
time constant tau = 0.1 s. Its force km (p2 - p1 - z), dz/dt = (p2 - p1 - z) /
tau, acts equally and oppositely on both bodies: one hidden state drives two
equations. The trace must name one force between the bodies, a first-order law
in their relative coordinate (not a 2-output subsystem driven by every signal,
28 parameters), with the time constant and the gain of the element.
"""

from __future__ import annotations

import numpy as np
import pytest

import greybox as gb
from plantlib import LinearF, chain, draw

KM, TAU = 10.0, 0.1


def _maxwell(seed):
    nom = chain(2, k=20.0)
    A, B = np.asarray(nom.A), np.asarray(nom.B)

    def f(x, u):
        dx = np.empty(5)
        fm = KM * (x[2] - x[0] - x[4])
        dx[:4] = A @ x[:4] + B[:, 0] * u[0]
        dx[1] += fm
        dx[3] -= fm
        dx[4] = fm / (KM * TAU)
        return dx

    d = draw(nom, f, n_true=5, dt=0.01, rng=np.random.default_rng(seed),
             q_std=np.array([0.0, 1e-4] * 2), r_std=1e-3)
    Ac = np.zeros((5, 5))
    Ac[:4, :4] = A
    Ac[1, [0, 2, 4]] += [-KM, KM, -KM]
    Ac[3, [0, 2, 4]] -= [-KM, KM, -KM]
    Ac[4, [0, 2, 4]] = np.array([-1.0, 1.0, -1.0]) / TAU
    Bc = np.vstack([B, [[0.0]]])
    true = gb.discretize(gb.named_ss(Ac, Bc, np.hstack([np.asarray(nom.C), np.zeros((4, 1))]),
                                     np.zeros((4, 1)), 0,
                                     states=list(nom.state_labels) + ["z"],
                                     inputs=nom.input_labels, outputs=nom.output_labels), d.dt)
    floor = gb.validate_model(true, d.y_val, d.u_val, Q=np.eye(5) * 1e-8, R=d.R).se.value
    return nom, d, floor


@pytest.mark.slow
def test_maxwell_element_is_one_force_with_a_first_order_law_in_the_relative_coordinate():
    nom, d, floor = _maxwell(0)
    rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    assert rep.updated and rep.channel.kind == "force", rep.message
    assert set(rep.effect.equations) == {"v1", "v2"}, rep.message
    dl = rep.effect.dynamic_law
    assert dl is not None, rep.effect.formula
    rel = [q for q, nm in enumerate(dl.drivers) if nm in ("(v2-v1)", "(p2-p1)")]
    assert rel, dl.drivers                                   # the relative coordinate drives
    assert dl.npar <= 7, dl.formula                          # not 28 parameters
    # tau within 5 % (its 95 % interval is ~2.5 % wide)
    np.testing.assert_allclose(dl.tau, TAU, rtol=0.05)
    # the element's force km tau s / (tau s + 1) (p2 - p1) reads km / (s + 1/tau) (v2 - v1)
    # in the velocity form (filtered gain km) or km - km/tau / (s + 1/tau) in the position
    # form (feedthrough km): |gain * direction| = km = 10 N/m within 10 % (the direction
    # comes from the static pair law, ~3 % off for a dynamic effect)
    g = np.asarray(rep.channel.G)[[rep.nominal.state_labels.index(e) for e in ("v1", "v2")], 0]
    q = rel[0]
    gain = dl.b[q] if dl.drivers[q] == "(v2-v1)" else dl.e[q]
    np.testing.assert_allclose(abs(gain * g[0]), KM, rtol=0.1)
    se = rep.table["updated"].se.value
    assert se < 1.5 * floor, (se, floor)


def _chain_positions(seed):
    """Two masses (unequal: 1 and 2 kg) with the coupling spring 20 N/m left out; positions only."""
    true = chain(2, k=20.0)
    A = np.asarray(true.A).copy()
    A[3] /= 2.0                                    # mass 2 weighs 2 kg
    B = np.asarray(true.B)
    nom = chain(2, k=20.0, missing=[(0, 1)], measured=["p1", "p2"])
    An = np.asarray(nom.A).copy()
    An[3] /= 2.0
    nom = gb.named_ss(An, B, nom.C, nom.D, 0, states=nom.state_labels, inputs=nom.input_labels,
                      outputs=nom.output_labels)
    d = draw(nom, LinearF(A, B), n_true=4, dt=0.01,
             rng=np.random.default_rng(seed), q_std=np.array([0.0, 1e-4] * 2), r_std=1e-3,
             n_est=20_000)
    return nom, d


@pytest.mark.parametrize("ratio", [-0.8, -0.5])
def test_a_force_law_refits_its_direction(ratio):
    """A force traced along a wrong direction (the pair law's, when d^ is noisy) refits it.

    True: the spring acts on v1 and v2 as [20, -10] per metre of (p2 - p1) (masses 1 and
    2 kg): ratio v2/v1 = -0.5. Traced along [1, -0.8] the law needs compensating terms;
    with the direction free the output error fit recovers -0.5 within its 95 % interval
    (about +-2e-4 at N = 2e4). Traced along the true direction, the data do not
    contradict it: no refitted direction is offered.
    """
    from greybox.trace import resolve_channel_spec, trace_channel
    from greybox.trace.channels import force_channel

    nom, d = _chain_positions(3)
    pair = resolve_channel_spec(nom, [("v1", "v2")])[0]
    fch = force_channel(nom, pair, np.array([1.0, ratio]))
    tr = trace_channel(nom, fch, d.y, d.u, Q=d.Q, R=d.R, dt=d.dt, max_order=0)
    assert tr.status == "ok", tr.reason
    if ratio == -0.5:
        assert tr.refined_G is None, tr.notes
        return
    assert tr.refined_G is not None, tr.notes
    g = np.asarray(tr.refined_G)[[1, 3], 0]
    note = next(s for s in tr.notes if "direction refitted" in s)
    half = float(note.split("(+-")[1].split(")")[0])
    assert half < 0.01, note                                  # the data pin the ratio
    # within 1.5x its 95 % half-width (~1.6e-4 here; 1.5x: one draw, 3 seeds tried gave
    # 0.6-0.7x)
    assert abs(g[1] / g[0] - (-0.5)) <= 1.5 * half, note


def test_among_shared_fits_of_one_size_the_lower_error_wins_unless_it_is_the_same_law():
    """The choice among a shared state's refined starts (``trace.dynamic._fewest_then_lowest``):
    the fewest parameters within 1 % of the lowest output error; at one size the lower
    error, the extra template start (flag 1) losing only to the same law (SEs within
    ``_SAME_LAW_RTOL``). The SEs are those of zoo thermal_mass 244465831 #0, where the
    flag alone had picked the local optimum (0.30216 %) over the true realization."""
    from types import SimpleNamespace as law

    from greybox.trace.dynamic import _SAME_LAW_RTOL, _fewest_then_lowest

    local, true = law(se_estimation=0.30216, npar=6), law(se_estimation=0.30198, npar=6)
    assert _fewest_then_lowest([(local, 0), (true, 1)]) is true
    scaled = law(se_estimation=0.30216 * (1 + 0.1 * _SAME_LAW_RTOL), npar=6)
    assert _fewest_then_lowest([(local, 0), (scaled, 1)]) is local  # one law: the ranked start
    dense = law(se_estimation=0.3000, npar=8)  # lower, but within 1 %: the sparser wins
    assert _fewest_then_lowest([(dense, 0), (local, 0), (true, 1)]) is true
    far = law(se_estimation=0.2900, npar=8)  # more than 1 % lower: the only one in reach
    assert _fewest_then_lowest([(far, 0), (true, 1)]) is far
