"""Meshes from gmsh ``.geo`` sources (meshed at run time), ``.msh`` files and meshio formats."""

import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

import dolfinx.io.gmsh
import numpy as np
from mpi4py import MPI

from diffsolids.errors import MeshError
from diffsolids.mesh.domain import Domain
from diffsolids.mesh.gmsh_session import gmsh_session
from diffsolids.parallel import collective_comm

__all__ = ["from_geo", "from_gmsh_model", "read_mesh"]


def from_gmsh_model(model, comm: MPI.Comm, dim: int, rank: int = 0) -> Domain:
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

    def mesh_geo(gmsh) -> int:
        return _mesh_geo(gmsh, path, dim, mesh_size, numbers)

    return _on_root(comm, mesh_geo)


def _on_root(comm: MPI.Comm, build) -> Domain:
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


def _mesh_geo(gmsh, path, dim, mesh_size, numbers) -> int:
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


def read_mesh(path: str | os.PathLike, comm: MPI.Comm = MPI.COMM_WORLD, dim: int | None = None):
    """Read a ``.msh`` (gmsh) or any meshio-readable mesh file into a Domain.

    Tags come from gmsh physical groups or from the first integer cell-data array of meshio.
    """
    path = Path(path)
    if not path.exists():
        raise MeshError(f"mesh file {path} does not exist")
    if path.suffix == ".geo":
        return from_geo(path, comm, dim)
    if path.suffix == ".msh":

        def open_msh(gmsh) -> int:
            gmsh.open(str(path))
            return dim or gmsh.model.getDimension()

        return _on_root(comm, open_msh)
    tmp = None
    if comm.rank == 0:
        tmp = tempfile.mkdtemp(prefix="diffsolids-mesh-")
        _meshio_to_msh(path, Path(tmp) / "mesh.msh", dim)
    tmp = collective_comm(comm).bcast(tmp)
    try:
        return read_mesh(Path(tmp) / "mesh.msh", comm, dim)
    finally:
        comm.barrier()
        if comm.rank == 0:
            os.remove(Path(tmp) / "mesh.msh")
            os.rmdir(tmp)


def _meshio_to_msh(src: Path, dst: Path, dim: int | None) -> None:
    import meshio

    m = meshio.read(src)
    kinds = {"triangle": 2, "tetra": 3, "line": 1}
    present = {b.type: b for b in m.cells if b.type in kinds}
    tdim = dim or max((kinds[k] for k in present if k != "line"), default=0)
    cell_type = {2: "triangle", 3: "tetra"}.get(tdim)
    if cell_type not in present:
        raise MeshError(f"{src}: no {cell_type or 'triangle/tetra'} cells found")
    facet_type = {2: "line", 3: "triangle"}[tdim]
    tag_key = next(
        (k for k, v in m.cell_data.items() if all(np.issubdtype(a.dtype, np.integer) for a in v)),
        None,
    )
    cells, phys = [], []
    for i, block in enumerate(m.cells):
        if block.type not in (cell_type, facet_type):
            continue
        tags = m.cell_data[tag_key][i] if tag_key else None
        if block.type == facet_type and tags is None:
            continue
        cells.append((block.type, block.data))
        phys.append(tags if tags is not None else np.ones(len(block.data), dtype=int))
    points = m.points[:, :tdim] if m.points.shape[1] > tdim else m.points
    points = np.hstack([points, np.zeros((len(points), 3 - points.shape[1]))])
    out = meshio.Mesh(
        points,
        cells,
        cell_data={"gmsh:physical": phys, "gmsh:geometrical": phys},
    )
    meshio.write(dst, out, file_format="gmsh22", binary=False)
