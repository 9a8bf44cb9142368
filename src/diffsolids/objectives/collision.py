"""The IPC barrier of the rest shape: shape designs that stay intersection-free.

PolyFEM's ``collision_barrier`` objective: J = kappa sum_k b(d_k; d_hat) over the pairs k of
boundary primitives of the rest mesh closer than d_hat (ipctk's BarrierPotential with the
squared distances of its convention, the same barrier as the contact term's). It depends on the
rest positions only, so it is a :class:`~diffsolids.objectives.Regulariser` with a shape
gradient: in shape optimisation it grows without bound as two parts of the design approach each
other. The rest surfaces are gathered on every rank in input order (the contact module's
:class:`~diffsolids.contact.surface.CollisionSurface`), so the value is partition independent.
"""

from typing import override

import ipctk
import numpy as np

from diffsolids.contact.surface import CollisionSurface
from diffsolids.errors import ParameterError
from diffsolids.objectives.functional import ObjectiveError, Regulariser
from diffsolids.objectives.regularisers import _check_model

__all__ = ["RestCollisionBarrier"]


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

    def __init__(self, model, dhat: float, stiffness: float = 1.0):
        for name, value in (("dhat", dhat), ("stiffness", stiffness)):
            if not (np.isfinite(value) and value > 0):
                raise ParameterError(f"rest collision barrier: {name} must be > 0, got {value}")
        self.model, self.dhat, self.stiffness = model, float(dhat), float(stiffness)
        self.name = f"rest collision barrier (dhat={dhat:g})"
        self.surface = CollisionSurface(model.domain, model.V)
        self.barrier = ipctk.BarrierPotential(self.dhat, self.stiffness)
        self.broad_phase = ipctk.LBVH()

    def _collisions(self) -> tuple[np.ndarray, ipctk.NormalCollisions]:
        X = np.asfortranarray(self.surface.current_rest_positions())
        mesh = self.surface.mesh
        if ipctk.has_intersections(mesh, X):
            raise ObjectiveError(
                f"{self.name}: the rest boundary intersects itself (an infeasible design)"
            )
        C = ipctk.NormalCollisions()
        C.build(mesh, X, self.dhat, 0.0, self.broad_phase)
        if len(C) and not C.compute_minimum_distance(mesh, X) > 0.0:
            raise ObjectiveError(f"{self.name}: two parts of the rest boundary touch")
        return X, C

    def smallest_distance(self) -> float:
        """The smallest distance between non-adjacent rest primitives within d_hat (else inf)."""
        X, C = self._collisions()
        return (
            float(np.sqrt(C.compute_minimum_distance(self.surface.mesh, X))) if len(C) else np.inf
        )

    @override
    def evaluate(self, model) -> float:
        _check_model(self, model)
        X, C = self._collisions()
        return float(self.barrier(C, self.surface.mesh, X))

    @override
    def gradient(self, model) -> dict[str, np.ndarray]:
        _check_model(self, model)
        X, C = self._collisions()
        dim = self.surface.dim
        G = np.asarray(self.barrier.gradient(C, self.surface.mesh, X)).reshape(-1, dim)
        S = model.shape_space
        omap = self.surface.shape_map(S)
        out = np.zeros((S.dofmap.index_map.size_local, dim))
        out[omap.blocks] = G[omap.cv]
        return {"shape": out.ravel()}
