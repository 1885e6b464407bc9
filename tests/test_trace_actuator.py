"""Actuator errors: an effect that enters where an input enters (G = B[:, j]).

Plant: two masses pushed apart by one actuator force F (B = [0, 1/m1, 0,
-1/m2], so F enters two state equations). The nominal model omits (a) a
gain error of +30 % and (b) a first-order actuator lag of 0.05 s. The trace
must name the input, not one of the equations, with the right law.
"""

from __future__ import annotations

import numpy as np
import pytest

import greybox as gb
from plantlib import draw, push_pair, with_actuator_lag, with_input_gain

Q_STD = np.array([0.0, 1e-4, 0.0, 1e-4])


def _run(kind, seed):
    nom = push_pair()
    f, nt = ((with_input_gain(nom, 1.3), 4) if kind == "gain"
             else (with_actuator_lag(nom, 0.05), 5))
    d = draw(nom, f, n_true=nt, dt=0.01, rng=np.random.default_rng(seed), q_std=Q_STD,
             r_std=1e-3)
    rep = gb.close_the_loop(nom, d.y, d.u, d.y_val, d.u_val, Q=d.Q, R=d.R, dt=d.dt,
                            delta=False)
    return rep, d


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(3))
def test_input_gain_error_named_with_interval(seed):
    rep, _ = _run("gain", seed)
    assert rep.updated and rep.channel.kind == "input", rep.message
    assert "input F" in rep.message and rep.effect.kind == "static"
    law = rep.effect.law
    j = [s[0] for s in law.spec].index("F")
    assert np.count_nonzero(law.coef) == 1            # one term: d_F = 0.3 F
    # +30 % gain: the 95 % interval covers 0.3 (P(miss) = 5 % per seed if calibrated;
    # 1 % of the value is > 10 half-widths, a gross error fails)
    assert abs(law.coef[0, j] - 0.3) <= max(law.ci[0, j], 0.0) or \
        abs(law.coef[0, j] - 0.3) < 0.003, (law.coef[0, j], law.ci[0, j])
    assert any("+30.0" in n for n in rep.effect.parameter_notes), rep.effect.parameter_notes
    # validation SE at the noise floor (measurement noise 1 mm against ~5 mm signals)
    assert rep.table["updated"].se.value < 0.05 * rep.table["nominal"].se.value


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(3))
def test_actuator_lag_named_with_time_constant(seed):
    rep, _ = _run("lag", seed)
    assert rep.updated and rep.channel.kind == "input", rep.message
    assert rep.effect.kind == "dynamic" and rep.effect.order == 1
    dl = rep.effect.dynamic_law
    assert dl is not None and dl.drivers == ("F",), rep.effect.formula
    # tau = 0.05 s: within 5 % (the interval is ~1 %; 5 % leaves room for a bad seed)
    np.testing.assert_allclose(dl.tau, 0.05, rtol=0.05)
    # d = -tau s/(tau s + 1) F: feedthrough -1, DC gain of the actuator 1
    np.testing.assert_allclose(dl.e[0], -1.0, atol=0.05)
    assert "reaches the plant through" in rep.effect.formula
    assert rep.table["updated"].se.value < 0.05 * rep.table["nominal"].se.value
