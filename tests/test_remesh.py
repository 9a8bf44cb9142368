"""Remeshing with a kept boundary, field transfer, checkpoints and the optimiser hook."""

import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import InitialCondition, ParameterControl, Simp
from diffsolids.errors import MeshError
from diffsolids.mesh import (
    Domain,
    check_orientation,
    create_box,
    create_rectangle,
    from_gmsh_model,
    gmsh_session,
    min_scaled_jacobian,
)
from diffsolids.mesh.scene import simplex_ball
from diffsolids.objectives import Integral, final_value
from diffsolids.optimize.mesh_motion import MeshMotionControl, ShapeInnerProduct
from diffsolids.optimize.remesh import (
    MeshArrays,
    Remesher,
    gather_mesh,
    load_domain,
    remesh_domain,
    save_domain,
)
from diffsolids.reduced_functional import ReducedFunctional

COMM = MPI.COMM_WORLD
CLAMP, HOLE = 1, 5


def _plate_with_hole(comm=COMM) -> Domain:
    """Two bodies [0,1]x[0,1] and [1,2]x[0,1] (shared edge), a hole in the right one."""
    with gmsh_session() as gmsh:
        if comm.rank == 0:
            occ = gmsh.model.occ
            left = occ.addRectangle(0, 0, 0, 1, 1)
            right = occ.addRectangle(1, 0, 0, 1, 1)
            disk = occ.addDisk(1.5, 0.5, 0, 0.2, 0.2)
            right_cut, _ = occ.cut([(2, right)], [(2, disk)])
            occ.fragment([(2, left)], right_cut)
            occ.synchronize()
            for _, tag in gmsh.model.getEntities(2):
                body = 1 if occ.getCenterOfMass(2, tag)[0] < 1 else 2
                gmsh.model.addPhysicalGroup(2, [tag], body, name=f"body{body}")
            clamp, hole = [], []
            for _, tag in gmsh.model.getEntities(1):
                x, y, _ = occ.getCenterOfMass(1, tag)
                if abs(x) < 1e-9:
                    clamp.append(tag)
                elif np.hypot(x - 1.5, y - 0.5) < 0.1:
                    hole.append(tag)
            gmsh.model.addPhysicalGroup(1, clamp, CLAMP, name="clamp")
            gmsh.model.addPhysicalGroup(1, hole, HOLE, name="hole")
            gmsh.option.setNumber("Mesh.MeshSizeMax", 0.2)
            gmsh.model.mesh.generate(2)
        return from_gmsh_model(gmsh.model, comm, 2)


def _measures(arrays: MeshArrays) -> dict[int, float]:
    """Volume (area) of every body."""
    pts, cells = arrays.points, arrays.cells
    d = pts.shape[1]
    edges = np.stack([pts[cells[:, k]] - pts[cells[:, 0]] for k in range(1, d + 1)], axis=1)
    vol = np.abs(np.linalg.det(edges)) / (2.0 if d == 2 else 6.0)
    return {
        int(b): float(vol[arrays.cell_values == b].sum()) for b in np.unique(arrays.cell_values)
    }


def _boundary_facets(arrays: MeshArrays) -> np.ndarray:
    """Coordinates of the facets on body boundaries (exterior and interfaces), sorted."""
    cells, d = arrays.cells, arrays.points.shape[1]
    faces, owners = [], []
    for k in range(d + 1):
        faces.append(np.sort(np.delete(cells, k, axis=1), axis=1))
        owners.append(arrays.cell_values)
    faces, owners = np.concatenate(faces), np.concatenate(owners)
    keys = np.c_[faces, owners]
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    faces = np.unique(faces[counts[inv.ravel()] == 1], axis=0)
    return _facet_coordinates(arrays.points, faces)


def _facet_coordinates(points: np.ndarray, facets: np.ndarray) -> np.ndarray:
    """Facet vertex coordinates, vertices sorted within a facet, rows sorted (keys rounded)."""
    key = lambda v: tuple(np.round(v, 8))  # noqa: E731
    rows = np.array([np.concatenate(sorted(f, key=key)) for f in points[facets]])
    return rows[np.lexsort(np.round(rows, 8).T[::-1])] if len(rows) else rows


