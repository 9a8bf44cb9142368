"""Which collision vertices a step's contact Hessians can couple: a vectorised broad phase.

The contact Hessian of a pair of primitives couples all the vertices of its stencil (3D: a
vertex and a face, or two edges; 2D: a vertex and an edge). The Newton matrix of a step must hold
the stencils of the pairs that are within dhat. :func:`reach_blocks` finds the pairs of
primitives whose boxes, each inflated by a margin (and optionally by a bound on how far its own
vertices can travel), overlap, and returns the vertex blocks of their stencils. The cost follows
the number of such pairs, not the size of the primitives: a coarse obstacle face (metres long)
couples only to the vertices that are near it.

Pairs of one body are closed by its deformation (and rotation), not by its translation: they are
inflated by how far each vertex can move relative to its body, and left out when they are
neighbours on the surface at rest (about one edge apart: not contacts). Pairs of different
bodies are inflated by the whole motion.

The broad phase (:func:`box_overlaps`) groups boxes by size (up to twice the median, then by
powers of two of their largest half-extent) and queries one KD-tree of box centres per size
class, so that a few large boxes do not widen the search radius of all the small ones.

Under MPI every rank computes the same reach pattern from the gathered surface, once per step
(it is the part of the matrix pattern that the owners of the rows must preallocate for the
Hessian entries that other ranks' collisions add; see
:mod:`diffsolids.contact.partition`).
"""

from collections.abc import Mapping

import numpy as np
from scipy.spatial import cKDTree

from diffsolids.solvers.sparsity import sorted_unique

__all__ = ["box_overlaps", "reach_blocks"]


