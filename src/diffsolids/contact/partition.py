"""Distributed contact: every collision candidate is evaluated on one rank, results summed.

All ranks hold the whole collision surface (gathered once per evaluation,
:class:`~diffsolids.contact.surface.CollisionSurface`) and run ipctk's broad phase on it (the
same candidates on every rank). :meth:`CollisionPartition.share` then keeps the candidates of
this rank: candidate k goes to rank ``h(key_k) mod size`` with ``key_k`` its "point" vertex
(vertex-vertex: the smaller vertex, edge-vertex and face-vertex: the vertex, edge-edge: the
smaller edge) and h a multiplicative (Fibonacci) hash. The rule reads nothing but the global
ids of the candidate, so it does not depend on the order in which ipctk's threads report the
candidates, on the partition of the mesh, or on which candidate set (the evaluation's, or the
CCD's of a line-search segment) the candidate came from; and the hash spreads contact regions
over the ranks (balanced to a few per cent when each rank has some hundreds of candidates).

Each rank builds its ``NormalCollisions`` from its share (the narrow phase runs once per
candidate in all), evaluates barrier, friction (the tangential collisions lagged from its own
normal collisions), CCD and every adjoint product on them, and the results are summed:

- energies and the friction-coefficient products with an allreduce (:meth:`total`);
- vectors in collision dofs (gradients, Hessian actions, adjoint products) with one allreduce of
  the (num_vertices * dim) surface vector (:meth:`sum`), after which each rank adds the rows it
  owns, as before; the surface vector is the size of the gather that every evaluation makes;
- matrices: each rank adds all rows of its share's Hessian with global indices
  (:func:`add_share_to_matrix`, PETSc ``ADD_VALUES``); PETSc sends the off-process rows to
  their owners in the matrix assembly. The owner's preallocated pattern must hold them: the
  contact term's vertex-block pattern is the step's reach pattern (computed from the gathered
  surface, the same on every rank) plus the blocks of any rank's Hessian outside it, united
  over the ranks (:meth:`union`);
- step bounds with a min (:class:`~diffsolids.contact.step_bound.StepBound`).

The IPC collision set is linear in its candidates: ipctk merges the vertex-vertex and
edge-vertex collisions that several candidates reduce to by adding their weights (and weight
gradients, ``normal_collisions_builder.cpp``), and barrier, friction force, their derivatives
and the PSD projection of each collision's Hessian are positively homogeneous in the weight.
So when such candidates land on different ranks, the pieces (each with its part of the
weight) sum to the serial collision exactly up to round-off. A merged collision split that way
is evaluated once per piece; :meth:`unique_count` counts the collisions of all ranks as the
serial set does (``ContactRecord.num_collisions``). Edge-edge collisions are never split (one
candidate each), so the mollifier correction of :mod:`~diffsolids.contact.shape`, which reads
the full edge-edge weight from the mesh, is applied once.

On one rank :meth:`share` returns the candidates themselves and every reduction is the identity:
the serial path is the same code and its results are unchanged (bit for bit).
"""

import ipctk
import numpy as np
import scipy.sparse as sp
from mpi4py import MPI
from petsc4py import PETSc

from diffsolids.parallel import collective_comm
from diffsolids.solvers.sparsity import sorted_unique

__all__ = ["CollisionPartition", "add_share_to_matrix"]

# Fibonacci hashing: key * 2^64 / golden ratio (mod 2^64), high bits
_MIX = np.uint64(0x9E3779B97F4A7C15)
_SHIFT = np.uint64(29)

# (list attribute, key of a candidate) per candidate type
_KINDS = (
    ("vv_candidates", lambda c: min(c.vertex0_id, c.vertex1_id)),
    ("ev_candidates", lambda c: c.vertex_id),
    ("ee_candidates", lambda c: min(c.edge0_id, c.edge1_id)),
    ("fv_candidates", lambda c: c.vertex_id),
)


