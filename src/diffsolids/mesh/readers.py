"""Meshes from gmsh ``.geo`` sources (meshed at run time), ``.msh`` files and meshio formats."""

import os
import types
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import dolfinx.io.gmsh
import numpy as np
from mpi4py import MPI

from diffsolids.errors import InvertedElementError, MeshError
from diffsolids.mesh.arrays import MeshArrays, boundary_facets, domain_from_arrays
from diffsolids.mesh.domain import Domain
from diffsolids.mesh.gmsh_session import gmsh_session
from diffsolids.parallel import collective_comm

if TYPE_CHECKING:
    import gmsh
    import meshio

__all__ = [
    "check_cells",
    "check_points_and_cells",
    "from_geo",
    "from_gmsh_model",
    "read_mesh",
    "transform_domain",
]


def from_gmsh_model(
    model: "type[gmsh.model] | None", comm: MPI.Comm, dim: int, rank: int = 0
) -> Domain:
    """Convert the current gmsh model (on ``rank``) to a Domain with physical-group tags."""
    data = dolfinx.io.gmsh.model_to_mesh(model, comm, rank, gdim=dim)
    names = {}
    if data.physical_groups:
        names = {name: int(tag) for name, (_, tag) in data.physical_groups.items()}
    return Domain.from_mesh(data.mesh, data.cell_tags, data.facet_tags, names)


def from_geo(
    path: str | os.PathLike,
    comm: MPI.Comm = MPI.COMM_WORLD,
    dim: int | None = None,
    mesh_size: float | None = None,
    numbers: Mapping[str, float] | None = None,
    order: int = 1,
) -> Domain:
    """Mesh a gmsh ``.geo`` file at run time and return it as a Domain.

    Args:
        path: The ``.geo`` file (physical groups become cell and facet tags).
        comm: Communicator of the resulting mesh; gmsh runs on rank 0 only.
        dim: Dimension to mesh (default: highest dimension in the geometry).
        mesh_size: Optional characteristic length (``Mesh.CharacteristicLengthMax``).
        numbers: ``DefineConstant``/``Define`` values passed as ``-setnumber`` overrides.
        order: Geometry order (only 1 is supported by our shape derivatives).
    """
    path = Path(path)
    if not path.exists():
        raise MeshError(f"gmsh geometry file {path} does not exist")
    if order != 1:
        raise MeshError("only affine (order 1) geometry is supported")

    def mesh_geo(gmsh: types.ModuleType) -> int:
        return _mesh_geo(gmsh, path, dim, mesh_size, numbers)

    return _on_root(comm, mesh_geo)


def _on_root(comm: MPI.Comm, build: Callable[[types.ModuleType], int]) -> Domain:
    """Run ``build(gmsh)`` (returns the dimension) in a gmsh session on rank 0; distribute.

    A failure on rank 0 is raised on every rank (the others would wait in the broadcast).
    """
    if comm.rank != 0:
        gdim = collective_comm(comm).bcast(None)
        if isinstance(gdim, str):
            raise MeshError(gdim)
        return from_gmsh_model(None, comm, gdim)
    with gmsh_session() as gmsh:
        try:
            gdim = build(gmsh)
        except Exception as error:
            collective_comm(comm).bcast(f"gmsh failed on rank 0: {error}")
            raise
        collective_comm(comm).bcast(gdim)
        return from_gmsh_model(gmsh.model, comm, gdim)


def _mesh_geo(
    gmsh: types.ModuleType,
    path: Path,
    dim: int | None,
    mesh_size: float | None,
    numbers: Mapping[str, float] | None,
) -> int:
    for name, value in (numbers or {}).items():
        gmsh.parser.setNumber(name, [float(value)])
    # gmsh.open would clear the parser variables just set; merge keeps them (DefineConstant then
    # leaves them alone, like -setnumber on the command line).
    gmsh.merge(str(path))
    if not gmsh.model.getEntities():
        raise MeshError(f"gmsh found no geometry in {path}: {gmsh.logger.getLastError()}")
    if mesh_size is not None:
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", float(mesh_size))
    dim = dim or gmsh.model.getDimension()
    gmsh.model.mesh.generate(dim)
    if not gmsh.model.getPhysicalGroups(dim):
        tags = [t for _, t in gmsh.model.getEntities(dim)]
        gmsh.model.addPhysicalGroup(dim, tags, 1)
    return dim


