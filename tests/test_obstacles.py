"""Kinematic obstacles (collision-only geometry, no dofs) in IPC contact and friction.

Physics: a block dropped on a fixed ground segment comes to rest on it with a positive gap at
every step; a belt moving under a block drags it by friction (and does not without); the
obstacle as the boundary of a clamped volume mesh (the former workaround) gives the same
trajectory, fixed and moving. Moving obstacles: the move of a step is collision-free with the
body held, or made together with the body's guess (an elevator carrying a block), or refused
with a clear error. Gradients (shape, friction coefficient, initial velocity) against central
differences along a random direction and along the gradient. Bad input: clear errors.
"""

import numpy as np
import pytest
from mpi4py import MPI
from test_gradients_contact import _direction, check_gradient

import diffsolids as ds
from diffsolids.contact import ContactTerm, Obstacle, suggest_barrier_stiffness
from diffsolids.controls import FrictionControl, InitialCondition, ShapeControl
from diffsolids.errors import IntersectionError, MeshError, ParameterError
from diffsolids.mesh.scene import combine_meshes, simplex_box
from diffsolids.objectives import Integral, final_value, time_integral
from diffsolids.optimize.invariants import BoundaryIntersection, check_trajectories
from diffsolids.reduced_functional import ReducedFunctional

DHAT = 1e-2
NEWTON = ds.SolverOptions(rtol=1e-12)
BLOCK = [[0.2, 0.5 * DHAT], [0.5, 0.15 + 0.5 * DHAT]]
GRAVITY = 9.81


def _material(damped: bool = False):
    damping = {"damping_psi": 10.0, "damping_phi": 1.0} if damped else {}
    return ds.NeoHookean(E=1e5, nu=0.3, density=1000.0, **damping)


def _contact(model, integrator, obstacles, stiffness=None, **kwargs) -> ContactTerm:
    kappa = stiffness
    if kappa is None:
        probe = ContactTerm(model, dhat=DHAT, stiffness=1.0, obstacles=obstacles)
        kappa = suggest_barrier_stiffness(probe, integrator)
    contact = ContactTerm(model, dhat=DHAT, stiffness=kappa, obstacles=obstacles, **kwargs)
    model.add_numeric_term(contact)
    return contact


def block_scene(
    obstacle: Obstacle,
    integrator,
    gravity=(0.0, -GRAVITY),
    block=BLOCK,
    damped: bool = False,
    comm=MPI.COMM_SELF,
    v0=None,
    degree: int = 1,
    **contact_kwargs,
):
    """A block (body 1) over an obstacle; returns (model, contact, simulation)."""
    dom = combine_meshes(comm, [simplex_box(block, [3, 2])], names={"block": 1})
    model = ds.Model(dom, {1: _material(damped)}, degree=degree)
    model.add_body_force(np.asarray(gravity, dtype=float), name="gravity")
    contact = _contact(model, integrator, [obstacle], **contact_kwargs)
    sim = ds.Simulation(model, integrator, NEWTON, v0=v0, progress=False)
    return model, contact, sim


def clamped_scene(motion, integrator, gravity=(0.0, -GRAVITY), comm=MPI.COMM_SELF, **kwargs):
    """The same block over a clamped slab whose top is y = 0 (moved by Dirichlet values)."""
    slab = simplex_box([[-0.5, -0.1], [1.5, 0.0]], [8, 1])
    dom = combine_meshes(comm, [slab, simplex_box(BLOCK, [3, 2])], names={"ground": 1, "block": 2})
    model = ds.Model(dom, {1: _material(), 2: _material()})
    model.add_body_force(np.asarray(gravity, dtype=float), bodies=[2], name="gravity")
    model.add_dirichlet(lambda x: x[1] < 1e-9, motion if motion is not None else 0.0)
    contact = _contact(model, integrator, [], **kwargs)
    sim = ds.Simulation(model, integrator, NEWTON, progress=False)
    return model, contact, sim