def _tagged(arrays: MeshArrays) -> dict[int, np.ndarray]:
    return {
        int(t): _facet_coordinates(arrays.points, arrays.facets[arrays.facet_values == t])
        for t in np.unique(arrays.facet_values)
    }


@pytest.mark.parametrize("scene", ["plate_with_hole", "two_boxes"])
def test_remesh_keeps_boundary_interfaces_tags_and_bodies(scene):
    if scene == "plate_with_hole":
        domain = _plate_with_hole()
    else:
        domain = create_box(
            COMM,
            [[0, 0, 0], [1, 1, 1]],
            [4, 4, 4],
            facets={CLAMP: lambda x: np.isclose(x[0], 0.0)},
            bodies={2: lambda x: x[0] > 0.5},
            names={"clamp": CLAMP},
        )
    new = remesh_domain(domain, mesh_size=0.15 if scene == "plate_with_hole" else None)
    old_arrays, new_arrays = gather_mesh(domain), gather_mesh(new)
    assert new.names == domain.names
    assert new.body_ids == domain.body_ids and new.facet_ids == domain.facet_ids
    signs = check_orientation(new.mesh)
    quality = min_scaled_jacobian(new.mesh, signs)
    print(f"{scene}: min scaled Jacobian of the new mesh {quality:.3f}")
    # the kept boundary triangulation bounds the quality (create_box's own cells: 0.258)
    assert quality > (0.5 if scene == "plate_with_hole" else 0.2)
    if COMM.rank == 0:
        print(f"{len(old_arrays.cells)} -> {len(new_arrays.cells)} cells")
        assert len(new_arrays.cells) != len(old_arrays.cells)  # really a new interior
        old_vol, new_vol = _measures(old_arrays), _measures(new_arrays)
        assert old_vol.keys() == new_vol.keys()
        for body, v in old_vol.items():
            assert new_vol[body] == pytest.approx(v, rel=1e-9)  # snapped boundary
        # same boundary facets; vertices rounded to 2^-32 of the bounding box (2 * 2^-32 here)
        snap = 2.0**-31
        old_faces, new_faces = _boundary_facets(old_arrays), _boundary_facets(new_arrays)
        assert old_faces.shape == new_faces.shape
        assert np.abs(old_faces - new_faces).max() <= snap / 2
        old_tags, new_tags = _tagged(old_arrays), _tagged(new_arrays)
        assert old_tags.keys() == new_tags.keys()
        for tag in old_tags:
            assert np.abs(old_tags[tag] - new_tags[tag]).max() <= snap / 2


def test_remesh_options_do_not_leak_into_later_gmsh_meshes():
    """The CI failure of stop 8: a 3D remesh (Mesh.Renumber = 0) then a gmsh ball in the same
    process gave non-contiguous node tags, which DOLFINx's gmsh reader refuses."""
    box = create_box(COMM, [[0, 0, 0], [1, 1, 1]], [3, 3, 3])
    remesh_domain(box)
    ball = simplex_ball([0.5, 0.5, 0.35], 0.2, 0.1)
    assert ball.topology.index_map(3).size_local > 0
    with pytest.raises(RuntimeError), gmsh_session() as gmsh:
        gmsh.option.setNumber("Mesh.Renumber", 0)
        raise RuntimeError("a failing mesher")
    with gmsh_session() as gmsh:
        assert gmsh.option.getNumber("Mesh.Renumber") == 1


