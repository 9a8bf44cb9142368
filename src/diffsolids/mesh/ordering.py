"""Partition-independent global ordering of the dofs of a function space.

Controls expose one flat parameter vector, identical on every rank and for any number of ranks.
Its order is canonical: DG0 dofs follow the original (input) cell order, P1 dofs the input vertex
order, other spaces the lexicographic order of their dof coordinates.
"""

import numpy as np
from dolfinx import fem
from mpi4py import MPI

from diffsolids.parallel import collective_comm

__all__ = ["CanonicalLayout"]


class CanonicalLayout:
    """Map between a global canonical vector (per dof block) and a space's local dofs.

    Args:
        V: The function space; its blocks (nodes) are ordered canonically, components within a
            block follow (a vector of length ``num_nodes * bs``).
    """

    def __init__(self, V: fem.FunctionSpace) -> None:
        self.V = V
        mesh = V.mesh
        self.comm = mesh.comm
        imap = V.dofmap.index_map
        self.bs = V.dofmap.index_map_bs
        self.num_owned = imap.size_local
        self.num_global = imap.size_global
        self.positions = self._positions()  # canonical node index of each owned node

    def _positions(self) -> np.ndarray:
        V, mesh = self.V, self.V.mesh
        element = V.element.basix_element
        num_local = self.num_owned + V.dofmap.index_map.num_ghosts
        order = np.empty(num_local, dtype=np.int64)
        if element.degree == 0:  # DG0: input cell order
            cells = np.arange(V.dofmap.list.shape[0])
            order[V.dofmap.list[:, 0]] = mesh.topology.original_cell_index[cells]
            return order[: self.num_owned]
        if element.degree == 1 and not element.discontinuous:  # P1: input vertex order
            nodes = mesh.geometry.dofmaps[0]
            order[V.dofmap.list.ravel()] = mesh.geometry.input_global_indices[nodes.ravel()]
            return order[: self.num_owned]
        return self._coordinate_order()

    def _coordinate_order(self) -> np.ndarray:
        x = self.V.tabulate_dof_coordinates()[: self.num_owned]
        gathered = collective_comm(self.comm).allgather(x)
        allx = np.vstack(gathered)
        scale = max(float(np.abs(allx).max()), 1.0) * 1e-10
        keys = np.round(allx / scale)
        perm = np.lexsort(keys.T[::-1])
        rank_of = np.empty(len(allx), dtype=np.int64)
        rank_of[perm] = np.arange(len(allx))
        start = sum(len(g) for g in gathered[: self.comm.rank])
        return rank_of[start : start + self.num_owned]

    @property
    def size(self) -> int:
        """Global vector length (nodes * block size)."""
        return self.num_global * self.bs

    def scatter(self, q: np.ndarray, f: fem.Function) -> None:
        """Write a global canonical vector into ``f`` (owned dofs, then ghosts updated)."""
        q = np.asarray(q, dtype=float).reshape(-1, self.bs)
        f.x.array[: self.num_owned * self.bs] = q[self.positions].ravel()
        f.x.scatter_forward()

    def gather(self, local: np.ndarray) -> np.ndarray:
        """Global canonical vector from owned local entries (identical on all ranks)."""
        out = np.zeros((self.num_global, self.bs))
        out[self.positions] = np.asarray(local)[: self.num_owned * self.bs].reshape(-1, self.bs)
        return collective_comm(self.comm).allreduce(out, op=MPI.SUM).ravel()
