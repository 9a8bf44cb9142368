"""A contact term without a given barrier stiffness chooses kappa itself, once."""

import numpy as np
import pytest
from mpi4py import MPI

import diffsolids as ds
from diffsolids.contact import ContactTerm, suggest_barrier_stiffness
from diffsolids.controls import InitialCondition, ParameterControl


def _scene(stiffness=None, comm=MPI.COMM_SELF, dynamic=True):
    slab = ds.mesh.simplex_box([[0, 0], [1, 0.1]], [8, 1])
    block = ds.mesh.simplex_box([[0.3, 0.1 + 5e-4], [0.6, 0.3]], [3, 2])
    domain = ds.combine_meshes(comm, [slab, block], names={"slab": 1, "block": 2})
    model = ds.Model(domain, ds.NeoHookean(E=2e4, nu=0.3, density=100.0))
    model.add_gravity(9.81)
    model.add_dirichlet(lambda x: x[1] < 0.05, 0.0)
    integrator = ds.BDF(1, 0.01, 3) if dynamic else ds.Static(num_steps=2, dt=0.5)
    contact = ContactTerm(model, dhat=1e-3, stiffness=stiffness, friction=0.2)
    model.add_numeric_term(contact)
    sim = ds.Simulation(model, integrator, ds.SolverOptions(rtol=1e-12), progress=False)
    return model, contact, sim


@pytest.mark.parametrize("dynamic", [True, False], ids=["bdf1", "static"])
def test_chosen_stiffness_is_the_suggested_one(dynamic):
    model, contact, sim = _scene(dynamic=dynamic)
    assert contact.stiffness is None
    traj = sim.run()
    probe = ContactTerm(model, dhat=1e-3, stiffness=1.0, friction=0.2)
    expected = suggest_barrier_stiffness(probe, sim.integrator)
    assert contact.stiffness == pytest.approx(expected, rel=1e-12)
    # the same run as with that kappa given
    _, _, sim_given = _scene(stiffness=contact.stiffness, dynamic=dynamic)
    given = sim_given.run()
    assert max(np.abs(a - b).max() for a, b in zip(traj.u, given.u, strict=True)) < 1e-12


def test_stiffness_stays_fixed_across_runs_and_gradients_match():
    model, contact, sim = _scene()
    controls = [InitialCondition(sim, "velocity"), ParameterControl(model, "E", "bodies", log=True)]
    height = ds.Integral(lambda f: (f.X[1] + f.u[1]) * f.dx(2), "height of block")
    rf = ds.ReducedFunctional(sim, ds.final_value(height), controls)
    q0 = rf.initial_parameters()
    g = rf.gradient(q0)
    kappa = contact.stiffness
    assert kappa is not None
    rng = np.random.default_rng(3)
    d = np.concatenate([1e-2 * rng.standard_normal(q0.size - 2), 0.05 * rng.standard_normal(2)])
    along = g * (0.05 / np.abs(g).max())
    for direction in (d, along):
        result = ds.finite_difference_check(rf, q0, direction, [1e-2, 1e-3], gradient=g)
        assert result.relative_error <= 1e-6, str(result)
    assert contact.stiffness == kappa  # perturbed runs kept the kappa of the first one


def test_bad_stiffness_is_refused():
    with pytest.raises(ds.ParameterError, match=r"contact stiffness = -1\.0 must be positive"):
        _scene(stiffness=-1.0)
