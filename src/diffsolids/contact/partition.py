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

- energies and the friction-coefficient products with an allreduce
  (:meth:`CollisionPartition.total`);
- vectors in collision dofs (gradients, Hessian actions, adjoint products) with one allreduce
  of the (num_vertices * dim) surface vector (:meth:`CollisionPartition.sum`), after which
  each rank adds the rows it owns, as before (the vector is the size of the gather that every
  evaluation makes);
- matrices: each rank adds all rows of its share's Hessian with global indices
  (:func:`add_share_to_matrix`, PETSc ``ADD_VALUES``); PETSc sends the off-process rows to
  their owners in the matrix assembly. The owner's preallocated pattern must hold them: the
  contact term's vertex-block pattern is the step's reach pattern (computed from the gathered
  surface, the same on every rank) plus the blocks of any rank's Hessian outside it, united
  over the ranks (:meth:`CollisionPartition.union`);
- step bounds with a min (:class:`~diffsolids.contact.step_bound.StepBound`).

Several candidates can reduce to one collision: ipctk merges the vertex-vertex (and, in 3D,
edge-vertex) collisions they produce by adding their weights and weight gradients
(``normal_collisions_builder.cpp``). When such candidates land on different ranks, each rank
holds a piece of the collision with part of the weight. :meth:`CollisionPartition.merge_split`
makes every collision whole on one rank: the ranks exchange the keys and weights of their
vertex-vertex and edge-vertex collisions (one allgather per build), the lowest rank holding a
piece keeps the collision with the summed weight (and weight gradient, for shape derivatives),
the others drop their pieces. So each collision is evaluated on exactly one rank and the ranks'
collision counts sum to the serial count (:meth:`CollisionPartition.count`). Without the merge
the results would still be right (barrier, friction, their derivatives and the PSD projection
of a collision's Hessian are positively homogeneous in the weight), but a split collision
would be evaluated once per piece: 5% of the collisions of an aligned flat-on-flat 3D scene on
2 ranks, 10% on 3. Edge-edge and face-vertex collisions come from one candidate each and are
never split.

On one rank :meth:`CollisionPartition.share` returns the candidates themselves and every
reduction is the identity: the serial path is the same code, its results unchanged bit for bit.
"""

from collections.abc import Callable

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

    def merge_split(self, collisions: ipctk.NormalCollisions, dim: int) -> None:
        """Make the collisions split between ranks whole on one rank (collective; see above).

        Args:
            collisions: This rank's collision set, built from :meth:`share`; edited in place.
            dim: Geometric dimension (in 2D only vertex-vertex collisions can be split).
        """
        if self.size == 1:
            return
        groups = [("vv_collisions", 0, lambda c: (c.vertex0_id, c.vertex1_id))]
        if dim == 3:
            groups.append(("ev_collisions", 1, lambda c: (c.edge_id, c.vertex_id)))
        lists = [getattr(collisions, name) for name, _, _ in groups]
        keys = [
            _pack(kind, listed, ids) for (_, kind, ids), listed in zip(groups, lists, strict=True)
        ]
        weights = [
            np.fromiter((c.weight for c in listed), dtype=float, count=len(listed))
            for listed in lists
        ]
        local_keys = np.concatenate([np.zeros(0, dtype=np.int64), *keys])
        local_weights = np.concatenate([np.zeros(0), *weights])
        parts = collective_comm(self.comm).allgather((local_keys, local_weights))
        all_keys = np.concatenate([p[0] for p in parts])
        all_ranks = np.repeat(np.arange(self.size), [len(p[0]) for p in parts])
        order = np.argsort(all_keys, kind="stable")  # equal keys stay in rank order
        sk = all_keys[order]
        first = np.ones(len(sk), dtype=bool)
        np.not_equal(sk[1:], sk[:-1], out=first[1:])
        group = np.cumsum(first) - 1
        sizes = np.bincount(group)
        if len(sizes) == 0 or sizes.max() == 1:
            return
        owner = all_ranks[order][first]
        total = np.bincount(group, weights=np.concatenate([p[1] for p in parts])[order])
        # this rank's collisions in the sorted order: their group, whether split, whether kept
        mine_sorted = np.flatnonzero(all_ranks[order] == self.rank)
        local_index = order[mine_sorted] - np.searchsorted(all_ranks, self.rank)
        g_local = np.empty(len(local_keys), dtype=np.int64)
        g_local[local_index] = group[mine_sorted]
        split = sizes[g_local] > 1
        keep = ~split | (owner[g_local] == self.rank)
        shape = collisions.enable_shape_derivatives
        pieces = {}
        if shape:  # the weight gradients of the pieces that are dropped go to their keepers
            sent = [
                (int(g_local[k]), _item(lists, k).weight_gradient)
                for k in np.flatnonzero(split & ~keep)
            ]
            for received in collective_comm(self.comm).allgather(sent):
                for g, grad in received:
                    pieces.setdefault(g, []).append(grad)
        offset = 0
        for (name, _, _), listed in zip(groups, lists, strict=True):
            n = len(listed)
            sel = slice(offset, offset + n)
            if split[sel].any():
                for k in np.flatnonzero(split[sel] & keep[sel]):
                    g = int(g_local[offset + k])
                    c = listed[k]
                    c.weight = float(total[g])
                    if shape:
                        grad = c.weight_gradient
                        for extra in pieces.get(g, []):
                            grad = grad + extra
                        c.weight_gradient = grad
                setattr(collisions, name, [listed[k] for k in np.flatnonzero(keep[sel])])
            offset += n

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

    def count(self, collisions: ipctk.NormalCollisions) -> int:
        """Number of collisions of all ranks' sets (collective; after :meth:`merge_split`)."""
        if self.size == 1:
            return len(collisions)
        return int(collective_comm(self.comm).allreduce(len(collisions), op=MPI.SUM))

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


def _pack(kind: int, listed: list, ids: "Callable") -> np.ndarray:
    """Keys (type in the top bits, the two sorted ids) of a list of collisions of one type."""
    a = np.array([ids(c) for c in listed], dtype=np.int64).reshape(-1, 2)
    if kind in (0, 2):  # vertex-vertex and edge-edge: unordered pairs
        a = np.sort(a, axis=1)
    return (np.int64(kind) << 60) | (a[:, 0] << 30) | a[:, 1]


def _item(lists: list[list], k: int) -> object:
    """Item k of the concatenation of lists."""
    for listed in lists:
        if k < len(listed):
            return listed[k]
        k -= len(listed)
    raise IndexError(k)


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
        if listed:
            parts.append(_pack(kind, listed, ids))
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
