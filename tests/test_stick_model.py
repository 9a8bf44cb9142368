"""Newton steps that hold sliding friction contacts at stick (contact.energy.stick_model).

The stick model's maps reproduce ipctk's friction gradient, its Hessian change is the
derivative of its gradient change (central differences), and on a disk that lands sliding and
then rolls the revised steps reach the same states in fewer Newton iterations, with an exact
gradient.
"""

import numpy as np
import pytest
from smoothness_scenes import roll

import diffsolids as ds
from diffsolids.contact.energy.stick_model import StickModel
from diffsolids.verification import line_scan


@pytest.fixture(scope="module")
def rolled():
    """The roll scene after 9 steps (sliding and sticking contacts on the slope)."""
    scene = roll(steps=9)
    scene.rf(scene.q0)
    contact = scene.contact
    T = contact.lagging.tangential
    assert T is not None and len(T) > 0
    return contact, StickModel(T, contact.surface.mesh, contact.eps_v)


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
