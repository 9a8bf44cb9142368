"""The IPC barriers of the rest and deformed shapes as objectives (PolyFEM's collision barriers).

PolyFEM's ``collision_barrier`` objective: J = kappa sum_k b(d_k; d_hat) over the pairs k of
boundary primitives of the rest mesh closer than d_hat (ipctk's BarrierPotential with the
squared distances of its convention, the same barrier as the contact term's). It depends on the
rest positions only, so it is a :class:`~diffsolids.objectives.Regulariser` with a shape
gradient: in shape optimisation it grows without bound as two parts of the design approach each
other. :class:`DeformedCollisionBarrier` is PolyFEM's ``deformed_collision_barrier``: the same
sum at the deformed positions X + u^i of every step, a per-step series computed by ipctk (a
:class:`~diffsolids.objectives.functional.NumericIntegral`, with its state and shape partials).
The surfaces are gathered on every rank in input order (the contact module's
:class:`~diffsolids.contact.geometry.surface.CollisionSurface`), so the values are partition
independent.
"""

from typing import TYPE_CHECKING, override

import ipctk
import numpy as np

from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.errors import ParameterError
from diffsolids.objectives.functional import NumericIntegral, ObjectiveError, Regulariser
from diffsolids.objectives.regularisers import _check_model

if TYPE_CHECKING:
    from diffsolids.model import Model

__all__ = ["DeformedCollisionBarrier", "RestCollisionBarrier"]


def _check_barrier(dhat: float, stiffness: float) -> None:
    for name, value in (("dhat", dhat), ("stiffness", stiffness)):
        if not (np.isfinite(value) and value > 0):
            raise ParameterError(f"collision barrier: {name} must be > 0, got {value}")


def _collision_set(
    surface: CollisionSurface, X: np.ndarray, dhat: float, broad_phase: ipctk.BroadPhase, what: str
) -> ipctk.NormalCollisions:
    """The pairs within d_hat at positions X; refuses intersecting or touching surfaces."""
    mesh = surface.mesh
    if ipctk.has_intersections(mesh, X):
        raise ObjectiveError(f"{what}: the boundary intersects itself")
    C = ipctk.NormalCollisions()
    C.build(mesh, X, dhat, 0.0, broad_phase)
    if len(C) and not C.compute_minimum_distance(mesh, X) > 0.0:
        raise ObjectiveError(f"{what}: two parts of the boundary touch")
    return C


class RestCollisionBarrier(Regulariser):
    """kappa sum_k b(d_k; d_hat) of the rest boundary (PolyFEM ``collision_barrier``).

    Primitives sharing a vertex are excluded (ipctk's rule); so are pairs within d_hat of each
    other in a fine mesh of one body (choose d_hat below the smallest boundary edge to leave
    them out, as for contact).

    Args:
        model: The Model (a volume mesh with affine geometry).
        dhat: Activation distance d_hat > 0 of the barrier.
        stiffness: kappa > 0.

    Raises:
        ParameterError: d_hat or kappa not positive.
    """

    def __init__(self, model: "Model", dhat: float, stiffness: float = 1.0) -> None:
        _check_barrier(dhat, stiffness)
        self.model, self.dhat, self.stiffness = model, float(dhat), float(stiffness)
        self.name = f"rest collision barrier (dhat={dhat:g})"
        self.surface = CollisionSurface(model.domain, model.V)
        self.barrier = ipctk.BarrierPotential(self.dhat, self.stiffness)
        self.broad_phase = ipctk.LBVH()

    def _collisions(self) -> tuple[np.ndarray, ipctk.NormalCollisions]:
        X = np.asfortranarray(self.surface.current_rest_positions())
        return X, _collision_set(self.surface, X, self.dhat, self.broad_phase, self.name)

    def smallest_distance(self) -> float:
        """The smallest distance between non-adjacent rest primitives within d_hat (else inf)."""
        X, C = self._collisions()
        return (
            float(np.sqrt(C.compute_minimum_distance(self.surface.mesh, X))) if len(C) else np.inf
        )

    @override
    def evaluate(self, model: "Model") -> float:
        _check_model(self, model)
        X, C = self._collisions()
        return float(self.barrier(C, self.surface.mesh, X))

    @override
    def gradient(self, model: "Model") -> dict[str, np.ndarray]:
        _check_model(self, model)
        X, C = self._collisions()
        dim = self.surface.dim
        G = np.asarray(self.barrier.gradient(C, self.surface.mesh, X)).reshape(-1, dim)
        S = model.shape_space
        omap = self.surface.shape_map(S)
        out = np.zeros((S.dofmap.index_map.size_local, dim))
        out[omap.blocks] = G[omap.cv]
        return {"shape": out.ravel()}


