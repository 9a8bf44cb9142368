"""Reading other people's meshes: the paper's files (no physical groups), transforms, bad files."""

import os
from pathlib import Path

import meshio
import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import create_domain, read_mesh, transform_domain

COMM = MPI.COMM_WORLD
DATA = Path(
    os.environ.get("DIFFSOLIDS_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)
DIFFIPC = DATA / "diffipc"

# file, format, dimension, cells
PAPER_MESHES = [
    ("fig14_puzzle_piece/puzzle.msh", "gmsh 2.2 ASCII", 2, 424),
    ("fig14_puzzle_piece/wave.msh", "gmsh 2.2 ASCII", 2, 66),
    ("fig20_kangaroo/kangaroo-coarse.msh", "gmsh 2.2 binary", 2, 276),
    ("fig20_kangaroo/square.obj", "Wavefront OBJ, 2D vertices", 2, 2),
    ("fig1_bunnies/flat-pool.msh", "gmsh 4.1 ASCII", 3, 486),
    ("fig1_bunnies/stanford-bunny.obj_.msh", "gmsh 2.2 binary", 3, 3538),
]


def _paper_file(name: str) -> Path:
    path = DIFFIPC / name
    if not path.exists():
        pytest.skip(f"the paper's data is not at {DIFFIPC} (set DIFFSOLIDS_DATA)")
    return path


def _paper_mesh(name: str, **placement):
    """A mesh of the paper's data on one process, scaled and translated as its scene places it."""
    return read_mesh(_paper_file(name), MPI.COMM_SELF, **placement)


def _integrate(domain, integrand, measure="dx", tag=None) -> float:
    if measure == "dx":
        dm = ufl.dx(domain=domain.mesh)
    else:
        dm = ufl.ds(domain=domain.mesh, subdomain_data=domain.facet_tags, subdomain_id=tag)
    return COMM.allreduce(fem.assemble_scalar(fem.form(integrand * dm)), op=MPI.SUM)


def _numpy_volume(path: Path, dim: int) -> float:
    """|Omega| from the file itself (meshio + numpy), independent of the reader."""
    m = meshio.read(path)
    kind = {2: "triangle", 3: "tetra"}[dim]
    cells = np.concatenate([b.data for b in m.cells if b.type == kind])
    x = m.points[:, :dim][cells]
    edges = x[:, 1:] - x[:, :1]
    return float(np.abs(np.linalg.det(edges)).sum()) / (2 if dim == 2 else 6)


@pytest.mark.parametrize(("name", "fmt", "dim", "num_cells"), PAPER_MESHES)
def test_paper_meshes_without_physical_groups(name, fmt, dim, num_cells):
    path = _paper_file(name)
    domain = read_mesh(path, COMM)
    assert domain.dim == dim, fmt
    assert domain.mesh.topology.index_map(dim).size_global == num_cells
    assert domain.body_ids == [1]
    volume = _integrate(domain, 1.0)
    assert volume == pytest.approx(_numpy_volume(path, dim), rel=1e-12)
    # the tagged facets are the whole boundary: int n ds = 0 and int x.n ds = dim |Omega|
    n, x = ufl.FacetNormal(domain.mesh), ufl.SpatialCoordinate(domain.mesh)
    tags = domain.facet_ids
    flux = sum(_integrate(domain, ufl.dot(x, n), "ds", t) for t in tags)
    assert flux == pytest.approx(dim * volume, rel=1e-10)
    for k in range(dim):
        assert abs(sum(_integrate(domain, n[k], "ds", t) for t in tags)) < 1e-10 * volume ** (
            (dim - 1) / dim
        )
    ds.Model(domain, ds.NeoHookean(E=1e5, nu=0.3))  # orientation and quality checks pass


def test_untagged_msh_facets_are_tagged_one_and_blocks_are_bodies(tmp_path):
    """Two blocks (entities 1, 2), no physical group, no facets: bodies 1, 2, boundary tag 1."""
    points = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [2, 0], [2, 1]], float)
    blocks = [("triangle", np.array([[0, 1, 2], [0, 2, 3]])), ("triangle", np.array([[1, 4, 5]]))]
    path = tmp_path / "two_blocks.msh"
    if COMM.rank == 0:
        zeros = [np.zeros(2, int), np.zeros(1, int)]  # physical 0: no physical group
        entities = [np.ones(2, int), np.full(1, 2)]
        cell_data = {"gmsh:physical": zeros, "gmsh:geometrical": entities}
        mesh = meshio.Mesh(points, blocks, cell_data=cell_data)
        meshio.write(path, mesh, file_format="gmsh22", binary=True)
    COMM.barrier()
    path = Path(COMM.bcast(str(path)))
    domain = read_mesh(path, COMM)
    assert domain.body_ids == [1, 2] and domain.facet_ids == [1]
    assert _integrate(domain, 1.0) == pytest.approx(1.5)
    # the bodies share vertex (1, 0) only: the square's 4 edges and the triangle's 3
    assert _integrate(domain, 1.0, "ds", 1) == pytest.approx(4.0 + 2.0 + np.sqrt(2.0))


