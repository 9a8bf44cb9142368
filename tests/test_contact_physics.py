"""Contact physics: friction on an incline, a ball dropped on a slab, self-contact, bad scenes."""

import numpy as np
import pytest
import ufl
from contact_checks import IntersectionMonitor
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.contact import ContactTerm, suggest_barrier_stiffness
from diffsolids.errors import IntersectionError, ParameterError
from diffsolids.mesh import Domain, gmsh_session, tag_facets
from diffsolids.mesh.scene import combine_meshes, simplex_ball, simplex_box
from diffsolids.simulation import Trajectory
from diffsolids.states import StepContext

COMM = MPI.COMM_WORLD
DHAT = 1e-3


def _contact(model, integrator, **kwargs) -> ContactTerm:
    """A contact term with the suggested (fixed) barrier stiffness, added to the model."""
    probe = ContactTerm(model, dhat=DHAT, stiffness=1.0, **kwargs)
    kappa = suggest_barrier_stiffness(probe, integrator)
    contact = ContactTerm(model, dhat=DHAT, stiffness=kappa, **kwargs)
    model.add_numeric_term(contact)
    return contact


def _mean(model, arr, nodes, comp):
    vals = arr.reshape(-1, model.dim)[nodes, comp]
    n = COMM.allreduce(len(vals), op=MPI.SUM)
    return COMM.allreduce(float(vals.sum()), op=MPI.SUM) / n


@pytest.mark.parametrize(("mu", "slides"), [(0.3, True), (0.8, False)])
def test_block_on_incline(mu, slides):
    """tan(30 deg) = 0.577: slides with a = g (sin - mu cos) for mu = 0.3, sticks for 0.8."""
    theta = np.deg2rad(30.0)
    slab = simplex_box([[0, 0], [3, 0.1]], [30, 1])
    block = simplex_box([[0.2, 0.1 + 0.5 * DHAT], [0.4, 0.2 + 0.5 * DHAT]], [4, 2])
    dom = combine_meshes(COMM, [slab, block], names={"slab": 1, "block": 2})
    model = ds.Model(dom, ds.NeoHookean(E=1e7, nu=0.3, density=1000.0))
    model.add_body_force(9.81 * np.array([np.sin(theta), -np.cos(theta)]), name="gravity")
    model.add_dirichlet(lambda x: x[1] < 0.1 + 1e-9, 0.0)
    integ = ds.BDF(2, 0.01, 30)
    eps_v = 1e-3
    contact = _contact(model, integ, friction={("slab", "block"): mu}, eps_v=eps_v)
    assert contact.friction_coefficients[contact.pair_index("slab", "block")] == mu
    traj = ds.Simulation(model, integ, ds.SolverOptions(rtol=1e-9)).run()
    X = model.V.tabulate_dof_coordinates()
    nodes = X[:, 1] > 0.1 + 1e-9
    t = np.array(traj.times)
    ux = np.array([_mean(model, u, nodes, 0) for u in traj.u])
    vx = np.array([_mean(model, v, nodes, 0) for v in traj.v])
    after = t >= 0.1  # after the start-up (normal force lagged from a non-equilibrium gap)
    if slides:
        a = 2 * np.polyfit(t[after], ux[after], 2)[0]
        expected = 9.81 * (np.sin(theta) - mu * np.cos(theta))
        assert abs(a - expected) <= 0.03 * expected
    else:
        assert np.abs(vx[after]).max() < eps_v
    assert all(r.num_collisions > 0 and 0 < r.min_distance < DHAT for r in contact.records[5:])


