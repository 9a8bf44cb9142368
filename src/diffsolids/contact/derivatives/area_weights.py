"""Rest-position gradients of the collision mesh's vertex and edge areas, applied in bulk.

ipctk weights a collision by surface areas of the collision mesh at rest
(``CollisionMesh::init_areas``, paper sec. 4): in 3D a vertex's area is a third of the areas
of its incident faces, an edge's likewise; a vertex in no face takes half the lengths of its
edges (2D and codimensional edges), an edge in no face its length, a vertex in neither 1.
A face-vertex collision weighs 0.25 A_v (its point's area), an edge-edge collision
0.25 (A_ea + A_eb) (``NormalCollisionsBuilder``, IPC and improved-max sets alike). Summing
alpha_v grad A_v + beta_e grad A_e over the mesh therefore gives the weight part of an adjoint
for those collisions with one pass over the faces and edges, instead of one sparse weight
gradient read per collision (``init_area_jacobians`` holds the same gradients per vertex).
"""

import contextlib
import threading
from collections.abc import Iterator

import ipctk
import numpy as np
import scipy.sparse

from diffsolids.contact.detection.collision_arrays import CollisionArrays, in_faces

__all__ = [
    "area_gradient_adjoint",
    "merged_weight_collisions",
    "weight_gradient_adjoint",
    "weight_gradient_rows",
]


def _triangle_area_gradients(x: np.ndarray) -> np.ndarray:
    """(n, 3, 3) gradient of each triangle's area w.r.t. its three corners."""
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    opposite = np.stack([x[:, 2] - x[:, 1], x[:, 0] - x[:, 2], x[:, 1] - x[:, 0]], axis=1)
    return 0.5 * np.cross(n[:, None, :], opposite)


def _edge_length_gradients(x: np.ndarray) -> np.ndarray:
    """(n, 2, dim) gradient of each edge's length w.r.t. its two ends."""
    t = x[:, 1] - x[:, 0]
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return np.stack([-t, t], axis=1)


def _add_at(out: np.ndarray, index: np.ndarray, values: np.ndarray) -> None:
    """``np.add.at(out, index, values)`` for non-negative indices into out's first axis.

    One bincount per column: ~10x faster than ``np.add.at`` (numpy 2.5: 0.07 against 0.7 ms
    for 12 000 rows of 3).
    """
    index = np.ravel(index)
    n = out.shape[0]
    columns = out.reshape(n, -1)  # a view: out is contiguous here
    v = np.asarray(values, dtype=float).reshape(len(index), columns.shape[1])
    for k in range(columns.shape[1]):
        columns[:, k] += np.bincount(index, weights=v[:, k], minlength=n)


def area_gradient_adjoint(
    mesh: ipctk.CollisionMesh, alpha: np.ndarray, beta: np.ndarray
) -> np.ndarray:
    """sum_v alpha_v grad A_v + sum_e beta_e grad A_e w.r.t. the rest positions.

    Args:
        mesh: The collision mesh (its rest positions, edges and faces).
        alpha: (num_vertices,) coefficient of each vertex area.
        beta: (num_edges,) coefficient of each edge area.

    Returns:
        (num_vertices * dim,) the sum, vertex-major as ipctk's gradients.
    """
    X = np.asarray(mesh.rest_positions)
    E, F = np.asarray(mesh.edges), np.asarray(mesh.faces)
    dim = X.shape[1]
    out = np.zeros_like(X)
    in_face, edge_in_face = in_faces(mesh)
    if dim == 3 and len(F):
        FE = np.asarray(mesh.faces_to_edges)
        c = (alpha[F].sum(axis=1) + beta[FE].sum(axis=1)) / 3.0
        grad = _triangle_area_gradients(X[F])
        _add_at(out, F, c[:, None, None] * grad)
    if len(E):
        # vertices in no face: half of each incident edge's length; edges in no face: length
        ends = np.where(in_face[E], 0.0, 0.5 * alpha[E])
        c = ends.sum(axis=1) + np.where(edge_in_face, 0.0, beta)
        grad = _edge_length_gradients(X[E])
        _add_at(out, E, c[:, None, None] * grad)
    return out.ravel()