def _size_classes(half: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Boxes grouped by size: (indices, largest half-extent in the group) per nonempty class.

    Boxes up to twice the median size form one class, larger ones one class per power of two.
    """
    radius = half.max(axis=1)
    ref = 2.0 * float(np.median(radius))
    if not ref > 0:
        ref = float(radius.max())
    if not ref > 0:
        return [(np.arange(len(half)), 0.0)]
    k = np.ceil(np.log2(np.maximum(radius, ref) / ref)).astype(np.int64)
    order = np.argsort(k, kind="stable")
    _, starts = np.unique(k[order], return_index=True)
    return [(g, float(radius[g].max())) for g in np.split(order, starts[1:])]


def box_overlaps(
    lo_a: np.ndarray,
    hi_a: np.ndarray,
    lo_b: np.ndarray | None = None,
    hi_b: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of overlapping axis-aligned boxes (closed: touching boxes overlap).

    Args:
        lo_a: (n, dim) lower corners of the first set.
        hi_a: (n, dim) upper corners of the first set.
        lo_b: (m, dim) lower corners of the second set (None: pairs within the first set).
        hi_b: (m, dim) upper corners of the second set.

    Returns:
        (i, j) int64 index arrays: box ``i`` of the first set overlaps box ``j`` of the second.
        Within one set, each unordered pair of distinct boxes once, with ``i < j``.
    """
    same = lo_b is None
    if same:
        lo_b, hi_b = lo_a, hi_a
    empty = np.zeros(0, dtype=np.int64)
    if len(lo_a) == 0 or len(lo_b) == 0:
        return empty, empty
    centre_a, half_a = 0.5 * (lo_a + hi_a), 0.5 * (hi_a - lo_a)
    centre_b, half_b = 0.5 * (lo_b + hi_b), 0.5 * (hi_b - lo_b)
    classes_a = _size_classes(half_a)
    classes_b = classes_a if same else _size_classes(half_b)
    trees_a = [cKDTree(centre_a[g]) for g, _ in classes_a]
    trees_b = trees_a if same else [cKDTree(centre_b[g]) for g, _ in classes_b]
    # centres closer than the sum of half-extents in every axis (max norm), with a round-off
    # margin: the exact test below decides
    tol = 1e-12 * float(max(np.abs(lo_a).max(), np.abs(hi_a).max(), np.abs(hi_b).max()))
    found_a, found_b = [empty], [empty]
    for ka, (ga, ra) in enumerate(classes_a):
        for kb, (gb, rb) in enumerate(classes_b):
            if same and kb < ka:
                continue
            reach = (ra + rb) * (1.0 + 1e-12) + tol
            if same and ka == kb:
                near = trees_a[ka].query_pairs(reach, p=np.inf, output_type="ndarray")
                i, j = ga[near[:, 0]], ga[near[:, 1]]
            else:
                near = trees_a[ka].sparse_distance_matrix(
                    trees_b[kb], reach, p=np.inf, output_type="ndarray"
                )
                i, j = ga[near["i"]], gb[near["j"]]
            found_a.append(i)
            found_b.append(j)
    i, j = np.concatenate(found_a), np.concatenate(found_b)
    if same:  # pairs come in either order
        i, j = np.minimum(i, j), np.maximum(i, j)
    overlap = np.all((lo_a[i] <= hi_b[j]) & (lo_b[j] <= hi_a[i]), axis=1)
    return i[overlap].astype(np.int64), j[overlap].astype(np.int64)


def _grown_boxes(
    x: np.ndarray, prims: np.ndarray, grow: Mapping[str, np.ndarray]
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Boxes of primitives (rows of vertex indices), grown by the largest value of a vertex."""
    pts = x[prims]
    lo, hi = pts.min(axis=1), pts.max(axis=1)
    grown = {}
    for name, values in grow.items():
        g = values[prims].max(axis=1)[:, None]
        grown[name] = (lo - g, hi + g)
    return grown


class _Primitives:
    """One kind of primitive (vertices, edges or faces): its boxes, split by body label.

    ``boxes[name]`` are the boxes at x grown by ``grow[name]``, ``rest`` those at the rest
    positions grown by ``rest_grow``.
    """

    def __init__(
        self,
        prims: np.ndarray,
        body: np.ndarray,
        x: np.ndarray,
        grow: Mapping[str, np.ndarray],
        X: np.ndarray,
        rest_grow: np.ndarray,
    ) -> None:
        self.prims = prims
        label = body[prims].min(axis=1)
        order = np.argsort(label, kind="stable")
        labels, starts = np.unique(label[order], return_index=True)
        groups = np.split(order, starts[1:]) if len(order) else []  # no primitive: no group
        self.of_label = dict(zip(labels.tolist(), groups, strict=True))
        self.boxes = _grown_boxes(x, prims, grow)
        self.rest = _grown_boxes(X, prims, {"rest": rest_grow})["rest"]

    def take(self, label: int) -> np.ndarray:
        """Indices of the primitives of one body label."""
        return self.of_label.get(label, np.zeros(0, dtype=np.int64))


def _pairs(
    p: _Primitives, q: _Primitives, a: np.ndarray, b: np.ndarray | None, grow: str
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (into p, q) of the primitives a of p and b of q whose boxes overlap.

    With ``b`` None, the pairs within ``a`` (p is q).
    """
    lo, hi = p.boxes[grow]
    if b is None:
        i, j = box_overlaps(lo[a], hi[a])
        return a[i], a[j]
    i, j = box_overlaps(lo[a], hi[a], *(c[b] for c in q.boxes[grow]))
    return a[i], b[j]


def reach_blocks(
    x: np.ndarray,
    X: np.ndarray,
    edges: np.ndarray,
    faces: np.ndarray,
    body: np.ndarray,
    margin: float,
    motion: np.ndarray | None = None,
    deformation: np.ndarray | None = None,
    static: np.ndarray | None = None,
) -> np.ndarray:
    """Vertex blocks of the stencils of all pairs of primitives that can meet within a step.

    Each primitive's box at ``x`` grows by ``margin`` plus the largest ``motion`` (pairs of
    different bodies) or ``deformation`` (pairs of one body) of its vertices; pairs whose boxes
    overlap are kept. So every pair that can come closer than ``2 margin`` is kept when no
    vertex moves farther than ``motion`` and, relative to one translation of its body, than
    ``deformation``. Left out: pairs sharing a vertex (ipctk skips them); pairs with a
    primitive of static vertices only (they couple only the other primitive's own vertices,
    whose blocks are always returned: each vertex with itself and the ends of each surface
    edge, all in the finite-element pattern); and pairs of one body whose boxes at the rest
    positions ``X``, grown by ``margin`` plus half the longest surface edge at each vertex,
    overlap (neighbours on the surface, e.g. two faces one face apart: not contacts).

    Args:
        x: (num_vertices, dim) positions at the start of the step.
        X: (num_vertices, dim) rest positions.
        edges: (num_edges, 2) surface edges.
        faces: (num_faces, 3) surface faces (3D; ignored in 2D).
        body: (num_vertices,) body label of every vertex (a primitive takes the smallest).
        margin: Growth of every box (half the distance within which pairs are wanted).
        motion: (num_vertices,) bound on each vertex's motion in the step (default 0).
        deformation: (num_vertices,) bound on each vertex's motion relative to its body
            (default 0).
        static: Optional (num_vertices,) mask of static (fully prescribed) vertices.

    Returns:
        Sorted unique keys ``a * num_vertices + b`` of the vertex pairs (a, b), both orders:
        each vertex with itself, the ends of each surface edge, and a vertex of one primitive
        with a vertex of the other for every kept pair. A superset of the vertex blocks
        without static vertices of the contact Hessian of any collision set made of these
        pairs (or of pairs with a static primitive).
    """
    nv, dim = x.shape
    static = np.zeros(nv, dtype=bool) if static is None else np.asarray(static, dtype=bool)
    body = np.asarray(body, dtype=np.int64)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    length = np.linalg.norm(X[edges[:, 0]] - X[edges[:, 1]], axis=1)
    half_edge = np.zeros(nv)
    np.maximum.at(half_edge, edges.ravel(), np.repeat(0.5 * length, 2))
    still = np.zeros(nv)
    grow = {
        "apart": margin + (still if motion is None else np.asarray(motion, dtype=float)),
        "together": margin + (still if deformation is None else np.asarray(deformation, float)),
    }

    def primitives(prims: np.ndarray) -> _Primitives:
        # primitives of static vertices only are left out from the start
        prims = prims[~np.all(static[prims], axis=1)]
        return _Primitives(prims, body, x, grow, X, margin + half_edge)

    vertices = primitives(np.arange(nv, dtype=np.int64)[:, None])
    surface_edges = primitives(edges)
    if dim == 2:
        kinds = [(vertices, surface_edges, False)]
    else:
        faces = primitives(np.asarray(faces, dtype=np.int64).reshape(-1, 3))
        kinds = [(vertices, faces, False), (surface_edges, surface_edges, True)]
    labels = np.unique(body).tolist()
    # pairs of bodies whose boxes (grown by the whole motion) overlap
    apart = grow["apart"][:, None]
    lo = np.array([(x[body == b] - apart[body == b]).min(axis=0) for b in labels])
    hi = np.array([(x[body == b] + apart[body == b]).max(axis=0) for b in labels])
    near = [(labels[i], labels[j]) for i, j in zip(*box_overlaps(lo, hi), strict=True)]
    # each vertex with itself and the ends of each surface edge (in the finite-element pattern)
    keys = [np.arange(nv, dtype=np.int64) * (nv + 1), edges @ [nv, 1], edges @ [1, nv]]
    for p, q, symmetric in kinds:
        a, b = _candidates(p, q, symmetric, labels, near)
        pa, qb = p.prims[a], q.prims[b]
        keys.append((pa[:, :, None] * nv + qb[:, None, :]).reshape(-1))
        keys.append((qb[:, :, None] * nv + pa[:, None, :]).reshape(-1))
    return sorted_unique(*keys)


def _candidates(
    p: _Primitives,
    q: _Primitives,
    symmetric: bool,
    labels: list[int],
    near: list[tuple[int, int]],
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (into p, q) of one kind of primitive pair that can meet."""
    found = []
    for label in labels:  # pairs of one body, unless neighbours on the surface at rest
        i, j = _pairs(p, q, p.take(label), None if symmetric else q.take(label), "together")
        keep = ~_neighbours(p, q, i, j)
        found.append((i[keep], j[keep]))
    for la, lb in near:
        found.append(_pairs(p, q, p.take(la), q.take(lb), "apart"))
        if not symmetric:
            found.append(_pairs(p, q, p.take(lb), q.take(la), "apart"))
    a = np.concatenate([np.zeros(0, dtype=np.int64)] + [i for i, _ in found])
    b = np.concatenate([np.zeros(0, dtype=np.int64)] + [j for _, j in found])
    # primitives sharing a vertex never collide (ipctk skips them)
    shared = np.any(p.prims[a][:, :, None] == q.prims[b][:, None, :], axis=(1, 2))
    return a[~shared], b[~shared]


def _neighbours(p: _Primitives, q: _Primitives, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Which pairs (of one body) are neighbours: their grown rest boxes overlap."""
    lo_a, hi_a = (c[a] for c in p.rest)
    lo_b, hi_b = (c[b] for c in q.rest)
    return np.all((lo_a <= hi_b) & (lo_b <= hi_a), axis=1)
