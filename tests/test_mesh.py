"""Meshes and their tags: built-in boxes, gmsh .geo (meshed at run time), .msh and meshio files."""

from pathlib import Path

import dolfinx
import meshio
import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import (
    Domain,
    create_box,
    create_rectangle,
    from_geo,
    gmsh_session,
    min_scaled_jacobian,
    read_mesh,
    signed_cell_volumes,
)

MESHES = Path(__file__).resolve().parents[1] / "meshes"


def _measure(dom: Domain, kind: str, tag: int | None = None) -> float:
    """Global area/volume of a body (kind "dx") or length/area of a facet tag (kind "ds")."""
    tags = dom.cell_tags if kind == "dx" else dom.facet_tags
    measure = ufl.Measure(kind, domain=dom.mesh, subdomain_data=tags)
    form = fem.form(fem.Constant(dom.mesh, 1.0) * (measure if tag is None else measure(tag)))
    return dom.comm.allreduce(fem.assemble_scalar(form), op=MPI.SUM)


def _check_measures(dom: Domain, expected: dict[tuple[str, int], float]) -> None:
    """``{(kind, tag): value}``: areas/volumes of bodies ("dx"), measures of facet tags ("ds")."""
    assert {key: _measure(dom, *key) for key in expected} == pytest.approx(expected)


def _num_tagged(dom: Domain, tag: int, facets: bool = True) -> int:
    """Global number of owned entities carrying a tag."""
    tags = dom.facet_tags if facets else dom.cell_tags
    imap = dom.mesh.topology.index_map(tags.dim)
    owned = tags.indices[tags.values == tag] < imap.size_local
    return dom.comm.allreduce(int(owned.sum()), op=MPI.SUM)


# -- built-in meshes ------------------------------------------------------------------------------
def test_rectangle_tags():
    dom = create_rectangle(
        MPI.COMM_WORLD,
        [[0, 0], [2, 1]],
        [4, 3],
        facets={1: lambda x: np.full(x.shape[1], True), 2: lambda x: np.isclose(x[0], 2)},
        bodies={7: lambda m: m[0] > 1.0},
        names={"boundary": 1, "right": 2, "stiff": 7},
    )
    assert dom.dim == 2
    assert dom.facet_ids == [1, 2]
    assert dom.body_ids == [1, 7]  # untagged cells are body 1
    # later markers win: the right edge is 2, the rest of the boundary 1
    assert _num_tagged(dom, 2) == 3
    assert _num_tagged(dom, 1) == 2 * 4 + 3
    _check_measures(dom, {("ds", 2): 1.0, ("ds", 1): 5.0, ("dx", 7): 1.0, ("dx", 1): 1.0})
    midpoints = dolfinx.mesh.compute_midpoints(dom.mesh, 2, dom.cells_of("stiff"))
    assert np.all(midpoints[:, 0] > 1.0)
    assert dom.facet_id("right") == 2
    lo, hi = dom.bounding_box()
    assert np.allclose(lo, [0, 0]) and np.allclose(hi, [2, 1])
    assert dom.characteristic_length() == pytest.approx(np.sqrt(5.0))


def test_box_tags():
    dom = create_box(
        MPI.COMM_WORLD,
        [[0, 0, 0], [1, 2, 1]],
        [2, 2, 2],
        facets={3: lambda x: np.isclose(x[2], 0), 4: lambda x: np.isclose(x[1], 2)},
        bodies={2: lambda m: m[1] < 1.0},
    )
    assert dom.dim == 3
    assert dom.facet_ids == [3, 4]
    assert dom.body_ids == [1, 2]
    assert _num_tagged(dom, 3) == 2 * 2 * 2  # two triangles per square
    _check_measures(dom, {("ds", 3): 2.0, ("ds", 4): 1.0, ("dx", 2): 1.0, ("dx", 1): 1.0})
    with pytest.raises(ds.TagError, match=r"unknown facet tag 5; the mesh has facet tags \[3, 4\]"):
        dom.facets_of(5)


def test_quality_of_a_structured_mesh():
    dom = create_rectangle(MPI.COMM_WORLD, [[0, 0], [1, 1]], [3, 3])
    volumes = signed_cell_volumes(dom.mesh)
    assert np.allclose(np.abs(volumes), 1 / 18)
    signs = np.sign(volumes)
    # right isosceles triangles: sin(45 deg) / sin(60 deg) at the acute corners
    assert min_scaled_jacobian(dom.mesh, signs) == pytest.approx(np.sqrt(2 / 3))
    # moving one vertex over its neighbour inverts cells: the measure turns negative
    x = dom.mesh.geometry.x.copy()
    inner = np.flatnonzero(np.isclose(x[:, 0], 1 / 3) & np.isclose(x[:, 1], 1 / 3))
    if len(inner):
        x[inner, 0] += 0.5
    has_inner = dom.comm.allreduce(len(inner), op=MPI.SUM)
    assert has_inner
    assert min_scaled_jacobian(dom.mesh, signs, x) < 0.0


