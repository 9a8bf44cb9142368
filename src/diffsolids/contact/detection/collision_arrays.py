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

__all__ = [
    "CollisionArrays",
    "collision_arrays",
    "cross_squared_norms",
    "edge_edge_weights",
    "in_faces",
    "merged_edge_edge",
    "read_weights",
    "stencil_blocks",
    "weights_from_gradients",
]


@dataclass
class CollisionArrays:
    """The collisions of a set, one row each, in ipctk's type order (vv, ev, ee, fv).

    Attributes:
        ids: (n, 4) vertex ids in the order of ``vertex_ids``, -1 padded.
        kind: (n,) type: 0 vertex-vertex, 1 edge-vertex, 2 edge-edge, 3 face-vertex.
        ee_edges: (number of ee, 2) edge ids of the edge-edge collisions.
        ee_dtype: (number of ee,) their ipctk ``EdgeEdgeDistanceType`` values.
        ee_eps: (number of ee,) their mollifier thresholds eps_x.
        weight: (n,) the collisions' weights, when read (:func:`read_weights`).
    """

    ids: np.ndarray
    kind: np.ndarray
    ee_edges: np.ndarray
    ee_dtype: np.ndarray
    ee_eps: np.ndarray
    weight: np.ndarray | None = None

    def without_ee(self, dropped: np.ndarray) -> "CollisionArrays":
        """These collisions less the edge-edge ones flagged in ``dropped`` (one per ee)."""
        keep = np.ones(len(self.kind), dtype=bool)
        keep[self.kind == 2] = ~dropped
        k = ~dropped
        weight = None if self.weight is None else self.weight[keep]
        return CollisionArrays(
            self.ids[keep],
            self.kind[keep],
            self.ee_edges[k],
            self.ee_dtype[k],
            self.ee_eps[k],
            weight,
        )


def _rows(items: list, *names: str) -> np.ndarray:
    get = attrgetter(*names)
    return np.array([get(c) for c in items], dtype=float).reshape(len(items), len(names))


def collision_arrays(
    collisions: ipctk.NormalCollisions, mesh: ipctk.CollisionMesh
) -> CollisionArrays:
    """The ids and types of the collisions of a set (one pass over each list)."""
    E, F = np.asarray(mesh.edges), np.asarray(mesh.faces)
    vv = _rows(collisions.vv_collisions, "vertex0_id", "vertex1_id").astype(np.int64)
    ev = _rows(collisions.ev_collisions, "vertex_id", "edge_id").astype(np.int64)
    ee = _rows(collisions.ee_collisions, "edge0_id", "edge1_id", "dtype.value", "eps_x")
    fv = _rows(collisions.fv_collisions, "vertex_id", "face_id").astype(np.int64)
    ee_ids = ee[:, :3].astype(np.int64)
    ids = np.concatenate(
        [
            np.column_stack([vv, np.full((len(vv), 2), -1)]),
            np.column_stack([ev[:, 0], E[ev[:, 1]].reshape(-1, 2), np.full(len(ev), -1)]),
            E[ee_ids[:, :2]].reshape(-1, 4),
            np.column_stack([fv[:, 0], F[fv[:, 1]].reshape(-1, 3)]),
        ]
    ).astype(np.int64)
    kind = np.repeat(np.arange(4), [len(vv), len(ev), len(ee), len(fv)])
    return CollisionArrays(ids, kind, ee_ids[:, :2], ee_ids[:, 2], ee[:, 3])


def merged_edge_edge(
    collisions: ipctk.NormalCollisions, arrays: CollisionArrays, positions: np.ndarray
) -> np.ndarray:
    """Which edge-edge collisions (one flag each) may carry merged weights.

    The convergent formulation (``NormalCollisionsBuilder``) adds negative terms to the
    edge-edge pairs below their mollifier threshold eps_x at the build's positions; those
    within round-off of it (1e-6 relative) are flagged too. None in the IPC formulation.
    """
    ee = arrays.kind == 2
    ipc = collisions.collision_set_type == ipctk.NormalCollisions.CollisionSetType.IPC
    if ipc or not ee.any():
        return np.zeros(int(ee.sum()), dtype=bool)
    return cross_squared_norms(positions[arrays.ids[ee]]) < arrays.ee_eps * (1.0 + 1e-6)


