"""Papercuts of issue 12: plain sums over steps, rigid throws of partly clamped bodies,
initial states in the canonical node order of the controls."""

import numpy as np
import pytest
import ufl
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import InitialCondition
from diffsolids.mesh.ordering import CanonicalLayout
from diffsolids.objectives.functional import TimeGrid, step_weights
from diffsolids.simulation import CanonicalValues


def test_sum_weights_are_one_per_computed_step():
    grid = TimeGrid(num_steps=4, dt=0.25, dynamic=True)
    assert np.array_equal(step_weights("sum", grid), [0.0, 1.0, 1.0, 1.0, 1.0])
    assert np.allclose(step_weights("uniform", grid), 0.25 * step_weights("sum", grid))


def _half_clamped_body():
    """A strip clamped at x = 0 only: its other nodes may be thrown rigidly."""
    domain = ds.mesh.create_rectangle(
        MPI.COMM_WORLD, [[0, 0], [1, 0.2]], [6, 2], facets={1: lambda x: np.isclose(x[0], 0.0)}
    )
    model = ds.Model(domain, ds.NeoHookean(E=1e3, nu=0.3, density=10.0))
    model.add_dirichlet(1, 0.0)
    sim = ds.Simulation(model, ds.BDF(1, 0.02, 3), ds.SolverOptions(rtol=1e-13), progress=False)
    return sim, ds.RigidVelocity(sim, 1)


def test_a_rigid_throw_leaves_clamped_nodes_at_rest_and_its_gradient_is_exact():
    sim, throw = _half_clamped_body()
    throw.assign(np.array([0.3, -0.2, 0.5]))
    clamped = sim.model.dirichlet_dofs()
    free = np.setdiff1d(np.arange(len(sim.v0)), clamped)
    comm = MPI.COMM_WORLD
    assert comm.allreduce(len(clamped)) > 0
    assert comm.allreduce(float(np.abs(sim.v0[clamped]).max(initial=0.0)), op=MPI.MAX) == 0.0
    assert comm.allreduce(float(np.abs(sim.v0[free]).max(initial=0.0)), op=MPI.MAX) > 0.1
    leaf = ds.Integral(lambda f: ufl.dot(f.u, f.u) * f.dx, "squared displacement")
    rf = ds.ReducedFunctional(sim, ds.time_integral(leaf, "sum"), [throw])
    q0 = rf.initial_parameters()
    g = rf.gradient(q0)
    for d in (np.array([0.1, -0.05, 0.2]), 0.1 * g / np.abs(g).max()):
        res = ds.finite_difference_check(rf, q0, d, [1e-2, 1e-3], gradient=g)
        assert abs(res.adjoint) > 0 and res.relative_error <= 1e-6, str(res)


@pytest.mark.parametrize("weights", ["sum", "uniform"])
def test_sum_and_uniform_objectives_differ_by_dt(weights):
    sim, throw = _half_clamped_body()
    throw.assign(np.array([0.3, -0.2, 0.5]))
    leaf = ds.Integral(lambda f: ufl.dot(f.u, f.u) * f.dx, "squared displacement")
    rf = ds.ReducedFunctional(sim, ds.time_integral(leaf, weights), [throw])
    j = rf(rf.initial_parameters())
    reference = ds.ReducedFunctional(sim, ds.time_integral(leaf, "sum"), [throw])
    expected = reference(reference.initial_parameters()) * (0.02 if weights == "uniform" else 1.0)
    assert j == pytest.approx(expected, rel=1e-12)


# -- initial states in the canonical node order ---------------------------------------------
def _throw_scene(comm: MPI.Comm) -> ds.Model:
    """An unclamped Neo-Hookean strip (P1) under gravity: the free-flying thrown body."""
    domain = ds.mesh.create_rectangle(comm, [[0, 0], [1, 0.25]], [6, 2])
    model = ds.Model(domain, ds.NeoHookean(E=1e3, nu=0.3, density=10.0))
    model.add_gravity(9.81)
    return model


