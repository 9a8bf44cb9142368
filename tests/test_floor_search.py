"""FloorSearch: one parameter projected out, the other along the floor of J's valley."""

import numpy as np
import pytest
from mpi4py import MPI
from optimize_script import bar_problem

from diffsolids.optimize import FloorSearch, OptimizationError


def test_floor_search_recovers_both_moduli(bar2):
    """The two bodies' log E from E = 1000 each: the truth, stopped by the step tolerance."""
    rf, q_true = bar2
    q0 = rf.initial_parameters()
    search = FloorSearch(rf, max_change=(1.0, 1.0), step_tol=(1e-8, 1e-6), max_evaluations=60)
    result = search.run(q0)
    assert result.reason == "step", result.message
    assert np.allclose(result.q, q_true, rtol=0, atol=1e-5)
    # one record per evaluation; the result is the lowest J evaluated
    values = [r.objective for r in result.history]
    assert len(values) == result.num_forward == result.iterations + 1 < 60
    assert result.objective == min(values) < 1e-10 * values[0]
    assert np.array_equal(result.history[0].q, q0)
    assert search.keeper.first is not None and search.keeper.last is not None
    rf.controls.assign(q0)


def test_floor_search_stops_at_the_evaluation_limit(bar2):
    rf, _ = bar2
    q0 = rf.initial_parameters()
    result = FloorSearch(rf, (1.0, 1.0), (1e-8, 1e-6), max_evaluations=3).run(q0)
    assert result.reason == "max_iterations"
    assert len(result.history) == 3
    rf.controls.assign(q0)


def test_floor_search_refuses_bad_input(bar2):
    rf, _ = bar2
    with pytest.raises(OptimizationError, match="step_tol must be two positive"):
        FloorSearch(rf, (1.0, 1.0), (1e-8, 0.0), 10)
    with pytest.raises(OptimizationError, match="max_change must be two positive"):
        FloorSearch(rf, (1.0,), (1e-8, 1e-6), 10)
    one, _ = bar_problem(MPI.COMM_WORLD, bodies=1)
    with pytest.raises(OptimizationError, match="two parameters"):
        FloorSearch(one, (1.0, 1.0), (1e-8, 1e-6), 10)


class _BentValley:
    """J(a, b) = 100 (a - b^2)^2 + (1 - b)^2 (floor a = b^2, minimum at (1, 1)) behind the
    protocol members FloorSearch uses; the controls (for the log) are the bar's."""

    def __init__(self, rf):
        self.comm, self.controls, self.model = rf.comm, rf.controls, rf.model
        self.size, self.trajectory = 2, None
        self.q = None

    def bounds(self):
        return np.full(2, -np.inf), np.full(2, np.inf)

    def forward(self, q):
        self.q = np.asarray(q, dtype=float)
        a, b = self.q
        return 100.0 * (a - b * b) ** 2 + (1.0 - b) ** 2

    def derivative(self):
        a, b = self.q
        return np.array([200.0 * (a - b * b), -400.0 * b * (a - b * b) - 2.0 * (1.0 - b)])

    def term_values(self):
        return {"J": self.forward(self.q)}


def test_floor_search_follows_a_bent_floor(bar2):
    """From (0, -1), across the valley's bend: the minimum in few evaluations."""
    rf, _ = bar2
    valley = _BentValley(rf)
    search = FloorSearch(valley, (1.0, 0.5), (1e-10, 1e-8), max_evaluations=100)
    result = search.run([0.0, -1.0])
    assert result.reason == "step", result.message
    assert np.allclose(result.q, [1.0, 1.0], rtol=0, atol=1e-6)
    assert len(result.history) <= 30
