"""Mesh motion (boundary displacement extended into the body) and its Riesz map."""

import dolfinx
import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import ControlError, ParameterControl, ShapeControl
from diffsolids.mesh import create_rectangle, min_scaled_jacobian
from diffsolids.objectives import Integral, final_value
from diffsolids.optimize.mesh_motion import (
    MeshMotion,
    MeshMotionControl,
    RieszMap,
    ShapeInnerProduct,
)
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.verification import finite_difference_check, taylor_test

CLAMP, LOAD, TOP = 1, 2, 3


def _rectangle(n=(8, 4), comm=MPI.COMM_WORLD):
    return create_rectangle(
        comm,
        [[0.0, 0.0], [2.0, 1.0]],
        n,
        facets={
            CLAMP: lambda x: np.isclose(x[0], 0.0),
            LOAD: lambda x: np.isclose(x[0], 2.0),
            TOP: lambda x: np.isclose(x[1], 1.0),
        },
    )


def _canonical_coordinates(motion: MeshMotion) -> np.ndarray:
    mesh = motion.domain.mesh
    x = np.zeros((motion.W.dofmap.index_map.size_local, 2))
    nodes = np.empty(len(motion.reference), dtype=np.int64)
    nodes[motion.W.dofmap.list.ravel()] = mesh.geometry.dofmaps[0].ravel()
    x[:] = motion.reference[nodes[: len(x)], :2]
    return motion.layout.gather(x).reshape(-1, 2)


@pytest.mark.parametrize("extension", ["elasticity", "harmonic"])
def test_extension_is_the_discrete_harmonic_map_and_its_adjoint_is_exact(extension):
    dom = _rectangle()
    P = MeshMotion(dom, "boundary", exclude_facets=[CLAMP], extension=extension)
    rng = np.random.default_rng(3)
    q = rng.standard_normal(P.shape[1])
    g = rng.standard_normal(P.shape[0])
    d = P @ q
    # dot test: P.T is the exact transpose of P
    assert abs(d @ g - q @ (P.T @ g)) <= 1e-13 * abs(q @ (P.T @ g))
    # design vertices move by q, fixed (clamped) ones not at all
    d = d.reshape(-1, 2)
    assert np.array_equal(d[P.design], q.reshape(-1, 2))
    x = _canonical_coordinates(P)
    clamped = np.setdiff1d(np.flatnonzero(np.isclose(x[:, 0], 0.0)), P.design)
    assert len(clamped) > 0 and np.all(d[clamped] == 0.0)
    # interior rows of K d vanish (the extension solves the stiffness equations)
    vec = dolfinx.fem.petsc.create_vector(P.W)
    n = P.W.dofmap.index_map.size_local
    vec.getArray()[:] = d[P.layout.positions].ravel()
    r = P.K.createVecLeft()
    P.K.mult(vec, r)
    free = np.ones(n * 2, dtype=bool)
    free[P._owned_constrained_dofs] = False
    scale = np.abs(r.getArray()).max()
    assert scale > 0 and np.abs(r.getArray()[free]).max() <= 1e-12 * scale
    # built once on the reference mesh: moving the mesh does not change the operator
    mesh = dom.mesh
    mesh.geometry.x[:, 1] *= 1.7
    assert np.array_equal(P @ q, d.ravel())
    mesh.geometry.x[:] = P.reference


