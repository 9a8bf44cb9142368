"""The boundary of a P2/P3 body subdivided at its finite-element nodes (the collision surface).

A boundary facet of a Lagrange degree-k body is split along its nodes: a 2D edge (a, b) into k
segments through its k - 1 edge nodes, a 3D triangle (a, b, c) into k^2 triangles on the lattice
of its vertex, edge and face nodes (the k + 1 nodes of an edge, (k + 1)(k + 2)/2 of a face). A
node is known by the facet vertices it depends on and its lattice index n (n_a + n_b (+ n_c) = k,
the node of lattice (n_a, n_b, n_c) sits at barycentric coordinates lambda(n) close to n / k):

    key = (v_0, n_0, v_1, n_1, v_2, n_2),  v sorted surface-vertex indices with n > 0
    (unused slots v = -1, n = 0),

which depends only on the vertices' input (file) indices, so every partition builds the same
nodes in the same order. Sub-facets keep the parent's orientation: lattice points (i, j) with
node v_a + i/k (v_b - v_a) + j/k (v_c - v_a) give the triangles (i, j), (i+1, j), (i, j+1) and
(i+1, j), (i+1, j+1), (i, j+1), both oriented as (a, b, c).

The rest position of a node is lambda(n) applied to its facet's vertices: with affine geometry
(required by the contact term) it is the node's dof coordinate, a fixed convex combination of
mesh vertices. lambda comes from the element's reference points (basix), so it is exact for
any symmetric Lagrange variant (DOLFINx's default for P3 is GLL-warped: edge nodes at 0.276 and
0.724, not thirds); the lattice index of a reference or physical node is round(k lambda), valid
while no node moves by more than 1 / (2k) from k-th points (GLL-warped: up to degree 6).
"""

import dolfinx
import ipctk
import numpy as np
import scipy.sparse as sp
from dolfinx import fem

from diffsolids.errors import MeshError

__all__ = [
    "Subdivision",
    "local_node_keys",
    "match_rows",
    "neighbour_filter",
    "neighbour_pairs",
    "reference_lambdas",
    "subdivide",
]

# basix reference entities holding the vertices 0, 1 (and 2) of the cell, in that order
_EDGE01 = {2: 2, 3: 5}
_FACE012 = 3


def _lagrange_element(V: fem.FunctionSpace):  # noqa: ANN202  (basix FiniteElement)
    # a blocked (vector) element gives its scalar sub-element's
    return V.ufl_element().basix_element


def reference_lambdas(V: fem.FunctionSpace) -> dict[tuple[int, ...], np.ndarray]:
    """Barycentric coordinates lambda(n) of the edge and face nodes, keyed by lattice index n.

    Edge nodes are keyed by (n_0, n_1), face nodes (3D) by (n_0, n_1, n_2); every permutation of
    a key is present (the variant must be symmetric under vertex permutations).

    Raises:
        MeshError: A variant whose nodes are not symmetric or too far from the k-th points.
    """
    element = _lagrange_element(V)
    k = int(element.degree)
    dim = V.mesh.topology.dim
    pts = np.asarray(element.points)
    table: dict[tuple[int, ...], np.ndarray] = {}

    def add(lam: np.ndarray) -> None:
        n = np.rint(k * lam).astype(int)
        if n.sum() != k or np.any(n <= 0) or np.abs(k * lam - n).max() >= 0.5 - 1e-9:
            raise MeshError(f"unsupported Lagrange node layout of degree {k} for contact")
        for perm in _permutations(len(lam)):
            key = tuple(int(v) for v in n[perm])
            if key in table and np.abs(table[key] - lam[perm]).max() > 1e-12:
                raise MeshError(
                    f"the Lagrange variant of degree {k} is not symmetric: a subdivided contact"
                    " surface needs nodes that do not depend on the edge direction"
                )
            table.setdefault(key, lam[perm].copy())

    for dof in element.entity_dofs[1][_EDGE01[dim]]:
        t = pts[dof, 0]
        add(np.array([1.0 - t, t]))
    if dim == 3:
        for dof in element.entity_dofs[2][_FACE012]:
            s, t = pts[dof, 0], pts[dof, 1]
            add(np.array([1.0 - s - t, s, t]))
    return table