def ground(motion=None, name="ground") -> Obstacle:
    """The segment y = 0 from x = -1 to 2 (two vertices)."""
    return Obstacle([[-1.0, 0.0], [2.0, 0.0]], motion=motion, name=name)


def block_positions(contact, u: np.ndarray, body: int) -> np.ndarray:
    """Positions of the collision vertices of ``body``, sorted by rest position."""
    surf = contact.surface
    sel = np.flatnonzero(surf.body == body)
    X = surf.rest_positions[sel]
    order = np.lexsort(X.T[::-1])
    return (X + surf.gather(u)[sel])[order]


def block_velocity(contact, v: np.ndarray, body: int) -> np.ndarray:
    surf = contact.surface
    return surf.gather(v)[surf.body == body].mean(axis=0)


# -- physics ----------------------------------------------------------------------------------
def test_block_comes_to_rest_on_fixed_ground():
    integ = ds.BDF(1, 0.01, 60)  # BDF1 damps the bounces on the barrier
    block = [[0.2, 0.02], [0.5, 0.17]]
    _, contact, sim = block_scene(ground(), integ, block=block, damped=True)
    traj = sim.run()
    gaps = np.array([r.min_distance for r in contact.records])
    touching = np.isfinite(gaps)
    assert touching[-50:].all() and not touching[0], gaps  # lands, then stays in contact
    assert np.all(gaps[touching] > 0)
    lowest = [block_positions(contact, u, 1)[:, 1].min() for u in traj.u]
    assert min(lowest) > 0  # never below the ground
    weight = 1000.0 * 0.3 * 0.15 * GRAVITY
    support = np.mean([r.normal_force[0, 1] for r in contact.records[-10:]])
    assert support == pytest.approx(weight, rel=1e-2)
    impact = abs(block_velocity(contact, traj.v[touching.argmax()], 1)[1])
    assert np.abs(block_velocity(contact, traj.v[-1], 1)).max() < 0.05 * impact
    # the obstacle's reaction is the body's with the opposite sign
    assert np.allclose(contact.records[-1].normal_force[1], -contact.records[-1].normal_force[0])
    assert contact.body_ids == [1, 2] and contact.surface.num_body_vertices == 10


@pytest.mark.parametrize("mu, degree", [(0.0, 1), (0.5, 1), (0.5, 2)])
def test_moving_belt_drags_block(mu, degree):
    speed = 0.5
    integ = ds.BDF(1, 0.01, 8)
    belt = ground(motion=lambda t: np.array([speed * t, 0.0]), name="belt")
    _, contact, sim = block_scene(
        belt, integ, degree=degree, friction={("block", "belt"): mu}, eps_v=1e-3
    )
    traj = sim.run()
    vx = [block_velocity(contact, v, 1)[0] for v in traj.v]
    assert all(np.isfinite(r.min_distance) and r.min_distance > 0 for r in contact.records)
    if mu == 0:  # a frictionless belt sliding along itself is the fixed ground
        assert np.abs([r.friction_force for r in contact.records]).max() == 0
        _, _, fixed = block_scene(ground(), ds.BDF(1, 0.01, 8))
        for u, u_fixed in zip(traj.u, fixed.run().u, strict=True):
            assert np.abs(u - u_fixed).max() <= 1e-12
    else:
        assert np.all(np.diff(vx) > 0) and 0 < vx[-1] <= speed + 1e-9
        assert all(r.friction_force[0, 0] > 0 for r in contact.records)
        assert all(r.friction_force[1, 0] < 0 for r in contact.records)


MOTIONS = {
    # a motion that stays at rest: a fixed obstacle's flat regions act as planes
    # (diffsolids.contact.geometry.flat), the clamped slab's segments one by one; a moving
    # obstacle's segments are taken one by one too, as the slab's
    "at rest": (lambda t: np.zeros(2), 0.0),
    "belt": (lambda t: np.array([0.4 * t, 0.0]), 0.4),
}


