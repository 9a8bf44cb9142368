"""A collision set as arrays: the vertex ids and the type of every collision, read once.

ipctk hands collisions over as Python objects; the ids of a candidate read ~0.3 us each, so a
set of a few thousand collisions becomes arrays in a few milliseconds, after which everything
is batched numpy.
"""

from dataclasses import dataclass
from operator import attrgetter

import ipctk
import numpy as np

from diffsolids.solvers.sparsity import sorted_unique

__all__ = ["CollisionArrays", "collision_arrays", "stencil_blocks"]


@dataclass
class CollisionArrays:
    """The collisions of a set, one row each, in ipctk's type order (vv, ev, ee, fv).

    Attributes:
        ids: (n, 4) vertex ids in the order of ``vertex_ids``, -1 padded.
        kind: (n,) type: 0 vertex-vertex, 1 edge-vertex, 2 edge-edge, 3 face-vertex.
        ee_edges: (number of ee, 2) edge ids of the edge-edge collisions.
        ee_dtype: (number of ee,) their ipctk ``EdgeEdgeDistanceType`` values.
    """

    ids: np.ndarray
    kind: np.ndarray
    ee_edges: np.ndarray
    ee_dtype: np.ndarray


def _rows(items: list, *names: str) -> np.ndarray:
    get = attrgetter(*names)
    return np.array([get(c) for c in items], dtype=np.int64).reshape(len(items), len(names))


def collision_arrays(
    collisions: ipctk.NormalCollisions, mesh: ipctk.CollisionMesh
) -> CollisionArrays:
    """The ids and types of the collisions of a set (one pass over each list)."""
    E, F = np.asarray(mesh.edges), np.asarray(mesh.faces)
    vv = _rows(collisions.vv_collisions, "vertex0_id", "vertex1_id")
    ev = _rows(collisions.ev_collisions, "vertex_id", "edge_id")
    ee = _rows(collisions.ee_collisions, "edge0_id", "edge1_id", "dtype.value")
    fv = _rows(collisions.fv_collisions, "vertex_id", "face_id")
    ids = np.concatenate(
        [
            np.column_stack([vv, np.full((len(vv), 2), -1)]),
            np.column_stack([ev[:, 0], E[ev[:, 1]].reshape(-1, 2), np.full(len(ev), -1)]),
            E[ee[:, :2]].reshape(-1, 4),
            np.column_stack([fv[:, 0], F[fv[:, 1]].reshape(-1, 3)]),
        ]
    ).astype(np.int64)
    kind = np.repeat(np.arange(4), [len(vv), len(ev), len(ee), len(fv)])
    return CollisionArrays(ids, kind, ee[:, :2], ee[:, 2])


def stencil_blocks(arrays: CollisionArrays, num_vertices: int) -> np.ndarray:
    """Sorted unique vertex-block keys (i * num_vertices + j) of the collisions' stencils.

    The blocks a collision's Hessian couples: every pair of its vertices.
    """
    i = np.repeat(arrays.ids, 4, axis=1)
    j = np.tile(arrays.ids, (1, 4))
    used = (i >= 0) & (j >= 0)
    return sorted_unique(i[used] * num_vertices + j[used])
