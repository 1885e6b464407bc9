"""Property test of the public API (issue 13): bad values give a greybox error, never another.

For every public function a small valid call is built; hypothesis replaces
one argument at a time by a random value (random shapes and dtypes, NaN and
inf, magnitudes from 1e-300 to 1e300, strings, None, ragged lists, the
valid value transposed, truncated or scaled) and the test asserts the
outcome is either a :class:`greybox.GreyboxError` or a result whose arrays
are finite and of the documented shape. Any other exception (TypeError,
IndexError, LinAlgError, a RuntimeWarning turned error, ...) fails.
"""

from __future__ import annotations

import warnings

import control as ct
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import greybox as gb
from greybox.filters import FilterResult

N = 240  # delta_update needs at least 200 samples
_RNG = np.random.default_rng(7)
A = np.array([[0.9, 0.1], [0.0, 0.7]])
B = np.array([[0.0], [1.0]])
C = np.eye(2)
SYS = gb.named_ss(A, B, C, np.zeros((2, 1)), 0.1, states=["x0", "x1"], inputs=["u0"],
                  outputs=["y0", "y1"])
SYS_D = gb.named_ss(A, np.hstack([B, [[1.0], [0.5]]]), C, np.zeros((2, 2)), 0.1,
                    states=["x0", "x1"], inputs=["u0", "d0"], outputs=["y0", "y1"])
U = _RNG.standard_normal((1, N))
Y = gb.simulate(SYS, U, R=1e-3 * np.eye(2), rng=1).y
Q, R = 1e-4 * np.eye(2), 1e-3 * np.eye(2)


def _finite(*arrays):
    for a in arrays:
        a = np.asarray(a)
        assert np.all(np.isfinite(a)), "non-finite result"


def _check_filter(res, args):
    assert isinstance(res, FilterResult)
    assert res.x_filt.shape == (2, np.asarray(args["y"]).reshape(2, -1).shape[1])
    _finite(res.x_filt, res.innovations)


def _check_sim(res, args):
    assert res.y.shape[0] == 2
    _finite(res.y, res.x)


def _sig(nsig):
    return lambda res, args: (res.shape[0] == nsig and _finite(res)) or True


# name -> (function, valid keyword arguments, result check)
SPECS = {
    "kalman_filter": (gb.kalman_filter, dict(sys=SYS, y=Y, u=U, Q=Q, R=R), _check_filter),
    "uikf": (gb.uikf, dict(sys=SYS_D, y=Y, u=U, unknown="d0", Q=Q, R=R), _check_filter),
    "steady_state_filter": (gb.steady_state_filter, dict(sys=SYS, Q=Q, R=R),
                            lambda r, a: _finite(r.L) or True),
    "simulate": (gb.simulate, dict(sys=SYS, u=U, x0=[0.1, 0.0], Q=Q, R=R, rng=0), _check_sim),
    "relative_error": (gb.relative_error, dict(y=Y, y_hat=0.9 * Y, skip=0),
                       lambda r, a: _finite(r.value)),
    "autocorrelation": (gb.autocorrelation, dict(e=Y, maxlag=5), _sig(2)),
    "cross_correlation": (gb.cross_correlation, dict(u=U, e=Y, maxlag=5),
                          lambda r, a: _finite(r)),
    "whiteness_test": (gb.whiteness_test, dict(e=Y, lags=5, alpha=0.01),
                       lambda r, a: _finite(r.pvalue)),
    "random_binary": (gb.random_binary, dict(nsteps=50, nsignals=2, amplitude=1.0, hold=2,
                                             rng=0), _sig(2)),
    "multisine": (gb.multisine, dict(nsteps=50, dt=0.1, nsignals=1, amplitude=1.0, nfreq=5,
                                     rng=0), _sig(1)),
    "lowpass_noise": (gb.lowpass_noise, dict(nsteps=50, dt=0.1, bandwidth=1.0, nsignals=1,
                                             rng=0), _sig(1)),
    "discretize": (gb.discretize, dict(sys=ct.ss(-np.eye(2), np.ones((2, 1)), np.eye(2),
                                                 np.zeros((2, 1))), dt=0.1),
                   lambda r, a: _finite(r.A, r.B)),
    "n4sid": (gb.n4sid, dict(y=Y, u=U, order=2, horizon=4, chunk_size=64),
              lambda r, a: _finite(r.sys.A, r.sys.B, r.sys.C)),
    "pbsid": (gb.pbsid, dict(y=Y, u=U, order=2, horizon=4),
              lambda r, a: _finite(r.sys.A, r.sys.B, r.sys.C)),
    "static_least_squares": (gb.static_least_squares, dict(w=np.vstack([Y, U]), d=Y[:1]),
                             lambda r, a: True),
    "estimate_initial_state": (gb.estimate_initial_state, dict(sys=SYS, y=Y, u=U, nsamples=20),
                               lambda r, a: r.shape == (2,) and _finite(r) or True),
    "validate_model": (gb.validate_model, dict(sys=SYS, y=Y, u=U, Q=Q, R=R, x0="estimate",
                                               lags=5, skip=2),
                       lambda r, a: _finite(r.pe.value)),
    "named_ss": (gb.named_ss, dict(A=A, B=B, C=C, D=np.zeros((2, 1)), dt=0.1,
                                   states=["a", "b"], inputs=["u"], outputs=["p", "q"]),
                 lambda r, a: r.nstates == 2 or True),
    "split_inputs": (gb.split_inputs, dict(sys=SYS_D, unknown="d0"), lambda r, a: True),
    "tape_drive_nominal": (gb.tape_drive_nominal, dict(dt=1e-4, with_tension_input=True),
                           lambda r, a: _finite(r.A)),
    "output_error": (gb.output_error, dict(d=Y[:1], w=np.vstack([U, Y[1:]]), order=1,
                                           starts=1, maxiter=20),
                     lambda r, a: True),
    "forward_selection": (gb.forward_selection, dict(terms=np.vstack([Y, U]), d=Y[:1],
                                                     names=["a", "b", "c"], max_terms=2),
                          lambda r, a: True),
    "delta_update": (gb.delta_update, dict(sys=SYS, y=Y, u=U, Q=Q, R=R, order=1, horizon=4),
                     lambda r, a: _finite(r.updated.sys.A)),
    "close_the_loop": (gb.close_the_loop, dict(sys=SYS, y=np.tile(Y, 2), u=np.tile(U, 2),
                                               y_val=Y, u_val=U, Q=Q, R=R, lags=5,
                                               max_order=1, delta=False),
                       lambda r, a: np.isfinite(r.table["nominal"].pe.value) or True),
    "check_rank_condition": (gb.check_rank_condition, dict(C=C, G=np.array([[1.0], [0.5]])),
                             lambda r, a: True),
}