def test_transform_on_loading_is_scale_then_rotation_then_translation():
    path = _paper_file("fig14_puzzle_piece/puzzle.msh")
    plain = read_mesh(path, COMM)
    moved = read_mesh(path, COMM, scale=0.001, rotation=90.0, translation=[-1.0, 0.2])
    assert _integrate(moved, 1.0) == pytest.approx(1e-6 * _integrate(plain, 1.0), rel=1e-12)
    x0 = plain.mesh.geometry.x[:, :2]
    expected = 0.001 * np.stack([-x0[:, 1], x0[:, 0]], axis=1) + [-1.0, 0.2]
    assert np.allclose(moved.mesh.geometry.x[:, :2], expected, rtol=0, atol=1e-12)
    ds.Model(moved, ds.NeoHookean(E=1e5, nu=0.3))


def test_3d_rotation_order_and_per_axis_scale():
    domain = ds.mesh.create_box(COMM, [[0, 0, 0], [1, 2, 3]], [1, 1, 1])
    x0 = domain.mesh.geometry.x.copy()
    transform_domain(domain, scale=[2, 1, 1], rotation=[90, 0, 90])
    # x scaled by 2, then Rx(90): (x, y, z) -> (x, -z, y), then Rz(90): (x, y, z) -> (-y, x, z)
    sx = x0 * [2, 1, 1]
    after_x = np.stack([sx[:, 0], -sx[:, 2], sx[:, 1]], axis=1)
    expected = np.stack([-after_x[:, 1], after_x[:, 0], after_x[:, 2]], axis=1)
    assert np.allclose(domain.mesh.geometry.x, expected, atol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"scale": 0.0}, "must be finite and positive"),
        ({"scale": [1.0, -1.0]}, "must be finite and positive"),
        ({"scale": [1.0, 1.0, 1.0]}, "needs 1 or 2 values"),
        ({"rotation": [0.0, 1.0, 2.0]}, "needs 1 finite angles"),
        ({"translation": [0.0]}, "needs 2 finite values"),
    ],
)
def test_bad_transforms_are_refused(kwargs, message):
    domain = ds.mesh.create_rectangle(COMM, [[0, 0], [1, 1]], [2, 2])
    with pytest.raises(ds.MeshError, match=message):
        transform_domain(domain, **kwargs)


def test_unreadable_and_surface_files_name_the_file_and_the_problem(tmp_path):
    garbage = tmp_path / "garbage.msh"
    surface = tmp_path / "surface.obj"
    if COMM.rank == 0:
        garbage.write_text("$MeshFormat\nthis is not gmsh\n")
        tri = np.array([[0, 1, 2], [0, 2, 3]])
        pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0.5], [0, 1, 0]], float)
        meshio.write(surface, meshio.Mesh(pts, [("triangle", tri)]))
    COMM.barrier()
    garbage, surface = (Path(COMM.bcast(str(p))) for p in (garbage, surface))
    with pytest.raises(ds.MeshError, match=r"garbage\.msh: cannot read the file"):
        read_mesh(garbage, COMM)
    with pytest.raises(ds.MeshError, match=r"surface\.obj: 2D cells in 3D space are a surface"):
        read_mesh(surface, COMM)