def _permutations(m: int) -> list[list[int]]:
    if m == 2:
        return [[0, 1], [1, 0]]
    return [[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]]


def _lattice(k: int, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """(lattice points n (L, dim), sub-facets (k or k^2, dim) as indices into them)."""
    if dim == 2:
        j = np.arange(k + 1)
        points = np.stack([k - j, j], axis=1)
        cells = np.stack([j[:-1], j[1:]], axis=1)
        return points, cells
    ij = [(i, j) for j in range(k + 1) for i in range(k + 1 - j)]
    index = {p: m for m, p in enumerate(ij)}
    points = np.array([(k - i - j, i, j) for i, j in ij])
    cells = [(index[i, j], index[i + 1, j], index[i, j + 1]) for i, j in ij if i + j <= k - 1]
    cells += [
        (index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]) for i, j in ij if i + j <= k - 2
    ]
    return points, np.array(cells)


def _canonical(vertices: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Key rows (v_0, n_0, v_1, n_1[, v_2, n_2]) of nodes: sorted vertices with n > 0 first."""
    big = np.iinfo(np.int64).max
    v = np.where(n > 0, vertices, big)
    order = np.argsort(v, axis=1, kind="stable")
    v = np.take_along_axis(v, order, axis=1)
    n = np.take_along_axis(n, order, axis=1)
    v = np.where(n > 0, v, -1)
    return np.stack([v, n], axis=2).reshape(len(v), -1).astype(np.int64)


def _rows(keys: np.ndarray) -> np.ndarray:
    """A 1D view of int64 key rows (one void scalar per row) for sorting and searching."""
    keys = np.ascontiguousarray(keys, dtype=np.int64)
    return keys.view(np.dtype((np.void, keys.dtype.itemsize * keys.shape[1]))).ravel()


class Subdivision:
    """The subdivided surface of a set of boundary facets.

    Args:
        prims: (num_facets, dim) surface-vertex indices of the boundary facets (parent order).
        num_vertices: Number of surface vertices (node indices start there).
        degree: Lagrange degree k >= 2.
        table: :func:`reference_lambdas` of the displacement space.

    Attributes:
        keys: (num_nodes, 2 dim) sorted unique node keys (node i is collision vertex
            num_vertices + i).
        parents: (num_facets, dim) surface vertices of the parent facets (``prims``).
        facet_nodes: (num_facets, L) collision vertices of the lattice points of each facet.
        prims: (num_facets * k^(dim-1), dim) collision-vertex indices of the sub-facets, those
            of facet f at rows f * k^(dim-1) ... (f + 1) * k^(dim-1) - 1.
        weights: (num_nodes, num_vertices) sparse CSR matrix P: node rest positions are
            P @ (surface vertex rest positions).
    """

    def __init__(
        self,
        prims: np.ndarray,
        num_vertices: int,
        degree: int,
        table: dict[tuple[int, ...], np.ndarray],
    ) -> None:
        dim = prims.shape[1]
        k = int(degree)
        points, cells = _lattice(k, dim)
        nf, npt = len(prims), len(points)
        # every lattice point of every facet: a vertex (one n = k) or a node
        n = np.broadcast_to(points, (nf, npt, dim)).reshape(-1, dim)
        verts = np.repeat(prims.astype(np.int64), npt, axis=0)
        is_vertex = (n == k).any(axis=1)
        ids = np.empty(nf * npt, dtype=np.int64)
        ids[is_vertex] = verts[is_vertex][n[is_vertex] == k]
        node_keys = _canonical(verts[~is_vertex], n[~is_vertex])
        if len(node_keys):
            self.keys, inverse = np.unique(node_keys, axis=0, return_inverse=True)
        else:
            self.keys = np.zeros((0, 2 * dim), dtype=np.int64)
            inverse = np.zeros(0, dtype=np.int64)
        ids[~is_vertex] = num_vertices + inverse.ravel()
        per_facet = ids.reshape(nf, npt)
        self.facet_nodes = per_facet
        self.parents = np.asarray(prims, dtype=np.int64)
        self.prims = np.ascontiguousarray(per_facet[:, cells].reshape(-1, dim), dtype=np.int32)
        self.num_vertices = int(num_vertices)
        self.weights = _weights(self.keys, num_vertices, dim, table)


def _weights(
    keys: np.ndarray, num_vertices: int, dim: int, table: dict[tuple[int, ...], np.ndarray]
) -> sp.csr_matrix:
    """P (num_nodes x num_vertices): the lambda(n) of each key on its vertices."""
    m = len(keys)
    v = keys[:, 0::2]
    n = keys[:, 1::2]
    lam = np.zeros(v.shape)
    used = n > 0
    for key, values in table.items():
        width = len(key)
        sel = np.all(n[:, :width] == key, axis=1) & (used.sum(axis=1) == width)
        lam[np.ix_(sel, np.arange(width))] = values
    if np.any(lam[used] <= 0):
        raise MeshError("a collision node has no reference coordinates (unsupported element)")
    rows = np.repeat(np.arange(m), v.shape[1])
    P = sp.csr_matrix(
        (lam[used], (rows[used.ravel()], v[used])), shape=(m, num_vertices), dtype=float
    )
    return P


def _check_simplices(mesh: dolfinx.mesh.Mesh) -> None:
    simplex = {2: dolfinx.mesh.CellType.triangle, 3: dolfinx.mesh.CellType.tetrahedron}
    if mesh.topology.cell_type != simplex.get(mesh.topology.dim):
        raise MeshError(
            "a subdivided contact surface needs triangles or tetrahedra, not "
            f"{mesh.topology.cell_type.name} cells (use boundary='vertices')"
        )


def subdivide(
    prims: np.ndarray, num_vertices: int, V: fem.FunctionSpace
) -> tuple[Subdivision, dict[tuple[int, ...], np.ndarray]]:
    """The :class:`Subdivision` of the facets ``prims`` for the degree of ``V`` (and the table)."""
    _check_simplices(V.mesh)
    table = reference_lambdas(V)
    degree = _lagrange_element(V).degree
    return Subdivision(prims, num_vertices, degree, table), table


def local_node_keys(
    mesh: dolfinx.mesh.Mesh,
    V: fem.FunctionSpace,
    surface_index: np.ndarray,
    table: dict[tuple[int, ...], np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keys, local V blocks and dof coordinates of the local edge/face nodes on the surface.

    Every local cell (owned and ghost) contributes the interior nodes of its edges (and, in 3D,
    faces) whose vertices are all surface vertices; a node shared by several cells is listed
    several times.

    Args:
        mesh: The mesh (affine geometry).
        V: The displacement space.
        surface_index: Surface-vertex index of every local geometry node (-1: not on it).
        table: :func:`reference_lambdas` of V.

    Returns:
        (keys (m, 2 tdim), blocks (m,), coordinates (m, gdim)).

    Raises:
        MeshError: A node whose coordinates are not those of its lattice index.
    """
    import basix

    tdim = mesh.topology.dim
    gdim = mesh.geometry.dim
    _check_simplices(mesh)
    k = int(_lagrange_element(V).degree)
    nv = dolfinx.cpp.mesh.cell_num_vertices(mesh.topology.cell_type)
    cell_type = basix.CellType.triangle if tdim == 2 else basix.CellType.tetrahedron
    topo = basix.topology(cell_type)
    gnodes = mesh.geometry.dofmaps[0][:, :nv]
    cell_surface = surface_index[gnodes]
    dofs = V.dofmap.list
    layout = V.dofmap.dof_layout
    X = V.tabulate_dof_coordinates()[:, :gdim]
    xg = mesh.geometry.x[:, :gdim]
    near = np.flatnonzero((cell_surface >= 0).sum(axis=1) >= 2)
    out_keys, out_blocks, out_x = [], [], []
    for d in range(1, tdim):
        for e, ev in enumerate(topo[d]):
            local = layout.entity_dofs(d, e)
            if len(local) == 0:
                continue
            sv = cell_surface[near][:, ev]
            cells = near[np.all(sv >= 0, axis=1)]
            if len(cells) == 0:
                continue
            sv = cell_surface[cells][:, ev]
            corners = xg[gnodes[cells][:, ev]]  # (c, d + 1, gdim)
            blocks = dofs[cells][:, local]  # (c, m)
            xd = X[blocks]  # (c, m, gdim)
            lam = _barycentric(corners, xd)  # (c, m, d + 1)
            n = np.rint(k * lam).astype(np.int64)
            vv = np.broadcast_to(sv[:, None, :], n.shape).reshape(-1, d + 1)
            keys = _canonical(vv, n.reshape(-1, d + 1))
            if tdim == 3 and d == 1:
                keys = np.concatenate([keys, np.tile([-1, 0], (len(keys), 1))], axis=1)
            out_keys.append(keys)
            out_blocks.append(blocks.ravel())
            out_x.append(xd.reshape(-1, gdim))
    if not out_keys:
        return np.zeros((0, 2 * tdim), np.int64), np.zeros(0, np.int64), np.zeros((0, gdim))
    keys = np.concatenate(out_keys)
    n = keys[:, 1::2]
    if np.any(n.sum(axis=1) != k):
        raise MeshError("a boundary node of the displacement space is off its lattice")
    return keys, np.concatenate(out_blocks).astype(np.int64), np.concatenate(out_x)


def _barycentric(corners: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of points x (c, m, g) in simplices corners (c, d + 1, g)."""
    E = corners[:, 1:] - corners[:, :1]  # (c, d, g)
    r = x - corners[:, None, 0]  # (c, m, g)
    G = np.einsum("cig,cjg->cij", E, E)
    rhs = np.einsum("cig,cmg->cmi", E, r)
    mu = np.linalg.solve(G[:, None], rhs[..., None])[..., 0]  # (c, m, d)
    return np.concatenate([1.0 - mu.sum(axis=2, keepdims=True), mu], axis=2)


def match_rows(table: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Row of ``table`` (unique key rows) equal to each row of ``keys`` (-1: none)."""
    if len(table) == 0 or len(keys) == 0:
        return np.full(len(keys), -1, dtype=np.int64)
    t, q = _rows(table), _rows(keys)
    order = np.argsort(t)
    ts = t[order]
    pos = np.minimum(np.searchsorted(ts, q), len(ts) - 1)
    return np.where(ts[pos] == q, order[pos], -1).astype(np.int64)


def neighbour_pairs(facet_nodes: np.ndarray, facet_vertices: np.ndarray) -> np.ndarray:
    """Sorted unique pairs (i < j) of collision vertices of facets that share a mesh vertex.

    The ipctk adjacency rule (primitives sharing a vertex never collide) lifted to the parent
    facets: a sub-facet pair is skipped when all its vertex pairs are listed here, which holds
    when their parent facets are equal or share a vertex v: both lie in the star of v (the
    nodes of the facets around v), and every pair of nodes of one star is listed. With M the
    0/1 incidence (vertex, node in its star), the pairs are the upper triangle of M^T M.

    Args:
        facet_nodes: (num_facets, L) collision vertices of each parent facet (its lattice).
        facet_vertices: (num_facets, dim) mesh (surface) vertices of each parent facet.

    Returns:
        (m, 2) int64 array of pairs i < j, sorted.
    """
    if len(facet_vertices) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    M = _star_incidence(facet_nodes, facet_vertices)
    n = M.shape[1]
    A = sp.triu(M.T @ M, k=1).tocsr()
    i = np.repeat(np.arange(n, dtype=np.int64), np.diff(A.indptr))
    return np.stack([i, A.indices.astype(np.int64)], axis=1)


def _star_incidence(facet_nodes: np.ndarray, facet_vertices: np.ndarray) -> sp.csr_matrix:
    """0/1 matrix M (surface vertex x collision vertex): node j lies in the star of vertex v."""
    n = int(facet_nodes.max()) + 1
    nv = int(facet_vertices.max()) + 1
    L = facet_nodes.shape[1]
    rows = np.repeat(facet_vertices.astype(np.int64)[:, :, None], L, axis=2).ravel()
    cols = np.broadcast_to(
        facet_nodes.astype(np.int64)[:, None, :], (len(facet_nodes), facet_vertices.shape[1], L)
    ).ravel()
    M = sp.csr_matrix((np.ones(len(rows), dtype=np.int32), (rows, cols)), shape=(nv, n))
    M.data[:] = 1  # duplicates summed: back to 0/1
    return M


def _colouring(G: sp.csr_matrix) -> np.ndarray:
    """A colouring of the graph G (symmetric pattern): adjacent vertices get different colours.

    Jones-Plassmann rounds, vectorised: every uncoloured vertex whose (fixed pseudo-random)
    weight beats all its uncoloured neighbours takes the smallest colour none of its coloured
    neighbours has. The weights are seeded, so every rank colours the same graph the same way.
    """
    n = G.shape[0]
    G = sp.csr_matrix(G)
    rows = np.repeat(np.arange(n), np.diff(G.indptr))
    cols = G.indices.astype(np.int64)
    off = rows != cols
    rows, cols = rows[off], cols[off]
    weight = np.random.default_rng(0).permutation(n)
    colour = np.full(n, -1, dtype=np.int64)
    while np.any(colour < 0):
        free = colour < 0
        best = np.full(n, -1, dtype=np.int64)
        np.maximum.at(best, rows, np.where(free[cols], weight[cols], -1))
        pick = np.flatnonzero(free & (weight > best))
        slot = np.full(n, -1, dtype=np.int64)
        slot[pick] = np.arange(len(pick))
        used = np.zeros((len(pick), int(colour.max()) + 2), dtype=bool)
        m = (slot[rows] >= 0) & (colour[cols] >= 0)
        used[slot[rows[m]], colour[cols[m]]] = True
        colour[pick] = np.argmin(used, axis=1)  # the first colour not used around
    return colour


def neighbour_filter(
    facet_nodes: np.ndarray, facet_vertices: np.ndarray, num_vertices: int
) -> ipctk.CollisionFilter:
    """An ipctk filter refusing exactly the pairs of :func:`neighbour_pairs` (all others pass).

    The stars of vertices of one colour of a colouring of the star-overlap graph (M M^T) are
    disjoint, so per colour a patch label (the star's vertex, or a label of its own for a node
    in no star of that colour) refuses the pairs within those stars; the filter is the AND of
    one vertex-patch filter per colour (about a dozen on a triangulated surface): no Python per
    pair, and array lookups instead of a hash map of all pairs.

    Args:
        facet_nodes: (num_facets, L) collision vertices of each parent facet (its lattice).
        facet_vertices: (num_facets, dim) mesh (surface) vertices of each parent facet.
        num_vertices: Number of collision vertices of the mesh (obstacles included).
    """
    M = _star_incidence(facet_nodes, facet_vertices)
    nv = M.shape[0]
    colour = _colouring((M @ M.T).tocsr())
    own = np.arange(num_vertices, dtype=np.int64) + nv  # never a vertex id
    filt = ipctk.CollisionFilter()
    coo = M.tocoo()
    for c in range(int(colour.max()) + 1):
        sel = colour[coo.row] == c
        label = own.copy()
        label[coo.col[sel]] = coo.row[sel]
        filt = filt & ipctk.make_vertex_patches_filter(label.astype(np.int32))
    return filt