class CollisionPartition:
    """Which collision candidates this rank evaluates, and the sums over ranks.

    Args:
        comm: Communicator of the ranks that share the collision set.

    Attributes:
        counts: Work done on this rank since construction: ``evaluations`` (collision sets
            built), ``candidates`` (candidates narrow-phased) and ``collisions`` (collisions
            built).
    """

    def __init__(self, comm: MPI.Comm) -> None:
        self.comm = comm
        self.size = comm.size
        self.rank = comm.rank
        self.counts = {"evaluations": 0, "candidates": 0, "collisions": 0}

    @property
    def distributed(self) -> bool:
        """Whether the collision work is split (more than one rank)."""
        return self.size > 1

    def owner(self, keys: np.ndarray) -> np.ndarray:
        """Rank of each candidate key (a function of the key and the number of ranks only)."""
        h = np.asarray(keys, dtype=np.uint64) * _MIX
        return ((h >> _SHIFT) % np.uint64(self.size)).astype(np.int64)

    def share(self, candidates: ipctk.Candidates) -> ipctk.Candidates:
        """The candidates this rank evaluates (all of them on one rank: the same object).

        Args:
            candidates: Candidates of the whole surface (the same set on every rank).
        """
        if self.size == 1:
            return candidates
        out = ipctk.Candidates()
        for name, key in _KINDS:
            listed = getattr(candidates, name)
            if not listed:
                continue
            keys = np.fromiter(map(key, listed), dtype=np.int64, count=len(listed))
            mine = np.flatnonzero(self.owner(keys) == self.rank)
            setattr(out, name, [listed[k] for k in mine])
        if self.rank == 0 and len(candidates.pv_candidates):
            out.pv_candidates = candidates.pv_candidates
        return out

    def record(self, candidates: ipctk.Candidates, collisions: ipctk.NormalCollisions) -> None:
        """Count one collision set built on this rank from ``candidates``."""
        c = self.counts
        c["evaluations"] += 1
        c["candidates"] += sum(len(getattr(candidates, name)) for name, _ in _KINDS)
        c["collisions"] += len(collisions)

    # -- sums over ranks ---------------------------------------------------------------------
    def sum(self, values: np.ndarray) -> np.ndarray:
        """Sum of a float array over the ranks (the array itself on one rank)."""
        if self.size == 1:
            return values
        local = np.ascontiguousarray(values, dtype=float)
        out = np.empty_like(local)
        self.comm.Allreduce(local, out, op=MPI.SUM)
        return out

    def total(self, value: float) -> float:
        """Sum of a float over the ranks."""
        if self.size == 1:
            return float(value)
        return float(collective_comm(self.comm).allreduce(float(value), op=MPI.SUM))

    def minimum(self, value: float) -> float:
        """Minimum of a float over the ranks."""
        if self.size == 1:
            return float(value)
        return float(collective_comm(self.comm).allreduce(float(value), op=MPI.MIN))

    def union(self, keys: np.ndarray) -> np.ndarray:
        """Sorted unique int64 keys of all ranks (the keys themselves on one rank)."""
        if self.size == 1:
            return keys
        parts = collective_comm(self.comm).allgather(np.asarray(keys, dtype=np.int64))
        return sorted_unique(np.zeros(0, dtype=np.int64), *parts)

    def unique_count(self, collisions: ipctk.NormalCollisions) -> int:
        """Number of distinct collisions of all ranks' sets (pieces of a split one count once).

        Collective; reads the ids of every collision (once per converged step).
        """
        if self.size == 1:
            return len(collisions)
        return len(self.union(collision_keys(collisions)))

    def minimum_distance(
        self, collisions: ipctk.NormalCollisions, mesh: ipctk.CollisionMesh, x: np.ndarray
    ) -> float:
        """Smallest distance of all ranks' collisions (inf when there are none; collective)."""
        d2 = (
            collisions.compute_minimum_distance(mesh, np.asfortranarray(x))
            if len(collisions)
            else np.inf
        )
        return float(np.sqrt(self.minimum(d2)))


