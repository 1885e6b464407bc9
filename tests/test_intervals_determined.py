"""An interval the data do not determine is said so, never printed as ± 1e-19."""

from __future__ import annotations

import numpy as np

from greybox.trace.intervals import UNDETERMINED_COND, undetermined
from greybox.trace.laws import _fmt_sum


def test_collinear_columns_are_not_determined_the_others_are():
    rng = np.random.default_rng(0)
    a, b, c = rng.standard_normal((3, 2000))
    assert not undetermined(np.c_[a, b, c]).any()
    # b2 = 3 a (exactly, and to a part in 1e9): a and b2 cannot be told apart; c can
    for eps in (0.0, 1e-9):
        mask = undetermined(np.c_[a, 3.0 * a + eps * b, c])
        assert mask.tolist() == [True, True, False], (eps, mask)
    # a zero column (a term that never moves) is not determined either
    assert undetermined(np.c_[a, np.zeros(2000)]).tolist() == [False, True]


def test_the_limit_is_the_condition_number_not_the_scale():
    """Column scale does not matter (a term in mm beside one in km); near-collinearity
    just inside the limit stays determined."""
    rng = np.random.default_rng(1)
    a, b = rng.standard_normal((2, 5000))
    assert not undetermined(np.c_[1e-6 * a, 1e6 * b]).any()
    # correlation 1 - 1/(2 cond^2) at 100x inside the limit: still determined
    near = a + (100.0 / UNDETERMINED_COND) * b
    assert not undetermined(np.c_[a, near]).any()
    far = a + (0.01 / UNDETERMINED_COND) * b
    assert undetermined(np.c_[a, far]).all()


def test_a_term_without_interval_is_printed_as_not_determined():
    txt = _fmt_sum(np.array([-2.4e-4, 0.5]), ["v", "sign(v)"], np.array([np.inf, 0.0074]))
    assert txt == "-(0.00024, interval not determined)*v + (0.5 ± 0.0074)*sign(v)"
    assert "e-19" not in txt