def _variants(valid):
    """Strategy of bad (or odd) replacements of one valid argument value."""
    base = [st.none(), st.just("abc"), st.just([[1.0, 2.0], [3.0]]), st.just(object()),
            st.just(True), st.just(-1), st.just(0), st.just(10 ** 5), st.just(float("nan")),
            st.just(float("inf")), st.just(1e300), st.just(1e-300), st.just([]),
            st.just(np.zeros((0, 3)))]
    arrays = hnp.arrays(
        dtype=st.sampled_from([np.float64, np.float32, np.int64, np.complex128, np.bool_]),
        shape=hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=5),
        elements=None)
    out = base + [arrays]
    a = None
    if isinstance(valid, np.ndarray) or (isinstance(valid, list) and valid and
                                         not isinstance(valid[0], str)):
        a = np.asarray(valid, dtype=float)
    if a is not None and a.size:
        def poke(v):
            b = a.copy()
            b.flat[len(b.flat) // 2] = v
            return b
        out += [st.sampled_from([1e-300, 1e-200, 1e200, 1e300, -1e300]).map(lambda s: a * s),
                st.sampled_from([np.nan, np.inf, -np.inf, 1e308]).map(poke),
                st.just(a.T), st.just(a[..., :1]), st.just(a.astype(np.int64)),
                st.just(a + 0j), st.just(a.astype(np.float32)), st.just(a.reshape(-1)),
                st.just(a[None])]
    if isinstance(valid, (int, float)) and not isinstance(valid, bool):
        out += [st.just(str(valid)), st.just(np.float64(valid)), st.just(-valid),
                # (sizes between 1e5 and 1e13 are legal but would fill the test machine)
                st.floats(allow_nan=True, allow_infinity=True).filter(
                    lambda v: not 1e5 < abs(v) < 1e13)]
    if isinstance(valid, ct.StateSpace):
        out += [st.just(ct.ss(valid.A, valid.B, valid.C, valid.D)),  # continuous
                st.just(ct.tf([1], [1, 0.5], 0.1)), st.just(np.eye(2))]
    return st.one_of(out)


@pytest.mark.parametrize("name", sorted(SPECS))
@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(data=st.data())
def test_public_functions_fail_only_with_greybox_errors(name, data):
    func, valid, check = SPECS[name]
    key = data.draw(st.sampled_from(sorted(valid)), label="argument")
    value = data.draw(_variants(valid[key]), label="value")
    args = dict(valid, **{key: value})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", gb.GreyboxWarning)
        try:
            res = func(**args)
        except gb.GreyboxError:
            return
    check(res, args)


@pytest.mark.parametrize("name", sorted(SPECS))
def test_valid_calls_pass_their_check(name):
    """The checks themselves can fail only on bad output: the valid call passes them."""
    func, valid, check = SPECS[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", gb.GreyboxWarning)
        check(func(**valid), valid)


def test_issue_13_edges():
    with pytest.raises(gb.DimensionError, match="chunk_size"):
        gb.n4sid(Y, U, chunk_size=0)
    with pytest.raises(gb.DataError, match="rescale"):
        gb.n4sid(Y * 1e200, U)
    res = gb.n4sid(Y * 1e100, U, order=2)  # large but representable: scaled, same model
    ref = gb.n4sid(Y, U, order=2)
    # the poles are scale-invariant: equal up to rounding of the scaled data
    np.testing.assert_allclose(np.sort_complex(res.sys.poles()), np.sort_complex(ref.sys.poles()),
                               rtol=1e-8)
    with pytest.raises(gb.DimensionError, match="min_se_drop"):
        gb.close_the_loop(SYS, np.tile(Y, 2), np.tile(U, 2), Y, U, Q=Q, R=R,
                          min_se_drop="0.8")
    with pytest.raises(gb.DimensionError, match="nsteps = 50 but u has 240"):
        gb.simulate(SYS, U, nsteps=50)
    assert gb.simulate(SYS, U, nsteps=N).y.shape == (2, N)
