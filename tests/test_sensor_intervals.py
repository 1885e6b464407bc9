"""The interval of a sensor's static law (a gain, an offset) under process noise.

A sensor law is fitted by least squares of the measured output on the terms of the
model's simulated output (it does not feed back into the states). With process noise
the simulation's error is a coloured, slowly wandering signal (the integrated
disturbance), which the residual's own autocorrelation (HAC) understates; the interval
is the larger of the HAC one and the sandwich under the model's noise (Q, R), as the
other output-error intervals.

Truth: a mass-spring-damper whose position sensor reads 0.8x, process noise on the
velocity, Monte Carlo over seeds.
"""

from __future__ import annotations

import numpy as np

import greybox as gb
from greybox._lti import lti_states
from greybox.terms import output_terms
from greybox.trace.channel_trace import refit_sensor_on_states
from greybox.trace.laws import StaticLaw
from plantlib import msd

DT, N, GAIN = 0.02, 4000, -0.2  # the sensor reads (1 + GAIN) pos
Q_STD, R_STD = 1e-3, 1e-3


def _fit(seed: int, noise: bool):
    """(coefficient, 95 % half-width) of the gain fitted on one record."""
    nom = gb.discretize(msd(), DT)
    A, B = np.asarray(nom.A, dtype=float), np.asarray(nom.B, dtype=float)
    c, dd = np.array([1.0, 0.0]), np.zeros(1)
    Q = np.diag([0.0, Q_STD**2]) + 1e-12 * np.eye(2)
    rng = np.random.default_rng(seed)
    u = gb.lowpass_noise(N, dt=DT, bandwidth=1.0, amplitude=2.0, rng=rng).reshape(1, -1)
    w = np.sqrt(np.diag(Q))[:, None] * rng.standard_normal((2, N))
    x_true = lti_states(A, B @ u + w, np.zeros(2))
    x_sim = lti_states(A, B @ u, np.zeros(2))
    y = (1 + GAIN) * x_true[0] + R_STD * rng.standard_normal(N)
    _, spec, eps = output_terms(x_sim, u, c, dd, "pos")
    coef = np.zeros((1, len(spec)))
    coef[0, 0] = -0.1  # the gain term selected (its value from the d^ fit, refitted here)
    law = StaticLaw(spec=tuple(spec), eps=eps, coef=coef, Ddx=np.zeros((1, 2)),
                    Ddu=np.zeros((1, 1)), nonlinear=True, residual_var=np.ones(1),
                    bic_gain=0.0, npar=1, formula="", ci=np.zeros_like(coef), output=0)
    new = refit_sensor_on_states(law, x_sim, c, dd, y, u, "pos", "m", [],
                                 noise=(A, Q, R_STD**2) if noise else None)
    return new.coef[0, 0], new.ci[0, 0]


def test_a_sensor_gain_interval_covers_the_truth_under_process_noise():
    """200 records: the interval with the noise model covers the true gain in >= 90 %
    (measured 99.5 %: the larger of two variances is conservative); the residual's HAC
    alone covers it in 80.5 % (its standardized errors' spread 1.67, not 1): until
    2026-11-28 the only interval of a refitted sensor law (the two-sensor gains of
    test_joint_refit: one 2.6 half-widths off). Binomial: at a true coverage of 95 %, 200
    draws fall below 90 % with probability ~0.002; the estimate is unbiased either way."""
    covered = {}
    for noise in (False, True):
        fits = np.array([_fit(seed, noise) for seed in range(200)])
        z = (fits[:, 0] - GAIN) / fits[:, 1]
        covered[noise] = float(np.mean(np.abs(z) <= 1.0))
        # unbiased: the mean over 200 records within 3 standard errors of the truth
        sd = np.std(fits[:, 0])
        assert abs(np.mean(fits[:, 0]) - GAIN) <= 3 * sd / np.sqrt(fits.shape[0]), fits[:5]
    assert covered[True] >= 0.90, covered
    assert covered[False] < 0.90, covered  # the HAC interval alone understates (the why)


def test_a_sensor_refit_within_its_interval_does_not_run_the_pass_again():
    """After a later effect, an earlier sensor law is refitted on the updated model; the
    pass is run again only where a refitted coefficient moved by its 95 % half-width or
    more (the data cannot tell the two laws apart otherwise). In the order-3 thermal test's
    sensor-first alternative the pass ran again after a refit that moved nothing (SE 33.4 %
    -> 33.4 %), 22 s of its 54 (seed 1; 35 s without the rerun, same verdict)."""
    from greybox.workflow import _within_interval

    _, spec, eps = output_terms(np.ones((2, 5)), np.zeros((1, 5)), [1.0, 0.0], [0.0], "pos")

    def law(g, off, half=(0.001, 0.01), sel=(0, 3)):
        coef, ci = np.zeros((1, len(spec))), np.full((1, len(spec)), np.nan)
        coef[0, list(sel)] = [g, off][:len(sel)]
        ci[0, list(sel)] = half[:len(sel)]
        return StaticLaw(spec=tuple(spec), eps=eps, coef=coef, Ddx=np.zeros((1, 2)),
                         Ddu=np.zeros((1, 1)), nonlinear=True, residual_var=np.ones(1),
                         bic_gain=0.0, npar=len(sel), formula="", ci=ci, output=0)

    old = law(-0.2, 0.05)
    assert _within_interval(old, old)
    assert _within_interval(old, law(-0.2009, 0.059))       # both inside their half-widths
    assert not _within_interval(old, law(-0.2011, 0.05))    # the gain moved by more
    assert not _within_interval(old, law(-0.2, 0.0611))     # the offset moved by more
    assert not _within_interval(old, law(-0.2, 0.05, sel=(0,)))  # a term dropped
    assert not _within_interval(old, law(-0.2, 0.05, half=(np.nan, 0.01)))  # undetermined
