"""The NumericTerm protocol: a new numeric force is one class, nothing else edited.

A linear spring to the ground, E = k/2 sum_i |u_i|^2 over the free dofs, written as a
:class:`~diffsolids.model.NumericTerm` in this file only: the forward solve uses its energy,
residual and Jacobian, the matrix-free adjoint its Hessian action; gradients are checked by
central differences along random directions and along the gradient.
"""

import numpy as np
import pytest
import ufl
from demo_modules import load_docs_example
from gradient_scenes import NEWTON, SCENES, build_model
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import InitialCondition, ParameterControl
from diffsolids.model import NumericTerm
from diffsolids.objectives import Integral, final_value, time_integral
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.states import Phase, StepContext
from diffsolids.verification import finite_difference_check, taylor_test

# the how-to's numeric term (docs/examples/howto_extend.py), checked here in depth
GroundSpring = load_docs_example("howto_extend").GroundSpring


def _spring_simulation(comm, k: float = 2.0e3) -> tuple[ds.Simulation, GroundSpring]:
    model = build_model(SCENES["2d-p1-nh-damped"], comm)
    spring = model.add_numeric_term(GroundSpring(model, k))
    assert type(spring) is GroundSpring and model.numeric_terms[-1] is spring
    v0 = np.array([0.0, 0.3])
    return ds.Simulation(model, ds.BDF(2, 0.05, 4), NEWTON, v0=v0, progress=False), spring


def _reduced(sim) -> ReducedFunctional:
    leaf = Integral(lambda f: ufl.dot(f.u, f.u) * f.dx, "squared displacement")
    objective = time_integral(leaf, "uniform") + final_value(leaf) ** 2
    controls = [ParameterControl(sim.model, "E", "bodies"), InitialCondition(sim, "velocity")]
    return ReducedFunctional(sim, objective, controls)


def _check(rf) -> float:
    q0 = rf.initial_parameters()
    g = rf.gradient(q0)
    rng = np.random.default_rng(1)
    d = rng.standard_normal(len(q0)) * (1e-2 * np.maximum(np.abs(q0), 1e-1))
    steps = np.array([1e-2, 1e-3, 1e-4])
    random = finite_difference_check(rf, q0, d, steps, gradient=g)
    along = finite_difference_check(rf, q0, 1e-2 * g / np.abs(g).max() * np.abs(q0).max(), steps)
    taylor = taylor_test(rf, q0, d, h0=0.5, num=3)
    for res in (random, along):
        assert abs(res.adjoint) > 0 and res.relative_error <= 1e-6, str(res)
    assert taylor.min_rate >= 1.9, str(taylor)
    return float(rf(q0))


def test_a_ground_spring_changes_the_motion_and_its_gradient_is_exact():
    sim, spring = _spring_simulation(MPI.COMM_SELF)
    rf = _reduced(sim)
    value = _check(rf)
    loose = _reduced(_spring_simulation(MPI.COMM_SELF, k=1e-12)[0])
    assert abs(value - loose(loose.initial_parameters())) > 1e-3 * abs(value)  # the spring acts
    u = sim.trajectory.u[-1]
    assert spring.energy(u) == pytest.approx(0.5 * spring.k * float(u @ u))


def test_a_numeric_term_must_declare_the_protocol():
    model = build_model(SCENES["2d-p1-nh-damped"], MPI.COMM_SELF)
    with pytest.raises(ds.ParameterError, match="takes a NumericTerm"):
        model.add_numeric_term(object())
    with pytest.raises(TypeError, match="abstract"):
        type("Incomplete", (NumericTerm,), {})()


def test_a_failed_contact_solve_names_the_contact_state():
    """A barrier far too soft for the load: the error says so and what to do."""
    from diffsolids.contact import ContactTerm
    from diffsolids.mesh import combine_meshes, simplex_box

    dhat = 1e-3
    lower = simplex_box([[0, 0], [1, 0.2]], [4, 1])
    upper = simplex_box([[0.3, 0.2 + 0.5 * dhat], [0.6, 0.5]], [2, 2])
    model = ds.Model(combine_meshes(MPI.COMM_WORLD, [lower, upper]), ds.NeoHookean(E=1e5, nu=0.3))
    model.add_gravity(1e3)
    model.add_dirichlet(lambda x: x[1] < 0.1, 0.0)
    model.add_numeric_term(ContactTerm(model, dhat=dhat, stiffness=1.0))
    options = ds.SolverOptions(max_iterations=8)
    sim = ds.Simulation(model, ds.BDF(1, 0.01, 3), options, progress=False)
    with pytest.raises(ds.NewtonConvergenceError) as info:
        sim.run()
    text = str(info.value)
    assert "Newton steps were cut by a step bound" in text
    assert "contact: kappa = 1, dhat = 0.001" in text
    assert "settles at a distance ~2 kappa dhat^4 / f" in text
    assert "the barrier is too soft for this load" in text


class _PhaseLog(GroundSpring):
    """The ground spring that records the step contexts it is given."""

    def __init__(self, model, k):
        super().__init__(model, k)
        self.seen: list[tuple[int, Phase, float]] = []

    def begin_step(self, context: StepContext) -> None:
        self.seen.append((context.index, context.phase, context.time(context.index)))


def test_numeric_terms_are_told_the_step_and_the_phase():
    model = build_model(SCENES["2d-p1-nh-damped"], MPI.COMM_SELF)
    term = _PhaseLog(model, 2.0e3)
    model.add_numeric_term(term)
    sim = ds.Simulation(model, ds.BDF(2, 0.05, 3), NEWTON, v0=np.array([0.0, 0.3]), progress=False)
    rf = _reduced(sim)
    q0 = rf.initial_parameters()
    rf(q0)
    assert term.seen == [(i, Phase.FORWARD, pytest.approx(0.05 * i)) for i in (1, 2, 3)]
    term.seen.clear()
    rf.gradient(q0)  # the objective's values are known: only the backward sweep sets steps up
    assert [(i, p) for i, p, _ in term.seen] == [(i, Phase.BACKWARD) for i in (3, 2, 1)]


def test_a_begin_step_of_the_old_form_warns_and_still_runs():
    with pytest.warns(DeprecationWarning, match=r"begin_step\(self, context\)"):

        class OldSpring(GroundSpring):
            def begin_step(self, i, traj, coeffs, sim=None):
                self.calls.append((i, len(traj.u), coeffs.dt, sim))

    model = build_model(SCENES["2d-p1-nh-damped"], MPI.COMM_SELF)
    term = OldSpring(model, 2.0e3)
    term.calls = []
    model.add_numeric_term(term)
    ds.Simulation(model, ds.BDF(1, 0.05, 2), NEWTON, progress=False).run()
    assert term.calls == [(1, 1, 0.05, None), (2, 2, 0.05, None)]


def test_simulation_begin_step_is_deprecated():
    sim, _ = _spring_simulation(MPI.COMM_SELF)
    traj = sim.run()
    with pytest.warns(DeprecationWarning, match="prepare_step"):
        step = sim.begin_step(2, traj)
    assert step.index == 2
