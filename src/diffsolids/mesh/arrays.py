"""Domains straight from point and cell arrays (canonical order, tags optional).

The arrays are given on rank 0 and distributed over the communicator; the vertex input order is
the row order of ``points`` and the original cell order the row order of ``cells``, so canonical
parameter orders (controls, checkpoints) are reproduced exactly on any number of ranks.
"""

from collections.abc import Mapping
from dataclasses import dataclass, field

import basix.ufl
import dolfinx
import numpy as np
import numpy.typing as npt
import ufl
from dolfinx.io.utils import distribute_entity_data
from mpi4py import MPI

from diffsolids.errors import MeshError
from diffsolids.mesh.domain import Domain
from diffsolids.parallel import collective_comm

__all__ = ["MeshArrays", "boundary_facets", "create_domain", "domain_from_arrays"]

_CELL_NAMES = {2: "triangle", 3: "tetrahedron"}
_LOCAL_FACETS = {  # facets of a simplex by its dimension, as local vertex indices
    2: np.array([[0, 1], [1, 2], [2, 0]]),
    3: np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]),
}


@dataclass
class MeshArrays:
    """A whole mesh in canonical order (vertex input order, original cell order).

    Attributes:
        points: Vertex coordinates (num_vertices, dim).
        cells: Vertex indices of every cell (num_cells, dim + 1).
        cell_values: Body tag of every cell.
        facets: Vertex indices of the tagged facets (num_tagged, dim).
        facet_values: Their tags.
        names: Tag names of the Domain.
    """

    points: np.ndarray
    cells: np.ndarray
    cell_values: np.ndarray
    facets: np.ndarray
    facet_values: np.ndarray
    names: dict[str, int] = field(default_factory=dict)


def boundary_facets(cells: np.ndarray) -> np.ndarray:
    """The facets of a simplex mesh that belong to exactly one cell, in first-seen order.

    Args:
        cells: (num_cells, dim + 1) vertex indices of triangles or tetrahedra.
    """
    cells = np.asarray(cells)
    local = _LOCAL_FACETS[cells.shape[1] - 1]
    all_facets = cells[:, local].reshape(-1, local.shape[1])
    _, first, counts = np.unique(
        np.sort(all_facets, axis=1), axis=0, return_index=True, return_counts=True
    )
    return all_facets[np.sort(first[counts == 1])]


def create_domain(
    points: np.ndarray,
    cells: np.ndarray,
    comm: MPI.Comm = MPI.COMM_WORLD,
    cell_tags: np.ndarray | None = None,
    facets: np.ndarray | None = None,
    facet_tags: np.ndarray | None = None,
    names: Mapping[str, int] | None = None,
) -> Domain:
    """A Domain from point and cell arrays given on rank 0 (collective; other ranks' ignored).

    Args:
        points: (num_vertices, dim) coordinates, dim 2 (triangles) or 3 (tetrahedra).
        cells: (num_cells, dim + 1) vertex indices.
        comm: Communicator of the distributed mesh.
        cell_tags: Body tag (> 0) of every cell; default 1 for all.
        facets: (num_tagged, dim) vertex indices of tagged facets; default every boundary facet.
        facet_tags: Their tags (> 0); default 1 for all.
        names: Optional tag names, e.g. ``{"ball": 1, "ground": 2}``.

    Raises:
        MeshError: Arrays of inconsistent shapes, out-of-range indices, non-finite points or
            non-positive tags (on every rank).
    """
    arrays, problem = None, None
    if comm.rank == 0:
        try:
            arrays = _checked_arrays(points, cells, cell_tags, facets, facet_tags, names)
        except MeshError as error:
            problem = str(error)
    problem = collective_comm(comm).bcast(problem)
    if problem is not None:
        raise MeshError(problem)
    return domain_from_arrays(arrays, comm)


def _checked_arrays(
    points: npt.ArrayLike,
    cells: npt.ArrayLike,
    cell_tags: npt.ArrayLike | None,
    facets: npt.ArrayLike | None,
    facet_tags: npt.ArrayLike | None,
    names: Mapping[str, int] | None,
) -> MeshArrays:
    points = np.asarray(points, dtype=float)
    cells = np.asarray(cells, dtype=np.int64)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise MeshError(f"points must have shape (n, 2) or (n, 3), not {points.shape}")
    dim = points.shape[1]
    if cells.ndim != 2 or cells.shape[1] != dim + 1:
        raise MeshError(f"{dim}D cells must have shape (m, {dim + 1}), not {cells.shape}")
    if not np.all(np.isfinite(points)):
        raise MeshError("points has non-finite coordinates")
    if cells.size and (cells.min() < 0 or cells.max() >= len(points)):
        raise MeshError(f"cells index vertices outside 0..{len(points) - 1}")
    cell_tags = np.ones(len(cells), np.int32) if cell_tags is None else np.asarray(cell_tags)
    if facets is None:
        facets = boundary_facets(cells)
    facets = np.asarray(facets, dtype=np.int64).reshape(-1, dim)
    facet_tags = np.ones(len(facets), np.int32) if facet_tags is None else np.asarray(facet_tags)
    for what, tags, n in (
        ("cell_tags", cell_tags, len(cells)),
        ("facet_tags", facet_tags, len(facets)),
    ):
        if tags.shape != (n,) or not np.issubdtype(tags.dtype, np.integer) or np.any(tags <= 0):
            raise MeshError(f"{what} must be {n} positive integers")
    return MeshArrays(points, cells, cell_tags, facets, facet_tags, dict(names or {}))


def domain_from_arrays(arrays: MeshArrays | None, comm: MPI.Comm, dim: int | None = None) -> Domain:
    """Create a distributed Domain from canonical arrays given on rank 0 (collective).

    The vertex input order is the row order of ``points`` and the original cell order the
    row order of ``cells``, so canonical parameter orders are reproduced exactly.
    """
    dim = collective_comm(comm).bcast(arrays.points.shape[1] if comm.rank == 0 else dim, root=0)
    names = collective_comm(comm).bcast(arrays.names if comm.rank == 0 else None, root=0)
    element = basix.ufl.element("Lagrange", _CELL_NAMES[dim], 1, shape=(dim,))
    if comm.rank == 0:
        x = np.ascontiguousarray(arrays.points, dtype=float)
        cells = np.ascontiguousarray(arrays.cells, dtype=np.int64)
        cell_values = arrays.cell_values.astype(np.int32)
        facets = np.ascontiguousarray(arrays.facets, dtype=np.int64).reshape(-1, dim)
        facet_values = arrays.facet_values.astype(np.int32)
    else:
        x = np.zeros((0, dim))
        cells = np.zeros((0, dim + 1), np.int64)
        cell_values = np.zeros(0, np.int32)
        facets = np.zeros((0, dim), np.int64)
        facet_values = np.zeros(0, np.int32)
    mesh = dolfinx.mesh.create_mesh(comm, cells, ufl.Mesh(element), x)
    tags = []
    for edim, entities, values in ((dim, cells, cell_values), (dim - 1, facets, facet_values)):
        mesh.topology.create_connectivity(edim, dim)
        local, local_values = distribute_entity_data(mesh, edim, entities, values)
        adj = dolfinx.graph.adjacencylist(local)
        tags.append(
            dolfinx.mesh.meshtags_from_entities(
                mesh, edim, adj, local_values.astype(np.int32, copy=False)
            )
        )
    return Domain.from_mesh(mesh, tags[0], tags[1], names)
