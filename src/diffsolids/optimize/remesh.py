"""Remeshing during shape optimisation (paper sec. 5, Algorithm 1, and sec. 10.1).

When the minimum scaled Jacobian of the rest mesh at the current shape drops below a threshold
(1e-3 in the paper) the interior is regenerated with gmsh while the boundary stays as it is:
every boundary vertex (its coordinates rounded to 2^-32 of the bounding box, so serial and
parallel runs mesh the same input) and boundary facet (and every interface between bodies) is
kept, so boundary-based objectives and facet tags carry over. 2D: the boundary loops of each
body become closed gmsh discrete curves bounding plane surfaces (holes included); 3D: the
boundary shells become discrete surfaces bounding volumes (cavities included), meshed with
tetrahedra. gmsh runs on rank 0; the new mesh is distributed over the communicator of the old
one.

The Model, Simulation, objective and controls live on one mesh, so a remesh rebuilds them with
a user factory ``build(domain) -> ReducedFunctional`` (see :class:`Remesher`). Controlled fields
are transferred by interpolation between the non-matching meshes, shape controls restart at
q = 0 on the new rest shape, all other control blocks are copied.

The same canonical (rank-independent) mesh arrays give a checkpoint format
(:func:`save_domain`, :func:`load_domain`) that restores the mesh with its vertex and cell
order, hence with the same parameter order.
"""

import json
import logging
import os
import time
import types
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import dolfinx
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from mpi4py import MPI

from diffsolids.controls import ControlError, ShapeControl
from diffsolids.controls.transfer import interpolate_nonmatching
from diffsolids.errors import MeshError
from diffsolids.mesh import Domain, gmsh_session, min_scaled_jacobian
from diffsolids.mesh.arrays import MeshArrays, domain_from_arrays
from diffsolids.parallel import collective_comm
from diffsolids.portability import ensure_ipctk_runs

if TYPE_CHECKING:
    from diffsolids.reduced_functional import ReducedFunctional

__all__ = [
    "MeshArrays",
    "RemeshRecord",
    "Remesher",
    "domain_from_arrays",
    "gather_mesh",
    "load_domain",
    "remesh_domain",
    "save_domain",
]

logger = logging.getLogger("diffsolids")

_CELL_NAMES = {2: "triangle", 3: "tetrahedron"}
_GMSH_CELL = {2: 2, 3: 4}  # gmsh element types: 3-node triangle, 4-node tetrahedron


# -- canonical mesh arrays -------------------------------------------------------------------
def _gather_rows(
    comm: MPI.Comm, keys: np.ndarray, rows: np.ndarray, root: int = 0
) -> np.ndarray | None:
    """Rows from all ranks on ``root``, ordered by their (global) keys."""
    keys = collective_comm(comm).gather(keys, root=root)
    rows = collective_comm(comm).gather(rows, root=root)
    if comm.rank != root:
        return None
    keys, rows = np.concatenate(keys), np.concatenate(rows)
    out = np.empty_like(rows)
    out[keys] = rows
    return out