@pytest.mark.parametrize("dim", [2, 3])
def test_ball_dropped_on_slab(dim):
    """No intersection at any Newton iterate, the ball rebounds, the total energy never grows."""
    if dim == 2:
        slab = simplex_box([[0, 0], [1, 0.1]], [10, 1])
        ball = simplex_ball([0.5, 0.35], 0.2, 0.08)
        steps = 40
    else:
        slab = simplex_box([[0, 0, 0], [1, 1, 0.1]], [4, 4, 1])
        ball = simplex_ball([0.5, 0.5, 0.35], 0.2, 0.1)
        steps = 22
    dom = combine_meshes(COMM, [slab, ball])
    model = ds.Model(dom, ds.NeoHookean(E=1e5, nu=0.3, density=100.0))
    model.add_gravity(9.81)
    model.add_dirichlet(lambda x: x[dim - 1] < 0.1 + 1e-9, 0.0)
    integ = ds.BDF(2, 0.005, steps)
    contact = _contact(model, integ)
    X = model.V.tabulate_dof_coordinates()[:, :dim]
    ball_nodes = X[:, dim - 1] > 0.1 + 1e-9
    v0 = np.zeros((len(X), dim))
    v0[ball_nodes, dim - 1] = -2.0
    sim = ds.Simulation(model, integ, ds.SolverOptions(rtol=1e-9), v0=v0.ravel())
    monitor = IntersectionMonitor(sim, contact)
    traj = sim.run()
    assert monitor.checked > steps and monitor.bad == []
    vz = [_mean(model, v, ball_nodes, dim - 1) for v in traj.v]
    assert min(vz) < -2.0 and max(vz[len(vz) // 2 :]) > 0.5  # fell, hit, came back up
    assert any(r.num_collisions > 0 for r in contact.records)
    f = model.fields
    kinetic = fem.form(0.5 * model.coefficients["density"] * ufl.inner(f.v, f.v) * f.dx)
    potential = [fem.form(t.energy(f)) for t in model.terms]  # elastic + gravity
    energy = []
    for u, v in zip(traj.u, traj.v, strict=True):
        f.u.x.array[:] = u
        f.v.x.array[:] = v
        e = sum(COMM.allreduce(fem.assemble_scalar(F), op=MPI.SUM) for F in (kinetic, *potential))
        energy.append(e + contact.potential.energy(contact._evaluate(u)))
    assert max(energy) <= energy[0] * (1 + 1e-6)


def _c_shape(comm) -> Domain:
    from dolfinx.io import gmsh as gmsh_io

    with gmsh_session() as gmsh:
        if comm.rank == 0:
            outer = gmsh.model.occ.addRectangle(0, 0, 0, 1, 0.5)
            slot = gmsh.model.occ.addRectangle(0.2, 0.2, 0, 0.8, 0.1)
            parts, _ = gmsh.model.occ.cut([(2, outer)], [(2, slot)])
            gmsh.model.occ.synchronize()
            gmsh.model.addPhysicalGroup(2, [t for _, t in parts], 1)
            gmsh.option.setNumber("Mesh.CharacteristicLengthMax", 0.05)
            gmsh.model.mesh.generate(2)
        data = gmsh_io.model_to_mesh(gmsh.model, comm, 0, gdim=2)
    facets = tag_facets(
        data.mesh,
        {
            1: lambda x: np.isclose(x[1], 0.0),
            2: lambda x: np.isclose(x[1], 0.5) & (x[0] > 0.6),
        },
    )
    return Domain.from_mesh(data.mesh, data.cell_tags, facets)


def test_c_shape_closed_by_a_load_never_self_intersects():
    """A load presses the upper arm of a C onto the lower arm (self-contact, static steps)."""
    model = ds.Model(_c_shape(COMM), ds.NeoHookean(E=1e5, nu=0.3, density=100.0))
    model.add_dirichlet(1, 0.0)
    model.add_traction(2, lambda t: np.array([0.0, -2000.0 * t]))
    integ = ds.Static(num_steps=5, dt=0.2)
    contact = _contact(model, integ)
    sim = ds.Simulation(model, integ, ds.SolverOptions(rtol=1e-9))
    monitor = IntersectionMonitor(sim, contact)
    sim.run()
    assert monitor.checked > 5 and monitor.bad == []
    last = contact.records[-1]
    assert last.num_collisions > 0 and 0 < last.min_distance < DHAT
    # the arms of the same body are coupled only through contact: the matrix had to grow
    assert sim.solver.patterns.rebuilds > 0
    # self-contact forces act and react on the same body: their sum vanishes
    f = contact.force_function.x.array
    owned = model.V.dofmap.index_map.size_local * 2
    magnitude = COMM.allreduce(float(np.abs(f[:owned]).sum()), op=MPI.SUM)
    assert magnitude > 0 and np.abs(last.normal_force).max() <= 1e-9 * magnitude


def _two_boxes(overlap: float):
    lower = simplex_box([[0, 0], [1, 0.2]], [4, 1])
    upper = simplex_box([[0.3, 0.2 - overlap], [0.6, 0.5 - overlap]], [2, 2])
    dom = combine_meshes(COMM, [lower, upper], names={"floor": 1, "crate": 2})
    model = ds.Model(dom, ds.LinearElastic(E=1e4, nu=0.3, density=1.0))
    return model, ContactTerm(model, dhat=DHAT, stiffness=1e6)


def _begin(model, contact):
    traj = Trajectory(times=[0.0], u=[np.zeros(len(model.fields.u.x.array))], v=[])
    contact.begin_step(StepContext.of(ds.Static(), 1, traj))


@pytest.mark.parametrize(
    ("overlap", "message"),
    [(0.05, "intersects"), (0.0, "intersects"), (-1e-9 * DHAT, "closer than")],
)
def test_bad_initial_scene_is_refused(overlap, message):
    model, contact = _two_boxes(overlap)
    with pytest.raises(IntersectionError) as err:
        _begin(model, contact)
    text = str(err.value)
    assert "body 1 ('floor') and body 2 ('crate')" in text
    assert message in text


def test_separated_scene_is_accepted_and_parameters_are_checked():
    model, contact = _two_boxes(-0.5 * DHAT)
    _begin(model, contact)
    assert contact.check_configuration(np.zeros((contact.surface.num_vertices, 2))) == (
        pytest.approx(0.5 * DHAT, rel=1e-9)
    )
    with pytest.raises(ParameterError):
        ContactTerm(model, dhat=-1.0, stiffness=1.0)
    with pytest.raises(ParameterError):
        contact.friction_coefficients = [0.1, -0.2, 0.3]
    with pytest.raises(ParameterError):
        contact.friction_coefficients = [0.1, 0.2]
