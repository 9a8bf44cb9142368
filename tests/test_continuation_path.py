"""The stages of a stiffness continuation: positions, interpolated factors and splits."""

import numpy as np
import pytest

from diffsolids.solvers.continuation import _MAX_SPLITS, _MIN_SPLIT_RATIO, ContinuationPath


def test_integer_positions_hold_each_terms_schedule_and_the_last_is_the_terms_own():
    path = ContinuationPath([(1e4, 1e2), (50.0,)])
    assert path.stages == 2 and path.positions == [0.0, 1.0, 2.0]
    assert path.factors(0) == pytest.approx([1e4, 50.0])
    assert path.factors(1) == pytest.approx([1e2, 1.0])
    assert path.factors(2) == pytest.approx([1.0, 1.0])
    assert path.largest_factors() == pytest.approx((1e4, 1e2))


def test_halfway_between_positions_is_the_geometric_mean():
    path = ContinuationPath([(1e4, 1e2)])
    assert path.factors(0.5) == pytest.approx([1e3])
    assert path.factors(1.5) == pytest.approx([10.0])
    assert path.factors(0.25) == pytest.approx([10**3.5])


def test_a_failed_stage_is_split_halfway_from_the_last_converged_one():
    path = ContinuationPath([(1e4, 1e2)])
    assert path.split(2, converged_at=1.0)  # the last stage (factor 1) failed after 1e2
    assert path.positions == [0.0, 1.0, 1.5, 2.0]
    assert path.largest_factors() == pytest.approx((1e4, 1e2, 10.0))
    # the inserted stage fails too: split again, between 1 and 1.5
    assert path.split(2, converged_at=1.0)
    assert path.positions == [0.0, 1.0, 1.25, 1.5, 2.0]


def test_splits_stop_at_the_ratio_floor_and_the_split_budget():
    near = ContinuationPath([(0.9 * _MIN_SPLIT_RATIO,)])
    assert not near.split(1, converged_at=0.0)
    assert near.positions == [0.0, 1.0]
    far = ContinuationPath([(1e30,)])
    for _ in range(_MAX_SPLITS):
        assert far.split(1, converged_at=0.0)
    assert not far.split(1, converged_at=0.0)
    assert len(far.positions) == 2 + _MAX_SPLITS
    assert np.all(np.diff(far.positions) > 0)


def test_no_schedule_no_stages():
    path = ContinuationPath([(), ()])
    assert path.stages == 0 and path.positions == [0.0]
    assert path.largest_factors() == ()
