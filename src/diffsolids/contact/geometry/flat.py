"""Flat regions of fixed obstacles: contact with a plane, whatever its triangulation.

An edge between two coplanar faces (3D), or a vertex between two collinear segments (2D) or
inside such faces (3D), is no geometric feature: near it the distance to the obstacle is the
distance to its plane. In the convergent formulation (ipctk's improved max approximation,
Li et al. 2023) the face, edge and vertex terms of a body vertex add up to one barrier of
that distance, but two kinds of term still see the triangulation:

- edge-edge pairs with an edge inside the plane (the distance between two crossing edges
  does not change as one slides along the other: a barrier ridge along the edge, which pushes
  a body resting over it sideways, so that round-off chooses between two mirror states);
- the obstacle's side of the two-sided quadrature: an obstacle vertex inside the plane under
  a body carries a barrier term weighted by its own vertex area (large for a coarse ground),
  so the force depends on where the obstacle has vertices.

:class:`FlatRegions` removes both: the candidates of those edge-edge pairs and of the flat
vertices against the bodies' faces (edges in 2D) are dropped before the build, and the
flat vertex's share of the vertex-vertex terms the improved max approximation adds is taken
out after it. The plane then acts through the bodies' vertices only (one-sided), as a plane
of one triangle does.

The IPC collision set (``formulation="ipc"``, the default) has one term per closest primitive
pair: a body vertex over a face next to a coplanar face gets the face's term and the edge
term of its neighbour (a barrier ridge along every flat edge). There the same two kinds of
candidate are dropped and, of a body vertex's face (segment) candidates within one flat
region, only the nearest is kept (:meth:`FlatRegions.nearest`): the vertex sees the distance
to the region, one polygon of a plane.
"""

from itertools import compress

import ipctk
import numpy as np

from diffsolids.contact.geometry.candidate_ids import candidate_ids
from diffsolids.contact.geometry.distances import pair_distances, point_segment_distances

__all__ = ["FlatRegions", "flat_edge_mask", "flat_primitive_regions", "flat_vertex_mask"]

_COPLANAR = 1e-10  # 1 - cos of the angle between the normals (or segments) of a flat joint
# a flat joint is also straight to round-off: its crease is at most _FLAT_ULPS ulps of the
# obstacle's largest coordinate high (as the step bound's gap floor). A crease of 1e-7 m (an
# obstacle read from a file with 7 digits) is geometry at the barrier's distances (~1e-11 m):
# an edge across a convex one meets it closer than its ends meet either plane, so dropping
# that edge-edge pair would leave the barrier blind to a contact the step bound still stops.
_FLAT_ULPS = 1e2


def _edge_rows(edges: np.ndarray, pairs: np.ndarray, n: int) -> np.ndarray:
    """Row of ``edges`` (sorted rows) holding each sorted vertex pair of ``pairs``."""
    key = edges[:, 0].astype(np.int64) * (n + 1) + edges[:, 1]
    order = np.argsort(key)
    wanted = pairs[:, 0].astype(np.int64) * (n + 1) + pairs[:, 1]
    return order[np.searchsorted(key, wanted, sorter=order)]


def _edge_faces(
    faces: np.ndarray, edges: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per edge: the number of faces holding it, the first and the last of them."""
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    row = _edge_rows(edges, pairs, n)
    face = np.repeat(np.arange(len(faces)), 3)
    count = np.bincount(row, minlength=len(edges))
    first = np.zeros(len(edges), dtype=np.int64)
    first[row[::-1]] = face[::-1]
    last = np.zeros(len(edges), dtype=np.int64)
    last[row] = face
    return count, first, last


def flat_primitive_regions(
    vertices: np.ndarray, edges: np.ndarray, faces: np.ndarray, flat_edges: np.ndarray | None
) -> np.ndarray:
    """The flat region of each primitive of one obstacle, numbered from 0.

    Faces (3D) are joined across flat edges, segments (2D) at flat vertices.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if flat_edges is not None:
        _, first, last = _edge_faces(faces, edges, len(vertices))
        a, b, m = first[flat_edges], last[flat_edges], len(faces)
    else:
        flat = flat_vertex_mask(vertices, edges, None)
        n = len(vertices)
        incoming = np.full(n, -1, dtype=np.int64)
        outgoing = np.full(n, -1, dtype=np.int64)
        incoming[edges[:, 1]] = np.arange(len(edges))
        outgoing[edges[:, 0]] = np.arange(len(edges))
        a, b, m = incoming[flat], outgoing[flat], len(edges)
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(m, m))
    return connected_components(graph, directed=False)[1]