def read_mesh(
    path: str | os.PathLike,
    comm: MPI.Comm = MPI.COMM_WORLD,
    dim: int | None = None,
    *,
    scale: float | Sequence[float] = 1.0,
    rotation: float | Sequence[float] | None = None,
    translation: Sequence[float] | None = None,
) -> Domain:
    """Read a ``.msh`` (gmsh 2.2/4.1, ASCII or binary) or any meshio-readable mesh into a Domain.

    Tags: gmsh physical groups when the file has them, else the first integer cell-data array
    of meshio whose values on the volume cells are all positive. A file without either (most
    meshes of the paper's data, ``.obj`` files) is read untagged: every element block of the
    top dimension is one body (cell tags 1, 2, ... in file order) and every boundary facet gets
    tag 1. A file that tags its cells but no facets gets tag 1 on every boundary facet too.
    Points not used by any cell are dropped.

    The geometry is then transformed as PolyFEM's ``transformation`` does: scaled, rotated
    about the origin, translated (x' = R (s * x) + t).

    Args:
        path: The mesh file (``.geo`` sources are meshed with :func:`from_geo`).
        comm: Communicator of the distributed mesh.
        dim: Cell dimension to read (default: the highest present).
        scale: Scale factor, or one per axis (> 0).
        rotation: Rotation in degrees: an angle in 2D, Euler angles about x, y, z (applied in
            that order) in 3D.
        translation: Translation vector.

    Raises:
        MeshError: A missing or unreadable file, no volume cells, a surface mesh in 3D space,
            non-finite coordinates, cells referring to missing vertices, inverted or degenerate
            cells (:func:`check_cells`: the file, how many, the first
            indices), or a bad transformation.
    """
    path = Path(path)
    if not path.exists():
        raise MeshError(f"mesh file {path} does not exist")
    if path.suffix == ".geo":
        domain = from_geo(path, comm, dim)
    elif path.suffix == ".msh" and _on_rank0(comm, lambda: _has_physical_groups(path, dim)):

        def open_msh(gmsh: types.ModuleType) -> int:
            gmsh.open(str(path))
            return dim or gmsh.model.getDimension()

        domain = _on_root(comm, open_msh)
    else:
        domain = _read_with_meshio(path, comm, dim)
    check_cells(domain, path)
    transform_domain(domain, scale, rotation, translation)
    return domain


# a cell is degenerate when |volume| <= _DEGENERATE_RTOL h^d (h the mean edge length)
_DEGENERATE_RTOL = 1e-10
_SHOWN_CELLS = 5


def check_cells(domain: Domain, source: str | os.PathLike = "the mesh") -> None:
    """Refuse folded and degenerate cells of a mesh just read (collective).

    A cell is degenerate when its volume (area in 2D) is at most 1e-10 h^d, h the mean edge
    length, and folded (inverted) when it lies on the same side of a shared facet as its
    neighbour there (``mesh.quality.folded_cells``; both cells of such a
    facet are named). The vertex order of the cells does not matter: a cell ordered backwards
    covers the same region. Serial and distributed meshes alike: each owned cell is counted
    once and named by its index in the file's order of cells of its type (0-based; DOLFINx's
    ``original_cell_index``).

    Args:
        domain: The Domain read from ``source``.
        source: The file, for the message.

    Raises:
        MeshError: Non-finite vertex coordinates (the file, how many, the first input indices).
        InvertedElementError: A :class:`~diffsolids.errors.MeshError` naming the file, the
            number of bad cells of each kind and the first few indices (``cells``: this
            rank's bad local cells).
    """
    from diffsolids.mesh.quality import _mean_edge_length, folded_cells, signed_cell_volumes

    _check_coordinates(domain, source)
    mesh = domain.mesh
    tdim = mesh.topology.dim
    owned = mesh.topology.index_map(tdim).size_local
    vol = signed_cell_volumes(mesh)[:owned]
    tiny = np.abs(vol) <= _DEGENERATE_RTOL * _mean_edge_length(mesh) ** mesh.geometry.dim
    folded = np.zeros(owned, dtype=bool)
    local = folded_cells(mesh)
    folded[local[local < owned]] = True
    inverted = folded & ~tiny
    counts = collective_comm(mesh.comm).allreduce(
        np.array([np.sum(inverted), np.sum(tiny), owned]), op=MPI.SUM
    )
    n_inverted, degenerate, total = (int(c) for c in counts)
    if not (n_inverted or degenerate):
        return
    index = np.asarray(mesh.topology.original_cell_index[:owned], dtype=np.int64)
    problems = []
    for what, bad, n in (
        ("inverted (folded over a neighbour)", inverted, n_inverted),
        ("degenerate (zero volume)", tiny, degenerate),
    ):
        if n:
            local = np.sort(index[bad])[:_SHOWN_CELLS].tolist()
            parts = collective_comm(mesh.comm).allgather(local)
            first = sorted(i for part in parts for i in part)[:_SHOWN_CELLS]
            more = ", ..." if n > len(first) else ""
            problems.append(f"{n} {what}: cells {', '.join(map(str, first))}{more}")
    kind = {2: "triangle", 3: "tetrahedron"}.get(tdim, "")
    raise InvertedElementError(
        f"{source}: {'; '.join(problems)} of {total} {kind} cells (0-based indices in the "
        "file's order)",
        cells=np.flatnonzero(inverted | tiny),
    )