def test_domain_checkpoint_roundtrip_keeps_canonical_order(tmp_path):
    path = COMM.bcast(str(tmp_path / "mesh.npz"), root=0)
    domain = create_rectangle(
        COMM,
        [[0, 0], [2, 1]],
        [6, 3],
        facets={CLAMP: lambda x: np.isclose(x[0], 0.0)},
        bodies={2: lambda x: x[0] > 1.0},
        names={"clamp": CLAMP},
    )
    moved = domain.mesh.geometry.x.copy()
    moved[:, 1] *= 1.0 + 0.1 * moved[:, 0]
    save_domain(domain, path, moved, note=7)
    loaded, info = load_domain(path, COMM)
    assert info == {"note": 7}
    assert loaded.names == domain.names
    a, b = gather_mesh(domain, moved), gather_mesh(loaded)
    if COMM.rank == 0:
        for name in ("points", "cells", "cell_values", "facets", "facet_values"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
    with pytest.raises(MeshError, match="does not exist"):
        load_domain(str(tmp_path / "missing.npz"), COMM)


# -- a small shape optimisation scene ---------------------------------------------------------
BOTTOM, TOP = 1, 2


def block_domain(comm: MPI.Comm = COMM) -> Domain:
    """A two-body block [0, 2] x [0, 1] with tagged bottom and top (also used on 2 ranks)."""
    return create_rectangle(
        comm,
        [[0, 0], [2, 1]],
        [8, 4],
        facets={BOTTOM: lambda x: np.isclose(x[1], 0.0), TOP: lambda x: np.isclose(x[1], 1.0)},
        bodies={2: lambda x: x[0] > 1.0},
        names={"bottom": BOTTOM, "top": TOP},
    )


def build_block(domain: Domain, displacement_weight: float = 0.0) -> ReducedFunctional:
    """Clamped block under gravity; its deformed top should follow a lowered wavy profile
    (plus ``displacement_weight`` times the squared displacement over the block)."""
    model = ds.Model(domain, ds.LinearElastic(E=100.0, nu=0.3, density=1.0))
    model.add_dirichlet("bottom", 0.0)
    model.add_gravity(1.0)
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-12))

    def misfit(f):
        target = 0.55 + 0.1 * ufl.cos(np.pi * f.X[0])
        misfit = (f.X[1] + f.u[1] - target) ** 2 * f.ds(TOP)
        return misfit + displacement_weight * ufl.inner(f.u, f.u) * f.dx

    control = MeshMotionControl(model, "boundary", exclude_facets=["bottom"])
    return ReducedFunctional(sim, final_value(Integral(misfit)), control)


def _descent(rf, remesher, iterations):
    """Steepest descent in the Riesz inner product with Armijo backtracking and the hooks."""
    inner = ShapeInnerProduct(rf)
    q = np.zeros(rf.size)
    J, g = rf.value_and_gradient(q)
    log = [("start", J, remesher.quality(rf, q))]
    for _ in range(iterations):
        d = -inner(g)
        step = 1.0
        while True:
            try:
                trial = rf(q + step * d)
                if trial <= J + 1e-4 * step * (g @ d):
                    break
            except ds.DiffsolidsError:
                pass
            step *= 0.5
        q = q + step * d
        J, g = rf.value_and_gradient(q)
        log.append(("step", J, remesher.quality(rf, q)))
        if remesher.needs_remesh(rf, q):
            rf, q = remesher.remesh(rf, q)
            inner = inner.rebuild(rf)
            J, g = rf.value_and_gradient(q)
            log.append(("remesh", J, remesher.quality(rf, q)))
    return rf, q, log


def test_shape_optimisation_continues_through_a_remesh():
    rf = build_block(block_domain())
    remesher = Remesher(build_block, threshold=0.6)
    rf, q, log = _descent(rf, remesher, 6)
    for kind, J, quality in log:
        print(f"{kind:6s} J = {J:.6e}  min scaled Jacobian {quality:.3f}")
    kinds = [k for k, _, _ in log]
    assert "remesh" in kinds
    k = kinds.index("remesh")
    (_, J_before, q_before), (_, J_after, q_after) = log[k - 1], log[k]
    rec = remesher.history[0]
    print(rec)
    assert rec.quality_before == pytest.approx(q_before) and q_before < 0.6
    assert q_after == pytest.approx(rec.quality_after) and q_after > q_before
    # the boundary is kept: the objective barely changes across the remesh
    assert abs(J_after - J_before) < 1e-3 * J_before
    assert log[-1][1] < 1e-2 * log[0][1]
    assert np.all(np.isfinite(q))