def _grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid of the unit square, 2 n^2 positively oriented triangles."""
    xs = np.linspace(0.0, 1.0, n + 1)
    points = np.array([[x, y] for y in xs for x in xs])
    v = lambda i, j: j * (n + 1) + i  # noqa: E731
    cells = [
        c
        for j in range(n)
        for i in range(n)
        for c in ([v(i, j), v(i + 1, j), v(i + 1, j + 1)], [v(i, j), v(i + 1, j + 1), v(i, j + 1)])
    ]
    return points, np.array(cells)


def _write(tmp_path, name: str, points: np.ndarray, cells: np.ndarray, kind: str) -> Path:
    path = tmp_path / name
    if COMM.rank == 0:
        meshio.write(path, meshio.Mesh(points, [(kind, cells)]), file_format="gmsh22")
    COMM.barrier()
    return Path(COMM.bcast(str(path)))


def _named_cells(text: str) -> set[int]:
    """The cell indices named after "cells " in a check_cells message (first kind)."""
    listed = text.split("cells ", 1)[1].split(" of ")[0].split(";")[0]
    return {int(c) for c in listed.replace(", ...", "").split(", ")}


def _star(cells: np.ndarray, vertex: int) -> set[int]:
    """The cells that hold ``vertex`` and their facet neighbours (the region a move folds)."""
    ring = set(np.flatnonzero((cells == vertex).any(axis=1)).tolist())
    near = np.unique(cells[sorted(ring)])
    return ring | set(np.flatnonzero(np.isin(cells, near).sum(axis=1) >= cells.shape[1] - 1))


def test_inverted_and_degenerate_cells_name_the_file_the_count_and_the_cells(tmp_path):
    """A folded patch (an interior vertex moved over its neighbours) and a zero-area cell: one
    MeshError naming the file, how many of each and the first indices, on every rank (the mesh
    distributed over 2 ranks: each owned cell counted once); cells ordered backwards are fine."""
    points, cells = _grid(8)
    good = _write(tmp_path, "good.msh", points, cells, "triangle")
    assert read_mesh(good, COMM).mesh.topology.index_map(2).size_global == 128
    moved = points.copy()
    vertex = 4 * 9 + 4  # the centre of the 8 x 8 grid
    moved[vertex] += [0.3, 0.05]  # past its right neighbours (cell width 0.125)
    path = _write(tmp_path, "folded.msh", moved, cells, "triangle")
    with pytest.raises(ds.InvertedElementError) as info:
        read_mesh(path, COMM)
    assert isinstance(info.value, ds.MeshError)
    assert COMM.allreduce(len(info.value.cells), op=MPI.SUM) >= 2
    text = str(info.value)
    assert text.startswith(f"{path}: ") and " inverted (folded over a neighbour)" in text
    assert "of 128 triangle cells" in text
    assert _named_cells(text) <= _star(cells, vertex), text
    # cells ordered backwards (some or all) cover the same region: valid files
    flipped = cells.copy()
    flipped[[5, 77, 90]] = flipped[[5, 77, 90]][:, [0, 2, 1]]
    for name, order in (("mixed.msh", flipped), ("backwards.msh", cells[:, [0, 2, 1]])):
        read = read_mesh(_write(tmp_path, name, points, order, "triangle"), COMM)
        assert read.mesh.topology.index_map(2).size_global == 128
    # a zero-area sliver on the bottom edge: a new vertex at the midpoint of vertices 1, 2
    sliver = np.vstack([points, 0.5 * (points[1] + points[2])])
    path = _write(tmp_path, "flat.msh", sliver, np.vstack([cells, [[1, 81, 2]]]), "triangle")
    with pytest.raises(
        ds.MeshError, match=r"flat\.msh: 1 degenerate \(zero volume\): cells 128 of"
    ):
        read_mesh(path, COMM)


def test_a_folded_tetrahedral_mesh_is_named(tmp_path):
    """3D: an interior vertex of a box moved past its neighbours folds the tetrahedra around it;
    a tetrahedron ordered backwards does not."""
    box = ds.mesh.simplex_box([[0, 0, 0], [1, 1, 1]], [3, 3, 3])
    points = box.geometry.x.copy()
    cells = box.geometry.dofmaps[0].copy()
    reordered = cells.copy()
    reordered[17] = reordered[17][[1, 0, 2, 3]]
    path = _write(tmp_path, "reordered.msh", points, reordered, "tetra")
    assert read_mesh(path, COMM).mesh.topology.index_map(3).size_global == 162
    vertex = int(np.flatnonzero(np.all(np.isclose(points, 1 / 3), axis=1))[0])
    points[vertex, 0] += 0.6  # past the vertices at x = 2/3
    path = _write(tmp_path, "box.msh", points, cells, "tetra")
    with pytest.raises(ds.MeshError, match=r"box\.msh: \d+ inverted .* of 162 tetrahedron") as info:
        read_mesh(path, COMM)
    assert _named_cells(str(info.value)) <= _star(cells, vertex), str(info.value)


def test_the_paper_meshes_pass_the_cell_check():
    for name, _, dim, _ in PAPER_MESHES:
        read_mesh(_paper_file(name), COMM, dim)


# -- Domains from arrays --------------------------------------------------------------------------
def test_create_domain_from_arrays_tags_the_boundary_by_default():
    points = [[0, 0], [1, 0], [1, 1], [0, 1], [2, 0], [2, 1]]
    cells = [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]]
    domain = create_domain(points, cells, COMM)
    assert domain.body_ids == [1] and domain.facet_ids == [1]
    assert _integrate(domain, 1.0) == pytest.approx(2.0)
    assert _integrate(domain, 1.0, "ds", 1) == pytest.approx(6.0)  # the shared edge is inside
    tagged = create_domain(
        points,
        cells,
        COMM,
        cell_tags=[1, 1, 2, 2],
        facets=[[0, 3]],
        facet_tags=[7],
        names={"left": 1, "right": 2, "wall": 7},
    )
    assert tagged.body_ids == [1, 2] and tagged.facet_ids == [7]
    assert tagged.body_id("right") == 2 and tagged.facet_id("wall") == 7
    assert _integrate(tagged, 1.0, "ds", 7) == pytest.approx(1.0)


def test_create_domain_3d_matches_a_dolfinx_box():
    box = ds.mesh.create_box(MPI.COMM_SELF, [[0, 0, 0], [1, 2, 3]], [2, 2, 2])
    points, cells = box.mesh.geometry.x, box.mesh.geometry.dofmaps[0]
    domain = create_domain(points, cells, COMM)
    assert _integrate(domain, 1.0) == pytest.approx(6.0)
    assert _integrate(domain, 1.0, "ds", 1) == pytest.approx(2 * (2 + 3 + 6))


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (([[0, 0, 0, 0]], [[0, 1, 2]]), r"points must have shape \(n, 2\) or \(n, 3\)"),
        (([[0, 0], [1, 0], [0, 1]], [[0, 1]]), r"2D cells must have shape \(m, 3\)"),
        (([[0, 0], [1, 0], [0, 1]], [[0, 1, 3]]), r"cells index vertices outside 0..2"),
        (([[0, 0], [1, 0], [0, float("nan")]], [[0, 1, 2]]), "non-finite"),
    ],
)
def test_create_domain_refuses_bad_arrays(args, message):
    with pytest.raises(ds.MeshError, match=message):
        create_domain(*args, COMM)
    with pytest.raises(ds.MeshError, match="cell_tags must be 1 positive integers"):
        create_domain([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]], COMM, cell_tags=[0])


# -- boundary selections (PolyFEM rule: the facet's barycentre) ----------------------------------
def _strip():
    return ds.mesh.create_rectangle(COMM, [[0, 0], [2, 1]], [2, 1])


def test_a_box_selects_facets_by_barycentre_where_vertex_markers_do_not():
    sel = ds.mesh.BoxSelection([0.4, -0.1], [2.1, 0.1])
    by_centre = ds.mesh.select_facets(_strip(), {5: sel}, names={"floor": 5})
    assert by_centre.facet_ids == [5] and by_centre.facet_id("floor") == 5
    assert _integrate(by_centre, 1.0, "ds", 5) == pytest.approx(2.0)  # both bottom edges
    mesh = _strip().mesh
    by_vertex = ds.Domain.from_mesh(
        mesh,
        facet_tags=ds.mesh.tag_facets(
            mesh, {5: lambda x: sel.inside(x[:2].T, (np.zeros(2), np.ones(2)))}
        ),
    )
    assert _integrate(by_vertex, 1.0, "ds", 5) == pytest.approx(1.0)  # (0, 0) is outside


@pytest.mark.parametrize(
    ("selection", "length"),
    [
        (ds.mesh.AxisPlaneSelection("-x", 0.0), 1.0),
        (ds.mesh.AxisPlaneSelection(2, 1.0), 2.0),
        (ds.mesh.AxisPlaneSelection(1, 0.99, relative=True), 1.0),
        (ds.mesh.PlaneSelection([0, -1], [0, 0.01]), 2.0),
        (ds.mesh.SphereSelection([2, 1], 0.8), 2.0),  # centres (2, 0.5) and (1.5, 1)
        (ds.mesh.SphereSelection([2, 1], 0.45), 0.0),
        (ds.mesh.BoxSelection([0.7, 0.4], [1.1, 1.1], relative=True), 2.0),
    ],
)
def test_selections_follow_polyfem(selection, length):
    domain = ds.mesh.select_facets(_strip(), {3: selection})
    assert _integrate(domain, 1.0, "ds", 3) == pytest.approx(length)


def test_later_selections_win_and_bad_tags_are_refused():
    domain = ds.mesh.select_facets(
        _strip(),
        {1: ds.mesh.AxisPlaneSelection(2, -1.0), 2: ds.mesh.AxisPlaneSelection(-2, 0.0)},
    )
    assert _integrate(domain, 1.0, "ds", 1) == pytest.approx(4.0)  # all but the bottom
    assert _integrate(domain, 1.0, "ds", 2) == pytest.approx(2.0)
    with pytest.raises(ds.ParameterError, match="facet tag 0 must be a positive integer"):
        ds.mesh.select_facets(_strip(), {0: ds.mesh.AxisPlaneSelection(1, 0.0)})
    with pytest.raises(ds.ParameterError, match="axis 4 must be"):
        ds.mesh.select_facets(_strip(), {1: ds.mesh.AxisPlaneSelection(4, 0.0)})


def test_a_paper_scene_assembled_from_its_files():
    """fig20: the ground square.obj and the kangaroo, placed as the scene JSON places them."""
    ground = _paper_mesh("fig20_kangaroo/square.obj", scale=[3, 0.02])
    kangaroo = _paper_mesh(
        "fig20_kangaroo/kangaroo-coarse.msh", scale=0.25, translation=[-1.5, 0.1]
    )
    domain = ds.mesh.combine_meshes(COMM, [ground, kangaroo], names={"ground": 1, "kangaroo": 2})
    assert domain.body_ids == [1, 2] and domain.body_id("kangaroo") == 2
    dx = ufl.Measure("dx", domain=domain.mesh, subdomain_data=domain.cell_tags)
    area = [COMM.allreduce(fem.assemble_scalar(fem.form(1.0 * dx(b))), op=MPI.SUM) for b in (1, 2)]
    assert area[0] == pytest.approx(3 * 0.02)
    assert area[1] == pytest.approx(0.25**2 * _integrate(read_mesh(kangaroo_path(), COMM), 1.0))


def kangaroo_path() -> Path:
    return _paper_file("fig20_kangaroo/kangaroo-coarse.msh")