def gather_mesh(domain: Domain, coordinates: np.ndarray | None = None) -> MeshArrays | None:
    """The mesh of a Domain as canonical arrays on rank 0 (None elsewhere; collective).

    Args:
        domain: The Domain.
        coordinates: Optional replacement of the local vertex coordinates
            (``mesh.geometry.x[:, :dim]`` layout), e.g. a reference shape.
    """
    mesh = domain.mesh
    comm = mesh.comm
    dim = mesh.geometry.dim
    tdim = mesh.topology.dim
    x = mesh.geometry.x[:, :dim] if coordinates is None else np.asarray(coordinates)[:, :dim]
    gmap = mesh.geometry.index_map()
    n_own = gmap.size_local
    inputs = mesh.geometry.input_global_indices
    points = _gather_rows(comm, inputs[:n_own], x[:n_own].copy())

    num_cells = mesh.topology.index_map(tdim).size_local
    cell_nodes = inputs[mesh.geometry.dofmaps[0][:num_cells]]
    values = np.zeros(num_cells + mesh.topology.index_map(tdim).num_ghosts, dtype=np.int32)
    values[domain.cell_tags.indices] = domain.cell_tags.values
    original = mesh.topology.original_cell_index[:num_cells].astype(np.int64)
    cells = _gather_rows(comm, original, cell_nodes.astype(np.int64))
    cell_values = _gather_rows(comm, original, values[:num_cells])

    ft = domain.facet_tags
    fnodes = dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, ft.indices.astype(np.int32))
    fverts = np.sort(inputs[fnodes].reshape(-1, dim), axis=1) if len(ft.indices) else None
    fverts = np.zeros((0, dim), np.int64) if fverts is None else fverts
    all_facets = collective_comm(comm).gather(fverts, root=0)
    all_values = collective_comm(comm).gather(ft.values.astype(np.int32), root=0)
    if comm.rank != 0:
        return None
    facets, idx = np.unique(np.concatenate(all_facets), axis=0, return_index=True)
    facet_values = np.concatenate(all_values)[idx]
    return MeshArrays(points, cells, cell_values, facets, facet_values, dict(domain.names))


def save_domain(
    domain: Domain, path: str | os.PathLike, coordinates: np.ndarray | None = None, **extra
) -> None:
    """Write a Domain with its tags and canonical order to a ``.npz`` file (collective).

    Args:
        domain: The Domain.
        path: Output file (written by rank 0).
        coordinates: Optional replacement of the local vertex coordinates (e.g. the
            reference shape X0 of a shape control instead of the displaced geometry).
        extra: Further scalars to store (read back by :func:`load_domain` as ``info``).
    """
    arrays = gather_mesh(domain, coordinates)
    if domain.comm.rank == 0:
        np.savez(
            Path(path),
            points=arrays.points,
            cells=arrays.cells,
            cell_values=arrays.cell_values,
            facets=arrays.facets,
            facet_values=arrays.facet_values,
            names=json.dumps(arrays.names),
            info=json.dumps(extra),
        )
    domain.comm.barrier()


def load_domain(path: str | os.PathLike, comm: MPI.Comm = MPI.COMM_WORLD) -> tuple[Domain, dict]:
    """Read a Domain written by :func:`save_domain` (collective).

    Returns:
        (domain, info) with ``info`` the extra values given to save_domain.
    """
    path = Path(path)
    arrays, info = None, None
    if comm.rank == 0:
        if not path.exists():
            raise_later = f"mesh checkpoint {path} does not exist"
        else:
            raise_later = None
            with np.load(path) as data:
                arrays = MeshArrays(
                    data["points"],
                    data["cells"],
                    data["cell_values"],
                    data["facets"],
                    data["facet_values"],
                    json.loads(str(data["names"])),
                )
                info = json.loads(str(data["info"]))
    else:
        raise_later = None
    raise_later = collective_comm(comm).bcast(raise_later, root=0)
    if raise_later:
        raise MeshError(raise_later)
    return domain_from_arrays(arrays, comm), collective_comm(comm).bcast(info, root=0)


