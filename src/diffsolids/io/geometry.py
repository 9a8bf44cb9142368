"""Deformed geometry of a model's mesh for figures and checks, gathered on every rank.

The displacement at the mesh nodes, the boundary edges of a 2D mesh (at rest or deformed), its
deformed triangles with cell values, and the silhouette edges of a 3D mesh's boundary: arrays
ready for ``matplotlib.collections.LineCollection`` / ``PolyCollection``. Every function is
collective over the mesh communicator and returns the same array on every rank (except
:func:`nodal_displacement`, which is local).
"""

from collections.abc import Sequence
from typing import TYPE_CHECKING

import dolfinx.mesh
import numpy as np
from dolfinx import fem

from diffsolids.parallel import collective_comm

if TYPE_CHECKING:
    from diffsolids.model import Model

__all__ = ["boundary_edges", "deformed_triangles", "nodal_displacement", "silhouette_edges"]


def nodal_displacement(model: "Model", u: np.ndarray) -> np.ndarray:
    """Displacement at the local geometry nodes, shape (num nodes, dim).

    Args:
        model: The Model (its displacement space and mesh).
        u: Local displacement array of ``model.V`` (ghosts included); interpolated into P1 for
            higher degrees.
    """
    mesh = model.domain.mesh
    d = model.dim
    uf = fem.Function(model.V)
    uf.x.array[:] = u
    uf.x.scatter_forward()
    if model.degree != 1:
        P1 = fem.functionspace(mesh, ("Lagrange", 1, (d,)))
        u1 = fem.Function(P1)
        u1.interpolate(uf)
        uf = u1
    node_of_dof = np.empty(len(mesh.geometry.x), dtype=np.int64)
    nv = mesh.geometry.dofmaps[0].shape[1]
    node_of_dof[mesh.geometry.dofmaps[0].ravel()] = uf.function_space.dofmap.list[:, :nv].ravel()
    return uf.x.array.reshape(-1, d)[node_of_dof]


def boundary_edges(model: "Model", u: np.ndarray | None = None) -> np.ndarray:
    """Boundary edges of a 2D model, at rest or deformed by ``u``, shape (n, 2, 2).

    Args:
        model: A 2D Model.
        u: Local displacement array (None: the rest shape).
    """
    mesh = model.domain.mesh
    fdim = mesh.topology.dim - 1
    mesh.topology.create_connectivity(fdim, fdim + 1)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    nodes = dolfinx.mesh.entities_to_geometry(mesh, fdim, facets)
    x = mesh.geometry.x[:, :2].copy()
    if u is not None:
        x += nodal_displacement(model, u)
    return np.concatenate(collective_comm(mesh.comm).allgather(x[nodes]))


def deformed_triangles(
    model: "Model", u: np.ndarray | None = None, values: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Triangles (n, 3, 2) of the owned cells of a 2D model, with their cell values.

    Args:
        model: A 2D Model.
        u: Local displacement array (None: the rest shape).
        values: Optional values of the owned cells (local cell order), gathered alike.

    Returns:
        (triangles, values or None), in the same order on every rank.
    """
    mesh = model.domain.mesh
    owned = mesh.topology.index_map(mesh.topology.dim).size_local
    x = mesh.geometry.x[:, :2].copy()
    if u is not None:
        x += nodal_displacement(model, u)
    tris = x[mesh.geometry.dofmaps[0][:owned, :3]]
    comm = collective_comm(mesh.comm)
    tris = np.concatenate(collective_comm(comm).allgather(tris))
    if values is None:
        return tris, None
    return tris, np.concatenate(collective_comm(comm).allgather(np.asarray(values)))


def silhouette_edges(model: "Model", axes: Sequence[int] = (1, 2)) -> list[np.ndarray]:
    """Silhouette edges of a 3D model's rest boundary seen along each of the given axes.

    An edge of the boundary belongs to the silhouette seen along axis k when the outward
    normals of its two boundary triangles point to opposite sides of k (one faces the viewer,
    the other away).

    Args:
        model: A 3D Model.
        axes: Viewing axes.

    Returns:
        One (n, 2, 3) array of edge end points per axis.
    """
    mesh = model.domain.mesh
    mesh.topology.create_connectivity(2, 3)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    nodes = dolfinx.mesh.entities_to_geometry(mesh, 2, facets)
    f2c = mesh.topology.connectivity(2, 3)
    cells = f2c.array[f2c.offsets[facets]]
    corner = mesh.geometry.dofmaps[0][cells]
    x = mesh.geometry.x
    tri = x[nodes]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centroid = x[corner].mean(axis=1)  # inside the cell: the normal points away from it
    normal *= -np.sign(np.sum(normal * (centroid - tri[:, 0]), axis=1))[:, None]
    ids = mesh.geometry.input_global_indices[nodes]
    parts = collective_comm(mesh.comm).allgather((ids, tri, normal))
    ids, tri, normal = (np.concatenate([p[k] for p in parts]) for k in range(3))
    _, first = np.unique(np.sort(ids, axis=1), axis=0, return_index=True)  # once per facet
    tri_ids, tri, normal = ids[first], tri[first], normal[first]
    # edges (sorted global vertex ids) of every triangle with the triangle they belong to
    edges, owner, ends = [], [], []
    for i, j in ((0, 1), (1, 2), (2, 0)):
        edges.append(np.sort(tri_ids[:, [i, j]], axis=1))
        owner.append(np.arange(len(tri_ids)))
        ends.append(tri[:, [i, j]])
    edges, owner, ends = np.concatenate(edges), np.concatenate(owner), np.concatenate(ends)
    key = np.lexsort(edges.T[::-1])
    edges, owner, ends = edges[key], owner[key], ends[key]
    pair = np.flatnonzero(np.all(edges[1:] == edges[:-1], axis=1))
    unit = normal / np.linalg.norm(normal, axis=1)[:, None]
    out = []
    for k in axes:
        side = np.where(np.abs(unit[:, k]) < 1e-6, 0.0, np.sign(unit[:, k]))
        flip = side[owner[pair]] != side[owner[pair + 1]]
        out.append(ends[pair[flip]])
    return out