def _canonical_nodes(model: ds.Model) -> np.ndarray:
    """Node coordinates (num_nodes, dim) in the canonical order of the controls."""
    layout = CanonicalLayout(model.V)
    x = model.V.tabulate_dof_coordinates()[: layout.num_owned, : model.dim]
    return layout.gather(x.ravel()).reshape(-1, model.dim)


def _velocity(x: np.ndarray) -> np.ndarray:
    """A spinning throw v(x) = (0.3 - 0.4 x1, 0.2 + 0.4 x0) on x of shape (dim, n)."""
    return np.stack([0.3 - 0.4 * x[1], 0.2 + 0.4 * x[0]])


def _displacement(x: np.ndarray) -> np.ndarray:
    return np.stack([0.01 * x[0] * x[1], -0.02 * x[0] ** 2])


def _canonical_run(comm: MPI.Comm) -> tuple[ds.Simulation, np.ndarray]:
    """A BDF2 run from canonical u0, v0; the final state gathered in the canonical order."""
    model = _throw_scene(comm)
    nodes = _canonical_nodes(model)
    sim = ds.Simulation(
        model,
        ds.BDF(2, 0.02, 3),
        ds.SolverOptions(rtol=1e-12),
        u0=CanonicalValues(_displacement(nodes.T).T),  # (num_nodes, dim) is accepted
        v0=CanonicalValues(_velocity(nodes.T).T.ravel()),  # so is the flat vector
        progress=False,
    )
    traj = sim.run()
    layout = CanonicalLayout(model.V)
    return sim, np.concatenate([layout.gather(traj.u[-1]), layout.gather(traj.v[-1])])


def test_canonical_initial_state_is_the_nodal_field_and_the_control_order():
    sim, _ = _canonical_run(MPI.COMM_WORLD)
    comm = sim.model.domain.comm
    # the same field as the functions of x the canonical values were sampled from
    by_function = ds.Simulation(
        sim.model, sim.integrator, u0=_displacement, v0=_velocity, progress=False
    )
    assert comm.allreduce(float(np.abs(sim.v0 - by_function.v0).max()), op=MPI.MAX) < 1e-15
    assert comm.allreduce(float(np.abs(sim.u0 - by_function.u0).max()), op=MPI.MAX) < 1e-15
    assert comm.allreduce(float(np.abs(sim.v0).max()), op=MPI.MAX) > 0.2
    # the order of the initial-condition controls: their value is the canonical input back
    nodes = _canonical_nodes(sim.model)
    velocity = InitialCondition(sim, "velocity")
    assert np.array_equal(velocity.value(), _velocity(nodes.T).T.ravel())
    other = ds.Simulation(sim.model, sim.integrator, progress=False)
    InitialCondition(other, "velocity").assign(velocity.value())
    assert np.array_equal(other.v0, sim.v0)


def test_canonical_initial_state_gives_the_serial_run_on_every_rank_count():
    """The run from canonical u0, v0 on COMM_WORLD equals the run of the same values on each
    rank alone (COMM_SELF), compared in the canonical order (run under mpiexec -n 2 too)."""
    _, parallel = _canonical_run(MPI.COMM_WORLD)
    _, serial = _canonical_run(MPI.COMM_SELF)
    scale = np.abs(serial).max()
    assert scale > 0.1
    assert np.abs(parallel - serial).max() <= 1e-12 * scale


def test_canonical_values_are_checked():
    model = _throw_scene(MPI.COMM_WORLD)
    integ = ds.BDF(1, 0.02, 2)
    n = CanonicalLayout(model.V).size
    with pytest.raises(ds.ParameterError, match=rf"v0: canonical values need {n} entries"):
        ds.Simulation(model, integ, v0=CanonicalValues(np.zeros(n + 2)))
    bad = np.zeros(n)
    bad[3] = np.nan
    with pytest.raises(ds.ParameterError, match="initial displacement u0 has non-finite"):
        ds.Simulation(model, integ, u0=CanonicalValues(bad))
    with pytest.raises(ds.ParameterError, match="an initial velocity needs a dynamic"):
        ds.Simulation(model, ds.Static(), v0=CanonicalValues(np.zeros(n)))