def flat_edge_mask(vertices: np.ndarray, faces: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Which edges of a triangle surface lie inside a plane of it.

    Args:
        vertices: (n, 3) coordinates.
        faces: (m, 3) triangles.
        edges: (k, 2) the faces' edges, each row sorted.

    Returns:
        Boolean mask over ``edges``: two faces, coplanar and alike oriented, each face's third
        vertex within ``_FLAT_ULPS`` ulps of the largest coordinate from the other's plane.
    """
    X = np.asarray(vertices, dtype=float)
    normal = np.cross(X[faces[:, 1]] - X[faces[:, 0]], X[faces[:, 2]] - X[faces[:, 0]])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    count, first, last = _edge_faces(faces, edges, len(X))
    flat = count == 2
    f0, f1, e = first[flat], last[flat], edges[flat]
    cos = np.einsum("ij,ij->i", normal[f0], normal[f1])
    ends = e.sum(axis=1)
    origin = X[e[:, 0]]
    crease = np.maximum(
        np.abs(np.einsum("ij,ij->i", X[faces[f1].sum(axis=1) - ends] - origin, normal[f0])),
        np.abs(np.einsum("ij,ij->i", X[faces[f0].sum(axis=1) - ends] - origin, normal[f1])),
    )
    flat[flat] = (cos >= 1.0 - _COPLANAR) & (crease <= _straight_tolerance(X))
    return flat


def _straight_tolerance(X: np.ndarray) -> float:
    """The largest crease (kink) of a flat joint: ``_FLAT_ULPS`` ulps of the coordinates."""
    return _FLAT_ULPS * np.finfo(float).eps * float(np.abs(X).max(initial=0.0))


def flat_vertex_mask(
    vertices: np.ndarray, edges: np.ndarray, flat_edges: np.ndarray | None
) -> np.ndarray:
    """Which vertices lie inside a plane (3D) or a straight run of segments (2D).

    Args:
        vertices: (n, dim) coordinates.
        edges: (k, 2) edges (3D: sorted rows) or directed segments (2D).
        flat_edges: 3D: the mask of :func:`flat_edge_mask`; 2D: None.

    Returns:
        Boolean mask over the vertices. 3D: every incident edge is flat. 2D: two segments,
        one ending and one starting at the vertex, in the same direction, the vertex within
        ``_FLAT_ULPS`` ulps of the largest coordinate from the line through their other ends.
    """
    n = len(vertices)
    if flat_edges is not None:
        incident = np.bincount(edges.ravel(), minlength=n)
        flat = np.bincount(edges[flat_edges].ravel(), minlength=n)
        return (incident > 0) & (flat == incident)
    X = np.asarray(vertices, dtype=float)
    ends = np.bincount(edges[:, 1], minlength=n)
    starts = np.bincount(edges[:, 0], minlength=n)
    joint = (ends == 1) & (starts == 1)
    incoming = np.zeros((n, X.shape[1]))
    outgoing = np.zeros((n, X.shape[1]))
    d = X[edges[:, 1]] - X[edges[:, 0]]
    d /= np.linalg.norm(d, axis=1)[:, None]
    incoming[edges[:, 1]] = d
    outgoing[edges[:, 0]] = d
    before, after = np.arange(n), np.arange(n)
    before[edges[:, 1]] = edges[:, 0]
    after[edges[:, 0]] = edges[:, 1]
    kink = point_segment_distances(X, X[before], X[after])
    straight = np.einsum("ij,ij->i", incoming, outgoing) >= 1.0 - _COPLANAR
    return joint & straight & (kink <= _straight_tolerance(X))


class FlatRegions:
    """The flat edges and vertices of a collision mesh's fixed obstacles, by global index.

    Args:
        dim: 2 or 3.
        edges: Global indices of flat edges (3D; empty in 2D).
        vertices: Global indices of flat vertices.
        primitive_region: Per face (3D) or edge (2D) of the collision mesh, the number of its
            flat region (faces joined across flat edges, segments at flat vertices), -1 for
            the bodies' primitives and moving obstacles'.
    """

    def __init__(
        self,
        dim: int,
        edges: np.ndarray,
        vertices: np.ndarray,
        primitive_region: np.ndarray | None = None,
    ) -> None:
        self.dim = dim
        self.edges = np.asarray(edges, dtype=np.int64)
        self.vertices = np.asarray(vertices, dtype=np.int64)
        self.primitive_region = (
            np.zeros(0, dtype=np.int64) if primitive_region is None else primitive_region
        )

    def __bool__(self) -> bool:
        return bool(len(self.edges) or len(self.vertices))

    def filter(self, candidates: ipctk.Candidates) -> ipctk.Candidates:
        """Drop the edge-edge candidates with a flat edge and the flat vertices' candidates.

        A flat vertex's candidates are those against the bodies' faces (3D) or edges (2D):
        the obstacle's side of the quadrature inside its plane.
        """
        if len(self.edges):
            ee = candidates.ee_candidates
            ids = candidate_ids(ee, "edge0_id", "edge1_id")
            keep = ~np.isin(ids, self.edges).any(axis=1)
            if not keep.all():
                candidates.ee_candidates = list(compress(ee, keep.tolist()))
        if not len(self.vertices):
            return candidates
        name = "fv_candidates" if self.dim == 3 else "ev_candidates"
        pairs = getattr(candidates, name)
        keep = ~np.isin(candidate_ids(pairs, "vertex_id")[:, 0], self.vertices)
        if not keep.all():
            setattr(candidates, name, list(compress(pairs, keep.tolist())))
        return candidates

    def nearest(
        self, candidates: ipctk.Candidates, x: np.ndarray, mesh: ipctk.CollisionMesh
    ) -> ipctk.Candidates:
        """Keep one candidate per body vertex and flat region: its nearest face (segment).

        The distance to a flat region is the distance to the nearest of its faces (the union
        is one polygon of a plane); the IPC collision set would add a term per face the vertex
        is close to, e.g. the face under it and the edge of the coplanar face next to it.
        Ties (a vertex over a flat edge) go to the first face in order.
        """
        if not len(self.primitive_region):
            return candidates
        if self.dim == 3:
            pairs = candidates.fv_candidates
            if not pairs:
                return candidates
            ids = candidate_ids(pairs, "face_id", "vertex_id")
            a, b, c = (x[np.asarray(mesh.faces)[ids[:, 0], k]] for k in range(3))
            dist = pair_distances([x[ids[:, 1]], a, b, c], "fv")
        else:
            pairs = candidates.ev_candidates
            if not pairs:
                return candidates
            ids = candidate_ids(pairs, "edge_id", "vertex_id")
            a, b = (x[np.asarray(mesh.edges)[ids[:, 0], k]] for k in range(2))
            dist = point_segment_distances(x[ids[:, 1]], a, b)
        region = self.primitive_region[ids[:, 0]]
        grouped = np.flatnonzero(region >= 0)
        order = grouped[
            np.lexsort((ids[grouped, 0], dist[grouped], region[grouped], ids[grouped, 1]))
        ]
        key = np.column_stack([ids[order, 1], region[order]])
        first = np.ones(len(order), dtype=bool)
        first[1:] = np.any(key[1:] != key[:-1], axis=1)
        keep = region < 0
        keep[order[first]] = True
        if keep.all():
            return candidates
        # a new Candidates: the line search builds several sets from one CCD segment's
        # candidates, at different x, so those must stay whole
        out = ipctk.Candidates()
        out.ee_candidates = candidates.ee_candidates
        out.vv_candidates = candidates.vv_candidates
        out.pv_candidates = candidates.pv_candidates
        kept = list(compress(pairs, keep.tolist()))
        if self.dim == 3:
            out.ev_candidates = candidates.ev_candidates
            out.fv_candidates = kept
        else:
            out.fv_candidates = candidates.fv_candidates
            out.ev_candidates = kept
        return out

    def correct(self, collisions: ipctk.NormalCollisions, mesh: ipctk.CollisionMesh) -> None:
        """Take the flat vertices' share out of the improved max approximation's vertex pairs.

        ``normal_collisions_builder.cpp`` adds to a vertex pair (v, p) the share of each side:
        3D (positive terms) 1/4 of the vertex area of the other side's vertex unless that one
        is on an open boundary; 2D (negative terms) (1 - n) / 2 of it, n the number of edges
        at the other vertex when above 1. The share of a flat vertex p is removed.
        """
        if not len(self.vertices) or not collisions.vv_collisions:
            return
        vv = collisions.vv_collisions
        ids = np.array([(c.vertex0_id, c.vertex1_id) for c in vv], dtype=np.int64)
        flat = np.isin(ids, self.vertices)
        rows = np.flatnonzero(flat.any(axis=1))
        if not len(rows):
            return
        areas = np.asarray(mesh.vertex_areas).ravel()
        adjacency = mesh.vertex_vertex_adjacencies
        for k in rows:  # the pairs at a flat vertex: a few per body vertex near one
            c = vv[k]
            for side in (0, 1):
                if not flat[k, side]:
                    continue
                p, v = ids[k, side], ids[k, 1 - side]
                if self.dim == 3:
                    share = 0.0 if mesh.is_vertex_on_boundary(v) else 0.25 * areas[p]
                else:
                    n = len(adjacency[v])
                    share = (1 - n) * 0.5 * areas[p] if n > 1 else 0.0
                c.weight = c.weight - share
        collisions.vv_collisions = vv