@pytest.mark.parametrize("case", sorted(MOTIONS))
def test_same_as_clamped_volume(case):
    """Obstacle = the boundary of the clamped slab: the same collision geometry and weights."""
    motion, _ = MOTIONS[case]
    integ = lambda: ds.BDF(2, 0.01, 6)  # noqa: E731
    kw = {"friction": 0.4, "eps_v": 1e-3}
    slab = simplex_box([[-0.5, -0.1], [1.5, 0.0]], [8, 1])
    obstacle = Obstacle.from_domain(slab, motion=motion, name="ground")
    assert obstacle.num_vertices == 18 and len(obstacle.edges) == 18
    _, c_obs, s_obs = block_scene(obstacle, integ(), **kw)
    _, c_vol, s_vol = clamped_scene(motion, integ(), stiffness=c_obs.stiffness, **kw)
    t_obs, t_vol = s_obs.run(), s_vol.run()
    for u_o, u_v in zip(t_obs.u, t_vol.u, strict=True):
        x_o, x_v = block_positions(c_obs, u_o, 1), block_positions(c_vol, u_v, 2)
        assert np.abs(x_o - x_v).max() <= 1e-9
    for r_o, r_v in zip(c_obs.records, c_vol.records, strict=True):
        assert r_o.num_collisions == r_v.num_collisions > 0
        assert r_o.min_distance == pytest.approx(r_v.min_distance, rel=1e-6)
        assert np.allclose(r_o.normal_force, r_v.normal_force[::-1], rtol=1e-6, atol=1e-6)
    # no dofs for the obstacle: only the block's
    assert s_obs.model.V.dofmap.index_map.size_global < s_vol.model.V.dofmap.index_map.size_global


def test_elevator_moves_block_with_guess():
    """The lift moves into the block by more than the gap per step: moved with the guess."""
    speed = 0.5
    integ = ds.BDF(1, 0.01, 6)
    lift = ground(motion=lambda t: np.array([0.0, speed * t]), name="lift")
    block = [[0.2, 1e-3], [0.5, 0.151]]
    _, contact, sim = block_scene(lift, integ, block=block, gravity=(0, 0), v0=np.array([0, speed]))
    traj = sim.run()
    assert contact.moved_with_guess  # the lift's own move would close the gap
    assert all(r.min_distance > 0 for r in contact.records if np.isfinite(r.min_distance))
    lowest = [block_positions(contact, u, 1)[:, 1].min() for u in traj.u]
    lift_y = [speed * t for t in traj.times]
    assert np.all(np.array(lowest) > np.array(lift_y))


@pytest.mark.parametrize("dynamic", [True, False])
def test_obstacle_faster_than_body_is_refused(dynamic):
    integ = ds.BDF(1, 0.01, 3) if dynamic else ds.Static(num_steps=3, dt=0.01)
    lift = ground(motion=lambda t: np.array([0.0, 1.0 * t]), name="lift")
    gravity = (0, 0) if dynamic else (0, -GRAVITY)
    _, _, sim = block_scene(lift, integ, gravity=gravity)  # block 0.005 above, at rest
    with pytest.raises(IntersectionError, match=r"obstacle 'lift'.*faster than") as info:
        sim.run()
    assert ("quasi-statically" in str(info.value)) != dynamic


def test_invariant_checks_see_obstacles():
    """check_trajectories and ContactTerm.intersects check the obstacle at each state's time."""
    speed = 0.5
    integ = ds.BDF(1, 0.01, 4)
    belt = ground(motion=lambda t: np.array([0.0, -speed * t]), name="sinking")
    _, contact, sim = block_scene(belt, integ, gravity=(0, 0))
    traj = sim.run()
    checks = check_trajectories(sim, [traj], contact)
    assert checks.intersecting == 0 and checks.min_distance > 0
    assert not contact.intersects(traj.u[-1], step=len(traj.u) - 1)
    # the block moved down by 2 cm: through the ground at rest, above it at step 4 (t = 0.04)
    down = np.zeros_like(traj.u[0]).reshape(-1, 2)
    down[:, 1] = -0.02
    state = down.ravel()
    assert contact.intersects(state, step=0) and not contact.intersects(state, step=4)
    moved = ds.Trajectory(times=traj.times, u=[traj.u[0], state, traj.u[2], traj.u[3], state])
    checks = check_trajectories(sim, [moved], contact)
    assert checks.intersecting == 1  # state 1 (t = 0.01, ground at -0.005) only


