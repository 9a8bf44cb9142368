"""Scene assembly: several meshes combined into one Domain, each a body (cell tag)."""

from collections.abc import Callable, Mapping, Sequence

import basix.ufl
import dolfinx
import numpy as np
import numpy.typing as npt
import ufl
from mpi4py import MPI

from diffsolids.errors import MeshError
from diffsolids.mesh.domain import Domain, tag_facets
from diffsolids.mesh.gmsh_session import gmsh_session

__all__ = ["combine_meshes", "simplex_ball", "simplex_box"]


def simplex_box(corners: npt.ArrayLike, n: Sequence[int]) -> dolfinx.mesh.Mesh:
    """A serial (COMM_SELF) triangulated rectangle or tetrahedral box, for :func:`combine_meshes`.

    Args:
        corners: ``[[x0, y0(, z0)], [x1, y1(, z1)]]``.
        n: Cells per direction.
    """
    corners = [np.asarray(c, dtype=float) for c in corners]
    if len(corners[0]) == 2:
        return dolfinx.mesh.create_rectangle(
            MPI.COMM_SELF, corners, list(n), dolfinx.mesh.CellType.triangle
        )
    return dolfinx.mesh.create_box(
        MPI.COMM_SELF, corners, list(n), dolfinx.mesh.CellType.tetrahedron
    )


def combine_meshes(
    comm: MPI.Comm,
    meshes: Sequence[dolfinx.mesh.Mesh | Domain],
    bodies: Sequence[int] | None = None,
    names: Mapping[str, int] | None = None,
    facets: Mapping[int, Callable[[np.ndarray], np.ndarray]] | None = None,
) -> Domain:
    """One Domain whose bodies are the given meshes (vertices are not merged).

    Args:
        comm: Communicator of the result (it is partitioned over ``comm``).
        meshes: Serial meshes or Domains (e.g. :func:`simplex_box`, or
            ``read_mesh(path, MPI.COMM_SELF, scale=..., translation=...)``) of the same cell type
            and dimension, already placed; they must not overlap. Their own tags are dropped.
        bodies: Body id of each mesh (default 1, 2, ...).
        names: Optional tag names.
        facets: Optional ``{tag: marker(x)}`` boundary markers (as in ``create_box``).

    Raises:
        MeshError: Meshes of different cell types or dimensions, or distributed inputs.
    """
    if not meshes:
        raise MeshError("combine_meshes needs at least one mesh")
    bodies = list(bodies) if bodies is not None else list(range(1, len(meshes) + 1))
    if len(bodies) != len(meshes):
        raise MeshError(f"{len(bodies)} body ids for {len(meshes)} meshes")
    meshes = [m.mesh if isinstance(m, Domain) else m for m in meshes]
    cell_type = meshes[0].topology.cell_type
    gdim = meshes[0].geometry.dim
    xs, cells, tags = [], [], []
    offset = 0
    for mesh, body in zip(meshes, bodies, strict=True):
        if mesh.comm.size != 1:
            raise MeshError("combine_meshes takes serial meshes (created on COMM_SELF)")
        if mesh.topology.cell_type != cell_type or mesh.geometry.dim != gdim:
            raise MeshError("all meshes must have the same cell type and dimension")
        if mesh.geometry.cmaps[0].degree != 1:
            raise MeshError("combine_meshes supports affine geometry only")
        x = mesh.geometry.x[:, :gdim]
        c = mesh.geometry.dofmaps[0].astype(np.int64)
        xs.append(x)
        cells.append(c + offset)
        tags.append(np.full(len(c), body, dtype=np.int32))
        offset += len(x)
    element = ufl.Mesh(
        basix.ufl.element("Lagrange", cell_type.name, 1, shape=(gdim,), dtype=np.float64)
    )
    if comm.rank == 0:
        all_x, all_cells = np.concatenate(xs), np.concatenate(cells)
    else:
        all_x = np.zeros((0, gdim))
        all_cells = np.zeros((0, cells[0].shape[1]), dtype=np.int64)
    mesh = dolfinx.mesh.create_mesh(comm, all_cells, element, all_x)
    tdim = mesh.topology.dim
    imap = mesh.topology.index_map(tdim)
    num_cells = imap.size_local + imap.num_ghosts
    body_of = np.concatenate(tags)
    local = np.arange(num_cells, dtype=np.int32)
    cell_tags = dolfinx.mesh.meshtags(
        mesh, tdim, local, body_of[mesh.topology.original_cell_index[:num_cells]]
    )
    mesh.topology.create_connectivity(tdim - 1, tdim)
    facet_tags = tag_facets(mesh, facets) if facets else None
    return Domain.from_mesh(mesh, cell_tags, facet_tags, names)


def simplex_ball(center: Sequence[float], radius: float, size: float) -> dolfinx.mesh.Mesh:
    """A serial disk (2D) or ball (3D) meshed by gmsh, for :func:`combine_meshes`.

    Args:
        center: Center point (its length sets the dimension).
        radius: Radius.
        size: Target edge length.
    """
    from dolfinx.io import gmsh as gmsh_io

    center = np.asarray(center, dtype=float)
    dim = len(center)
    with gmsh_session() as gmsh:
        if dim == 2:
            tag = gmsh.model.occ.addDisk(center[0], center[1], 0.0, radius, radius)
        else:
            tag = gmsh.model.occ.addSphere(*center, radius)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(dim, [tag], 1)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", size)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMin", size / 2)
        gmsh.model.mesh.generate(dim)
        data = gmsh_io.model_to_mesh(gmsh.model, MPI.COMM_SELF, 0, gdim=dim)
    return data.mesh
