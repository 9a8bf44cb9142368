"""Newton steps that hold sliding friction contacts at stick (contact.energy.stick_model).

The lagged friction arrays equal ipctk's tangential collisions read one by one (2D and 3D, every
collision type, area-weighted or not, per-pair coefficients), the stick model's maps reproduce
ipctk's friction gradient, its Hessian change is the
derivative of its gradient change (central differences), and on a disk that lands sliding and
then rolls the revised steps reach the same states in fewer Newton iterations, with an exact
gradient.
"""

import numpy as np
import pytest
from mpi4py import MPI
from smoothness_scenes import roll
from test_contact_kernels import _scene

import diffsolids as ds
from diffsolids.contact.energy.lagged_arrays import friction_arrays
from diffsolids.contact.energy.stick_model import StickModel
from diffsolids.verification import line_scan


def _stick_model(contact) -> StickModel:
    """The stick model of the contact's current step, from its lagged friction arrays."""
    lagging = contact.lagging
    x, C = lagging.lagged_state()
    potential = contact.potential
    arrays = friction_arrays(
        C,
        contact.surface.mesh,
        x,
        potential.barrier,
        potential.stiffness,
        lagging.mu_table(lagging.mu),
        contact.surface.body_index,
    )
    return StickModel(arrays, contact.surface.num_vertices, contact.eps_v)