def test_obstacle_files(tmp_path):
    """Surface files are the obstacle, volume files give their boundary; bad files: errors."""
    import meshio

    X = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [5, 5, 5.0]])
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    meshio.write(tmp_path / "plane.obj", meshio.Mesh(X, [("triangle", tris)]))
    plane = Obstacle.from_file(tmp_path / "plane.obj", scale=2.0, translation=[0, 0, -1])
    assert plane.name == "plane" and plane.dim == 3 and len(plane.faces) == 2
    assert np.allclose(plane.rest_positions, 2.0 * X[:4] + [0, 0, -1])  # unused point dropped
    lines = meshio.Mesh(X[:3, :2], [("line", np.array([[0, 1], [1, 2]]))])
    meshio.write(tmp_path / "curve.vtu", lines)
    curve = Obstacle.from_file(tmp_path / "curve.vtu", dim=2, rotation=90.0)
    assert curve.dim == 2 and len(curve.edges) == 2
    assert np.allclose(curve.rest_positions, [[0, 0], [0, 1], [-1, 1]], atol=1e-15)
    square = meshio.Mesh(X[:4, :2], [("triangle", tris)])
    meshio.write(tmp_path / "square.vtu", square)
    boundary = Obstacle.from_file(tmp_path / "square.vtu", dim=2)
    assert len(boundary.edges) == 4 and boundary.num_vertices == 4
    with pytest.raises(MeshError, match="does not exist"):
        Obstacle.from_file(tmp_path / "missing.obj")
    (tmp_path / "bad.obj").write_text("this is not a mesh")
    with pytest.raises(MeshError, match=r"bad\.obj"):
        Obstacle.from_file(tmp_path / "bad.obj")


# -- errors -------------------------------------------------------------------------------
def _block_model(dim=2, damped=False):
    box = BLOCK if dim == 2 else [[0.2, 0.2, 0.005], [0.5, 0.5, 0.15]]
    dom = combine_meshes(MPI.COMM_SELF, [simplex_box(box, [2] * dim)], names={"block": 1})
    return ds.Model(dom, {1: _material(damped)})


def test_intersecting_obstacle_is_refused():
    model = _block_model()
    through = Obstacle([[0.0, 0.05], [1.0, 0.05]], name="blade")
    contact = ContactTerm(model, dhat=DHAT, stiffness=1e5, obstacles=[through])
    model.add_numeric_term(contact)
    sim = ds.Simulation(model, ds.BDF(1, 0.01, 1), progress=False)
    with pytest.raises(IntersectionError, match="obstacle 'blade'"):
        sim.run()