def check_points_and_cells(
    source: str | os.PathLike, points: np.ndarray, cells: Sequence[tuple[str, np.ndarray]]
) -> None:
    """Refuse non-finite coordinates and cells that refer to vertices the file does not have.

    Args:
        source: The file, for the message.
        points: Vertex coordinates (num_points x gdim).
        cells: (cell type, connectivity array) per block, 0-based vertex indices.

    Raises:
        MeshError: Naming the file, the first bad vertices (0-based, with their coordinates) or
            the first bad cell (its block, index and the vertex index it uses).
    """
    bad = np.flatnonzero(~np.all(np.isfinite(points), axis=1))
    if bad.size:
        shown = "; ".join(f"vertex {i} {points[i].tolist()}" for i in bad[:_SHOWN_CELLS])
        raise MeshError(
            f"{source}: {bad.size} vertices have non-finite coordinates ({shown}; 0-based)"
        )
    for kind, conn in cells:
        conn = np.asarray(conn)
        wrong = (conn < 0) | (conn >= len(points))
        if np.any(wrong):
            cell, corner = np.argwhere(wrong)[0]
            raise MeshError(
                f"{source}: {kind} cell {cell} refers to vertex {conn[cell, corner]} (0-based), "
                f"but the file has {len(points)} vertices (0..{len(points) - 1}); "
                f"{int(np.any(wrong, axis=1).sum())} {kind} cells are affected"
            )


def _check_coordinates(domain: Domain, source: str | os.PathLike) -> None:
    """Refuse non-finite vertex coordinates of a distributed mesh (collective)."""
    geometry = domain.mesh.geometry
    owned = geometry.index_map().size_local
    bad = ~np.all(np.isfinite(geometry.x[:owned]), axis=1)
    local = np.sort(np.asarray(geometry.input_global_indices[:owned])[bad])[:_SHOWN_CELLS]
    shown = sorted(
        i for part in collective_comm(domain.comm).allgather(local.tolist()) for i in part
    )
    count = collective_comm(domain.comm).allreduce(int(bad.sum()), op=MPI.SUM)
    if count:
        more = ", ..." if count > _SHOWN_CELLS else ""
        raise MeshError(
            f"{source}: {count} vertices have non-finite coordinates (input indices "
            f"{', '.join(map(str, shown[:_SHOWN_CELLS]))}{more}; 0-based, in the file's order "
            "of nodes)"
        )


def _on_rank0[T](comm: MPI.Comm, task: Callable[[], T], share: bool = True) -> T | None:
    """``task()`` on rank 0; its MeshError on every rank, its result on every rank if shared."""
    value, problem = None, None
    if comm.rank == 0:
        try:
            value = task()
        except MeshError as error:
            problem = str(error)
    problem = collective_comm(comm).bcast(problem)
    if problem is not None:
        raise MeshError(problem)
    return collective_comm(comm).bcast(value) if share else value


def _read_with_meshio(path: Path, comm: MPI.Comm, dim: int | None) -> Domain:
    return domain_from_arrays(_on_rank0(comm, lambda: _meshio_arrays(path, dim), False), comm)


def transform_domain(
    domain: Domain,
    scale: float | Sequence[float] = 1.0,
    rotation: float | Sequence[float] | None = None,
    translation: Sequence[float] | None = None,
) -> None:
    """Scale, rotate (degrees, about the origin) and translate a Domain's geometry in place.

    Args:
        domain: The Domain (before any Model is made on it).
        scale: Scale factor, or one per axis (> 0).
        rotation: An angle in 2D; Euler angles about x, y, z (applied in that order) in 3D.
        translation: Translation vector.

    Raises:
        MeshError: A non-positive or non-finite scale, or arguments of the wrong length.
    """
    d = domain.dim
    s = np.broadcast_to(np.asarray(scale, dtype=float), (d,)) if np.ndim(scale) == 0 else None
    if s is None:
        s = np.asarray(scale, dtype=float)
        if s.shape != (d,):
            raise MeshError(f"scale {scale} needs 1 or {d} values")
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise MeshError(f"scale {scale} must be finite and positive")
    R = _rotation_matrix(d, rotation)
    t = np.zeros(d) if translation is None else np.asarray(translation, dtype=float)
    if t.shape != (d,) or not np.all(np.isfinite(t)):
        raise MeshError(f"translation {translation} needs {d} finite values")
    x = domain.mesh.geometry.x
    x[:, :d] = (x[:, :d] * s) @ R.T + t


