"""The free collision dofs of the contact term (not Dirichlet) and its static vertices."""

import numpy as np
from mpi4py import MPI

from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.parallel import collective_comm

__all__ = ["FreeDofs"]


class FreeDofs:
    """Mask of the free collision dofs for given Dirichlet dofs, recomputed when they change.

    Args:
        surface: The collision surface (its dof mask; its static vertices are set here).
        comm: Communicator of the mesh (the change test is collective).
        dim: Geometric dimension.

    Attributes:
        key: (count, hash) of the Dirichlet dofs of :attr:`free` (None before the first).
        free: (num_vertices * dim,) bool: the collision dofs that are not prescribed.
    """

    def __init__(self, surface: CollisionSurface, comm: MPI.Comm, dim: int) -> None:
        self.surface = surface
        self.comm = comm
        self.dim = dim
        self.key: tuple | None = None
        self.free = np.ones(surface.num_vertices * dim, dtype=bool)

    def _refresh(self, bc_dofs: np.ndarray) -> bool:
        """Recompute :attr:`free` if the Dirichlet dofs changed on any rank (collective)."""
        bc = np.asarray(bc_dofs)
        key = (len(bc), hash(bc.tobytes()))
        changed = collective_comm(self.comm).allreduce(key != self.key, op=MPI.LOR)
        if changed:
            self.free = ~self.surface.dof_mask(bc)
            self.key = key
        return changed

    def mask(self, bc_dofs: np.ndarray) -> np.ndarray:
        """Free collision dofs for these (local) Dirichlet dofs; collective."""
        self._refresh(bc_dofs)
        return self.free

    def update_static(self, bc_dofs: np.ndarray) -> bool:
        """Mark fully prescribed vertices as static obstacles; whether anything changed.

        Collective (see :meth:`mask`).
        """
        changed = self._refresh(bc_dofs)
        if changed or self.surface.static is None:
            fixed = ~self.free.reshape(-1, self.dim)
            self.surface.set_static(fixed.all(axis=1))
            return True
        return False