def test_bad_obstacles():
    model = _block_model()
    plane3d = Obstacle([[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 2]], name="plane")
    with pytest.raises(MeshError, match="obstacle 'plane' is 3D, the model is 2D"):
        ContactTerm(model, dhat=DHAT, stiffness=1.0, obstacles=[plane3d])
    bad = ground(motion=lambda t: np.zeros((3, 2)))
    with pytest.raises(ParameterError, match=r"motion\(0\) returned shape \(3, 2\); expected"):
        ContactTerm(model, dhat=DHAT, stiffness=1.0, obstacles=[bad])
    rigid = ground(motion=lambda t: (np.eye(3), np.zeros(3)))
    with pytest.raises(ParameterError, match=r"returned R \(3, 3\), b \(3,\)"):
        ContactTerm(model, dhat=DHAT, stiffness=1.0, obstacles=[rigid])
    with pytest.raises(ParameterError, match="is taken"):
        ContactTerm(model, dhat=DHAT, stiffness=1.0, obstacles=[ground(name="block")])
    with pytest.raises(ParameterError, match="Obstacle objects"):
        ContactTerm(model, dhat=DHAT, stiffness=1.0, obstacles=[np.zeros((2, 2))])
    with pytest.raises(MeshError, match="vertices of shape"):
        Obstacle(np.zeros((3, 4)))
    with pytest.raises(MeshError, match="needs triangles"):
        Obstacle(np.zeros((3, 3)))
    with pytest.raises(MeshError, match="refer to vertex 5"):
        Obstacle(np.eye(2), edges=[[0, 5]])
    with pytest.raises(MeshError, match="degenerate"):
        Obstacle([[0, 0], [0, 0]])
    with pytest.raises(ParameterError, match="function of time"):
        Obstacle(np.eye(2), motion=np.zeros(2))


def test_motion_forms_agree():
    """Displacement array, translation and rigid pair describe the same placement."""
    X = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    b = np.array([0.1, 0.2, 0.3])
    rigid = Obstacle(X, faces=[[0, 1, 2]], motion=lambda t: (R, t * b))
    array = Obstacle(X, faces=[[0, 1, 2]], motion=lambda t: X @ R.T + t * b - X)
    assert np.allclose(rigid.positions(2.0), array.positions(2.0), atol=1e-15)
    shift = Obstacle(X, faces=[[0, 1, 2]], motion=lambda t: t * b)
    assert np.allclose(shift.positions(2.0), X + 2 * b)


def test_3d_block_on_plane_obstacle():
    """3D: a tetrahedral block lands on a two-triangle plane; gap > 0, no intersection."""
    model = _block_model(3, damped=True)  # the forms of the 3D gradient test (compiled once)
    model.add_body_force(np.array([0.0, 0.0, -GRAVITY]), name="g")
    plane = Obstacle(
        [[-1, -1, 0], [2, -1, 0], [2, 2, 0], [-1, 2, 0]], faces=[[0, 1, 2], [0, 2, 3]], name="p"
    )
    integ = ds.BDF(1, 0.01, 6)
    contact = _contact(model, integ, [plane])
    sim = ds.Simulation(model, integ, NEWTON, progress=False)
    sim.run()
    gaps = [r.min_distance for r in contact.records]
    assert np.isfinite(gaps[-1]) and min(gaps) > 0
    assert contact.records[-1].normal_force[0, 2] > 0


# -- gradients ----------------------------------------------------------------------------
def slide_scene(order: int, comm=MPI.COMM_SELF):
    """A block sliding down (gravity tilted 20 degrees) with friction 0.2 on a fixed segment."""
    theta = np.deg2rad(20.0)
    integ = ds.BDF(order, 0.01, 4)
    g = GRAVITY * np.array([np.sin(theta), -np.cos(theta)])
    model, contact, sim = block_scene(
        ground(), integ, gravity=g, damped=True, comm=comm, friction=0.2, eps_v=1e-2
    )
    objective = final_value(Integral(lambda f: (f.X[0] + f.u[0]) * f.dx(1), "x")) + time_integral(
        Integral(lambda f: f.v[0] * f.v[0] * f.dx(1), "v2")
    )
    return model, contact, sim, objective


def belt_scene(comm=MPI.COMM_SELF):
    """A block on a belt moving at 0.3 (friction 0.3, BDF2)."""
    integ = ds.BDF(2, 0.01, 4)
    belt = ground(motion=lambda t: np.array([0.3 * t, 0.0]), name="belt")
    model, contact, sim = block_scene(
        belt, integ, damped=True, comm=comm, friction={("block", "belt"): 0.3}, eps_v=1e-2
    )
    objective = final_value(Integral(lambda f: (f.X[0] + f.u[0]) * f.dx(1), "x")) + time_integral(
        Integral(lambda f: f.v[1] * f.v[1] * f.dx(1), "vy2")
    )
    return model, contact, sim, objective


