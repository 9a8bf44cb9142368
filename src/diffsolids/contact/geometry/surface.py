"""The collision surface: the boundary of the mesh as one ipctk CollisionMesh on every rank.

Collision vertices are the mesh vertices on the exterior boundary, then, for P2/P3 bodies with
``boundary="nodes"``, the edge and face nodes of the boundary facets: every facet is split along
its nodes (2D: k segments, 3D: k^2 triangles, as PolyFEM does; ``subdivision.py``), so the
collision surface is the piecewise-linear interpolant of the simulated boundary through all its
nodes and the intersection-free guarantee holds at every node, not only at the vertices. The
displacement map W (collision vertices x FE nodes) stays a 0/1 selection of displacement blocks
(every collision vertex is one FE node); the rest positions of the nodes are fixed convex
combinations of the mesh vertices (affine geometry), X_nodes = P X_vertices, so the map from
the shape space (mesh vertex positions) to the collision rest positions is sparse linear, and
shape gradients are pulled back through P^T (``pull_back`` of the map
:meth:`CollisionSurface.shape_map` returns). Split facets put primitives of one body about
h/(2k) apart at rest, closer than a typical dhat: two nodes in the star of one mesh vertex (the
nodes of the facets around it) never collide, so sub-facets whose parent facets are equal or
share a vertex never do (ipctk's rule for primitives sharing a vertex, applied to the parent
facets; one ipctk filter built once: an AND of vertex-patch filters, one per colour of the
vertex stars). ``boundary="vertices"`` keeps the facets between the mesh vertices only (the
P2/P3 boundary then moves with the displacement at the vertices and may sag through another
body by O(h^2 curvature) between them); for P1 both are the same surface.

The surface is numbered by the input (file) index of the vertices, independent of the partition,
so a run on n ranks builds the same collision mesh as a serial run; the nodes follow, sorted by
a key made of their facet vertices' indices and lattice position (partition independent too).
Each rank contributes the values of the vertices and nodes whose displacement block it owns
(one allgather per evaluation).

Kinematic obstacles (:class:`~diffsolids.contact.geometry.obstacle.Obstacle`) are appended after the
body vertices (``num_body_vertices`` ... ``num_vertices``): they are part of the CollisionMesh
(collision set, CCD, area weights from their own segments/triangles) but have no dofs: every
array gathered from a V array holds zeros in their rows, their dofs count as prescribed
(:meth:`CollisionSurface.dof_mask`), and the owner maps, global dofs and matrix insertion see
body vertices only. Each obstacle has a body id after the domain's (``body_ids``).
"""

from collections.abc import Sequence

import dolfinx
import dolfinx.common
import ipctk
import numpy as np
import scipy.sparse as sp
from dolfinx import fem
from mpi4py import MPI
from mpi4py.util import dtlib
from petsc4py import PETSc

from diffsolids.contact.geometry.flat import (
    FlatRegions,
    flat_edge_mask,
    flat_primitive_regions,
    flat_vertex_mask,
)
from diffsolids.contact.geometry.obstacle import Obstacle
from diffsolids.contact.geometry.subdivision import (
    local_node_keys,
    match_rows,
    neighbour_filter,
    subdivide,
)
from diffsolids.errors import MeshError, ParameterError
from diffsolids.mesh import Domain
from diffsolids.parallel import collective_comm
from diffsolids.portability import ensure_ipctk_runs
from diffsolids.solvers.sparsity import sorted_unique

__all__ = ["CollisionSurface"]


def _vertex_blocks(mesh: dolfinx.mesh.Mesh, space: fem.FunctionSpace) -> np.ndarray:
    """Block (node) index in ``space`` of every local geometry node (-1 where none).

    Lagrange elements number the vertex dofs first, in the reference vertex order, exactly like
    the first nodes of the geometry dofmap.
    """
    gdofmap = mesh.geometry.dofmaps[0]
    nv = dolfinx.cpp.mesh.cell_num_vertices(mesh.topology.cell_type)
    blocks = np.full(mesh.geometry.x.shape[0], -1, dtype=np.int64)
    blocks[gdofmap[:, :nv]] = space.dofmap.list[:, :nv]
    return blocks


