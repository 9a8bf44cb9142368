"""Papercuts of issue 12: plain sums over steps, rigid throws of partly clamped bodies."""

import numpy as np
import pytest
import ufl
from mpi4py import MPI

import diffsolids as ds
from diffsolids.objectives.functional import TimeGrid, step_weights


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