def collision_keys(collisions: ipctk.NormalCollisions) -> np.ndarray:
    """An int64 key per collision, the same for the pieces of one collision on any rank.

    The key packs the type (2 bits) and the two sorted ids of the pair (vertex-vertex: the
    vertices, edge-vertex: edge and vertex, edge-edge: the edges, face-vertex: face and
    vertex), 30 bits each.
    """
    parts = [np.zeros(0, dtype=np.int64)]
    groups = (
        (0, collisions.vv_collisions, lambda c: (c.vertex0_id, c.vertex1_id)),
        (1, collisions.ev_collisions, lambda c: (c.edge_id, c.vertex_id)),
        (2, collisions.ee_collisions, lambda c: (c.edge0_id, c.edge1_id)),
        (3, collisions.fv_collisions, lambda c: (c.face_id, c.vertex_id)),
    )
    for kind, listed, ids in groups:
        if not listed:
            continue
        a = np.array([ids(c) for c in listed], dtype=np.int64).reshape(-1, 2)
        if kind in (0, 2):
            a = np.sort(a, axis=1)
        parts.append((np.int64(kind) << 60) | (a[:, 0] << 30) | a[:, 1])
    return np.concatenate(parts)


def add_share_to_matrix(
    A: PETSc.Mat,
    H: sp.spmatrix,
    free: np.ndarray,
    global_dofs: np.ndarray,
    num_vertices: int,
    dim: int,
    keep: np.ndarray | None = None,
) -> None:
    """Add all free rows of this rank's collision-dof matrix H into A (global indices).

    Rows owned by other ranks are sent by PETSc in the matrix assembly (``ADD_VALUES``); the
    owners' patterns must hold them (see the module docstring). Collective (a flush assembly
    first: DOLFINx inserts the Dirichlet diagonal last).

    Args:
        A: PETSc matrix (not yet finally assembled).
        H: (num_vertices*dim)^2 sparse matrix in collision dofs (this rank's share).
        free: Boolean mask of collision dofs that are not Dirichlet (rows and columns kept).
        global_dofs: Global (PETSc) index of every collision dof.
        num_vertices: Number of collision vertices.
        dim: Geometric dimension.
        keep: Optional sorted vertex-block keys (row_vertex * num_vertices + col_vertex);
            entries outside them are dropped.
    """
    A.assemblyBegin(PETSc.Mat.AssemblyType.FLUSH)
    A.assemblyEnd(PETSc.Mat.AssemblyType.FLUSH)
    if H.nnz == 0:
        return
    rows_c = np.flatnonzero(free)
    Hr = sp.csr_matrix(H)[rows_c].tocoo()
    mask = free[Hr.col]
    if keep is not None and len(Hr.row):
        keys = (rows_c[Hr.row] // dim).astype(np.int64) * num_vertices + Hr.col // dim
        if len(keep) == 0:
            mask &= False
        else:
            pos = np.minimum(np.searchsorted(keep, keys), len(keep) - 1)
            mask &= keep[pos] == keys
    r, c, v = Hr.row[mask], Hr.col[mask], Hr.data[mask]
    csr = sp.csr_matrix((v, (r, c)), shape=(len(rows_c), H.shape[1]))
    csr.sum_duplicates()
    nonempty = np.flatnonzero(np.diff(csr.indptr))
    if len(nonempty) == 0:
        return
    csr = csr[nonempty]
    A.setValuesIJV(
        csr.indptr.astype(PETSc.IntType),
        global_dofs[csr.indices].astype(PETSc.IntType),
        csr.data,
        addv=PETSc.InsertMode.ADD_VALUES,
        rowmap=global_dofs[rows_c[nonempty]].astype(PETSc.IntType),
    )
