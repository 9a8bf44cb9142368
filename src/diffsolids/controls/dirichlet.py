"""Control of prescribed (Dirichlet) displacement values, constant or per step."""

import functools
from typing import TYPE_CHECKING, override

import numpy as np
from mpi4py import MPI

from diffsolids.adjoint.sensitivities import Sensitivities, Targets
from diffsolids.controls.base import Control, ControlError
from diffsolids.model import undo_on_refusal
from diffsolids.parallel import collective_comm

if TYPE_CHECKING:
    from diffsolids.model.boundary_conditions import RealisedDirichlet
    from diffsolids.simulation import Simulation

__all__ = ["DirichletControl"]


class DirichletControl(Control):
    """The value of a Dirichlet condition (one vector of its components) as parameters.

    Args:
        simulation: The Simulation.
        condition: A RealisedDirichlet returned by ``model.add_dirichlet``.
        per_step: One value per step 1..N (else one value for all steps).
    """

    def __init__(
        self, simulation: "Simulation", condition: "RealisedDirichlet", per_step: bool = False
    ) -> None:
        if condition not in simulation.model.dirichlet:
            raise ControlError("the Dirichlet condition does not belong to the simulation's model")
        self.sim, self.condition, self.per_step = simulation, condition, per_step
        self.name = "dirichlet" + ("[per step]" if per_step else "")
        self.ncomp = len(condition.components)
        self.steps = simulation.integrator.num_steps if per_step else 1
        self.q = np.zeros(self.size)
        bs = simulation.model.V.dofmap.index_map_bs
        self.owned = simulation.model.V.dofmap.index_map.size_local * bs
        dofs = condition.dofs[condition.dofs < self.owned]
        self._dofs_by_comp = [dofs[dofs % bs == c] for c in condition.components]

    @override
    def check(self, simulation: "Simulation") -> None:
        if simulation is not self.sim:
            raise ControlError("Dirichlet control belongs to a different simulation")

    @override
    def footprint(self) -> set[tuple]:
        index = self.sim.model.dirichlet.index(self.condition)
        where = self.condition.condition.where
        return {(f"Dirichlet condition {index} (on {where!r})", None)}

    @override
    @property
    def size(self) -> int:
        return self.ncomp * self.steps

    @override
    def value(self) -> np.ndarray:
        return self.q.copy()

    @override
    def assign(self, q: np.ndarray) -> None:
        q = np.asarray(q, dtype=float).reshape(self.steps, self.ncomp)
        dim, comps, dt = self.condition.dim, self.condition.components, self.sim.integrator.dt

        def value(t: float) -> np.ndarray:
            k = min(max(round(t / dt), 1), self.steps) - 1 if self.per_step else 0
            out = np.zeros(dim)
            out[comps] = q[k]
            return out

        undo_on_refusal(functools.partial(self._restore, self.condition.condition.value, self.q))
        self.condition.set_value(value)
        self.q = q.ravel().copy()

    def _restore(self, value: object, q: np.ndarray) -> None:
        self.condition.set_value(value)
        self.q = q

    @override
    def targets(self) -> Targets:
        return Targets(dirichlet=True)

    @override
    def pullback(self, sens: Sensitivities) -> np.ndarray:
        g = np.zeros((self.steps, self.ncomp))
        for i in range(1, len(sens.dirichlet)):
            k = i - 1 if self.per_step else 0
            for c, dofs in enumerate(self._dofs_by_comp):
                g[k, c] += sens.dirichlet[i][dofs].sum()
        return collective_comm(self.sim.model.domain.comm).allreduce(g, op=MPI.SUM).ravel()