@contextlib.contextmanager
def _sparse_as_arrays() -> Iterator[None]:
    """Let pybind11 return Eigen sparse vectors as (data, indices, indptr) arrays.

    pybind11 casts an Eigen sparse matrix by calling ``scipy.sparse.csc_matrix((data, indices,
    indptr), shape)``, looked up at each cast; scipy's checks cost ~30 us per call, most of the
    cost of reading one weight gradient per collision. Inside this block that name is a
    subclass whose constructor returns the arrays themselves to this thread and a real
    ``csc_matrix`` to any other thread.
    """
    original = scipy.sparse.csc_matrix
    owner = threading.get_ident()

    class _Raw(original):
        def __new__(cls, arg: tuple, shape: tuple | None = None, **kwargs: object) -> object:
            if threading.get_ident() == owner:
                return arg
            return original(arg, shape=shape, **kwargs)

    scipy.sparse.csc_matrix = _Raw
    try:
        yield
    finally:
        scipy.sparse.csc_matrix = original


def _sparse_parts(g: tuple | scipy.sparse.spmatrix) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(g, tuple):
        return np.asarray(g[1]), np.asarray(g[0])
    g = scipy.sparse.csc_matrix(g)
    return g.indices, g.data


def weight_gradient_rows(collisions: list, size: int) -> scipy.sparse.csr_matrix:
    """The weight gradients of ``collisions`` read from ipctk, one row per collision."""
    if not len(collisions):
        return scipy.sparse.csr_matrix((0, size))
    with _sparse_as_arrays():
        raw = [c.weight_gradient for c in collisions]
    grads = [_sparse_parts(g) for g in raw]
    counts = np.array([len(g[0]) for g in grads])
    indptr = np.concatenate([[0], np.cumsum(counts)])
    index = np.concatenate([g[0] for g in grads]).astype(np.int64)
    data = np.concatenate([g[1] for g in grads])
    return scipy.sparse.csr_matrix((data, index, indptr), shape=(len(collisions), size))


def merged_weight_collisions(collisions: ipctk.NormalCollisions, dim: int) -> list:
    """The collisions whose weights may sum several candidates' (read, not computed).

    Vertex-vertex collisions, and in 3D the edge-vertex ones (``NormalCollisionsBuilder``
    merges the shares of face-vertex and edge-edge candidates, and of the convergent
    formulation's negative terms, into them); in this order.
    """
    read = list(collisions.vv_collisions)
    return read + list(collisions.ev_collisions) if dim == 3 else read


def weight_gradient_adjoint(
    mesh: ipctk.CollisionMesh,
    arrays: CollisionArrays,
    s: np.ndarray,
    merged_rows: scipy.sparse.csr_matrix,
) -> np.ndarray:
    """sum_c s_c grad_X w_c over the collisions of ``arrays`` (one s_c per row).

    Face-vertex (0.25 A_v), edge-edge (0.25 (A_ea + A_eb)) and 2D edge-vertex (0.5 A_v)
    weights go through :func:`area_gradient_adjoint` at once; the merged ones (the first rows,
    :func:`merged_weight_collisions`) through their read gradients ``merged_rows``.
    """
    alpha = np.zeros(mesh.num_vertices)
    beta = np.zeros(mesh.num_edges)
    kind, ids = arrays.kind, arrays.ids
    fv = kind == 3
    _add_at(alpha, ids[fv, 0], 0.25 * s[fv])
    _add_at(beta, arrays.ee_edges, np.repeat(0.25 * s[kind == 2], 2))
    if mesh.dim == 2:
        ev = kind == 1
        _add_at(alpha, ids[ev, 0], 0.5 * s[ev])
    return area_gradient_adjoint(mesh, alpha, beta) + merged_rows.T @ s[: merged_rows.shape[0]]
