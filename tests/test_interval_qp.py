"""The predictive filter's QP form (``lo <= A x <= hi``) against solutions worked by hand."""

import numpy as np
import pytest
import scipy.sparse as sp

from saferace.safety.cbf.interval_qp import IntervalQP

#: Rows: ``a0 x0 + x1`` (an equality where ``lo == hi``), ``x2``, ``x0``, ``x2`` again.
ROWS = sp.csc_matrix(np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
IDENTITY = sp.identity(3, format="csc")


def _problem(target, a0=1.0, sum_bounds=(1.0, 1.0), x2_above=-np.inf):
    """``min 1/2 |x - target|^2`` s.t. ``a0 x0 + x1`` in ``sum_bounds``, ``x2 <= 0.5``,
    ``x0 >= 0`` and ``x2 >= x2_above``: the QP's vectors and the rows' values."""
    a = ROWS.toarray()
    a[0, 0] = a0
    lo = np.array([sum_bounds[0], -np.inf, 0.0, x2_above])
    hi = np.array([sum_bounds[1], 0.5, np.inf, np.inf])
    return IDENTITY.data.copy(), -np.asarray(target, float), sp.csc_matrix(a).data, lo, hi


def test_an_equality_and_one_sided_rows_give_the_hand_solution():
    qp = IntervalQP(ROWS, IDENTITY)
    # x0 + x1 = 1 nearest (2, 0): (1.5, -0.5); x2 clipped to 0.5.
    np.testing.assert_allclose(qp.solve(*_problem([2.0, 0.0, 3.0])), [1.5, -0.5, 0.5], atol=1e-6)


def test_new_row_values_on_the_same_rows_are_taken():
    qp = IntervalQP(ROWS, IDENTITY)
    qp.solve(*_problem([2.0, 0.0, 3.0]))
    # 2 x0 + x1 = 1 nearest (2, 0): x = t - 0.6 (2, 1).
    x = qp.solve(*_problem([2.0, 0.0, 3.0], a0=2.0))
    np.testing.assert_allclose(x, [0.8, -0.6, 0.5], atol=1e-6)


def test_an_equality_that_becomes_an_inequality_is_set_up_anew():
    qp = IntervalQP(ROWS, IDENTITY)
    qp.solve(*_problem([0.2, 0.1, 0.0]))  # x0 + x1 = 1 binds: (0.55, 0.45)
    x = qp.solve(*_problem([0.2, 0.1, 0.0], sum_bounds=(-np.inf, 1.0)))  # now free
    np.testing.assert_allclose(x, [0.2, 0.1, 0.0], atol=1e-6)
    x = qp.solve(*_problem([0.2, 0.1, 0.0]))
    np.testing.assert_allclose(x, [0.55, 0.45, 0.0], atol=1e-6)


@pytest.mark.parametrize("x2_above", [1.0, 0.6])
def test_contradicting_rows_give_none(x2_above):
    qp = IntervalQP(ROWS, IDENTITY)
    assert qp.solve(*_problem([0.0, 0.0, 0.0], x2_above=x2_above)) is None


def test_it_solves_again_after_an_infeasible_problem():
    qp = IntervalQP(ROWS, IDENTITY)
    assert qp.solve(*_problem([0.0, 0.0, 0.0], x2_above=1.0)) is None
    x = qp.solve(*_problem([0.0, 0.0, 0.0], x2_above=0.25))
    np.testing.assert_allclose(x, [0.5, 0.5, 0.25], atol=1e-6)
