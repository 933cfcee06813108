"""The gated assignment (core.matching) that joint ids and the joint scores both use."""
import numpy as np
import pytest

from skel_extract_ros.core.matching import gated_assignment


def pairs(rows, cols):
    return sorted(zip(rows.tolist(), cols.tolist()))


def test_a_pair_within_the_gate_is_not_given_up_to_make_one_beyond_it_cheaper():
    # pairing A-K1 (within) leaves B-K2 at 1e5; pairing A-K2 and B-K1 (both beyond) costs
    # less in total: a rule that ranks the pairs beyond the gate by their cost takes that
    cost = np.array([[0.5, 5.0],
                     [100.0, 1e5]])
    assert pairs(*gated_assignment(cost, 1.0)) == [(0, 0)]


def test_the_most_pairs_within_the_gate_first_then_the_cheapest():
    cost = np.array([[0.1, 0.9],
                     [0.95, 1.5]])
    # the cheaper total (0.1 + 1.5, beyond) keeps one pair; two pairs within the gate win
    assert pairs(*gated_assignment(cost, 1.0)) == [(0, 1), (1, 0)]
    # among as many pairs within the gate, the cheapest
    cost = np.array([[0.1, 0.2],
                     [0.3, 0.9]])
    assert pairs(*gated_assignment(cost, 1.0)) == [(0, 1), (1, 0)]


def test_rectangular_nonfinite_and_empty_costs():
    cost = np.array([[np.inf, 0.2, 3.0],
                     [np.nan, 0.1, 0.4]])
    assert pairs(*gated_assignment(cost, 0.5)) == [(0, 1), (1, 2)]
    assert pairs(*gated_assignment(np.full((2, 2), np.inf), 1.0)) == []
    rows, cols = gated_assignment(np.zeros((0, 4)), 1.0)
    assert rows.shape == cols.shape == (0,)
    # a zero gate pairs exact matches only
    assert pairs(*gated_assignment(np.array([[0.0, 1.0], [1.0, 0.0]]), 0.0)) == [(0, 0), (1, 1)]
    with pytest.raises(ValueError, match='2-D'):
        gated_assignment(np.zeros(3), 1.0)
