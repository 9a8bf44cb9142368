"""Observers of accepted iterates: ``minimize(rf, on_accept=[...])``.

The optimiser calls each observer as ``observer(record, optimizer)`` once per accepted iterate
(the initial point included), on every rank; ``optimizer.point`` is the accepted iterate (its
``q``, ``J``, ``g`` and ``trajectory``) and ``optimizer.rf`` its reduced functional (a new one
after remeshing), whose model holds the iterate.
"""

from typing import TYPE_CHECKING

from diffsolids.optimize.invariants import BoundaryIntersection, inverted_rest_cells

if TYPE_CHECKING:
    from diffsolids.optimize.monitor import IterationRecord
    from diffsolids.optimize.optimizer import LBFGS

__all__ = ["InvariantMonitor", "TrajectoryKeeper"]


class TrajectoryKeeper:
    """Keeps the trajectories of the first and the last accepted iterate (no extra solve).

    Attributes:
        first: Trajectory of the initial iterate (None before the run).
        last: Trajectory of the last accepted iterate.
        accepted: Accepted iterates seen.
    """

    def __init__(self) -> None:
        self.first = None
        self.last = None
        self.accepted = 0

    def __call__(self, record: "IterationRecord", optimizer: "LBFGS") -> None:
        """Keep the accepted iterate's trajectory."""
        traj = optimizer.point.trajectory
        if self.first is None:
            self.first = traj
        self.last = traj
        self.accepted += 1


class InvariantMonitor:
    """Counts accepted shape iterates that break an invariant (collective).

    Per accepted iterate: inverted cells of the rest mesh against the original mesh, a rest
    boundary that intersects itself (or another body) and, with ``deformed``, an intersecting
    deformed boundary at the last state of the iterate's trajectory.

    Args:
        deformed: Also check the deformed boundary.

    Attributes:
        inverted: Iterates with inverted rest cells.
        intersecting: Iterates with an intersecting rest boundary.
        intersecting_deformed: Iterates with an intersecting deformed boundary (``deformed``).
        checked: Iterates checked.
    """

    def __init__(self, deformed: bool = False) -> None:
        self.deformed = deformed
        self.inverted = 0
        self.intersecting = 0
        self.intersecting_deformed = 0
        self.checked = 0
        self._checks: dict[int, BoundaryIntersection] = {}

    def __call__(self, record: "IterationRecord", optimizer: "LBFGS") -> None:
        """Check the accepted iterate of ``optimizer``."""
        rf = optimizer.rf
        model = rf.model
        if id(model) not in self._checks:  # a new model after remeshing
            self._checks[id(model)] = BoundaryIntersection(model)
        check = self._checks[id(model)]
        self.inverted += int(inverted_rest_cells(model) > 0)
        self.intersecting += int(check.intersects())
        if self.deformed:
            last = len(rf.trajectory.u) - 1
            self.intersecting_deformed += int(check.intersects(rf.trajectory.u[-1], last))
        self.checked += 1