def _reference_maps(T, mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """dofs, P^T Gamma and w mu N of every collision, read from ipctk one by one."""
    dim, n = mesh.dim, len(T)
    dofs = np.full((n, 4 * dim), -1, dtype=np.int64)
    maps = np.zeros((n, dim - 1, 4 * dim))
    coefficients = np.zeros(n)
    for k, c in enumerate(T):
        ids = np.asarray(c.vertex_ids(mesh.edges, mesh.faces))
        nd = int(np.count_nonzero(ids >= 0)) * dim
        dofs[k, :nd] = (ids[ids >= 0, None] * dim + np.arange(dim)).ravel()
        G = np.asarray(c.relative_velocity_jacobian(c.closest_point))[:, :nd]
        maps[k, :, :nd] = np.asarray(c.tangent_basis).T @ G
        coefficients[k] = c.weight * c.mu_k * c.normal_force_magnitude
    return dofs, maps, coefficients


@pytest.mark.parametrize(
    ("dim", "formulation"), [(2, "ipc"), (3, "ipc"), (2, "convergent"), (3, "convergent")]
)
def test_friction_arrays_equal_ipctk_collisions(dim, formulation):
    _, contact, _, u, _ = _scene(dim, 1, 1, 0.5, comm=MPI.COMM_SELF, formulation=formulation)
    contact.set_friction(1, 2, 0.3)
    contact.set_friction(1, 1, 0.7)
    ev = contact._evaluate(u)
    T = ev.friction
    assert T is not None and len(T) > 0
    kinds = [len(g) > 0 for g in (T.vv_collisions, T.ev_collisions, T.ee_collisions)]
    assert sum(kinds) + (len(T.fv_collisions) > 0) >= 2  # more than one collision type
    dofs, maps, coefficients = _reference_maps(T, contact.surface.mesh)
    model = _stick_model(contact)
    assert np.array_equal(model.dofs, dofs)
    assert np.abs(model.maps - maps).max() <= 1e-12 * np.abs(maps).max()
    assert np.abs(coefficients).max() > 0
    assert np.abs(model.coefficients - coefficients).max() <= 1e-12 * coefficients.max()


@pytest.fixture(scope="module")
def rolled():
    """The roll scene after 9 steps (sliding and sticking contacts on the slope)."""
    scene = roll(steps=9)
    scene.rf(scene.q0)
    contact = scene.contact
    T = contact.lagging.tangential
    assert T is not None and len(T) > 0
    return contact, _stick_model(contact)


def _velocities(contact, scale, seed):
    n, dim = contact.surface.num_vertices, contact.surface.dim
    return scale * np.random.default_rng(seed).standard_normal((n, dim))


@pytest.mark.parametrize("scale", [1.0, 1e-5])  # sliding (|tau| >> eps_v) and stuck
def test_maps_reproduce_ipctk_friction_gradient(rolled, scale):
    contact, model = rolled
    V = _velocities(contact, scale, seed=3)
    tau = model.tangential_velocities(V)
    y = np.linalg.norm(tau, axis=1)
    eps = contact.eps_v
    f1_over_y = np.where(y < eps, (2.0 - y / eps) / eps, 1.0 / np.maximum(y, eps))
    ours = np.zeros(model.size + 1)
    per = np.einsum("kia,ki->ka", model.maps, (model.coefficients * f1_over_y)[:, None] * tau)
    np.add.at(ours, model.dofs.ravel(), per.ravel())
    mesh = contact.surface.mesh
    theirs = contact.friction_potential.gradient(contact.lagging.tangential, mesh, V)
    assert np.abs(theirs).max() > 0
    assert np.allclose(ours[:-1], theirs, rtol=1e-10, atol=1e-12 * np.abs(theirs).max())


@pytest.mark.parametrize("along", ["random", "gradient"])
@pytest.mark.parametrize("scale", [1.0, 1e-5])
def test_hessian_change_is_the_derivative_of_the_gradient_change(rolled, scale, along):
    """ipctk's friction Hessian + hessian_change = d/dV (ipctk's gradient + gradient_change),
    in a random direction and along that gradient itself."""
    contact, model = rolled
    T, mesh = contact.lagging.tangential, contact.surface.mesh
    held = np.random.default_rng(5).random(len(T)) < 0.6
    assert held.any() and not held.all()

    def gradient(V):
        g = contact.friction_potential.gradient(T, mesh, V)
        return g + model.gradient_change(V, held)

    V = _velocities(contact, scale, seed=7)
    d = _velocities(contact, scale, seed=8)
    if along == "gradient":
        g = gradient(V)
        d = (np.linalg.norm(d) / np.linalg.norm(g)) * g.reshape(d.shape)
    H = contact.friction_potential.hessian(T, mesh, V) + model.hessian_change(V, held)
    h = 1e-6
    fd = (gradient(V + h * d) - gradient(V - h * d)) / (2 * h)
    exact = H @ d.ravel()
    assert np.linalg.norm(exact) > 0
    assert np.linalg.norm(fd - exact) <= 1e-6 * np.linalg.norm(exact)


def test_held_collisions_are_the_reversed_sliding_ones(rolled):
    contact, model = rolled
    V = _velocities(contact, 1.0, seed=11)
    tau = model.tangential_velocities(V)
    reversed_ = model.reversed(V, -2.0 * V)  # every slip reversed
    sliding = np.linalg.norm(tau, axis=1) >= contact.eps_v
    assert np.array_equal(reversed_, sliding)
    assert not model.reversed(V, 0.5 * V).any()  # slowed down, not reversed


def test_revised_steps_reach_the_same_states_in_fewer_newton_iterations():
    revised = roll()
    plain = roll(solver_options=ds.SolverOptions(revise_steps=False))
    J, Jp = revised.rf(revised.q0), plain.rf(plain.q0)
    assert abs(J - Jp) <= 1e-9 * abs(Jp)
    u, up = revised.rf.trajectory.u[-1], plain.rf.trajectory.u[-1]
    assert np.abs(u - up).max() <= 1e-8
    its = [r.iterations for r in revised.rf.trajectory.records]
    its_plain = [r.iterations for r in plain.rf.trajectory.records]
    assert max(its) < 0.5 * max(its_plain), (its, its_plain)
    assert sum(its) < 0.7 * sum(its_plain), (its, its_plain)
    assert revised.rf.simulation.solver.revised_steps > 0
    assert plain.rf.simulation.solver.revised_steps == 0


def test_roll_gradient_random_and_along_gradient():
    scene = roll(steps=30)
    J, d = scene.check_gradient(1e-6, seed=2, rtol=1e-5)
    scan = line_scan(scene.rf, scene.q0, d, scene.radius, 7)
    assert len(scan.jumps) == 0, str(scan)
    assert scene.rf(scene.q0) == J