def test_remesh_transfers_controlled_fields():
    def build(domain):
        mesh = domain.mesh
        E = fem.Function(fem.functionspace(mesh, ("Lagrange", 1)), name="E")
        E.interpolate(lambda x: 100.0 + 10.0 * x[0] + 5.0 * x[1])
        density = fem.Function(fem.functionspace(mesh, ("DG", 0)), name="density")
        density.x.array[:] = 1.0
        model = ds.Model(
            domain, ds.LinearElastic(E=100.0, nu=0.3), fields={"E": E, "density": density}
        )
        model.add_dirichlet("bottom", 0.0)
        model.add_gravity(1.0)
        sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-12))
        controls = [
            ParameterControl(model, "E", "field", map=Simp(50.0, 500.0)),
            ParameterControl(model, "density", "field"),
            ParameterControl(model, "nu", "bodies"),
            MeshMotionControl(model, "boundary", exclude_facets=["bottom"]),
        ]
        objective = final_value(Integral(lambda f: ufl.inner(f.u, f.u) * f.dx))
        return ReducedFunctional(sim, objective, controls)

    rf = build(block_domain())
    E_ctrl, rho_ctrl, _, shape = rf.controls.controls
    # the current iterate: a moved shape and fields set on it
    q_shape = 0.1 * np.sin(np.arange(shape.size))
    shape.assign(q_shape)
    E_ctrl.function.interpolate(lambda x: 200.0 + 20.0 * x[0] - 7.0 * x[1])
    rho = rho_ctrl.function
    rho.x.array[rf.model.domain.cells_of(1)] = 3.0
    rho.x.array[rf.model.domain.cells_of(2)] = 4.0
    q = np.concatenate([E_ctrl.value(), rho_ctrl.value(), [0.25, 0.35], q_shape])
    new_rf, new_q = Remesher(build, threshold=0.5).remesh(rf, q)
    E2, rho2, _, shape2 = new_rf.controls.controls
    blocks = new_rf.controls.split(new_q)
    assert np.array_equal(blocks[2], [0.25, 0.35])
    assert np.array_equal(blocks[3], np.zeros(shape2.size))
    # P1 field linear in the (moved) coordinates: transferred exactly
    x = E2.function.function_space.tabulate_dof_coordinates()
    assert np.allclose(E2.function.x.array, 200.0 + 20.0 * x[:, 0] - 7.0 * x[:, 1], rtol=1e-12)
    # DG0 field constant per body: transferred exactly (new cells stay in their body)
    domain = new_rf.model.domain
    assert np.all(rho2.function.x.array[domain.cells_of(1)] == 3.0)
    assert np.all(rho2.function.x.array[domain.cells_of(2)] == 4.0)
    new_rf.controls.assign(new_q)  # the blocks reproduce the transferred fields
    assert np.allclose(E2.function.x.array, 200.0 + 20.0 * x[:, 0] - 7.0 * x[:, 1], rtol=1e-12)
    assert np.isfinite(new_rf(new_q))


def test_optimiser_hook_remeshes_checkpoints_and_resumes(tmp_path):
    from diffsolids.optimize import LBFGSOptions, minimize

    ckpt = COMM.bcast(str(tmp_path / "ckpt"), root=0)
    rf = build_block(block_domain())
    remesher = Remesher(build_block, threshold=0.6)
    options = LBFGSOptions(max_iterations=6, gradient_rtol=0.0)
    result = minimize(
        rf,
        options=options,
        remesher=remesher,
        inner_product=ShapeInnerProduct(rf),
        checkpoint_dir=ckpt,
    )
    print(result)
    assert remesher.count >= 1
    assert result.functional is not rf
    J_first = result.history[0].objective
    assert result.history[-1].objective < 1e-2 * J_first
    # resume from the checkpoint with a fresh problem on the original mesh
    again = Remesher(build_block, threshold=0.6)
    fresh = build_block(block_domain())
    resumed = minimize(
        fresh,
        options=LBFGSOptions(max_iterations=7, gradient_rtol=0.0),
        remesher=again,
        inner_product=ShapeInnerProduct(fresh),
        checkpoint_dir=ckpt,
    )
    assert again.count == remesher.count
    assert resumed.history[-1].objective <= result.history[-1].objective
    assert resumed.functional.size == result.functional.size