class DeformedCollisionBarrier(NumericIntegral):
    """kappa sum_k b(d_k(X + u^i); d_hat) per step (PolyFEM ``deformed_collision_barrier``).

    The IPC barrier of the deformed boundary at every step, as a per-step series: reduce it
    with time weights. With a contact term in the model the states never intersect and this
    keeps designs away from contact; without one, an intersecting state is refused with an
    ObjectiveError naming its time.

    Args:
        model: The Model (a volume mesh with affine geometry; P1, P2 or P3 displacements; the
            P2/P3 boundary split at its edge and face nodes, as the contact term's).
        dhat: Activation distance d_hat > 0.
        stiffness: kappa > 0.
    """

    def __init__(self, model: "Model", dhat: float, stiffness: float = 1.0) -> None:
        _check_barrier(dhat, stiffness)
        self.model, self.dhat, self.stiffness = model, float(dhat), float(stiffness)
        self.name = "deformed collision barrier"
        self.surface = CollisionSurface(model.domain, model.V, boundary="nodes")
        self.barrier = ipctk.BarrierPotential(self.dhat, self.stiffness)
        self.broad_phase = ipctk.LBVH()
        self._last: tuple[np.ndarray, ipctk.NormalCollisions] | None = None

    def _state(self, model: "Model") -> tuple[np.ndarray, ipctk.NormalCollisions]:
        if model is not self.model:
            raise ObjectiveError(f"{self.name} was built for a different model")
        surface = self.surface
        X = surface.current_rest_positions() + surface.gather(model.fields.u.x.array)
        X = np.asfortranarray(X)
        cached = self._last
        if cached is not None and np.array_equal(cached[0], X):
            return cached
        what = f"{self.name} at t = {float(model.fields.t.value):g}"
        self._last = (X, _collision_set(surface, X, self.dhat, self.broad_phase, what))
        return self._last

    def _vertex_gradient(self, model: "Model") -> np.ndarray:
        X, C = self._state(model)
        return np.asarray(self.barrier.gradient(C, self.surface.mesh, X)).ravel()

    def evaluate(self, model: "Model") -> float:
        """The barrier at the state in ``model.fields`` (collective)."""
        X, C = self._state(model)
        return float(self.barrier(C, self.surface.mesh, X))

    def state_gradient(self, model: "Model") -> np.ndarray:
        """dJ/du on the owned collision dofs of the displacement space (local layout)."""
        g = self._vertex_gradient(model)
        return self.surface.to_local(g, len(model.fields.u.x.array))

    def shape_gradient(self, model: "Model") -> np.ndarray:
        """dJ/dX (x = X + u: the same vertex gradient) on the owned shape-space entries."""
        dim = self.surface.dim
        G = self._vertex_gradient(model).reshape(-1, dim)
        S = model.shape_space
        omap = self.surface.shape_map(S)
        out = np.zeros((S.dofmap.index_map.size_local, dim))
        out[omap.blocks] = omap.pull_back(G)[omap.cv]  # nodes move with their facet's vertices
        return out.ravel()
