"""Distributed contact: every collision is evaluated on one rank, the results summed.

All ranks hold the whole collision surface (gathered once per evaluation,
:class:`~diffsolids.contact.geometry.surface.CollisionSurface`) and build the whole collision set on
it (ipctk's broad and narrow phase: the same set on every rank).
:meth:`CollisionPartition.keep_share` then keeps the collisions of this rank: collision c goes
to rank ``h(key_c) mod size``, with ``key_c`` its type and ids (vertex-vertex: the two
vertices sorted, edge-vertex and face-vertex: the vertex, edge-edge: the two edges sorted) and
h the splitmix64 hash. The rule reads nothing but global ids, so it does not depend on the
order in which ipctk's threads report the collisions or on the partition of the mesh, every
collision is kept by exactly one rank with its whole weight, and the hash spreads a contact
region over the ranks (balanced to a few per cent with some hundreds of collisions per rank).

Each rank evaluates barrier, friction (the tangential collisions lagged from its own normal
collisions), their derivatives and every adjoint product on its share, and the results are
summed:

- energies and the friction-coefficient products with an allreduce
  (:meth:`CollisionPartition.total`);
- vectors in collision dofs (gradients, Hessian actions, adjoint products) with one allreduce
  of the (num_vertices * dim) surface vector (:meth:`CollisionPartition.sum`), after which
  each rank adds the rows it owns, as before (the vector is the size of the gather that every
  evaluation makes);
- matrices: each rank adds all rows of its share's Hessian with global indices
  (``CollisionSurface.add_matrix``, PETSc ``ADD_VALUES``); PETSc sends the off-process rows to
  their owners in the matrix assembly. The owner's preallocated pattern must hold them: the
  contact term's vertex-block pattern is the step's reach pattern (computed from the gathered
  surface, the same on every rank) plus the blocks of any rank's Hessian outside it, united
  over the ranks (:meth:`CollisionPartition.union`);
- minimum distances with a min.

Why collisions and not broad-phase candidates: ipctk's Python API hands candidates and
collisions over as lists of Python objects, about 1 us each to convert and read. A flat-on-flat
3D contact has ~10 candidates per collision (measured on ``bench_contact``: 29 000 candidates,
1 950 collisions per build), so splitting the candidates cost 28 ms per build against 3.3 ms
for the narrow phase it would share out, while splitting the collisions costs ~4 ms and shares
out the Hessians, gradients, friction and adjoint kernels, which are most of the contact work.
For the same reason the CCD step bound (:class:`~diffsolids.contact.detection.step_bound.StepBound`,
AdditiveCCD: ~0.4 us per candidate) stays the same computation on every rank. The broad and
narrow phase of the collision set, the CCD and the reach pattern are the replicated part of
distributed contact (``bench_contact --ranks`` measures it and projects it to more ranks).

On one rank :meth:`CollisionPartition.keep_share` keeps everything and every reduction is the
identity: the serial path is the same code, its results unchanged bit for bit.
"""

from operator import attrgetter

import ipctk
import numpy as np
from mpi4py import MPI

from diffsolids.contact.timing import timed
from diffsolids.parallel import collective_comm
from diffsolids.solvers.sparsity import sorted_unique

__all__ = ["CollisionPartition"]

# the splitmix64 finaliser (every bit of the key moves every bit of the hash)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S = (np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(32))

# (list attribute, ids of a collision) per collision type, in key order
_KINDS = (
    ("vv_collisions", ("vertex0_id", "vertex1_id")),
    ("ev_collisions", ("edge_id", "vertex_id")),
    ("ee_collisions", ("edge0_id", "edge1_id")),
    ("fv_collisions", ("face_id", "vertex_id")),
)
# the ids the rank of a collision is hashed from: both ids of the unordered pairs (ipctk may
# report them either way round), the vertex of edge-vertex and face-vertex collisions (one
# attribute read, ~0.5 us each, instead of two; the collisions of a vertex stay together)
_OWNER_IDS = (
    ("vertex0_id", "vertex1_id"),
    ("vertex_id",),
    ("edge0_id", "edge1_id"),
    ("vertex_id",),
)