# -- boundary extraction (rank 0, numpy) -------------------------------------------------------
def _simplex_facets(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All facets of all cells: (facet vertices, owning cell, opposite vertex)."""
    n = cells.shape[1]
    faces, owner, opposite = [], [], []
    for k in range(n):
        keep = [j for j in range(n) if j != k]
        faces.append(cells[:, keep])
        owner.append(np.arange(len(cells)))
        opposite.append(cells[:, k])
    return np.concatenate(faces), np.concatenate(owner), np.concatenate(opposite)


def _region_boundaries(arrays: MeshArrays) -> dict[int, np.ndarray]:
    """Per body: its boundary facets oriented outwards (exterior boundary and interfaces)."""
    pts, cells = arrays.points, arrays.cells
    out = {}
    for region in np.unique(arrays.cell_values):
        faces, _, opposite = _simplex_facets(cells[arrays.cell_values == region])
        key = np.sort(faces, axis=1)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        single = counts[inverse.ravel()] == 1
        faces, opposite = faces[single], opposite[single]
        base = pts[faces[:, 0]]
        frame = np.stack([pts[faces[:, j]] - base for j in range(1, faces.shape[1])], axis=1)
        inward = (pts[opposite] - base)[:, None, :]
        # 2D: region on the left of a->b; 3D: normal (b-a)x(c-a) pointing away from the cell
        side = np.linalg.det(np.concatenate([frame, inward], axis=1))
        flip = side < 0 if pts.shape[1] == 2 else side > 0
        faces[flip] = faces[flip][:, ::-1]
        out[int(region)] = faces
    return out


def _loops(edges: np.ndarray) -> list[np.ndarray]:
    """Closed vertex loops of oriented boundary edges (each vertex one outgoing edge)."""
    starts, counts = np.unique(edges[:, 0], return_counts=True)
    if np.any(counts > 1):
        v = starts[counts > 1][0]
        raise MeshError(f"cannot remesh: the boundary touches itself at vertex {v}")
    nxt = dict(zip(edges[:, 0].tolist(), edges[:, 1].tolist(), strict=True))
    loops, seen = [], set()
    for start in edges[:, 0].tolist():
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = nxt[v]
        loops.append(np.array(loop, dtype=np.int64))
    return loops


def _shells(triangles: np.ndarray, indices: bool = False) -> list[np.ndarray]:
    """Connected components (edge-connected) of a triangulated surface.

    Returns the triangles of every component, or their row indices with ``indices``.
    """
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    tri = np.tile(np.arange(len(triangles)), 3)
    _, edge_id = np.unique(np.sort(edges, axis=1), axis=0, return_inverse=True)
    edge_id = edge_id.ravel()
    incidence = sp.csr_matrix(
        (np.ones(len(tri)), (tri, edge_id)), shape=(len(triangles), edge_id.max() + 1)
    )
    num, labels = sp.csgraph.connected_components(incidence @ incidence.T, directed=False)
    rows = [np.flatnonzero(labels == k) for k in range(num)]
    return rows if indices else [triangles[r] for r in rows]


def _winding_number(points: np.ndarray, boundary: np.ndarray, p: np.ndarray) -> float:
    """Winding number of a closed loop (2D, vertex sequence) or shell (3D, triangles) at p."""
    if boundary.ndim == 1:
        a = points[boundary] - p
        b = np.roll(a, -1, axis=0)
        angles = np.arctan2(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], np.sum(a * b, axis=1))
        return float(angles.sum() / (2 * np.pi))
    a, b, c = (points[boundary[:, k]] - p for k in range(3))
    la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
    num = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc
    den += np.einsum("ij,ij->i", a, c) * lb + np.einsum("ij,ij->i", b, c) * la
    return float(2.0 * np.arctan2(num, den).sum() / (4 * np.pi))


def _enclosed_measure(points: np.ndarray, boundary: np.ndarray) -> float:
    """Signed area (2D loop) or volume (3D shell) enclosed by an outward-oriented boundary."""
    if boundary.ndim == 1:
        x, y = points[boundary, 0], points[boundary, 1]
        return float(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    a, b, c = (points[boundary[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _components(points: np.ndarray, boundaries: list[np.ndarray]) -> list[list[int]]:
    """Group closed loops/shells of one body into components: [outer, holes...] indices."""
    measures = [_enclosed_measure(points, b) for b in boundaries]
    outers = [k for k, m in enumerate(measures) if m > 0]
    groups = {k: [k] for k in outers}
    for k, m in enumerate(measures):
        if m > 0:
            continue
        probe = points[boundaries[k].ravel()[0]]
        inside = [o for o in outers if abs(_winding_number(points, boundaries[o], probe)) > 0.5]
        if not inside:
            raise MeshError("cannot remesh: a hole of a body lies outside all its outer boundaries")
        groups[min(inside, key=lambda o: measures[o])].append(k)
    return list(groups.values())


def _boundary_pieces(
    points: np.ndarray, boundaries: dict[int, np.ndarray]
) -> tuple[list[np.ndarray], list[tuple[int, list[list[list[int]]]]]]:
    """Boundary pieces (one gmsh entity each) and, per body, its components as piece lists.

    2D: every closed boundary loop of a body is a piece (interfaces appear in both bodies'
    loops). 3D: pieces are connected patches of facets with the same adjacent bodies, so an
    interface is one surface shared by the volumes on both sides (the 3D mesher needs that).

    Returns:
        (pieces, bodies): element arrays (2D: vertex loops; 3D: triangles) and, per body,
        (body, components), each component a list of shells: [[piece indices of the outer
        shell], [of a hole], ...].
    """
    pieces: list[np.ndarray] = []
    bodies: list[tuple[int, list[list[list[int]]]]] = []
    if points.shape[1] == 2:
        for body, faces in boundaries.items():
            loops = _loops(faces)
            first = len(pieces)
            pieces.extend(loops)
            comps = _components(points, loops)
            bodies.append((body, [[[first + k] for k in comp] for comp in comps]))
        return pieces, bodies
    regions = np.concatenate([np.full(len(f), b) for b, f in boundaries.items()])
    faces = np.concatenate(list(boundaries.values()))
    key = np.sort(faces, axis=1)
    _, unique_id, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    unique_id = unique_id.ravel()
    # adjacent bodies of every unique face: (min, max) of its one or two owners
    lo = np.full(len(counts), np.iinfo(np.int64).max)
    hi = np.full(len(counts), np.iinfo(np.int64).min)
    np.minimum.at(lo, unique_id, regions)
    np.maximum.at(hi, unique_id, regions)
    first_face = np.full(len(counts), -1)
    first_face[unique_id[::-1]] = np.arange(len(faces))[::-1]
    patch_of_unique = np.empty(len(counts), dtype=np.int64)
    for pair in np.unique(np.c_[lo, hi], axis=0):
        members = np.flatnonzero((lo == pair[0]) & (hi == pair[1]))
        for patch in _shells(faces[first_face[members]], indices=True):
            patch_of_unique[members[patch]] = len(pieces)
            pieces.append(faces[first_face[members[patch]]])
    offset = 0
    for body, body_faces in boundaries.items():
        ids = unique_id[offset : offset + len(body_faces)]
        offset += len(body_faces)
        shells = _shells(body_faces, indices=True)
        comps = _components(points, [body_faces[sh] for sh in shells])
        bodies.append(
            (
                body,
                [
                    [sorted(set(patch_of_unique[ids[shells[k]]].tolist())) for k in comp]
                    for comp in comps
                ],
            )
        )
    return pieces, bodies


# -- gmsh --------------------------------------------------------------------------------------
def _mean_edge_length(arrays: MeshArrays) -> float:
    c = arrays.cells
    pts = arrays.points
    n = c.shape[1]
    lengths = [
        np.linalg.norm(pts[c[:, i]] - pts[c[:, j]], axis=1) for i in range(n) for j in range(i)
    ]
    return float(np.mean(lengths))


# gmsh defaults of the remesher: quality optimisation; in 3D the HXT Delaunay mesher (fewer
# slivers than the default Delaunay on kept boundary triangulations; measured min scaled
# Jacobian 0.16 against 0.03 on a 16^3 box)
_GMSH_DEFAULTS = {2: {"Mesh.Optimize": 1}, 3: {"Mesh.Optimize": 1, "Mesh.Algorithm3D": 10}}


def _snapped(points: np.ndarray) -> np.ndarray:
    """Coordinates rounded to 2^-32 of the bounding box (a power of two: exact grid values).

    Serial and parallel runs give rest shapes that differ by round-off (parallel solves), and
    gmsh is sensitive to that; on the grid both feed gmsh the same boundary, so both produce
    the same mesh (unless a coordinate lies within round-off of a grid midpoint).
    """
    extent = float(np.ptp(points, axis=0).max()) if len(points) else 1.0
    quantum = 2.0 ** (np.ceil(np.log2(max(extent, 1e-300))) - 32)
    return np.round(points / quantum) * quantum


def _add_boundary_entities(
    gmsh: types.ModuleType, pts: np.ndarray, boundaries: dict[int, np.ndarray]
) -> list[tuple[int, int]]:
    """Add each body's kept boundary as discrete gmsh entities; return (entity, body) pairs."""
    dim = pts.shape[1]
    xyz = np.zeros((len(pts), 3))
    xyz[:, :dim] = pts
    added = np.zeros(len(pts), dtype=bool)
    pieces, bodies = _boundary_pieces(pts, boundaries)
    piece_tags = []
    for piece in pieces:
        ent = gmsh.model.addDiscreteEntity(dim - 1)
        elems = np.c_[piece, np.roll(piece, -1)] if dim == 2 else piece
        nodes = np.unique(elems)
        new = nodes[~added[nodes]]
        added[new] = True
        gmsh.model.mesh.addNodes(dim - 1, ent, new + 1, xyz[new].ravel())
        gmsh.model.mesh.addElementsByType(ent, dim - 1, [], (elems + 1).ravel())
        piece_tags.append(ent)
    entities = []
    for body, components in bodies:
        for component in components:
            tags = [[piece_tags[k] for k in shell] for shell in component]
            if dim == 2:
                loops = [gmsh.model.geo.addCurveLoop(t) for t in tags]
                entity = gmsh.model.geo.addPlaneSurface(loops)
            else:
                loops = [gmsh.model.geo.addSurfaceLoop(t) for t in tags]
                entity = gmsh.model.geo.addVolume(loops)
            entities.append((entity, body))
    gmsh.model.geo.synchronize()
    return entities


def _remesh_arrays(
    arrays: MeshArrays, mesh_size: float | None, gmsh_options: Mapping[str, float] | None
) -> MeshArrays:
    """Regenerate the interior of every body of a canonical mesh, keeping its boundaries."""
    arrays = replace(arrays, points=_snapped(arrays.points))
    pts = arrays.points
    dim = pts.shape[1]
    boundaries = _region_boundaries(arrays)
    _check_tagged_facets(arrays, boundaries)
    _check_boundary_free(pts, boundaries)
    with gmsh_session() as gmsh:
        entities = _add_boundary_entities(gmsh, pts, boundaries)
        size = _mean_edge_length(arrays) if mesh_size is None else float(mesh_size)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        for name, value in {**_GMSH_DEFAULTS[dim], **(gmsh_options or {})}.items():
            gmsh.option.setNumber(name, float(value))
        gmsh.option.setNumber("Mesh.Renumber", 0)  # boundary node tags = old index + 1
        gmsh.model.mesh.generate(dim)
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        cells, values = [], []
        for entity, body in entities:
            types, _, nodes = gmsh.model.mesh.getElements(dim, entity)
            if list(types) != [_GMSH_CELL[dim]]:
                raise MeshError(f"gmsh produced element types {list(types)} while remeshing")
            cells.append(nodes[0].reshape(-1, dim + 1).astype(np.int64))
            values.append(np.full(len(cells[-1]), body, dtype=np.int32))
    order = np.argsort(node_tags)
    node_tags = node_tags[order]
    new_points = coords.reshape(-1, 3)[order, :dim]
    renumber = lambda t: np.searchsorted(node_tags, t)  # noqa: E731
    cells = renumber(np.concatenate(cells))
    old_to_new = renumber(np.arange(len(pts)) + 1)
    result = MeshArrays(
        new_points,
        cells,
        np.concatenate(values),
        old_to_new[arrays.facets] if len(arrays.facets) else arrays.facets,
        arrays.facet_values,
        dict(arrays.names),
    )
    _check_boundary_kept(arrays, boundaries, result, old_to_new)
    return result


def _check_boundary_free(points: np.ndarray, boundaries: dict) -> None:
    """Refuse a boundary that intersects itself (gmsh does not return on such input)."""
    import ipctk

    ensure_ipctk_runs()

    facets = np.unique(np.sort(np.concatenate(list(boundaries.values())), axis=1), axis=0)
    used, local = np.unique(facets, return_inverse=True)
    local = local.reshape(facets.shape).astype(np.int32)
    x = np.asfortranarray(points[used], dtype=float)
    if points.shape[1] == 2:
        mesh = ipctk.CollisionMesh(x, np.asfortranarray(local), np.zeros((0, 3), np.int32))
    else:
        edges = np.asfortranarray(ipctk.edges(local), dtype=np.int32)
        mesh = ipctk.CollisionMesh(x, edges, np.asfortranarray(local))
    if ipctk.has_intersections(mesh, x, ipctk.LBVH()):
        raise MeshError(
            "cannot remesh: the boundary intersects itself (the shape folds over itself; "
            "refuse such shapes before remeshing)"
        )


def _check_tagged_facets(arrays: MeshArrays, boundaries: dict) -> None:
    if not len(arrays.facets):
        return
    kept = np.unique(np.sort(np.concatenate(list(boundaries.values())), axis=1), axis=0)
    tagged = np.sort(arrays.facets, axis=1)
    inside = ~_rows_in(tagged, kept)
    if inside.any():
        raise MeshError(
            f"cannot remesh: {int(inside.sum())} tagged facets lie inside a body (only facets "
            "on the boundary or on interfaces between bodies are kept)"
        )


def _rows_in(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Which rows of a occur in b (integer rows)."""
    both = np.concatenate([b, a])
    _, inverse = np.unique(both, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    return np.isin(inverse[len(b) :], inverse[: len(b)])


def _check_boundary_kept(
    old: MeshArrays,
    boundaries: dict[int, np.ndarray],
    new: MeshArrays,
    old_to_new: np.ndarray,
) -> None:
    """The new mesh's body boundaries are exactly the old ones, at the same positions."""
    old_faces = np.sort(old_to_new[np.concatenate(list(boundaries.values()))], axis=1)
    new_faces = np.sort(np.concatenate(list(_region_boundaries(new).values())), axis=1)
    same = len(np.unique(old_faces, axis=0)) == len(np.unique(new_faces, axis=0)) and np.all(
        _rows_in(new_faces, old_faces)
    )
    used = np.zeros(len(old.points), dtype=bool)
    used[np.concatenate(list(boundaries.values())).ravel()] = True
    moved = np.abs(new.points[old_to_new[used]] - old.points[used]).max()
    if not same or moved > 0.0:
        raise MeshError("gmsh changed the boundary while remeshing the interior")


def remesh_domain(
    domain: Domain,
    coordinates: np.ndarray | None = None,
    mesh_size: float | None = None,
    gmsh_options: Mapping[str, float] | None = None,
) -> Domain:
    """A new mesh of the same bodies with the same boundary vertices, facets and tags.

    Args:
        domain: The Domain to remesh.
        coordinates: Optional local vertex coordinates replacing the mesh geometry.
        mesh_size: Maximum element size of the interior (default: the current mean edge
            length); sizes grow from the boundary edge lengths inwards.
        gmsh_options: gmsh options overriding the defaults ({"Mesh.Optimize": 1} and, in 3D,
            {"Mesh.Algorithm3D": 10}, the HXT mesher), e.g. {"Mesh.OptimizeNetgen": 1}.

    Returns:
        A Domain on the same communicator (gmsh runs on rank 0).
    """
    comm = domain.comm
    arrays = gather_mesh(domain, coordinates)
    new, error = None, None
    if comm.rank == 0:
        try:
            new = _remesh_arrays(arrays, mesh_size, gmsh_options)
        except Exception as exc:  # re-raised on every rank below
            error = f"{type(exc).__name__}: {exc}"
    error = collective_comm(comm).bcast(error, root=0)
    if error:
        raise MeshError(f"remeshing failed: {error}")
    return domain_from_arrays(new, comm, domain.dim)


# -- the optimiser hook ------------------------------------------------------------------------
@dataclass
class RemeshRecord:
    """One remesh: qualities of the rest mesh before and after, sizes and time."""

    quality_before: float
    quality_after: float
    cells_before: int
    cells_after: int
    seconds: float


def _shape_controls(
    rf: "ReducedFunctional", q: np.ndarray
) -> list[tuple[ShapeControl, np.ndarray]]:
    blocks = rf.controls.split(q)
    return [
        (c, b)
        for c, b in zip(rf.controls.controls, blocks, strict=True)
        if isinstance(c, ShapeControl)
    ]


class Remesher:
    """Remeshing hook of the optimiser: ``needs_remesh(rf, q)`` and ``remesh(rf, q)``.

    Args:
        build: Factory ``build(domain) -> ReducedFunctional``. It must create the model,
            simulation, objective and controls on the given Domain (same bodies, facet tags
            and tag names as the original one; its geometry is the rest shape) and return the
            ReducedFunctional with the controls in the same order as before. Shape controls
            created there take the new geometry as reference (q = 0). The factory is called
            by :meth:`remesh` and :meth:`load_checkpoint`.
        threshold: Remesh when the minimum scaled Jacobian of the rest mesh at q drops below
            this (paper: 1e-3). If a remesh cannot lift the quality above it (the boundary
            itself is that poor), the next remesh waits until the quality halves again.
        mesh_size: Maximum element size of new meshes (default: the mean edge length before).
        transfer_fields: Names of further model coefficients to interpolate to the new mesh
            (controlled fields are always transferred).
        max_remeshes: Upper bound on the number of remeshes (None: unbounded).
        gmsh_options: gmsh options of the mesher (see :func:`remesh_domain`).

    Attributes:
        history: One RemeshRecord per remesh.

    Example:
        ``remesher = Remesher(build, threshold=1e-3)``; the optimiser calls
        ``remesher.needs_remesh(rf, q)`` after every accepted iterate and, when true,
        ``rf, q = remesher.remesh(rf, q)`` (and resets its quasi-Newton memory).
    """

    def __init__(
        self,
        build: Callable[[Domain], "ReducedFunctional"],
        threshold: float = 1e-3,
        mesh_size: float | None = None,
        transfer_fields: Sequence[str] = (),
        max_remeshes: int | None = None,
        gmsh_options: Mapping[str, float] | None = None,
    ) -> None:
        if not callable(build):
            raise TypeError("Remesher needs a factory build(domain) -> ReducedFunctional")
        if not threshold < 1.0:
            raise MeshError(f"remesh threshold {threshold} must be below 1 (the ideal quality)")
        self.build = build
        self.threshold = float(threshold)
        self.mesh_size = mesh_size
        self.transfer_fields = tuple(transfer_fields)
        self.max_remeshes = max_remeshes
        self.gmsh_options = dict(gmsh_options or {})
        self.history: list[RemeshRecord] = []
        self._trigger = self.threshold
        self._restored = 0

    @property
    def count(self) -> int:
        """Number of remeshes so far (including those before a restored checkpoint)."""
        return self._restored + len(self.history)

    def rest_coordinates(self, rf: "ReducedFunctional", q: npt.ArrayLike) -> np.ndarray:
        """Local vertex coordinates of the rest shape at q (collective)."""
        mesh = rf.model.domain.mesh
        x = mesh.geometry.x.copy()
        for control, block in _shape_controls(rf, np.asarray(q, dtype=float)):
            d = control.displacement(block)[control.input_index]
            x[:, : control.dim] = control.X0 + d
        return x

    def quality(self, rf: "ReducedFunctional", q: npt.ArrayLike) -> float:
        """Minimum scaled Jacobian of the rest mesh at q (collective)."""
        mesh = rf.model.domain.mesh
        return min_scaled_jacobian(mesh, rf.model.reference_signs, self.rest_coordinates(rf, q))

    def needs_remesh(self, rf: "ReducedFunctional", q: npt.ArrayLike) -> bool:
        """True when the rest mesh at q is below the quality threshold (collective)."""
        if self.max_remeshes is not None and self.count >= self.max_remeshes:
            return False
        return self.quality(rf, q) < self._trigger

    def remesh(
        self, rf: "ReducedFunctional", q: npt.ArrayLike
    ) -> tuple["ReducedFunctional", np.ndarray]:
        """Remesh the rest shape at q and rebuild the problem on it (collective).

        Returns:
            (new_rf, new_q): the factory's ReducedFunctional on the new mesh and parameters
            with shape blocks zero, field blocks interpolated and other blocks copied.
        """
        t0 = time.perf_counter()
        q = np.asarray(q, dtype=float)
        before = self.quality(rf, q)
        rf.controls.assign(q)  # geometry and fields of the current iterate
        old_domain = rf.model.domain
        domain = remesh_domain(old_domain, mesh_size=self.mesh_size, gmsh_options=self.gmsh_options)
        new_rf = self.build(domain)
        if new_rf.model.domain is not domain:
            raise MeshError("the remesh factory must build the problem on the domain it is given")
        new_q = self._transfer(rf, q, new_rf)
        after = min_scaled_jacobian(domain.mesh, new_rf.model.reference_signs)
        tdim = domain.mesh.topology.dim
        count = lambda d: d.mesh.topology.index_map(tdim).size_global  # noqa: E731
        record = RemeshRecord(before, after, count(old_domain), count(domain), 0.0)
        record.seconds = time.perf_counter() - t0
        self.history.append(record)
        self._trigger = self.threshold if after >= self.threshold else 0.5 * after
        logger.info(
            "remesh %d: min scaled Jacobian %.3e -> %.3e, %d -> %d cells (%.2f s)",
            self.count,
            before,
            after,
            record.cells_before,
            record.cells_after,
            record.seconds,
        )
        if after < self.threshold:
            logger.warning(
                "remeshing kept the boundary but the quality %.3e is still below %.3e",
                after,
                self.threshold,
            )
        return new_rf, new_q

    def _transfer(
        self, rf: "ReducedFunctional", q: npt.ArrayLike, new_rf: "ReducedFunctional"
    ) -> np.ndarray:
        old, new = rf.controls.controls, new_rf.controls.controls
        if [type(c) for c in old] != [type(c) for c in new]:
            raise MeshError(
                "the remesh factory returned different controls: "
                f"{[c.name for c in new]} instead of {[c.name for c in old]}"
            )
        for name in self.transfer_fields:
            interpolate_nonmatching(rf.model.coefficients[name], new_rf.model.coefficients[name])
        blocks = []
        for c_old, c_new, block in zip(old, new, rf.controls.split(q), strict=True):
            try:
                blocks.append(c_new.transfer(c_old, block))
            except ControlError as err:
                raise MeshError(str(err)) from None
        return np.concatenate(blocks)

    # -- checkpoints ---------------------------------------------------------------------------
    CHECKPOINT_FILE = "mesh.npz"

    def save_checkpoint(self, directory: str | os.PathLike, rf: "ReducedFunctional") -> None:
        """Write the reference mesh (q = 0 of the shape controls) of ``rf`` (collective).

        The optimiser calls this after a remesh; with its q this restores the state after any
        number of remeshes. The file is ``directory / "mesh.npz"`` (see :func:`save_domain`).
        """
        mesh = rf.model.domain.mesh
        x = mesh.geometry.x.copy()
        for control, _ in _shape_controls(rf, rf.controls.value()):
            x[:, : control.dim] = control.X0
        path = Path(directory) / self.CHECKPOINT_FILE
        save_domain(rf.model.domain, path, x, remeshes=self.count, trigger=self._trigger)

    def load_checkpoint(
        self, directory: str | os.PathLike, rf: "ReducedFunctional"
    ) -> "ReducedFunctional":
        """Read the mesh written by :meth:`save_checkpoint` and rebuild the problem on it.

        Args:
            directory: The directory given to save_checkpoint.
            rf: The functional of the original problem (gives the communicator).

        Returns:
            The factory's ReducedFunctional on the restored mesh (same parameter order).
        """
        comm = rf.model.domain.comm
        domain, info = load_domain(Path(directory) / self.CHECKPOINT_FILE, comm)
        self._trigger = float(info.get("trigger", self.threshold))
        self._restored = int(info.get("remeshes", 0)) - len(self.history)
        return self.build(domain)