# -- gmsh .geo meshed at run time ----------------------------------------------------------------
def _check_two_squares(dom: Domain) -> None:
    assert dom.dim == 2
    assert dom.body_ids == [1, 2]
    assert dom.facet_ids == [11, 12, 13]
    assert {"left_body": 1, "right_body": 2, "clamp": 11, "load": 12, "bottom": 13}.items() <= (
        dom.names.items()
    )
    expected = {
        ("dx", dom.body_id("left_body")): 1.0,
        ("dx", dom.body_id("right_body")): 1.0,
        ("ds", dom.facet_id("clamp")): 1.0,
        ("ds", dom.facet_id("load")): 1.0,
        ("ds", dom.facet_id("bottom")): 2.0,
    }
    _check_measures(dom, expected)
    mid = dolfinx.mesh.compute_midpoints(dom.mesh, 2, dom.cells_of("right_body"))
    assert np.all(mid[:, 0] > 1.0)
    fmid = dolfinx.mesh.compute_midpoints(dom.mesh, 1, dom.facets_of("clamp"))
    assert np.allclose(fmid[:, 0], 0.0)


def test_from_geo_2d():
    dom = from_geo(MESHES / "test_two_squares.geo", MPI.COMM_WORLD)
    _check_two_squares(dom)
    coarse = dom.comm.allreduce(dom.mesh.topology.index_map(2).size_local, op=MPI.SUM)
    finer = from_geo(MESHES / "test_two_squares.geo", MPI.COMM_WORLD, numbers={"h": 0.25})
    _check_two_squares(finer)
    fine = finer.comm.allreduce(finer.mesh.topology.index_map(2).size_local, op=MPI.SUM)
    assert fine > 3 * coarse  # the -setnumber override reached the geometry
    # the tags are usable by a model
    model = ds.Model(
        dom, {"left_body": ds.LinearElastic(E=1.0, nu=0.3), 2: ds.LinearElastic(E=2.0, nu=0.3)}
    )
    model.add_dirichlet("clamp", 0.0)
    model.add_traction("load", [0.0, -1e-3])


def _check_two_boxes(dom: Domain) -> None:
    assert dom.dim == 3
    assert dom.body_ids == [1, 2]
    assert dom.facet_ids == [5, 6]
    assert dom.body_id("cap") == 2 and dom.facet_id("roof") == 6
    _check_measures(dom, {("dx", 1): 1.0, ("dx", 2): 0.5, ("ds", 5): 1.0, ("ds", 6): 1.0})
    mid = dolfinx.mesh.compute_midpoints(dom.mesh, 3, dom.cells_of("cap"))
    assert np.all(mid[:, 2] > 1.0)


def test_from_geo_3d():
    _check_two_boxes(from_geo(MESHES / "test_two_boxes.geo", MPI.COMM_WORLD))


def test_missing_files_and_unsupported_order(tmp_path):
    with pytest.raises(ds.MeshError, match="does not exist"):
        from_geo(tmp_path / "nothing.geo")
    with pytest.raises(ds.MeshError, match="does not exist"):
        read_mesh(tmp_path / "nothing.msh")
    with pytest.raises(ds.MeshError, match="only affine"):
        from_geo(MESHES / "test_two_squares.geo", order=2)


# -- .msh files -----------------------------------------------------------------------------------
def _write_msh(geo: Path, dst: Path, dim: int) -> None:
    """Mesh a .geo with the gmsh API and save it as .msh (what a user would bring)."""
    if MPI.COMM_WORLD.rank == 0:
        with gmsh_session() as gmsh:
            gmsh.open(str(geo))
            gmsh.model.mesh.generate(dim)
            gmsh.write(str(dst))
    MPI.COMM_WORLD.barrier()


@pytest.mark.parametrize(
    ("geo", "dim", "check"),
    [("test_two_squares.geo", 2, _check_two_squares), ("test_two_boxes.geo", 3, _check_two_boxes)],
)
def test_read_msh(tmp_path, geo, dim, check):
    path = tmp_path / f"{Path(geo).stem}.msh"
    _write_msh(MESHES / geo, path, dim)
    check(read_mesh(path, MPI.COMM_WORLD))


