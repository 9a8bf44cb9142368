"""A material field with thousands of parameters: the gradient costs one backward sweep with one
linear solve per step whatever the number of parameters (counted, not timed); it matches
finite differences; forward runs and gradients are reproducible."""

import numpy as np
import pytest
from mpi4py import MPI

import diffsolids as ds
from diffsolids.adjoint import BackwardSweep
from diffsolids.controls import ParameterControl
from diffsolids.mesh import create_rectangle
from diffsolids.objectives import final_value, stress_lp_norm, target_displacement, time_integral
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.verification import check_reproducible, finite_difference_check

FD_TOLERANCE = 1e-6


@pytest.fixture(scope="module")
def plate():
    """A 4 x 1 Neo-Hookean plate with 2400 cells, clamped left, pulled down on the right."""
    dom = create_rectangle(
        MPI.COMM_SELF,
        [[0, 0], [4, 1]],
        [60, 20],
        facets={1: lambda x: np.isclose(x[0], 0), 2: lambda x: np.isclose(x[0], 4)},
    )
    model = ds.Model(dom, ds.NeoHookean(E=500.0, nu=0.3, density=1.0, damping_psi=0.2))
    model.add_gravity(2.0)
    model.add_traction(2, [0.0, -5.0])
    model.add_dirichlet(1, 0.0)
    return model


@pytest.fixture(scope="module", params=["static", "bdf2"])
def simulation(request, plate):
    if request.param == "static":
        return ds.Simulation(plate, ds.Static(), ds.SolverOptions(rtol=1e-13), progress=False)
    return ds.Simulation(
        plate, ds.BDF(2, 0.05, 3), ds.SolverOptions(rtol=1e-13), v0=[0.0, 0.2], progress=False
    )


def _objective(model, dynamic: bool):
    stress = stress_lp_norm(model, 4)
    tip = target_displacement(model, [0.0, -0.1], facets=2)
    if dynamic:
        return time_integral(stress, "uniform") + 10.0 * time_integral(tip, "trapezoidal")
    return final_value(stress) + 10.0 * final_value(tip)


class _Counter:
    """Counts calls of methods of objects (by wrapping the bound methods)."""

    def __init__(self, monkeypatch):
        self.monkeypatch, self.counts = monkeypatch, {}

    def wrap(self, obj, name, label):
        original = getattr(obj, name)

        def counted(*args, **kwargs):
            self.counts[label] = self.counts.get(label, 0) + 1
            return original(*args, **kwargs)

        self.monkeypatch.setattr(obj, name, counted)


def _gradient_work(monkeypatch, rf, q):
    """Counts of sweeps, adjoint linear solves, vector assemblies and Newton solves of one
    gradient (the forward run at q is done before counting)."""
    rf(q)
    rf.derivative()  # builds (compiles) the sweep
    counter = _Counter(monkeypatch)
    counter.wrap(BackwardSweep, "run", "sweeps")
    counter.wrap(rf.simulation.solver, "solve", "newton")
    counter.wrap(rf._sweep.linear, "solve", "adjoint solves")
    counter.wrap(rf._sweep, "_assemble", "assemblies")
    g = rf.derivative()
    monkeypatch.undo()
    return g, counter.counts


def test_cost_independent_of_number_of_parameters(monkeypatch, simulation):
    model = simulation.model
    objective = _objective(model, simulation.integrator.dynamic)
    field = ParameterControl(model, "E", "field", log=True)
    uniform = ParameterControl(model, "E", "uniform", log=True)
    assert field.size == 2400 and uniform.size == 1
    counts = {}
    for control in (field, uniform):
        rf = ReducedFunctional(simulation, objective, [control])
        q = rf.initial_parameters()
        g, counts[control.size] = _gradient_work(monkeypatch, rf, q)
        assert g.shape == (control.size,)
    steps = simulation.integrator.num_steps
    assert counts[2400]["sweeps"] == 1
    assert counts[2400]["adjoint solves"] == steps
    assert "newton" not in counts[2400]  # no forward run inside the gradient
    assert counts[2400] == counts[1]


def test_field_gradient_matches_finite_differences(simulation):
    model = simulation.model
    control = ParameterControl(model, "E", "field", log=True)
    rf = ReducedFunctional(simulation, _objective(model, simulation.integrator.dynamic), [control])
    q0 = rf.initial_parameters()
    try:
        g = rf.gradient(q0)
        assert np.count_nonzero(g) == g.size  # every cell matters
        rng = np.random.default_rng(7)
        steps = [1e-1, 1e-2, 1e-3]
        for direction in (0.05 * rng.standard_normal(q0.size), g * (0.05 / np.abs(g).max())):
            res = finite_difference_check(rf, q0, direction, steps, gradient=g)
            assert res.relative_error <= FD_TOLERANCE, res
    finally:
        rf.controls.assign(q0)


def test_reproducible(simulation):
    """Two forward runs give bit-identical J, two sweeps bit-identical gradients."""
    model = simulation.model
    control = ParameterControl(model, "E", "field", log=True)
    rf = ReducedFunctional(simulation, _objective(model, simulation.integrator.dynamic), [control])
    q0 = rf.initial_parameters()
    q = q0 + 0.1 * np.random.default_rng(8).standard_normal(q0.size)
    try:
        J = check_reproducible(rf, q)
        g1 = rf.derivative()
        g2 = rf.derivative()
        rf.forward(q)
        g3 = rf.derivative()
        assert rf(q) == J
        assert np.array_equal(g1, g2) and np.array_equal(g1, g3)
    finally:
        rf.controls.assign(q0)