def test_extension_keeps_elements_valid_where_moving_only_the_boundary_inverts():
    dom = _rectangle((16, 8))
    model = ds.Model(dom, ds.LinearElastic(E=1.0, nu=0.3))
    signs = model.reference_signs
    top = lambda x: np.isclose(x[1], 1.0)  # noqa: E731
    motion = MeshMotionControl(model, top, extension="elasticity")
    harmonic = MeshMotion(dom, top, extension="harmonic")
    only_boundary = ShapeControl(model, top)
    assert np.array_equal(np.unique(only_boundary.P.nonzero()[0] // 2), motion.motion.design)
    x_top = _canonical_coordinates(motion.motion)[motion.motion.design]
    q = np.zeros((len(x_top), 2))
    q[:, 1] = -0.6 * np.sin(np.pi * x_top[:, 0] / 2.0)  # push the top down by up to 60 %

    mesh_x = dom.mesh.geometry.x.copy()

    def quality(control):
        x = mesh_x.copy()
        x[:, :2] = control.X0 + control.displacement(q.ravel())[control.input_index]
        return min_scaled_jacobian(dom.mesh, signs, x)

    before = min_scaled_jacobian(dom.mesh, signs)
    q_boundary, q_motion = quality(only_boundary), quality(motion)
    d_harmonic = (harmonic @ q.ravel()).reshape(-1, 2)[motion.input_index]
    x = mesh_x.copy()
    x[:, :2] += d_harmonic
    q_harmonic = min_scaled_jacobian(dom.mesh, signs, x)
    print(f"min scaled Jacobian: rest {before:.3f}, boundary only {q_boundary:.3f}, ")
    print(f"elasticity extension {q_motion:.3f}, harmonic extension {q_harmonic:.3f}")
    assert q_boundary < 0.0
    assert q_motion > 0.25 and q_harmonic > 0.0
    with pytest.raises(ds.InvertedElementError):
        only_boundary.assign(q.ravel())
    motion.assign(q.ravel())  # valid
    assert min_scaled_jacobian(dom.mesh, signs) == pytest.approx(q_motion, rel=1e-12)


@pytest.fixture(scope="module")
def scene():
    dom = _rectangle()
    model = ds.Model(dom, ds.NeoHookean(E=100.0, nu=0.3))
    model.add_dirichlet(CLAMP, 0.0)
    model.add_traction(LOAD, [0.0, -5.0])
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-13))
    objective = final_value(Integral(lambda f: ufl.inner(f.u, f.u) * f.dx))
    control = MeshMotionControl(model, "boundary", exclude_facets=[CLAMP])
    return ReducedFunctional(sim, objective, control), sim, objective


def test_mesh_motion_shape_gradient_taylor_and_finite_differences(scene):
    rf, _, _ = scene
    q0 = np.zeros(rf.size)
    g = rf.gradient(q0)
    rng = np.random.default_rng(0)
    directions = {"random": rng.standard_normal(rf.size), "gradient": -g}
    for name, dq in directions.items():
        dq = 0.05 * dq / np.abs(dq).max()  # vertex moves up to 5 % of the element size
        taylor = taylor_test(rf, q0, dq, h0=1.0, num=4)
        print(name, taylor)
        assert taylor.min_rate > 1.9
        fd = finite_difference_check(rf, q0, dq, steps=[1e-1, 3e-2, 1e-2], gradient=g)
        print(name, fd)
        assert fd.relative_error < 1e-5


def test_mesh_motion_gradient_is_the_chain_rule_through_the_extension(scene):
    """dJ/dq = P^T dJ/dX with dJ/dX of every vertex: interior vertices contribute."""
    rf, sim, objective = scene
    control = rf.controls.controls[0]
    control.assign(np.zeros(rf.size))  # reference geometry = X0 of both controls
    all_vertices = ReducedFunctional(sim, objective, ShapeControl(sim.model, "all"))
    q = np.full(rf.size, 0.01)
    g = rf.gradient(q)
    x = control.displacement(q).ravel()
    dJ_dX = all_vertices.gradient(x)  # same geometry, per vertex
    assert np.allclose(g, control.motion.T @ dJ_dX, rtol=1e-12, atol=1e-14 * np.abs(g).max())
    boundary_only = dJ_dX.reshape(-1, 2)[control.motion.design].ravel()
    interior_share = np.linalg.norm(g - boundary_only) / np.linalg.norm(g)
    print(f"interior vertices change the gradient by {interior_share:.1%}")
    assert interior_share > 0.05


def _roughness(motion: MeshMotion, d: np.ndarray) -> float:
    """|differences of d across boundary edges between design vertices| / |d|."""
    mesh = motion.domain.mesh
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    nodes = dolfinx.mesh.entities_to_geometry(mesh, 1, facets)
    edges = np.concatenate(MPI.COMM_WORLD.allgather(mesh.geometry.input_global_indices[nodes]))
    pos = {v: k for k, v in enumerate(motion.design)}
    pairs = np.array([[pos[a], pos[b]] for a, b in edges if a in pos and b in pos])
    d = d.reshape(-1, 2)
    return float(np.linalg.norm(d[pairs[:, 0]] - d[pairs[:, 1]]) / np.linalg.norm(d))