# -- meshio formats -------------------------------------------------------------------------------
def _meshio_square() -> meshio.Mesh:
    """2x2 squares of [0, 2] x [0, 1] as 16 triangles; x > 1 is body 2; x = 0 edges tagged 4."""
    xs, ys = np.meshgrid(np.linspace(0, 2, 5), np.linspace(0, 1, 3), indexing="ij")
    points = np.stack([xs.ravel(), ys.ravel()], axis=1)
    index = np.arange(points.shape[0]).reshape(5, 3)
    a, b, c, d = index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]
    triangles = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)]).reshape(-1, 3)
    body = np.where(points[triangles].mean(axis=1)[:, 0] > 1.0, 2, 1)
    lines = np.stack([index[0, :-1], index[0, 1:]], axis=1)
    return meshio.Mesh(
        points,
        [("triangle", triangles), ("line", lines)],
        cell_data={"tags": [body.astype(np.int32), np.full(len(lines), 4, dtype=np.int32)]},
    )


def _meshio_cube() -> meshio.Mesh:
    """A DOLFINx unit cube (2^3 x 6 tets) exported: z > 1/2 is body 3; z = 0 faces tagged 8."""
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, 2, 2, 2)
    points = mesh.geometry.x
    tets = mesh.geometry.dofmaps[0]
    body = np.where(points[tets].mean(axis=1)[:, 2] > 0.5, 3, 1)
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    candidates = tets[:, faces].reshape(-1, 3)
    floor = candidates[np.all(np.isclose(points[candidates][:, :, 2], 0.0), axis=1)]
    return meshio.Mesh(
        points,
        [("tetra", tets), ("triangle", floor)],
        cell_data={"tags": [body.astype(np.int32), np.full(len(floor), 8, dtype=np.int32)]},
    )


# meshio's XDMF writer and reader need h5py, which diffsolids does not depend on: VTU and legacy
# VTK cover the meshio path of read_mesh.
def _write_and_read(path: Path, mesh: meshio.Mesh) -> Domain:
    """Writes ``mesh`` on rank 0 with meshio and reads it back with ``read_mesh`` on every rank."""
    if MPI.COMM_WORLD.rank == 0:
        meshio.write(path, mesh)
    MPI.COMM_WORLD.barrier()
    return read_mesh(path, MPI.COMM_WORLD)


# (mesh, dim, body ids, facet ids, body volumes, tagged facet measure)
_MESHIO_CASES = {
    "2d": (_meshio_square, 2, [1, 2], [4], (1.0, 1.0), 1.0),
    "3d": (_meshio_cube, 3, [1, 3], [8], (0.5, 0.5), 1.0),
}


@pytest.mark.parametrize("suffix", [".vtu", ".vtk"])
@pytest.mark.parametrize("case", sorted(_MESHIO_CASES))
def test_meshio_tags_and_measures(tmp_path, suffix, case):
    make, dim, bodies, facets, volumes, area = _MESHIO_CASES[case]
    dom = _write_and_read(tmp_path / f"mesh{suffix}", make())
    assert dom.dim == dim
    assert dom.body_ids == bodies and dom.facet_ids == facets
    expected = {("dx", body): volume for body, volume in zip(bodies, volumes, strict=True)}
    _check_measures(dom, {**expected, ("ds", facets[0]): area})
    if dim == 2:
        fmid = dolfinx.mesh.compute_midpoints(dom.mesh, 1, dom.facets_of(4))
        assert np.allclose(fmid[:, 0], 0.0)
        assert np.allclose(np.abs(signed_cell_volumes(dom.mesh)), 1 / 8)
    else:
        mid = dolfinx.mesh.compute_midpoints(dom.mesh, 3, dom.cells_of(3))
        assert np.all(mid[:, 2] > 0.5)


def test_meshio_without_volume_cells(tmp_path):
    path = tmp_path / "lines.vtu"
    if MPI.COMM_WORLD.rank == 0:
        meshio.write(path, meshio.Mesh(np.array([[0.0, 0, 0], [1, 0, 0]]), [("line", [[0, 1]])]))
    MPI.COMM_WORLD.barrier()
    with pytest.raises(ds.MeshError, match="no triangle/tetra cells found"):
        read_mesh(path, MPI.COMM_WORLD)


def test_a_broken_geo_file_is_named_with_gmsh_error(file_from_rank_0):
    """A syntax error used to surface as DOLFINx's "No 'physical groups' in gmsh mesh"."""
    path = file_from_rank_0("broken.geo", "Point(1) = {0, 0, 0;\nthis is not gmsh\n")
    with pytest.raises(ds.MeshError, match=r"broken\.geo.*syntax error"):
        from_geo(path)
    # a later mesh in the same process is unaffected
    dom = from_geo(MESHES / "test_two_squares.geo")
    assert dom.mesh.topology.index_map(2).size_global > 0