def read_weights(
    collisions: ipctk.NormalCollisions,
    arrays: CollisionArrays,
    mesh: ipctk.CollisionMesh,
    positions: np.ndarray,
    merged: np.ndarray | None = None,
) -> np.ndarray:
    """The weights of the collisions of a set, in the order of :func:`collision_arrays`.

    ``NormalCollisionsBuilder`` gives a face-vertex collision 0.25 A_v, an edge-edge one
    0.25 (A_ea + A_eb) and a 2D edge-vertex one 0.5 A_v (the mesh's vertex and edge areas),
    or 1 each without area weighting, computed here; the vertex-vertex and 3D edge-vertex ones
    may sum the shares of several candidates (without area weighting: count them) and the
    flat regions' corrections, and the edge-edge ones of :func:`merged_edge_edge` negative
    terms: those are read from ipctk, one attribute each.

    Args:
        collisions: The set.
        arrays: Its :func:`collision_arrays`.
        mesh: The collision mesh of the build.
        positions: (num_vertices, dim) the positions the set was built at.
        merged: The weights of the vertex-vertex and 3D edge-vertex collisions if known
            (:func:`weights_from_gradients`), else they are read.
    """
    kind, ids = arrays.kind, arrays.ids
    weight = np.ones(len(kind))
    if merged is None:
        listed = list(collisions.vv_collisions)
        if mesh.dim == 3:
            listed += list(collisions.ev_collisions)
        merged = [c.weight for c in listed]
    weight[: len(merged)] = merged
    if collisions.use_area_weighting:
        vertex_areas = np.asarray(mesh.vertex_areas).ravel()
        if mesh.dim == 2:
            ev = kind == 1
            weight[ev] = 0.5 * vertex_areas[ids[ev, 0]]
        fv = kind == 3
        weight[fv] = 0.25 * vertex_areas[ids[fv, 0]]
    weight[kind == 2] = edge_edge_weights(collisions, arrays, mesh, positions)
    return weight


def weights_from_gradients(
    collisions: ipctk.NormalCollisions, mesh: ipctk.CollisionMesh, gradients: object
) -> np.ndarray | None:
    """Area weights recovered from their rest-position gradients (one per row), or None.

    A collision's area weight is a sum of multiples of vertex and edge areas of the collision
    mesh, and those are homogeneous in the rest positions X: of degree 2 for the areas of
    triangles (3D), 1 for lengths. Where all have one degree k (2D; 3D with every vertex and
    edge in a face), Euler's identity gives w = X . grad w / k. None where it does not apply
    (no area weighting, or 3D vertices or edges in no face).

    Args:
        collisions: The set (for its area weighting).
        mesh: Its collision mesh.
        gradients: (n, num_vertices * dim) sparse rows, the weights' gradients.
    """
    if not collisions.use_area_weighting:
        return None
    X = np.asarray(mesh.rest_positions)
    degree = 1
    if mesh.dim == 3:
        in_face, edge_in_face = in_faces(mesh)
        if not (in_face.all() and edge_in_face.all()):
            return None
        degree = 2
    return np.asarray(gradients @ X.ravel()).ravel() / degree


def in_faces(mesh: ipctk.CollisionMesh) -> tuple[np.ndarray, np.ndarray]:
    """(vertex, edge) flags of the collision mesh's vertices and edges in some face (3D)."""
    in_face = np.zeros(mesh.num_vertices, dtype=bool)
    edge_in_face = np.zeros(mesh.num_edges, dtype=bool)
    if mesh.dim == 3 and len(np.asarray(mesh.faces)):
        in_face[np.asarray(mesh.faces).ravel()] = True
        edge_in_face[np.asarray(mesh.faces_to_edges).ravel()] = True
    return in_face, edge_in_face


def edge_edge_weights(
    collisions: ipctk.NormalCollisions,
    arrays: CollisionArrays,
    mesh: ipctk.CollisionMesh,
    positions: np.ndarray,
) -> np.ndarray:
    """The weights of a set's edge-edge collisions (one per ee row of ``arrays``).

    0.25 (A_ea + A_eb) (1 without area weighting), read from ipctk for the pairs of
    :func:`merged_edge_edge` only (see :func:`read_weights`).
    """
    if collisions.use_area_weighting:
        edge_areas = np.asarray(mesh.edge_areas()).ravel()
        weight = 0.25 * edge_areas[arrays.ee_edges].sum(axis=1)
    else:
        weight = np.ones(len(arrays.ee_edges))
    read = np.flatnonzero(merged_edge_edge(collisions, arrays, positions))
    if len(read):
        ee = collisions.ee_collisions
        weight[read] = [ee[k].weight for k in read]
    return weight


def cross_squared_norms(edge_positions: np.ndarray) -> np.ndarray:
    """|ea x eb|^2 of (n, 4, 3) edge pairs (ea0, ea1, eb0, eb1; ``edge_edge_cross_squarednorm``)."""
    x = edge_positions
    c = np.cross(x[:, 1] - x[:, 0], x[:, 3] - x[:, 2])
    return c[:, 0] * c[:, 0] + c[:, 1] * c[:, 1] + c[:, 2] * c[:, 2]


def stencil_blocks(arrays: CollisionArrays, num_vertices: int) -> np.ndarray:
    """Sorted unique vertex-block keys (i * num_vertices + j) of the collisions' stencils.

    The blocks a collision's Hessian couples: every pair of its vertices.
    """
    i = np.repeat(arrays.ids, 4, axis=1)
    j = np.tile(arrays.ids, (1, 4))
    used = (i >= 0) & (j >= 0)
    return sorted_unique(i[used] * num_vertices + j[used])