class _OwnedMap:
    """Which collision vertices a rank owns in some function space, and their blocks."""

    def __init__(
        self,
        comm: MPI.Comm,
        owned_cv: np.ndarray,
        blocks: np.ndarray,
        imap: dolfinx.common.IndexMap,
        nv: int,
    ) -> None:
        self.comm = comm
        self.cv = owned_cv
        self.blocks = blocks
        counts = np.array(collective_comm(comm).allgather(len(owned_cv)), dtype=np.int64)
        self.counts = counts
        self.displs = np.concatenate([[0], np.cumsum(counts)[:-1]])
        order = (
            np.concatenate(collective_comm(comm).allgather(owned_cv)) if comm.size > 1 else owned_cv
        )
        if len(order) != nv or len(np.unique(order)) != nv:
            raise MeshError("collision surface vertices are not owned exactly once across ranks")
        self.order = order
        global_blocks = imap.local_to_global(blocks.astype(np.int32)) if len(blocks) else []
        self.global_blocks = np.empty(nv, dtype=np.int64)
        self.global_blocks[order] = self.allgather(np.asarray(global_blocks, dtype=np.int64))
        self.weights: sp.csr_matrix | None = None

    def pull_back(self, G: np.ndarray) -> np.ndarray:
        """Per-collision-vertex values G (rows) pulled back to the rows this map selects.

        A shape map selects surface (mesh) vertices; the edge and face nodes of a subdivided
        P2/P3 boundary sit at fixed convex combinations X_nodes = P X_vertices of them, so a
        gradient with respect to the collision rest positions reaches the mesh vertices as
        G_vertices + P^T G_nodes. Use as ``out[m.blocks] += m.pull_back(G)[m.cv]``. Without
        nodes (P1, or the vertex-only surface) G itself is returned.

        Args:
            G: (num_vertices, width) values at the collision vertices (obstacle rows ignored).
        """
        if self.weights is None:
            return G
        G = np.asarray(G)
        nv = self.weights.shape[1]
        out = np.array(G[:nv], dtype=np.result_type(G.dtype, float))
        out += self.weights.T @ G[nv : nv + self.weights.shape[0]]
        return out

    def allgather(self, local: np.ndarray) -> np.ndarray:
        """Concatenate per-rank arrays (first axis = owned collision vertices) in rank order."""
        if self.comm.size == 1:
            return local
        width = int(np.prod(local.shape[1:])) if local.ndim > 1 else 1
        recv = np.empty((int(self.counts.sum()), *local.shape[1:]), dtype=local.dtype)
        mpi_type = dtlib.from_numpy_dtype(local.dtype)
        self.comm.Allgatherv(
            np.ascontiguousarray(local),
            [recv, self.counts * width, self.displs * width, mpi_type],
        )
        return recv

    def gather(self, per_block: np.ndarray, width: int) -> np.ndarray:
        """Full (num_vertices, width) array from a local blocked array (owned entries used)."""
        local = per_block.reshape(-1, width)[self.blocks]
        full = np.empty((len(self.order), width), dtype=per_block.dtype)
        full[self.order] = self.allgather(local)
        return full