def slide_scene_3d(comm=MPI.COMM_SELF):
    """3D: a tetrahedral block sliding (friction 0.2) on a fixed two-triangle plane.

    The plane's diagonal is kept away from under the block: a block edge exactly above a plane
    edge and parallel to it is a degenerate edge-edge pair whose distance has a kink in the
    rest positions (measured there: one-sided differences 2.96e-8 and 3.44e-8).
    """
    theta = np.deg2rad(20.0)
    box = [[0.2, 0.2, 0.5 * DHAT], [0.5, 0.5, 0.15]]
    dom = combine_meshes(comm, [simplex_box(box, [2, 2, 1])], names={"block": 1})
    model = ds.Model(dom, {1: _material(damped=True)})
    model.add_body_force(GRAVITY * np.array([np.sin(theta), 0.0, -np.cos(theta)]), name="g")
    corners = [[-1.3, -1, 0], [2, -1, 0], [2, 2.6, 0], [-1.3, 2.6, 0]]
    plane = Obstacle(corners, faces=[[0, 1, 2], [0, 2, 3]], name="plane")
    integ = ds.BDF(1, 0.01, 3)
    contact = _contact(model, integ, [plane], friction=0.2, eps_v=1e-2)
    sim = ds.Simulation(model, integ, NEWTON, progress=False)
    objective = final_value(Integral(lambda f: (f.X[0] + f.u[0]) * f.dx(1), "x")) + time_integral(
        Integral(lambda f: f.v[0] * f.v[0] * f.dx(1), "v2")
    )
    return model, contact, sim, objective


def _friction_active(contact) -> bool:
    return min(np.abs(r.friction_force[0]).max() for r in contact.records) > 0


def test_shape_gradient_slide_on_fixed_obstacle():
    model, contact, sim, objective = slide_scene(2)
    rf = ReducedFunctional(sim, objective, ShapeControl(model, "all"))
    check_gradient(rf, contact, _direction(rf.size, 1e-4), taylor_h0=0.1)
    assert _friction_active(contact)


def test_shape_gradient_3d_plane_obstacle():
    model, contact, sim, objective = slide_scene_3d()
    rf = ReducedFunctional(sim, objective, ShapeControl(model, "all"))
    check_gradient(rf, contact, _direction(rf.size, 1e-4), taylor_h0=0.1)
    assert _friction_active(contact)


def test_friction_gradient_moving_belt():
    _, contact, sim, objective = belt_scene()
    rf = ReducedFunctional(sim, objective, FrictionControl(contact, pairs=[("block", "belt")]))
    check_gradient(rf, contact, np.array([0.05]), taylor_h0=0.2)
    assert _friction_active(contact)


def test_initial_velocity_gradient_moving_belt():
    _, contact, sim, objective = belt_scene()
    rf = ReducedFunctional(sim, objective, InitialCondition(sim, "velocity"))
    check_gradient(rf, contact, _direction(rf.size, 2e-3))
    assert _friction_active(contact)


def test_boundary_intersection_sees_obstacles():
    """BoundaryIntersection (the optimiser's iterate check) places obstacles at the step's time."""
    integ = ds.BDF(1, 0.01, 4)
    belt = ground(motion=lambda t: np.array([0.0, -0.5 * t]), name="sinking")
    model, _, sim = block_scene(belt, integ, gravity=(0, 0))
    traj = sim.run()  # the steps' times
    check = BoundaryIntersection(model)
    assert not check.intersects()
    assert not check.intersects(traj.u[-1], step=len(traj.u) - 1)
    down = np.zeros(
        model.V.dofmap.index_map.size_local * 2 + model.V.dofmap.index_map.num_ghosts * 2
    )
    down.reshape(-1, 2)[:, 1] = -0.02
    assert check.intersects(down, step=0) and not check.intersects(down, step=4)