@pytest.mark.parametrize("extension", ["elasticity", "harmonic"])
def test_riesz_map_is_spd_smoothing_and_a_descent_direction(scene, extension):
    rf, _, _ = scene
    motion = MeshMotion(rf.model.domain, "boundary", exclude_facets=[CLAMP], extension=extension)
    riesz = motion.riesz_map()
    A = np.column_stack([riesz(e) for e in np.eye(riesz.size)])
    assert np.abs(A - A.T).max() <= 1e-12 * np.abs(A).max()
    eig = np.linalg.eigvalsh(0.5 * (A + A.T))
    print(f"{extension}: eigenvalues of A^-1 in [{eig.min():.3e}, {eig.max():.3e}]")
    assert eig.min() > 0
    rng = np.random.default_rng(5)
    g = rng.standard_normal(riesz.size)
    assert _roughness(motion, riesz(g)) < 0.5 * _roughness(motion, g)
    # along -riesz(dJ/dq) the objective decreases (the map is SPD)
    if extension == "elasticity":
        q0 = np.zeros(rf.size)
        J0, gJ = rf.value_and_gradient(q0)
        d = -riesz(gJ)
        assert gJ @ d < 0
        h = 0.02 / np.abs(d).max()
        assert rf(q0 + h * d) < J0


def test_riesz_map_is_mesh_independent():
    """A^{-1} of a boundary load converges under refinement; the raw gradient halves."""
    peak = {}
    for n in (8, 16, 32):
        dom = create_rectangle(MPI.COMM_WORLD, [[0.0, 0.0], [2.0, 1.0]], [n, n // 2])
        motion = MeshMotion(dom, lambda x: np.isclose(x[1], 1.0))
        v = ufl.TestFunction(motion.W)
        X = ufl.SpatialCoordinate(dom.mesh)
        load = ufl.as_vector([0.0 * X[0], ufl.sin(np.pi * X[0] / 2.0)])
        b = fem.assemble_vector(fem.form(ufl.inner(load, v) * ufl.ds))
        b.scatter_reverse(dolfinx.la.InsertMode.add)
        g = motion.layout.gather(b.array).reshape(-1, 2)[motion.design].ravel()
        r = motion.riesz_map()(g)
        peak[n] = (np.abs(g).max(), np.abs(r).max())
    print(peak)
    assert peak[16][0] == pytest.approx(peak[8][0] / 2, rel=0.05)
    assert peak[32][0] == pytest.approx(peak[16][0] / 2, rel=0.05)
    assert abs(peak[32][1] - peak[16][1]) < 0.5 * abs(peak[16][1] - peak[8][1])
    assert peak[32][1] == pytest.approx(peak[16][1], rel=0.02)


def test_shape_inner_product_acts_blockwise_and_rebuilds(scene):
    rf, sim, objective = scene
    model = sim.model
    shape = rf.controls.controls[0]
    mixed = ReducedFunctional(
        sim, objective, [ParameterControl(model, "E", "bodies"), shape], factor_memory_mb=0
    )
    inner = ShapeInnerProduct(mixed, other_scale=3.0)
    rng = np.random.default_rng(2)
    g = rng.standard_normal(mixed.size)
    out = inner(g)
    assert out[0] == 3.0 * g[0]
    assert np.allclose(out[1:], shape.riesz_map()(g[1:]), rtol=1e-13)
    assert isinstance(inner.rebuild(mixed), ShapeInnerProduct)
    with pytest.raises(ControlError, match="length"):
        inner(g[:-1])
    with pytest.raises(ControlError, match="MeshMotionControl"):
        ShapeInnerProduct(ReducedFunctional(sim, objective, ParameterControl(model, "E")))


def test_mesh_motion_errors():
    dom = _rectangle((4, 2))
    with pytest.raises(ControlError, match="extension"):
        MeshMotion(dom, extension="laplace")
    with pytest.raises(ControlError, match="Poisson"):
        MeshMotion(dom, poisson_ratio=0.5)
    with pytest.raises(ControlError, match="out of range"):
        MeshMotion(dom, np.array([0, 10_000]))
    with pytest.raises(ControlError, match="without design vertices"):
        MeshMotion(dom, lambda x: x[0] > 5.0)
    with pytest.raises(ds.TagError):
        MeshMotion(dom, exclude_facets=[99])
    motion = MeshMotion(dom)
    with pytest.raises(ControlError, match="mass_weight"):
        RieszMap(motion, mass_weight=-1.0)
    with pytest.raises(ControlError, match="length"):
        motion.riesz_map()(np.zeros(3))
