"""Controls of the initial conditions u^0, v^0 (paper sec. 4.2, g^u and g^v)."""

import functools
from typing import TYPE_CHECKING, override

import numpy as np
from dolfinx import fem
from mpi4py import MPI

from diffsolids.adjoint.sensitivities import Sensitivities, Targets
from diffsolids.controls.base import Control, ControlError
from diffsolids.controls.transfer import interpolate_nonmatching
from diffsolids.mesh.ordering import CanonicalLayout
from diffsolids.model import undo_on_refusal
from diffsolids.parallel import collective_comm

if TYPE_CHECKING:
    from diffsolids.simulation import Simulation

__all__ = ["InitialCondition", "RigidVelocity"]


class _InitialStateControl(Control):
    """A control of one simulation's initial state (``self.sim``): refused by any other."""

    sim: "Simulation"

    @override
    def check(self, simulation: "Simulation") -> None:
        if simulation is not self.sim:
            raise ControlError(f"control {self.name} belongs to a different simulation")


class InitialCondition(_InitialStateControl):
    """Nodal initial displacement or velocity field.

    Args:
        simulation: The Simulation whose u0/v0 the parameters set.
        which: "displacement" or "velocity".
    """

    def __init__(self, simulation: "Simulation", which: str = "velocity") -> None:
        if which not in ("displacement", "velocity"):
            raise ControlError("InitialCondition controls 'displacement' or 'velocity'")
        if which == "velocity" and not simulation.integrator.dynamic:
            raise ControlError("an initial-velocity control needs a dynamic (BDF) simulation")
        self.sim, self.which = simulation, which
        self.name = f"initial_{which}"
        self.layout = CanonicalLayout(simulation.model.V)
        self._f = fem.Function(simulation.model.V)

    def _array(self) -> np.ndarray:
        return self.sim.u0 if self.which == "displacement" else self.sim.v0

    @override
    def footprint(self) -> set[tuple]:
        return {(f"the initial {self.which}", None)}

    @override
    @property
    def size(self) -> int:
        return self.layout.size

    @override
    def value(self) -> np.ndarray:
        return self.layout.gather(self._array())

    @override
    def assign(self, q: np.ndarray) -> None:
        self.layout.scatter(q, self._f)
        state = self._array()
        undo_on_refusal(functools.partial(state.__setitem__, slice(None), state.copy()))
        state[:] = self._f.x.array

    @override
    def targets(self) -> Targets:
        return Targets(initial=True)

    @override
    def pullback(self, sens: Sensitivities) -> np.ndarray:
        return self.layout.gather(sens.u0 if self.which == "displacement" else sens.v0)

    @override
    def transfer(self, old: Control, block: np.ndarray) -> np.ndarray:
        if not isinstance(old, InitialCondition) or old.which != self.which:
            return super().transfer(old, block)
        old.assign(block)
        old._f.x.array[:] = old._array()
        interpolate_nonmatching(old._f, self._f)
        self._array()[:] = self._f.x.array
        return self.value()


class RigidVelocity(_InitialStateControl):
    """Initial velocity of one body as a rigid motion v(x) = v + omega x (x - c).

    Parameters: the translation velocity (dim) and, with ``angular``, the angular velocity
    (1 component in 2D, 3 in 3D) about the body's rest centroid c. Nodes with a Dirichlet
    condition keep their prescribed motion: the rigid velocity is the free nodes' initial
    velocity.
    """

    def __init__(self, simulation: "Simulation", body: int | str, angular: bool = True) -> None:
        if not simulation.integrator.dynamic:
            raise ControlError("a rigid initial-velocity control needs a dynamic simulation")
        self.sim = simulation
        model = simulation.model
        self.body = model.domain.body_id(body)
        self.name = f"rigid_velocity[{self.body}]"
        V = model.V
        self.dim = model.dim
        self.angular = angular
        cells = model.domain.cells_of(self.body)
        self.nodes = np.unique(V.dofmap.list[cells])
        self.owned = V.dofmap.index_map.size_local
        x = V.tabulate_dof_coordinates()[:, : self.dim]
        owned_nodes = self.nodes[self.nodes < self.owned]
        comm = model.domain.comm
        count = collective_comm(comm).allreduce(len(owned_nodes), op=MPI.SUM)
        self.center = (
            collective_comm(comm).allreduce(x[owned_nodes].sum(axis=0), op=MPI.SUM) / count
        )
        prescribed = np.unique(model.dirichlet_dofs() // self.dim)
        self.nodes = np.setdiff1d(self.nodes, prescribed)
        self.r = x[self.nodes] - self.center
        self.comm = comm
        self.q = np.zeros(self.size)

    @override
    def footprint(self) -> set[tuple]:
        return {("the initial velocity", f"body {self.body}")}

    @override
    @property
    def size(self) -> int:
        return self.dim + ((1 if self.dim == 2 else 3) if self.angular else 0)

    @override
    def value(self) -> np.ndarray:
        return self.q.copy()

    def _velocity(self, q: np.ndarray) -> np.ndarray:
        v = np.tile(q[: self.dim], (len(self.nodes), 1))
        if self.angular:
            w = q[self.dim :]
            if self.dim == 2:
                v += w[0] * np.column_stack([-self.r[:, 1], self.r[:, 0]])
            else:
                v += np.cross(w, self.r)
        return v

    @override
    def assign(self, q: np.ndarray) -> None:
        q = np.asarray(q, dtype=float)
        v0 = self.sim.v0.reshape(-1, self.dim)
        undo_on_refusal(functools.partial(self._restore, v0[self.nodes].copy(), self.q))
        v0[self.nodes] = self._velocity(q)
        self.q = q.copy()

    def _restore(self, velocities: np.ndarray, q: np.ndarray) -> None:
        self.sim.v0.reshape(-1, self.dim)[self.nodes] = velocities
        self.q = q

    @override
    def targets(self) -> Targets:
        return Targets(initial=True)

    @override
    def pullback(self, sens: Sensitivities) -> np.ndarray:
        vbar = sens.v0.reshape(-1, self.dim)
        owned = self.nodes < self.owned
        g_nodes = vbar[self.nodes[owned]]
        parts = [g_nodes.sum(axis=0)]
        if self.angular:
            r = self.r[owned]
            if self.dim == 2:
                parts.append(np.array([np.sum(-r[:, 1] * g_nodes[:, 0] + r[:, 0] * g_nodes[:, 1])]))
            else:
                parts.append(np.cross(r, g_nodes).sum(axis=0))
        return collective_comm(self.comm).allreduce(np.concatenate(parts), op=MPI.SUM)