def _rotation_matrix(d: int, rotation: float | Sequence[float] | None) -> np.ndarray:
    if rotation is None:
        return np.eye(d)
    angles = np.radians(np.atleast_1d(np.asarray(rotation, dtype=float)))
    if angles.shape != ((1,) if d == 2 else (3,)) or not np.all(np.isfinite(angles)):
        raise MeshError(f"rotation {rotation} needs {1 if d == 2 else 3} finite angles (degrees)")
    if d == 2:
        c, s = np.cos(angles[0]), np.sin(angles[0])
        return np.array([[c, -s], [s, c]])
    out = np.eye(3)
    for axis, angle in enumerate(angles):  # x first, then y, then z: R = Rz Ry Rx
        i, j = [k for k in range(3) if k != axis]
        c, s = np.cos(angle), np.sin(angle)
        step = np.eye(3)
        step[i, i], step[i, j], step[j, i], step[j, j] = c, -s, s, c
        out = step @ out
    return out


_KINDS = {"line": 1, "triangle": 2, "tetra": 3}


def _read_meshio(src: Path) -> "meshio.Mesh":
    import meshio

    try:
        return meshio.read(src)
    except (Exception, SystemExit) as error:  # meshio raises ReadError, ..., or exits
        raise MeshError(f"{src}: cannot read the file ({type(error).__name__}: {error})") from None


def _has_physical_groups(path: Path, dim: int | None) -> bool:
    """Whether a gmsh file tags its volume cells with physical groups."""
    m = _read_meshio(path)
    tdim = dim or max((_KINDS[b.type] for b in m.cells if b.type in _KINDS), default=0)
    return any(
        b.type in _KINDS and _KINDS[b.type] == tdim and np.all(tags > 0)
        for b, tags in zip(m.cells, m.cell_data.get("gmsh:physical", []), strict=False)
    )


def _meshio_arrays(src: Path, dim: int | None) -> MeshArrays:
    m = _read_meshio(src)
    check_points_and_cells(src, m.points, [(b.type, b.data) for b in m.cells])
    present = {b.type for b in m.cells if b.type in _KINDS}
    tdim = dim or max((_KINDS[k] for k in present if k != "line"), default=0)
    cell_type = {2: "triangle", 3: "tetra"}.get(tdim)
    if cell_type not in present:
        raise MeshError(f"{src}: no {cell_type or 'triangle/tetra'} cells found")
    facet_type = {2: "line", 3: "triangle"}[tdim]
    volume = [i for i, b in enumerate(m.cells) if b.type == cell_type]
    tag_key = next(
        (
            k
            for k, v in m.cell_data.items()
            if all(np.issubdtype(a.dtype, np.integer) for a in v)
            and all(np.all(v[i] > 0) for i in volume)
        ),
        None,
    )
    cells = [m.cells[i].data for i in volume]
    phys = [
        m.cell_data[tag_key][i] if tag_key else np.full(len(cells[k]), k + 1)
        for k, i in enumerate(volume)
    ]
    facet_blocks = [
        i
        for i, b in enumerate(m.cells)
        if tag_key and b.type == facet_type and np.all(m.cell_data[tag_key][i] > 0)
    ]
    facets = [m.cells[i].data for i in facet_blocks]
    facet_phys = [m.cell_data[tag_key][i] for i in facet_blocks]
    if not facets:  # no facet tags in the file: every boundary facet gets tag 1
        facets = [boundary_facets(np.concatenate(cells))]
        facet_phys = [np.ones(len(facets[0]), dtype=np.int32)]
    points = _planar_points(src, m.points, tdim)
    all_cells = np.concatenate(cells)
    used = np.unique(all_cells)
    renumber = np.full(len(points), -1)
    renumber[used] = np.arange(len(used))
    return MeshArrays(
        points[used],
        renumber[all_cells],
        np.concatenate(phys).astype(np.int32),
        renumber[np.concatenate(facets)],
        np.concatenate(facet_phys).astype(np.int32),
    )


def _planar_points(src: Path, points: np.ndarray, tdim: int) -> np.ndarray:
    """The first tdim coordinates; a 2D mesh must lie in a plane z = const."""
    if points.shape[1] > tdim:
        extra = points[:, tdim:]
        if np.ptp(extra, axis=0).max() > 1e-12 * max(np.ptp(points, axis=0).max(), 1.0):
            raise MeshError(
                f"{src}: {tdim}D cells in {points.shape[1]}D space are a surface, not a volume "
                "mesh (contact obstacles given as surfaces are not supported yet)"
            )
    return points[:, :tdim]
