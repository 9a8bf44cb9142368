"""Checks of the invariants the optimiser keeps: no inverted element, no intersection.

The optimiser accepts only valid iterates (see :mod:`diffsolids.optimize.optimizer`); these
functions verify that after the fact, for reports and tests:

- :func:`check_trajectories`: every state of given trajectories, det F > 0 at the quadrature
  points (the solver's inversion guard) and, with a contact term, no intersecting collision
  surface (with the smallest distance);
- :func:`min_volume_ratio`: the smallest deformed/rest volume ratio of the cells of one state
  (also for laws without an inversion guard, e.g. linear elasticity);
- :func:`inverted_rest_cells` and :class:`BoundaryIntersection`: the rest mesh of a shape
  iterate (cells flipped against the original mesh; a boundary folded over itself or over
  another body, which can happen without inverted cells).

All of them are collective over the mesh communicator and return the same value on every rank.
"""

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from mpi4py import MPI

from diffsolids.contact.boundary_intersection import BoundaryIntersection
from diffsolids.contact.term import ContactTerm
from diffsolids.errors import IntersectionError
from diffsolids.io.geometry import nodal_displacement
from diffsolids.mesh import inverted_cells, signed_cell_volumes
from diffsolids.parallel import collective_comm

if TYPE_CHECKING:
    from diffsolids.model import Model
    from diffsolids.simulation import Simulation, Trajectory

__all__ = [
    "BoundaryIntersection",
    "StateChecks",
    "check_trajectories",
    "inverted_rest_cells",
    "min_volume_ratio",
]


@dataclass(frozen=True)
class StateChecks:
    """Result of :func:`check_trajectories`.

    Attributes:
        states: States checked.
        inverted: States with an inverted element (det F <= 0 at a quadrature point).
        intersecting: States whose collision surface intersects (or touches).
        min_distance: Smallest distance between collision primitives over the other states
            (infinity without a contact term).
    """

    states: int
    inverted: int
    intersecting: int
    min_distance: float


def check_trajectories(
    simulation: "Simulation",
    trajectories: Iterable["Trajectory"],
    contact: ContactTerm | None = None,
) -> StateChecks:
    """Check every state of the trajectories for inverted elements and intersections.

    Args:
        simulation: The Simulation of the trajectories (its solver's inversion guard; a law
            without one, e.g. linear elasticity, counts no state as inverted: use
            :func:`min_volume_ratio` there).
        trajectories: Trajectories of ``simulation``'s model.
        contact: Optional ContactTerm whose collision surface is checked at every state
            (``check_configuration``: intersecting or closer than its ``min_gap``).

    Returns:
        The counts; the model's ``u`` is unchanged.
    """
    u = simulation.model.fields.u
    saved = u.x.array.copy()
    states = inverted = intersecting = 0
    distance = np.inf
    try:
        for traj in trajectories:
            for i, state in enumerate(traj.u):
                states += 1
                u.x.array[:] = state
                inverted += int(simulation.solver.inverted())
                if contact is None:
                    continue
                try:
                    gap = contact.check_configuration(contact.surface.gather(state), i)
                    distance = min(distance, gap)
                except IntersectionError:
                    intersecting += 1
    finally:
        u.x.array[:] = saved
    return StateChecks(states, inverted, intersecting, float(distance))


def min_volume_ratio(model: "Model", u: np.ndarray) -> float:
    """Smallest deformed/rest volume ratio of the cells deformed by ``u`` at their vertices.

    A non-positive value means an inverted element.

    Args:
        model: The Model.
        u: Local displacement array.
    """
    mesh = model.domain.mesh
    d = model.dim
    owned = mesh.topology.index_map(mesh.topology.dim).size_local
    x = mesh.geometry.x.copy()
    x[:, :d] += nodal_displacement(model, u)
    rest = signed_cell_volumes(mesh)[:owned]
    deformed = signed_cell_volumes(mesh, x)[:owned]
    local = float((deformed / rest).min()) if owned else np.inf
    return collective_comm(mesh.comm).allreduce(local, op=MPI.MIN)


def inverted_rest_cells(model: "Model") -> int:
    """Cells of the model's current rest mesh whose orientation flipped against the original."""
    mesh = model.domain.mesh
    owned = mesh.topology.index_map(mesh.topology.dim).size_local
    bad = inverted_cells(mesh, model.reference_signs)
    local = int(np.count_nonzero(bad < owned))  # ghost cells are counted by their owners
    return collective_comm(model.domain.comm).allreduce(local, op=MPI.SUM)
