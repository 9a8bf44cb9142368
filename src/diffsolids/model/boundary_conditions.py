"""Dirichlet conditions on tagged facets, whole bodies or located nodes, constant or in time."""

import inspect
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import dolfinx.mesh
import numpy as np
from dolfinx import fem
from mpi4py import MPI

from diffsolids.errors import ParameterError, TagError
from diffsolids.parallel import collective_comm

if TYPE_CHECKING:
    from diffsolids.mesh import Domain

__all__ = ["DirichletCondition", "OnBody", "RealisedDirichlet"]

Value = float | Sequence[float] | Callable


@dataclass(frozen=True)
class OnBody:
    """Where a Dirichlet condition holds: every node of a body (all dofs of its cells).

    A body meshed together with another (shared interface nodes) constrains the interface too.
    Prescribing a body's whole motion is how a driven rigid part (a PolyFEM volume selection
    with a Dirichlet condition, an indenter, a moving support) enters the FE system; geometry
    that only collides is better a kinematic :class:`~diffsolids.contact.Obstacle`.

    Attributes:
        body: The body's cell tag (id or name).
    """

    body: int | str


@dataclass
class DirichletCondition:
    """Prescribed displacement.

    Attributes:
        where: A facet tag (id or name), a whole body (:class:`OnBody`), or a node locator
            ``marker(x) -> bool mask``.
        value: Displacement: a scalar (all constrained components), a vector, ``value(t)``
            returning a vector, or ``value(x, t)`` returning an array of shape (d, num_points).
        components: Constrained components (default: all).
    """

    where: int | str | OnBody | Callable
    value: Value = 0.0
    components: Sequence[int] | None = None

    def time_dependent(self) -> bool:
        """Whether the value is a function of time."""
        return callable(self.value)


class RealisedDirichlet:
    """A DirichletCondition located on a function space: one DOLFINx BC per component.

    Attributes:
        bcs: The DOLFINx Dirichlet conditions (one per constrained component).
        dofs: Sorted unrolled local indices (owned and ghost) of all constrained dofs.
    """

    def __init__(
        self, condition: DirichletCondition, V: fem.FunctionSpace, domain: "Domain"
    ) -> None:
        self.condition = condition
        mesh = V.mesh
        self.dim = mesh.geometry.dim
        comps = (
            list(range(self.dim)) if condition.components is None else list(condition.components)
        )
        if not comps or any(c < 0 or c >= self.dim for c in comps):
            raise ParameterError(f"Dirichlet components {comps} invalid for dimension {self.dim}")
        self.components = comps
        self._nparams = _num_params(condition.value)
        dim, entities = _located_entities(condition.where, mesh, domain)
        self._parts = []  # (component, function in collapsed space, collapsed dof indices)
        self.bcs = []
        for c in comps:
            Vc, _ = V.sub(c).collapse()
            if entities is None:
                pair = fem.locate_dofs_geometrical((V.sub(c), Vc), condition.where)
            else:
                pair = fem.locate_dofs_topological((V.sub(c), Vc), dim, entities)
            gc = fem.Function(Vc)
            self._parts.append((c, gc, pair[1], Vc))
            self.bcs.append(fem.dirichletbc(gc, pair, V.sub(c)))
        count = collective_comm(mesh.comm).allreduce(len(self._parts[0][2]), op=MPI.SUM)
        if count == 0:
            raise TagError(f"Dirichlet condition on {condition.where!r} constrains no dof")
        self.dofs = np.unique(np.concatenate([bc.dof_indices()[0] for bc in self.bcs]))
        self.update(0.0)

    def set_value(self, value: Value) -> None:
        """Replace the prescribed value (same forms as DirichletCondition.value)."""
        self._nparams = _num_params(value)
        self.condition.value = value

    def prescribe(self, values: np.ndarray) -> None:
        """Prescribe the values a local V array holds at the constrained dofs (until ``update``).

        Used for intermediate values within a step (continuation of a large increment).
        """
        for (_, gc, cdofs, _), bc in zip(self._parts, self.bcs, strict=True):
            gc.x.array[cdofs] = values[bc.dof_indices()[0]]

    def update(self, t: float) -> None:
        """Set the prescribed values at time ``t``."""
        value = self.condition.value
        vec = None
        if self._nparams < 2:
            vec = value(t) if self._nparams == 1 else value
            vec = np.broadcast_to(np.asarray(vec, dtype=float), (self.dim,))
            if not np.all(np.isfinite(vec)):
                raise ParameterError(f"Dirichlet value {vec} at t = {t} is not finite")
        for c, gc, cdofs, Vc in self._parts:
            if vec is not None:
                gc.x.array[cdofs] = vec[c]
            else:
                x = Vc.tabulate_dof_coordinates()[cdofs].T
                vals = np.asarray(value(x, t), dtype=float).reshape(self.dim, -1)
                if not np.all(np.isfinite(vals)):
                    raise ParameterError(f"Dirichlet value at t = {t} is not finite")
                gc.x.array[cdofs] = vals[c]


def _located_entities(
    where: int | str | OnBody | Callable, mesh: dolfinx.mesh.Mesh, domain: "Domain"
) -> tuple[int, np.ndarray | None]:
    """The entity dimension and local entities a condition's ``where`` names (None: a locator)."""
    if isinstance(where, OnBody):
        tdim = mesh.topology.dim
        mesh.topology.create_connectivity(tdim, tdim)  # locate_dofs_topological on cells
        return tdim, domain.cells_of(where.body)
    if callable(where):
        return 0, None
    return mesh.topology.dim - 1, domain.facets_of(where)


def _num_params(value: Value) -> int:
    if not callable(value):
        return 0
    n = len(inspect.signature(value).parameters)
    if n not in (1, 2):
        raise ParameterError("a Dirichlet value function takes (t) or (x, t)")
    return n