def test_remesher_trigger_limits_and_errors():
    rf = build_block(block_domain())
    q = np.zeros(rf.size)
    assert Remesher(build_block, threshold=0.9).needs_remesh(rf, q)  # rest quality 0.816
    assert not Remesher(build_block, threshold=1e-3).needs_remesh(rf, q)
    assert not Remesher(build_block, threshold=0.9, max_remeshes=0).needs_remesh(rf, q)
    with pytest.raises(MeshError, match="below 1"):
        Remesher(build_block, threshold=1.0)
    with pytest.raises(TypeError, match="factory"):
        Remesher(None)
    with pytest.raises(MeshError, match="domain it is given"):
        Remesher(lambda domain: build_block(block_domain())).remesh(rf, q)

    def other_controls(domain):
        out = build_block(domain)
        model = out.model
        return ReducedFunctional(out.simulation, out.objective, ParameterControl(model, "E"))

    with pytest.raises(MeshError, match="different controls"):
        Remesher(other_controls).remesh(rf, q)


def test_remesh_refuses_tagged_facets_inside_a_body():
    import dolfinx

    domain = create_rectangle(COMM, [[0, 0], [2, 1]], [4, 2])
    mesh = domain.mesh
    inner = dolfinx.mesh.locate_entities(mesh, 1, lambda x: np.isclose(x[0], 1.0))
    tags = dolfinx.mesh.meshtags(mesh, 1, inner, np.full(len(inner), 7, dtype=np.int32))
    bad = Domain.from_mesh(mesh, domain.cell_tags, tags)
    with pytest.raises(MeshError, match="inside a body"):
        remesh_domain(bad)


@pytest.mark.parametrize("turns", [0.9, 1.15])
def test_remesh_refuses_a_boundary_that_intersects_itself(turns):
    """A strip wound into a spiral: past one turn its ends overlap without inverted cells.

    gmsh never returns on such a boundary; the remesher refuses it instead.
    """
    domain = create_rectangle(COMM, [[0, 0], [1, 1]], [40, 2])
    x = domain.mesh.geometry.x
    theta, r = 2 * np.pi * turns * x[:, 0], 1.0 + 0.3 * x[:, 1]
    x[:, 0], x[:, 1] = r * np.cos(theta), r * np.sin(theta)
    if turns < 1:
        assert remesh_domain(domain).mesh.topology.index_map(2).size_global > 0
    else:
        with pytest.raises(MeshError, match="boundary intersects itself"):
            remesh_domain(domain)


def test_remesh_transfers_initial_conditions():
    def build(domain):
        model = ds.Model(domain, ds.LinearElastic(E=100.0, nu=0.3, density=1.0))
        model.add_dirichlet("bottom", 0.0)
        sim = ds.Simulation(model, ds.BDF(1, 0.05, 2), ds.SolverOptions(rtol=1e-12))
        objective = final_value(Integral(lambda f: ufl.inner(f.u, f.u) * f.dx))
        controls = [
            InitialCondition(sim, "velocity"),
            MeshMotionControl(model, "boundary", exclude_facets=["bottom"]),
        ]
        return ReducedFunctional(sim, objective, controls)

    rf = build(block_domain())
    velocity, shape = rf.controls.controls
    shape.assign(0.05 * np.cos(np.arange(shape.size)))
    V = rf.model.V
    v = fem.Function(V)
    v.interpolate(lambda x: np.stack([2.0 * x[0] - x[1], x[0] + 3.0 * x[1]]))
    rf.simulation.v0[:] = v.x.array
    q = np.concatenate([velocity.value(), shape.value()])
    new_rf, new_q = Remesher(build).remesh(rf, q)
    new_velocity = new_rf.controls.controls[0]
    x = new_rf.model.V.tabulate_dof_coordinates()
    expected = np.stack([2.0 * x[:, 0] - x[:, 1], x[:, 0] + 3.0 * x[:, 1]], axis=1).ravel()
    assert np.allclose(new_rf.simulation.v0, expected, rtol=1e-12, atol=1e-12)
    new_rf.controls.assign(new_q)
    assert np.allclose(new_rf.simulation.v0, expected, rtol=1e-12, atol=1e-12)
    assert new_velocity.size == new_rf.model.V.dofmap.index_map.size_global * 2