class CollisionSurface:
    """The boundary of a Domain as an ipctk CollisionMesh, identical on all ranks.

    Args:
        domain: Mesh with body tags (cell tags).
        V: Displacement space (blocked Lagrange of any degree, block size = gdim).
        obstacles: Kinematic obstacles appended after the bodies.
        boundary: "nodes": P2/P3 boundary facets split at their edge and face nodes (the
            simulated boundary); "vertices": facets between the mesh vertices only. The same
            surface for P1.

    Attributes:
        dim: Geometric dimension.
        num_vertices: Number of collision vertices (surface vertices, then the edge/face nodes
            of a subdivided surface up to ``num_body_vertices``, then obstacles).
        rest_positions: (num_vertices, dim) rest coordinates.
        edges: (num_edges, 2) vertex indices (2D: the boundary facets or their segments).
        faces: (num_faces, 3) vertex indices (3D only; facets or their sub-triangles).
        body: Body id (cell tag) of every vertex (the smallest if several bodies meet there).
        body_ids: Sorted body ids of the domain.
        mesh: The ipctk CollisionMesh (area Jacobians initialised).

    Raises:
        MeshError: No volume mesh, curved geometry, no boundary, an unsupported node layout.
        ParameterError: An unknown ``boundary``.
    """

    def __init__(
        self,
        domain: Domain,
        V: fem.FunctionSpace,
        obstacles: Sequence[Obstacle] = (),
        boundary: str = "vertices",
    ) -> None:
        mesh = domain.mesh
        self.comm = mesh.comm
        self.dim = mesh.geometry.dim
        tdim = mesh.topology.dim
        if tdim != self.dim:
            raise MeshError(f"contact needs a volume mesh (tdim {tdim} != gdim {self.dim})")
        if mesh.geometry.cmaps[0].degree != 1:
            raise MeshError("contact needs an affine (degree 1) mesh geometry")
        if boundary not in ("nodes", "vertices"):
            raise ParameterError(f"boundary {boundary!r}: expected 'nodes' or 'vertices'")
        self.V = V
        self.bs = V.dofmap.index_map_bs
        self.degree = int(V.ufl_element().embedded_superdegree)
        self.boundary = boundary
        self.body_ids = list(domain.body_ids)
        self._domain = domain
        ensure_ipctk_runs(self.comm)  # a PortabilityError here instead of a SIGILL below
        self._subdivision = None
        self._neighbours = None
        self._facet_data(domain)
        self._add_obstacles(obstacles)
        if self._subdivision is not None:
            sub = self._subdivision
            self._neighbours = neighbour_filter(sub.facet_nodes, sub.parents, self.num_vertices)
        self._build_ipc_mesh()
        self._node_blocks = _vertex_blocks(mesh, V)
        self._geometry = self._owned_map(V, self._node_blocks)
        self.displacement = self._geometry
        if self._subdivision is not None:
            self.displacement = self._with_nodes(self._geometry)
        self._shape_map: _OwnedMap | None = None

    @property
    def subdivided(self) -> bool:
        """Whether the boundary is split at edge/face nodes (``boundary="nodes"``, degree >= 2)."""
        return self._subdivision is not None

    @property
    def num_surface_vertices(self) -> int:
        """Number of mesh vertices on the surface (collision vertices 0 ... this - 1)."""
        return len(self.vertex_input_ids)

    # -- construction --------------------------------------------------------------------------
    def _facet_data(self, domain: Domain) -> None:
        mesh = domain.mesh
        tdim = mesh.topology.dim
        mesh.topology.create_connectivity(tdim - 1, tdim)
        facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
        f2c = mesh.topology.connectivity(tdim - 1, tdim)
        cells = f2c.array[f2c.offsets[facets]]
        num_cells = mesh.topology.index_map(tdim).size_local
        num_cells += mesh.topology.index_map(tdim).num_ghosts
        cell_body = np.zeros(num_cells, dtype=np.int64)
        cell_body[domain.cell_tags.indices] = domain.cell_tags.values
        nodes = dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, facets)
        input_ids = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)
        local = (
            input_ids[nodes].reshape(len(facets), tdim),
            cell_body[cells],
            input_ids[nodes.ravel()],
            mesh.geometry.x[nodes.ravel(), : self.dim],
        )
        parts = collective_comm(self.comm).allgather(local)
        facet_ids = np.concatenate([p[0] for p in parts])
        facet_body = np.concatenate([p[1] for p in parts])
        node_ids = np.concatenate([p[2] for p in parts])
        node_x = np.concatenate([p[3] for p in parts])
        if len(facet_ids) == 0:
            raise MeshError("the mesh has no boundary facets")
        # vertices numbered by input index; facets sorted for a partition-independent order
        self.vertex_input_ids, first = np.unique(node_ids, return_index=True)
        self.num_vertices = len(self.vertex_input_ids)
        self.rest_positions = np.ascontiguousarray(node_x[first], dtype=float)
        prims = np.searchsorted(self.vertex_input_ids, facet_ids).astype(np.int32)
        order = np.lexsort(np.sort(prims, axis=1).T[::-1])
        prims, facet_body = prims[order], facet_body[order]
        if self.boundary == "nodes" and self.degree >= 2:
            # split every facet at its nodes (subdivision.py); nodes after the vertices
            sub, self._reference = subdivide(prims, self.num_vertices, self.V)
            self._subdivision = sub
            per_facet = len(sub.prims) // len(prims)
            prims = sub.prims
            facet_body = np.repeat(facet_body, per_facet)
            nodes_x = sub.weights @ self.rest_positions
            self.rest_positions = np.ascontiguousarray(
                np.concatenate([self.rest_positions, nodes_x]), dtype=float
            )
            self.num_vertices += len(sub.keys)
        self.primitive_body = facet_body
        body = np.full(self.num_vertices, np.iinfo(np.int64).max, dtype=np.int64)
        np.minimum.at(body, prims.ravel(), np.repeat(facet_body, prims.shape[1]))
        self.body = body
        self.body_index = np.searchsorted(self.body_ids, body)
        if self.dim == 2:
            self.edges = np.ascontiguousarray(prims)
            self.faces = np.zeros((0, 3), dtype=np.int32)
        else:
            self.faces = np.ascontiguousarray(prims)
            pairs = np.sort(prims[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
            self.edges = np.ascontiguousarray(np.unique(pairs, axis=0), dtype=np.int32)

    def _add_obstacles(self, obstacles: Sequence[Obstacle]) -> None:
        """Append the obstacles' vertices and primitives after the body surface."""
        nb = self.num_vertices
        self.num_body_vertices = nb
        self.obstacles = tuple(obstacles)
        first = max(self.body_ids, default=0) + 1
        self.obstacle_ids = list(range(first, first + len(self.obstacles)))
        self.obstacle_offsets = np.cumsum([nb] + [o.num_vertices for o in self.obstacles])
        self.flat = FlatRegions(self.dim, np.zeros(0), np.zeros(0))
        if not self.obstacles:
            return
        for o in self.obstacles:
            o.broadcast(self.comm)
            if o.dim != self.dim:
                raise MeshError(f"{o.label} is {o.dim}D, the model is {self.dim}D")
        offsets = self.obstacle_offsets
        rest = [self.rest_positions] + [o.rest_positions for o in self.obstacles]
        self.rest_positions = np.ascontiguousarray(np.concatenate(rest), dtype=float)
        self._obstacle_rest = self.rest_positions[nb:].copy()
        pairs = list(zip(self.obstacles, offsets[:-1], self.obstacle_ids, strict=True))
        self.flat = self._flat_regions(offsets)
        self.edges = np.ascontiguousarray(
            np.concatenate([self.edges] + [o.edges + k for o, k, _ in pairs]), dtype=np.int32
        )
        if self.dim == 3:
            self.faces = np.ascontiguousarray(
                np.concatenate([self.faces] + [o.faces + k for o, k, _ in pairs]), dtype=np.int32
            )
        prims = [len(o.edges) if self.dim == 2 else len(o.faces) for o in self.obstacles]
        tags = [np.full(m, b) for m, b in zip(prims, self.obstacle_ids, strict=True)]
        self.primitive_body = np.concatenate([self.primitive_body, *tags])
        self.body = np.concatenate(
            [self.body] + [np.full(o.num_vertices, b) for o, _, b in pairs]
        ).astype(np.int64)
        self.num_vertices = int(offsets[-1])
        self.body_ids = self.body_ids + self.obstacle_ids
        self.body_index = np.searchsorted(self.body_ids, self.body)

    def _flat_regions(self, offsets: np.ndarray) -> FlatRegions:
        """The flat edges and vertices of the fixed obstacles (global indices)."""
        edge_start = np.cumsum([len(self.edges)] + [len(o.edges) for o in self.obstacles])
        edges, vertices = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
        body_prims = len(self.faces) if self.dim == 3 else len(self.edges)
        regions = [np.full(body_prims, -1, dtype=np.int64)]
        next_region = 0
        for o, e0, v0 in zip(self.obstacles, edge_start[:-1], offsets[:-1], strict=True):
            prims = len(o.faces) if self.dim == 3 else len(o.edges)
            if o.moving:
                regions.append(np.full(prims, -1, dtype=np.int64))
                continue
            X = o.rest_positions
            fe = flat_edge_mask(X, o.faces, o.edges) if self.dim == 3 else None
            if fe is not None:
                edges.append(e0 + np.flatnonzero(fe))
            vertices.append(v0 + np.flatnonzero(flat_vertex_mask(X, o.edges, fe)))
            region = flat_primitive_regions(X, o.edges, o.faces, fe)
            regions.append(next_region + region)
            next_region += int(region.max(initial=-1)) + 1
        return FlatRegions(
            self.dim, np.concatenate(edges), np.concatenate(vertices), np.concatenate(regions)
        )

    def obstacle_displacement(self, t: float) -> np.ndarray:
        """(num_vertices, dim) displacements with the obstacles' at time ``t`` (zero body rows).

        Every rank evaluates the motions (bad output fails everywhere alike); rank 0's values
        are broadcast, so the collision mesh is the same on all ranks.
        """
        U = np.zeros((self.num_vertices, self.dim))
        for o, a, b in zip(
            self.obstacles, self.obstacle_offsets[:-1], self.obstacle_offsets[1:], strict=True
        ):
            if o.moving:
                U[a:b] = o.displacement(t)
        if self.comm.size > 1 and any(o.moving for o in self.obstacles):
            self.comm.Bcast(U, root=0)
        return U

    @property
    def has_moving_obstacles(self) -> bool:
        """Whether any obstacle moves."""
        return any(o.moving for o in self.obstacles)

    def _build_ipc_mesh(self) -> None:
        self.mesh = ipctk.CollisionMesh(
            np.asfortranarray(self.rest_positions),
            np.asfortranarray(self.edges),
            np.asfortranarray(self.faces),
        )
        self.mesh.init_area_jacobians()
        if self._neighbours is not None:
            self.mesh.can_collide = self._neighbours
        self._static = None

    def _owned_map(self, space: fem.FunctionSpace, node_blocks: np.ndarray) -> _OwnedMap:
        """Owned surface (mesh) vertices in ``space`` (geometry node -> block ``node_blocks``)."""
        imap = space.dofmap.index_map
        cv, nodes = self._owned_vertices(node_blocks, imap.size_local)
        omap = _OwnedMap(self.comm, cv, node_blocks[nodes], imap, self.num_surface_vertices)
        omap.nodes = nodes
        return omap

    def _surface_index(self) -> np.ndarray:
        """Surface-vertex index of every local geometry node (-1: not on the surface)."""
        input_ids = np.asarray(self._domain.mesh.geometry.input_global_indices, dtype=np.int64)
        pos = np.searchsorted(self.vertex_input_ids, input_ids)
        pos = np.minimum(pos, len(self.vertex_input_ids) - 1)
        return np.where(self.vertex_input_ids[pos] == input_ids, pos, -1)

    def _owned_vertices(
        self, node_blocks: np.ndarray, size_local: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """(surface-vertex indices, geometry nodes) of the surface vertices owned here."""
        pos = self._surface_index()
        owned = (pos >= 0) & (node_blocks >= 0) & (node_blocks < size_local)
        nodes = np.flatnonzero(owned)
        cv = pos[nodes]
        # a node can be listed once per rank only; several nodes never share a block
        cv, first = np.unique(cv, return_index=True)
        return cv, nodes[first]

    def _with_nodes(self, vertices: _OwnedMap) -> _OwnedMap:
        """The displacement map of the subdivided surface: owned vertices and edge/face nodes."""
        mesh = self._domain.mesh
        V = self.V
        imap = V.dofmap.index_map
        sub = self._subdivision
        keys, blocks, x = local_node_keys(mesh, V, self._surface_index(), self._reference)
        row = match_rows(sub.keys, keys)
        on = row >= 0
        if np.any(on):  # the dof coordinates are the lattice nodes' rest positions
            rest = self.rest_positions[self.num_surface_vertices + row[on]]
            scale = np.abs(self.rest_positions).max() + 1.0
            if np.abs(rest - x[on]).max() > 1e-9 * scale:
                raise MeshError(
                    "the boundary nodes of the displacement space are not on the facets"
                )
        owned = on & (blocks < imap.size_local)
        cv, first = np.unique(self.num_surface_vertices + row[owned], return_index=True)
        node_blocks = blocks[owned][first]
        omap = _OwnedMap(
            self.comm,
            np.concatenate([vertices.cv, cv]),
            np.concatenate([vertices.blocks, node_blocks]),
            imap,
            self.num_body_vertices,
        )
        return omap

    # -- data movement -------------------------------------------------------------------------
    def gather(self, values: np.ndarray) -> np.ndarray:
        """(num_vertices, dim) values at the collision vertices of a local V array (collective).

        Rows of obstacle vertices are zero (they have no dofs).

        Args:
            values: Local blocked array of V (``u.x.array`` or the owned part of a PETSc Vec).
        """
        body = self.displacement.gather(np.asarray(values), self.bs)[:, : self.dim]
        if self.num_vertices == self.num_body_vertices:
            return body
        full = np.zeros((self.num_vertices, self.dim), dtype=body.dtype)
        full[: self.num_body_vertices] = body
        return full

    def current_rest_positions(self) -> np.ndarray:
        """Rest coordinates of the collision vertices from the current mesh geometry."""
        x = self._domain.mesh.geometry.x[:, : self.dim]
        omap = self._geometry
        full = np.empty((self.num_vertices, self.dim))
        full[omap.order] = omap.allgather(np.ascontiguousarray(x[omap.nodes]))
        if self._subdivision is not None:  # nodes: fixed convex combinations of the vertices
            nv, nb = self.num_surface_vertices, self.num_body_vertices
            full[nv:nb] = self._subdivision.weights @ full[:nv]
        full[self.num_body_vertices :] = self.rest_positions[self.num_body_vertices :]
        return full

    def update_rest_positions(self) -> bool:
        """Re-read the rest positions from the mesh (shape changes); True if they changed."""
        X = self.current_rest_positions()
        if np.array_equal(X, self.rest_positions):
            return False
        self.rest_positions = X
        static = self._static
        self._build_ipc_mesh()
        if static is not None:
            self.set_static(static)
        return True

    @property
    def static(self) -> np.ndarray | None:
        """Boolean mask of static (fully prescribed) vertices, None before :meth:`set_static`."""
        return self._static

    def state_key(self) -> tuple:
        """What a collision set built on the surface depends on besides the positions.

        The ipctk mesh (replaced when the rest shape changes) and a copy of the static mask
        (which pairs may collide); compare with :meth:`has_state`.
        """
        return (self.mesh, None if self._static is None else self._static.copy())

    def has_state(self, key: tuple) -> bool:
        """Whether the surface is still in the state of :meth:`state_key` ``key``."""
        mesh, static = key
        if mesh is not self.mesh or (static is None) != (self._static is None):
            return False
        return static is None or np.array_equal(static, self._static)

    def set_static(self, static: np.ndarray) -> None:
        """Exclude pairs of primitives whose vertices are all static (fully prescribed)."""
        self._static = np.asarray(static, dtype=bool)
        ids = np.arange(self.num_vertices, dtype=np.int32)
        ids[self._static] = -1
        filt = ipctk.make_vertex_patches_filter(ids)
        if self._neighbours is not None:  # and neighbours on a subdivided surface
            filt = filt & self._neighbours
        self.mesh.can_collide = filt

    def owned_dof_indices(self) -> tuple[np.ndarray, np.ndarray]:
        """(collision dof indices, local V dof indices) of the dofs this rank owns."""
        d, bs = self.dim, self.bs
        omap = self.displacement
        cdofs = (omap.cv[:, None] * d + np.arange(d)).ravel()
        vdofs = (omap.blocks[:, None] * bs + np.arange(d)).ravel()
        return cdofs, vdofs

    def global_dofs(self) -> np.ndarray:
        """Global (PETSc) index of every collision dof (interleaved, length num_vertices*dim)."""
        blocks = np.full(self.num_vertices, -1, dtype=np.int64)  # obstacles: no dofs
        blocks[: self.num_body_vertices] = self.displacement.global_blocks
        return (blocks[:, None] * self.bs + np.arange(self.dim)).ravel()

    def add_to_owned(self, target: np.ndarray, g: np.ndarray) -> None:
        """target[owned V dofs] += g[collision dofs] (g interleaved, length num_vertices*dim)."""
        cdofs, vdofs = self.owned_dof_indices()
        target[vdofs] += g[cdofs]

    def to_local(self, g: np.ndarray, size: int) -> np.ndarray:
        """A local V-layout array of length ``size`` holding g on the owned collision dofs."""
        out = np.zeros(size)
        self.add_to_owned(out, g)
        return out

    def dof_mask(self, local_dofs: np.ndarray) -> np.ndarray:
        """Boolean (num_vertices*dim) mask of collision dofs listed in ``local_dofs`` (V local).

        Obstacle vertices are always in it (their motion is prescribed).
        """
        _, vdofs = self.owned_dof_indices()
        flags = np.isin(vdofs, local_dofs).reshape(-1, self.dim).astype(np.int8)
        full = np.ones((self.num_vertices, self.dim), dtype=np.int8)
        full[self.displacement.order] = self.displacement.allgather(flags)
        return full.ravel().astype(bool)

    # -- shape (P1 geometry space) -----------------------------------------------------------
    def shape_map(self, S: fem.FunctionSpace) -> _OwnedMap:
        """Owned surface vertices in the P1 vector space S of the rest coordinates.

        A gradient G with respect to the collision rest positions becomes the shape gradient
        ``out[m.blocks] += m.pull_back(G)[m.cv]`` (``pull_back`` adds P^T G_nodes: the edge and
        face nodes of a subdivided surface move with the vertices of their facet).
        """
        if self._shape_map is None or self._shape_map.space is not S:
            omap = self._owned_map(S, _vertex_blocks(self._domain.mesh, S))
            omap.space = S
            if self._subdivision is not None:
                omap.weights = self._subdivision.weights
            self._shape_map = omap
        return self._shape_map

    def add_matrix(
        self,
        A: PETSc.Mat,
        H: sp.spmatrix,
        free: np.ndarray,
        keep: np.ndarray | None = None,
    ) -> None:
        """Add every free row of a collision-dof matrix H (this rank's share) into A.

        Rows are added with global indices wherever they live: PETSc sends those owned by other
        ranks in the assembly (``ADD_VALUES``), and the owners' patterns must hold them
        (``diffsolids.contact.partition``). Collective (a flush assembly first: DOLFINx
        inserts the Dirichlet diagonal last).

        Args:
            A: PETSc matrix (not yet finally assembled); global rows and columns.
            H: (num_vertices*dim)^2 sparse matrix in collision dofs.
            free: Boolean mask of collision dofs that are not Dirichlet (rows and columns kept).
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
        if keep is not None:
            mask &= _contains(
                keep, _block_keys(Hr.row, Hr.col, rows_c, self.dim, self.num_vertices)
            )
        r, c, v = Hr.row[mask], Hr.col[mask], Hr.data[mask]
        csr = sp.csr_matrix((v, (r, c)), shape=(len(rows_c), H.shape[1]))
        csr.sum_duplicates()
        nonempty = np.flatnonzero(np.diff(csr.indptr))
        if len(nonempty) == 0:
            return
        csr = csr[nonempty]
        gdofs = self.global_dofs()
        A.setValuesIJV(
            csr.indptr.astype(PETSc.IntType),
            gdofs[csr.indices].astype(PETSc.IntType),
            csr.data,
            addv=PETSc.InsertMode.ADD_VALUES,
            rowmap=gdofs[rows_c[nonempty]].astype(PETSc.IntType),
        )

    def matrix_entries(
        self, block_keys: np.ndarray, free: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Global (rows, cols) of the owned free entries of the given vertex blocks."""
        nv, d = self.num_vertices, self.dim
        a, b = np.divmod(block_keys, nv)
        owned = np.zeros(nv, dtype=bool)
        owned[self.displacement.cv] = True
        sel = owned[a]
        a, b = a[sel], b[sel]
        rows = (a[:, None, None] * d + np.arange(d)[None, :, None]).repeat(d, axis=2).ravel()
        cols = (b[:, None, None] * d + np.arange(d)[None, None, :]).repeat(d, axis=1).ravel()
        m = free[rows] & free[cols]
        gdofs = self.global_dofs()
        return gdofs[rows[m]], gdofs[cols[m]]


def _block_keys(r: np.ndarray, c: np.ndarray, rows_c: np.ndarray, d: int, nv: int) -> np.ndarray:
    return (rows_c[r] // d).astype(np.int64) * nv + c // d


def _contains(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    if len(sorted_keys) == 0:
        return np.zeros(len(keys), dtype=bool)
    pos = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return sorted_keys[pos] == keys


def block_pattern(*matrices: sp.spmatrix, dim: int, num_vertices: int) -> np.ndarray:
    """Sorted unique vertex-block keys (i * num_vertices + j) of the nonzeros of the matrices."""
    keys = [np.zeros(0, dtype=np.int64)]
    for H in matrices:
        if H is None or H.nnz == 0:
            continue
        coo = H.tocoo()
        nz = coo.data != 0
        keys.append((coo.row[nz] // dim).astype(np.int64) * num_vertices + coo.col[nz] // dim)
    return sorted_unique(*keys)