class CollisionPartition:
    """Which collisions this rank evaluates, and the sums over ranks.

    Args:
        comm: Communicator of the ranks that share the collision set.

    Attributes:
        counts: Work done on this rank since construction: ``evaluations`` (collision sets
            built) and ``collisions`` (collisions kept, summed over the sets).
        timings: [wall seconds, calls, CPU seconds] of :meth:`keep_share` (``share``); it is
            inside the contact term's ``build`` timer, listed apart for the benchmark.
    """

    def __init__(self, comm: MPI.Comm) -> None:
        self.comm = comm
        self.size = comm.size
        self.rank = comm.rank
        self.counts = {"evaluations": 0, "collisions": 0}
        self.timings: dict[str, list] = {}

    @property
    def distributed(self) -> bool:
        """Whether the collision work is split (more than one rank)."""
        return self.size > 1

    def owner(self, keys: np.ndarray) -> np.ndarray:
        """Rank of each collision key (a function of the key and the number of ranks only)."""
        h = np.asarray(keys, dtype=np.int64).astype(np.uint64)
        h = (h ^ (h >> _S[0])) * _M1
        h = (h ^ (h >> _S[1])) * _M2
        h = h ^ (h >> _S[2])
        # the high 32 bits scaled to [0, size): (h_hi * size) / 2^32
        return (((h >> _S[3]) * np.uint64(self.size)) >> _S[3]).astype(np.int64)

    def keep_share(self, collisions: ipctk.NormalCollisions) -> ipctk.NormalCollisions:
        """Drop the collisions of other ranks from ``collisions`` (in place; also returned).

        Args:
            collisions: The whole collision set (the same on every rank).
        """
        if self.size > 1:
            with timed(self.timings, "share"):
                for kind, (name, _) in enumerate(_KINDS):
                    listed = getattr(collisions, name)
                    if not listed:
                        continue
                    keys = _pack(kind, listed, _OWNER_IDS[kind])
                    mine = np.flatnonzero(self.owner(keys) == self.rank)
                    if len(mine) < len(listed):
                        setattr(collisions, name, [listed[k] for k in mine])
        self.counts["evaluations"] += 1
        self.counts["collisions"] += len(collisions)
        return collisions

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
        """Number of collisions of all ranks' shares (collective)."""
        if self.size == 1:
            return len(collisions)
        return int(collective_comm(self.comm).allreduce(len(collisions), op=MPI.SUM))

    def minimum_distance(
        self, collisions: ipctk.NormalCollisions, mesh: ipctk.CollisionMesh, x: np.ndarray
    ) -> float:
        """Smallest distance of all ranks' collisions (inf when there are none; collective)."""
        d2 = np.inf
        if len(collisions):
            d2 = collisions.compute_minimum_distance(mesh, np.asfortranarray(x))
        return float(np.sqrt(self.minimum(d2)))


def _pack(kind: int, listed: list, names: tuple[str, ...]) -> np.ndarray:
    """Keys of collisions of one type: the type in the top bits, then the ids ``names``.

    Two ids are sorted for the unordered pairs (vertex-vertex, edge-edge), 30 bits each.
    """
    n = len(listed)
    ids = [np.fromiter(map(attrgetter(a), listed), dtype=np.int64, count=n) for a in names]
    key = np.int64(kind) << 60
    if len(ids) == 1:
        return key | ids[0]
    a, b = ids
    if kind in (0, 2):  # vertex-vertex and edge-edge: unordered pairs
        a, b = np.minimum(a, b), np.maximum(a, b)
    return key | (a << 30) | b


def collision_keys(collisions: ipctk.NormalCollisions) -> np.ndarray:
    """The int64 key of every collision (see :func:`_pack`), in list order."""
    parts = [np.zeros(0, dtype=np.int64)]
    for kind, (name, names) in enumerate(_KINDS):
        listed = getattr(collisions, name)
        if listed:
            parts.append(_pack(kind, listed, names))
    return np.concatenate(parts)
