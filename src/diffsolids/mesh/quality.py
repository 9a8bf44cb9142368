"""Cell orientation and quality measures of simplex meshes (vectorised over cells)."""

import dolfinx
import numpy as np
from mpi4py import MPI

from diffsolids.errors import InvertedElementError, MeshError
from diffsolids.parallel import collective_comm

__all__ = [
    "cell_vertex_coordinates",
    "check_orientation",
    "inverted_cells",
    "min_scaled_jacobian",
    "signed_cell_volumes",
]


def cell_vertex_coordinates(mesh: dolfinx.mesh.Mesh, x: np.ndarray | None = None) -> np.ndarray:
    """Vertex coordinates per local cell, shape (num_cells, d + 1, d).

    Args:
        mesh: An affine simplex mesh.
        x: Optional replacement of ``mesh.geometry.x`` (same layout), e.g. a trial shape.
    """
    d = mesh.geometry.dim
    x = mesh.geometry.x if x is None else x
    return x[mesh.geometry.dofmaps[0]][:, :, :d]


def signed_cell_volumes(mesh: dolfinx.mesh.Mesh, x: np.ndarray | None = None) -> np.ndarray:
    """Signed volume (area in 2D) of every local cell in its stored vertex order."""
    v = cell_vertex_coordinates(mesh, x)
    edges = v[:, 1:, :] - v[:, :1, :]
    d = v.shape[2]
    return np.linalg.det(edges) / (2.0 if d == 2 else 6.0)


def _facet_opposite_orientations(mesh: dolfinx.mesh.Mesh) -> tuple[np.ndarray, np.ndarray]:
    """For local interior facets, the orientation signs of their two opposite vertices.

    Returns:
        (signs, cells): both of shape (number of local interior facets, 2); the two cells of a
        facet lie on opposite sides of it where the signs differ.
    """
    tdim = mesh.topology.dim
    fdim = tdim - 1
    mesh.topology.create_connectivity(fdim, tdim)
    f2c = mesh.topology.connectivity(fdim, tdim)
    counts = np.diff(f2c.offsets)
    interior = np.flatnonzero(counts == 2).astype(np.int32)
    if interior.size == 0:
        return np.zeros((0, 2)), np.zeros((0, 2), dtype=np.int32)
    cells = f2c.array[f2c.offsets[interior][:, None] + np.arange(2)]
    fnodes = dolfinx.mesh.entities_to_geometry(mesh, fdim, interior)
    dofmap = mesh.geometry.dofmaps[0]
    x = mesh.geometry.x[:, : mesh.geometry.dim]
    signs = np.empty((interior.size, 2))
    base = x[fnodes]  # (nf, d, d)
    frame = base[:, 1:, :] - base[:, :1, :]
    for k in range(2):
        cnodes = dofmap[cells[:, k]]  # (nf, d + 1)
        on_facet = (cnodes[:, :, None] == fnodes[:, None, :]).any(axis=2)
        opposite = cnodes[~on_facet]
        rows = np.concatenate([frame, (x[opposite] - base[:, 0, :])[:, None, :]], axis=1)
        signs[:, k] = np.sign(np.linalg.det(rows))
    return signs, cells


def folded_cells(mesh: dolfinx.mesh.Mesh) -> np.ndarray:
    """Local cells folded over a neighbour: both cells of an interior facet on the same side.

    Independent of the vertex order of the cells (a cell ordered backwards covers the same
    region and is not folded).
    """
    signs, cells = _facet_opposite_orientations(mesh)
    return np.unique(cells[signs[:, 0] == signs[:, 1]])


def check_orientation(mesh: dolfinx.mesh.Mesh, rtol: float = 1e-10) -> np.ndarray:
    """Validate a rest mesh and return the orientation sign of every local cell.

    Raises:
        InvertedElementError: Degenerate cells, or neighbouring cells folded over each other
            (both on the same side of their shared facet).
    """
    vol = signed_cell_volumes(mesh)
    h = _mean_edge_length(mesh)
    degenerate = np.flatnonzero(np.abs(vol) <= rtol * h**mesh.geometry.dim)
    _raise_if_any(mesh, degenerate, "degenerate (zero-volume) cells")
    signs, _ = _facet_opposite_orientations(mesh)
    folded = np.flatnonzero(signs[:, 0] == signs[:, 1])
    n_folded = collective_comm(mesh.comm).allreduce(folded.size, op=MPI.SUM)
    if n_folded:
        raise InvertedElementError(
            f"inverted input mesh: {n_folded} interior facets "
            "have both neighbouring cells on the same side (folded or inverted elements)",
            cells=folded,
        )
    return np.sign(vol)


def inverted_cells(
    mesh: dolfinx.mesh.Mesh, reference_signs: np.ndarray, x: np.ndarray | None = None
) -> np.ndarray:
    """Local cells whose orientation flipped (or collapsed) relative to ``reference_signs``."""
    vol = signed_cell_volumes(mesh, x) * reference_signs
    return np.flatnonzero(vol <= 0.0)


def _raise_if_any(mesh: dolfinx.mesh.Mesh, cells: np.ndarray, what: str) -> None:
    total = collective_comm(mesh.comm).allreduce(cells.size, op=MPI.SUM)
    if total:
        shown = collective_comm(mesh.comm).allgather(cells[:10].tolist())
        raise InvertedElementError(f"{total} {what}; first local cells per rank: {shown}", cells)


def _mean_edge_length(mesh: dolfinx.mesh.Mesh) -> float:
    v = cell_vertex_coordinates(mesh)
    if v.shape[0] == 0:
        local = (0.0, 0)
    else:
        e = np.linalg.norm(v[:, 1:, :] - v[:, :1, :], axis=2)
        local = (float(e.sum()), e.size)
    total = collective_comm(mesh.comm).allreduce(np.array(local, dtype=float), op=MPI.SUM)
    if total[1] == 0:
        raise MeshError("the mesh has no cells")
    return total[0] / total[1]


def min_scaled_jacobian(
    mesh: dolfinx.mesh.Mesh, reference_signs: np.ndarray, x: np.ndarray | None = None
) -> float:
    """Global minimum scaled Jacobian (1 for equilateral simplices, <= 0 when inverted).

    Per corner: det(incident edges) / prod(edge lengths), normalised by its equilateral value.
    """
    v = cell_vertex_coordinates(mesh, x)
    d = v.shape[2]
    n = v.shape[0]
    worst = np.inf
    if n:
        ideal = np.sqrt(3.0) / 2.0 if d == 2 else 1.0 / np.sqrt(2.0)
        for corner in range(d + 1):
            others = [(corner + k) % (d + 1) for k in range(1, d + 1)]
            edges = v[:, others, :] - v[:, corner : corner + 1, :]
            det = np.linalg.det(edges)
            if corner % 2 == 1 and d == 3:  # an odd cyclic shift of 4 vertices flips sign
                det = -det
            lengths = np.prod(np.linalg.norm(edges, axis=2), axis=1)
            sj = reference_signs * det / lengths / ideal
            worst = min(worst, float(sj.min()))
    return collective_comm(mesh.comm).allreduce(worst, op=MPI.MIN)
