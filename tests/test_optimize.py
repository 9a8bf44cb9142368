"""L-BFGS optimiser: convergence, bounds, validity of iterates, failures, hooks, output."""

import itertools
import json
import logging

import numpy as np
import pytest
import ufl
from mpi4py import MPI
from optimize_script import (
    E_TRUE,
    bar_problem,
    check_observed_run,
    contact_problem,
    dynamic_problem,
    observed_run,
    shape_problem,
)

import diffsolids as ds
from diffsolids.errors import MeshError, NewtonConvergenceError, ParameterError
from diffsolids.mesh import signed_cell_volumes
from diffsolids.optimize import (
    LBFGS,
    LBFGSMemory,
    LBFGSOptions,
    OptimizationError,
    OptimizationWarning,
    minimize,
)
from diffsolids.optimize.bounds import projected_gradient


@pytest.fixture(scope="module")
def bar1():
    return bar_problem(MPI.COMM_WORLD, bodies=1)


# -- L-BFGS memory ------------------------------------------------------------------------------
def test_memory_satisfies_secant_equations_and_recovers_quadratic_inverse():
    rng = np.random.default_rng(1)
    n = 5
    A = rng.standard_normal((n, n))
    H_true = A @ A.T + n * np.eye(n)  # SPD Hessian of a quadratic
    # H-conjugate steps (those of exact line searches): s_k = L^-T Q e_k with H = L L^T
    L = np.linalg.cholesky(H_true)
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    steps = np.linalg.solve(L.T, Q).T
    mem = LBFGSMemory(n)
    for s in steps:
        assert mem.update(s, H_true @ s)
    g = rng.standard_normal(n)
    # n conjugate pairs of a quadratic: BFGS reproduces the inverse Hessian exactly
    assert np.allclose(mem.apply(g), np.linalg.solve(H_true, g), rtol=1e-8)
    # secant equation of the newest pair holds for any memory size
    small = LBFGSMemory(2)
    for _ in range(4):
        s = rng.standard_normal(n)
        small.update(s, H_true @ s)
    assert np.allclose(small.apply(small.y[-1]), small.s[-1], rtol=1e-10)
    # negative curvature is skipped; the masked direction stays on the free set
    assert not small.update(np.ones(n), -np.ones(n))
    free = np.array([True, False, True, True, False])
    d = small.apply(g, free)
    assert np.all(d[~free] == 0) and float(g[free] @ d[free]) > 0


def test_memory_with_inner_product_uses_it_as_initial_inverse():
    M = np.array([[4.0, 1.0], [1.0, 2.0]])
    mem = LBFGSMemory(3, inner_product=lambda g: np.linalg.solve(M, g))
    g = np.array([1.0, -2.0])
    assert np.allclose(mem.apply(g), np.linalg.solve(M, g))
    # gamma scaling: H0 = gamma M^-1 with gamma = s.y / (y.M^-1 y) after one pair
    s, y = np.array([1.0, 0.5]), np.array([2.0, 0.3])
    mem.update(s, y)
    Hy = mem.apply(y)
    assert np.allclose(Hy, s)  # secant equation


# -- convergence on a problem with a known optimum ------------------------------------------------
def test_recovers_youngs_modulus_in_few_iterations(bar1):
    rf, _ = bar1
    q0 = rf.initial_parameters()
    result = minimize(rf, q0, LBFGSOptions(gradient_rtol=1e-8))
    E = np.exp(result.q)
    assert result.converged, result
    assert abs(E[0] - E_TRUE[0]) <= 1e-6 * E_TRUE[0], E
    assert result.iterations <= 10  # 8 here: a factor 2 off, unit first step in log E
    J = [r.objective for r in result.history]
    assert all(b < a for a, b in itertools.pairwise(J))  # monotone decrease
    assert J[-1] <= 1e-12 * J[0]
    # the model holds the optimum after the run
    assert np.allclose(rf.controls.value(), result.q)
    rf.controls.assign(q0)


def _with_bounds(rf, lower, upper):
    from diffsolids.controls import ParameterControl
    from diffsolids.reduced_functional import ReducedFunctional

    control = ParameterControl(rf.model, "E", "bodies", log=True, lower=lower, upper=upper)
    return ReducedFunctional(rf.simulation, rf.objective, control)


def test_bounds_and_max_change_are_respected_at_every_iterate(bar2):
    # the truth of body 1 (log 2000) lies beyond the upper bound log 1500
    upper = np.array([np.log(1500.0), np.log(5000.0)])
    lower = np.log([200.0, 200.0])
    rf = _with_bounds(bar2[0], lower, upper)
    q0 = rf.initial_parameters()
    result = minimize(
        rf,
        q0,
        LBFGSOptions(gradient_rtol=1e-9, max_change=0.25, max_iterations=60),
        write_parameters=True,
    )
    qs = np.array([r.q for r in result.history])
    assert np.all(qs >= lower) and np.all(qs <= upper)
    assert np.all(np.abs(np.diff(qs, axis=0)).max(axis=1) <= 0.25 * (1 + 1e-12))
    assert result.converged, result
    assert result.q[0] == upper[0]  # active bound, exactly on it
    g = result.gradient
    assert g[0] < 0  # the objective still wants a larger E_1: the bound is active
    pg = projected_gradient(result.q, g, lower, upper)
    assert np.linalg.norm(pg) <= 1e-9 * result.history[0].gradient_norm
    # the free parameter is optimal for E_1 at its bound: J does not decrease along E_2
    J = result.objective
    for h in (1e-3, -1e-3):
        assert rf(result.q + np.array([0.0, h])) >= J
    rf.controls.assign(q0)


def test_initial_step_and_inner_product_shape_the_first_step(bar2):
    rf, _ = bar2
    q0 = rf.initial_parameters()
    M = np.array([[1.0, 0.0], [0.0, 25.0]])
    calls = []

    def riesz(g):
        calls.append(1)
        return np.linalg.solve(M, g)

    g0 = rf.gradient(q0)
    first_step = LBFGSOptions(initial_step=0.1, max_iterations=1)
    result = minimize(rf, q0, first_step, inner_product=riesz, write_parameters=True)
    step = np.array(result.history[1].q) - q0
    d = -np.linalg.solve(M, g0)
    assert calls
    assert np.allclose(step / np.abs(step).max(), d / np.abs(d).max(), rtol=1e-10)
    assert np.isclose(np.abs(step).max(), 0.1, rtol=1e-12)  # max-norm of the first step
    # with the inner product the run still converges
    full = minimize(rf, q0, LBFGSOptions(gradient_rtol=1e-8), inner_product=riesz)
    assert full.converged
    assert np.allclose(np.exp(full.q), E_TRUE, rtol=1e-6)
    rf.controls.assign(q0)


# -- validity of iterates -------------------------------------------------------------------------
def test_no_inverted_iterate_is_ever_accepted():
    rf, control = shape_problem(MPI.COMM_WORLD)
    model = rf.model
    mesh = model.domain.mesh
    signs = model.reference_signs
    checked = []

    def mesh_is_valid(rec, opt):
        vol = signed_cell_volumes(mesh) * signs
        checked.append(MPI.COMM_WORLD.allreduce(float(vol.min()), op=MPI.MIN))
        assert np.allclose(control.value(), opt.point.q)  # the mesh shows the accepted q
        return False

    result = minimize(rf, options=LBFGSOptions(max_iterations=6), stop_conditions=[mesh_is_valid])
    assert result.num_invalid_trials > 0  # long steps were tried and refused
    assert sum(r.invalid_trials for r in result.history) == result.num_invalid_trials
    assert len(checked) == len(result.history)
    assert min(checked) > 0
    J = [r.objective for r in result.history]
    assert all(b < a for a, b in itertools.pairwise(J))


def test_no_intersecting_iterate_is_ever_accepted(caplog):
    rf, contact = contact_problem(MPI.COMM_WORLD)
    rest = np.zeros_like(contact.surface.rest_positions)
    distances = []

    def rest_shape_is_free(rec, opt):
        # raises IntersectionError for an intersecting or touching rest configuration
        distances.append(contact.check_configuration(rest))
        return False

    with caplog.at_level(logging.INFO, logger="diffsolids"):
        result = minimize(
            rf,
            options=LBFGSOptions(max_iterations=6, initial_step=0.25, max_change=0.25),
            stop_conditions=[rest_shape_is_free],
        )
    refused = [r.getMessage() for r in caplog.records if "invalid trial" in r.getMessage()]
    assert result.num_invalid_trials == len(refused) > 0
    assert any("IntersectionError" in m for m in refused)
    assert len(distances) == len(result.history) and min(distances) > 0
    J = [r.objective for r in result.history]
    assert all(b < a for a, b in itertools.pairwise(J))
    # the block came down into the barrier zone (within dhat = 0.02 of the slab)
    assert distances[-1] < 0.02 < distances[0]


def _failing_run(rf, predicate):
    """Make the simulation raise NewtonConvergenceError when predicate(E) holds."""
    sim = rf.simulation
    run = sim.run
    E = rf.model.coefficients["E"]

    def guarded():
        if predicate(float(E.x.array.max())):
            raise NewtonConvergenceError(1, 50, 1.0, 1e-9, "DIVERGED_MAX_IT (test)")
        return run()

    sim.run = guarded
    return run


def test_failed_forward_solves_are_invalid_trials(bar1):
    rf, _ = bar1
    q0 = rf.initial_parameters()
    run = _failing_run(rf, lambda E: E > 2200.0)
    try:
        result = minimize(
            rf, q0, LBFGSOptions(initial_step=3.0, gradient_rtol=1e-8), write_parameters=True
        )
    finally:
        rf.simulation.run = run
    assert result.history[1].invalid_trials >= 2  # e^3 and e^1.5 times 1000 exceed 2200
    assert all(np.exp(r.q[0]) <= 2200.0 for r in result.history)
    assert result.converged
    assert abs(np.exp(result.q[0]) - E_TRUE[0]) <= 1e-6 * E_TRUE[0]
    rf.controls.assign(q0)


def test_model_is_restored_when_no_valid_step_exists(bar1):
    rf, _ = bar1
    q0 = rf.initial_parameters()
    E0 = float(np.exp(q0[0]))
    run = _failing_run(rf, lambda E: not np.isclose(E, E0, rtol=1e-14))
    try:
        with pytest.warns(OptimizationWarning, match="line search"):
            result = minimize(rf, q0, LBFGSOptions(max_trials=4))
    finally:
        rf.simulation.run = run
    assert result.reason == "line_search"
    assert result.iterations == 0
    assert result.num_invalid_trials == 4  # no memory to reset at the first iteration
    assert np.array_equal(result.q, q0)
    assert np.allclose(rf.model.coefficients["E"].x.array, E0, rtol=1e-14)
    assert np.array_equal(rf.controls.value(), q0)


# -- stopping -----------------------------------------------------------------------------------
def test_stopping_criteria_and_reasons(bar2):
    rf, _ = bar2
    q0 = rf.initial_parameters()
    r = minimize(rf, q0, LBFGSOptions(max_iterations=3, gradient_rtol=0))
    assert (r.reason, r.iterations, r.converged) == ("max_iterations", 3, False)
    r = minimize(rf, q0, LBFGSOptions(gradient_atol=1e-3, gradient_rtol=0))
    assert r.reason == "gradient_atol" and r.history[-1].gradient_norm <= 1e-3
    assert r.history[-2].gradient_norm > 1e-3
    r = minimize(rf, q0, LBFGSOptions(step_tol=0.05, gradient_rtol=0))
    assert r.reason == "step" and r.history[-1].step_norm <= 0.05
    assert all(h.step_norm > 0.05 for h in r.history[1:-1])
    r = minimize(rf, q0, LBFGSOptions(objective_rtol=0.1, gradient_rtol=0))
    J = [h.objective for h in r.history]
    assert r.reason == "objective" and J[-2] - J[-1] <= 0.1 * J[-2]
    assert all(a - b > 0.1 * a for a, b in itertools.pairwise(J[:-1]))

    def below(rec, opt):
        return "small J" if rec.objective < 1e-4 else False

    r = minimize(rf, q0, LBFGSOptions(gradient_rtol=0), stop_conditions=[below])
    assert r.reason == "user: small J" and r.converged
    assert r.history[-1].objective < 1e-4 <= r.history[-2].objective
    rf.controls.assign(q0)


# -- observers ----------------------------------------------------------------------------------
def test_on_accept_is_called_once_per_accepted_iterate_in_order(bar1):
    rf, _ = bar1
    q0 = rf.initial_parameters()
    # long first steps: E above 2200 fails (invalid trials), others overshoot (Armijo)
    options = LBFGSOptions(initial_step=3.0, gradient_rtol=1e-8)
    result, trials, calls = observed_run(rf, options, fail_above=2200.0)
    assert result.num_invalid_trials >= 2 and result.converged
    check_observed_run(result, trials, calls)
    rf.controls.assign(q0)


def test_on_accept_sees_the_remeshed_iterate_and_takes_a_single_callable():
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=2)
    seen = []

    def observer(rec, opt):
        cells = opt.rf.model.domain.mesh.topology.index_map(2).size_global
        seen.append((rec.iteration, rec.remeshed, cells, opt.point.trajectory is opt.rf.trajectory))

    result = minimize(
        rf,
        options=LBFGSOptions(max_iterations=4, gradient_rtol=0.0),
        remesher=_RefiningRemesher(),
        on_accept=observer,
    )
    assert [s[0] for s in seen] == list(range(result.iterations + 1))
    assert [s[1] for s in seen] == [r.remeshed for r in result.history]
    k = next(i for i, s in enumerate(seen) if s[1])  # the remeshed iterate, on the new mesh
    assert {s[2] for s in seen[:k]} == {32} and {s[2] for s in seen[k:]} == {128}
    assert all(s[3] for s in seen)


# -- errors -------------------------------------------------------------------------------------
def test_clear_errors(bar1):
    rf, _ = bar1
    q0 = rf.initial_parameters()
    control = rf.controls.controls[0]
    control._lower = np.log(1500.0)
    try:
        with pytest.raises(OptimizationError, match="exclude the initial point"):
            minimize(rf, q0)
    finally:
        control._lower = -np.inf
    with pytest.raises(OptimizationError, match="armijo"):
        LBFGSOptions(armijo=1.5).validate()
    with pytest.raises(OptimizationError, match="max_change"):
        minimize(rf, q0, LBFGSOptions(max_change=[0.1, 0.2]))
    with pytest.raises(OptimizationError, match="iterate_format"):
        minimize(rf, q0, output_dir="unused", iterate_format="vtk")
    rf.controls.assign(q0)


def test_non_finite_objective_and_gradient_are_reported():
    from diffsolids.controls import ParameterControl
    from diffsolids.reduced_functional import ReducedFunctional

    rf0, _ = bar_problem(MPI.COMM_WORLD, bodies=1)
    sim, model = rf0.simulation, rf0.model
    misfit = rf0.objective
    control = ParameterControl(model, "E", "uniform", log=True)
    nan_objective = misfit.apply(lambda x: np.log(x - 1.0), lambda x: 1.0 / (x - 1.0), "log")
    with pytest.raises(OptimizationError, match="initial point"), np.errstate(invalid="ignore"):
        minimize(ReducedFunctional(sim, nan_objective, control))
    inf_gradient = misfit.apply(lambda x: x, lambda x: np.inf, "flat")
    with pytest.raises(OptimizationError, match="gradient"), np.errstate(invalid="ignore"):
        minimize(ReducedFunctional(sim, inf_gradient, control))
    # a control that does not act on a static, unloaded-by-gravity problem: density
    density = ParameterControl(model, "density", "uniform")
    rf = ReducedFunctional(sim, misfit, [control, density])
    with pytest.warns(OptimizationWarning, match="density.*no effect"):
        result = minimize(rf, options=LBFGSOptions(max_iterations=1))
    assert np.all(result.gradient[1:] == 0)


# -- output -------------------------------------------------------------------------------------
def test_history_plots_log_and_iterates(tmp_path, caplog):
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=2, regularised=True)
    q0 = rf.initial_parameters()
    with caplog.at_level(logging.INFO, logger="diffsolids"):
        result = minimize(
            rf,
            q0,
            LBFGSOptions(max_iterations=4, gradient_rtol=0),
            output_dir=tmp_path,
            write_parameters=True,
            plot_every=10,
            iterate_every=3,
        )
    lines = [json.loads(s) for s in (tmp_path / "history.jsonl").read_text().splitlines()]
    assert [d["iteration"] for d in lines] == list(range(5))
    for d, rec in zip(lines, result.history, strict=True):
        assert d["objective"] == rec.objective
        assert set(d["terms"]) == {"misfit", "0.0001*u2"}
        assert np.isclose(sum(d["terms"].values()), d["objective"], rtol=1e-13)
        assert len(d["q"]) == 2 and d["gradient_norm"] >= 0
        assert d["forward_seconds"] >= 0 and d["gradient_seconds"] >= 0
    for name in ("objective.png", "gradient_norm.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in (tmp_path / "iterates").iterdir() if "cells" not in p.name) == [
        "iterate_0000.bp",
        "iterate_0003.bp",
        "iterate_0004.bp",
    ]
    opt_lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("opt ")]
    assert sum("misfit=" in m and "0.0001*u2=" in m and "|g|=" in m for m in opt_lines) == 5


def test_xdmf_iterates(tmp_path):
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=1)
    minimize(
        rf,
        options=LBFGSOptions(max_iterations=1),
        output_dir=tmp_path,
        plot_every=0,
        iterate_every=1,
        iterate_format="xdmf",
    )
    assert (tmp_path / "iterates" / "iterate_0001.xdmf").is_file()
    assert not (tmp_path / "objective.png").exists()


# -- warm start ---------------------------------------------------------------------------------
def test_warm_start_changes_only_the_newton_guess():
    rf, _ = dynamic_problem(MPI.COMM_WORLD)
    sim = rf.simulation
    q0 = rf.initial_parameters()
    q1 = q0 + np.array([0.02, -0.01])
    rf.forward(q0)
    warm = rf.trajectory
    J_cold = rf.forward(q1)
    cold = rf.trajectory
    sim.warm_start = warm
    try:
        J_warm = rf.forward(q1)
    finally:
        sim.warm_start = None
    hot = rf.trajectory
    assert hot.newton_iterations() < cold.newton_iterations()
    assert abs(J_warm - J_cold) <= 1e-8 * abs(J_cold)
    scale = max(np.abs(u).max() for u in cold.u)
    assert max(np.abs(a - b).max() for a, b in zip(hot.u, cold.u, strict=True)) <= 1e-8 * scale


def test_an_optimisation_that_raises_leaves_no_warm_start(monkeypatch):
    """The warm start is the optimisation's: when a gradient raises part-way, later
    evaluations of the functional start from their own guesses again."""
    rf, _ = dynamic_problem(MPI.COMM_WORLD)
    real, calls = rf.derivative, []

    def derivative():
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("gradient failed")
        return real()

    monkeypatch.setattr(rf, "derivative", derivative)
    with pytest.raises(RuntimeError, match="gradient failed"):
        minimize(rf, options=LBFGSOptions(max_iterations=5, warm_start=True))
    assert len(calls) == 3
    assert rf.simulation.warm_start is None


# -- remeshing hook -----------------------------------------------------------------------------
class _RefiningRemesher:
    """Rebuilds the bar on a finer mesh once, after iteration 2."""

    def __init__(self):
        self.calls = []
        self.done = False

    def needs_remesh(self, rf, q):
        self.calls.append(np.array(q))
        coarse = rf.model.domain.mesh.topology.index_map(2).size_global < 128
        return coarse and len(self.calls) >= 2  # decided by the mesh, as a real remesher

    def remesh(self, rf, q):
        new_rf, _ = bar_problem(MPI.COMM_WORLD, bodies=2, n=(16, 4))
        self.done = True
        return new_rf, np.array(q)


class _CheckpointingRemesher(_RefiningRemesher):
    """The refining remesher with the optional checkpoint hooks."""

    def save_checkpoint(self, directory, rf):
        if MPI.COMM_WORLD.rank == 0:
            (directory / "mesh.json").write_text(json.dumps({"n": [16, 4]}))

    def load_checkpoint(self, directory, rf):
        n = json.loads((directory / "mesh.json").read_text())["n"]
        return bar_problem(MPI.COMM_WORLD, bodies=2, n=n)[0]


def _remeshed_run(iterations, remesher, **kwargs):
    """L-BFGS on a fresh two-body bar with a remesher (no gradient tolerance)."""
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=2)
    options = LBFGSOptions(max_iterations=iterations, gradient_rtol=0.0)
    return LBFGS(rf, options, remesher=remesher, **kwargs).run()


def test_resume_after_remesh_uses_the_remesher_hooks(tmp_path, caplog):
    hooks = {"checkpoint_dir": tmp_path, "write_parameters": True}
    first = _remeshed_run(4, _CheckpointingRemesher(), **hooks)
    assert first.history[2].remeshed
    resumed = _remeshed_run(7, _CheckpointingRemesher(), **hooks)
    assert resumed.resumed_from == 4
    assert resumed.functional.model.domain.mesh.topology.index_map(2).size_global == 128
    reference = _remeshed_run(7, _CheckpointingRemesher(), write_parameters=True)
    Ja = np.array([r.objective for r in resumed.history])
    Jb = np.array([r.objective for r in reference.history])
    assert np.all(np.abs(Ja - Jb) <= 1e-10 * np.abs(Jb))
    # a remesher without the hooks: the checkpoint cannot be resumed, and that is said
    other = tmp_path / "plain"
    with caplog.at_level(logging.WARNING, logger="diffsolids"):
        _remeshed_run(3, _RefiningRemesher(), checkpoint_dir=other)
    assert any("save_checkpoint" in r.getMessage() for r in caplog.records)
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=2)
    with pytest.raises(OptimizationError, match="load_checkpoint"):
        LBFGS(rf, remesher=_RefiningRemesher(), checkpoint_dir=other).run()


def test_remesh_hook_resets_memory_and_continues():
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=2)
    remesher = _RefiningRemesher()
    opt = LBFGS(rf, LBFGSOptions(gradient_rtol=1e-8, max_iterations=40), remesher=remesher)
    result = opt.run()
    assert remesher.done
    assert len(remesher.calls) == result.iterations  # asked after every accepted iterate
    assert [r.remeshed for r in result.history].count(True) == 1
    rec = result.history[2]
    assert rec.remeshed and rec.objective_before_remesh != rec.objective
    assert result.functional is not rf
    assert result.functional.model.domain.mesh.topology.index_map(2).size_global == 128
    # memory reset: the step after the remesh has unit length, possibly halved
    assert np.log2(result.history[3].step_norm) == pytest.approx(
        round(np.log2(result.history[3].step_norm)), abs=1e-9
    )
    assert result.converged
    assert np.allclose(np.exp(result.q), E_TRUE, rtol=1e-6)


def _lame_bar_problem():
    """The bar with Lame parameters, each a log-parametrised control (lmbda, then mu)."""
    from dolfinx import fem

    from diffsolids.controls import ParameterControl
    from diffsolids.objectives import Integral, final_value
    from diffsolids.reduced_functional import ReducedFunctional

    facets = {1: lambda x: np.isclose(x[0], 0.0), 2: lambda x: np.isclose(x[0], 4.0)}
    dom = ds.mesh.create_rectangle(MPI.COMM_WORLD, [[0, 0], [4, 1]], [8, 2], facets=facets)
    model = ds.Model(dom, ds.LinearElastic(lmbda=600.0, mu=400.0))
    model.add_traction(2, [10.0, -2.0])
    model.add_dirichlet(1, 0.0)
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-12), progress=False)
    target = fem.Function(model.V)
    misfit = Integral(lambda f: ufl.inner(f.u - target, f.u - target) * f.dx, "misfit")
    controls = [ParameterControl(model, n, "uniform", log=True) for n in ("lmbda", "mu")]
    rf = ReducedFunctional(sim, final_value(misfit), controls)
    q0 = rf.initial_parameters()
    rf(np.log([900.0, 700.0]))
    target.x.array[:] = rf.trajectory.u[-1]
    return rf, q0


def test_a_trial_with_an_overflowing_field_is_rejected_and_the_run_goes_on():
    rf, q0 = _lame_bar_problem()
    with pytest.raises(ParameterError, match=r"mu has \d+ non-finite"):
        rf.controls.assign(q0 + np.array([0.0, 800.0]))  # exp overflows: mu = inf
    rf.controls.assign(q0)  # lmbda first while mu still holds inf: validated together
    assert np.allclose(rf.model.coefficients["mu"].x.array, 400.0)
    result = minimize(rf, q0, LBFGSOptions(initial_step=800.0, gradient_rtol=1e-6))
    assert result.history[1].invalid_trials >= 1
    assert result.objective < 1e-3 * result.history[0].objective


class _FailingRemesher(_RefiningRemesher):
    """Asks for a remesh after iteration 2 and fails as a remesher meeting a folded boundary."""

    def remesh(self, rf, q):
        raise MeshError("remeshing failed: the boundary intersects itself (test)")


def test_a_failed_remesh_ends_the_run_at_the_accepted_point():
    remesher = _FailingRemesher()
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=2)
    options = LBFGSOptions(max_iterations=10, gradient_rtol=0.0)
    with pytest.warns(OptimizationWarning, match="remeshing failed.*intersects itself"):
        result = LBFGS(rf, options, remesher=remesher).run()
    assert result.reason.startswith("remesh: MeshError")
    assert result.iterations == 2 and len(result.history) == 3
    assert result.functional is rf
    assert np.array_equal(rf.controls.value(), result.q)
    assert result.objective == result.history[-1].objective
    assert result.objective == pytest.approx(rf(result.q), rel=1e-12)


def test_shape_control_refuses_a_boundary_folded_into_another_body():
    from diffsolids.controls import ShapeControl
    from diffsolids.errors import InvertedElementError

    left = ds.mesh.simplex_box([[0.0, 0.0], [1.0, 1.0]], [2, 2])
    right = ds.mesh.simplex_box([[1.5, 0.0], [2.5, 1.0]], [2, 2])
    domain = ds.combine_meshes(MPI.COMM_WORLD, [left, right], names={"left": 1, "right": 2})
    model = ds.Model(domain, ds.LinearElastic(E=1e3, nu=0.3))
    right_side = lambda x: x[0] > 1.2  # noqa: E731
    guarded = ShapeControl(model, right_side, refuse_intersections=True)
    plain = ShapeControl(model, right_side)
    q = np.tile([-0.8, 0.0], guarded.size // 2)  # the right square, rigidly into the left one
    X = model.domain.mesh.geometry.x.copy()
    with pytest.raises(InvertedElementError, match="folds the boundary"):
        guarded.assign(q)
    assert np.array_equal(model.domain.mesh.geometry.x, X)  # not applied
    guarded.assign(0.5 * q)  # still 0.1 apart: accepted
    assert np.allclose(guarded.value(), 0.5 * q)
    plain.assign(q)  # without the option: accepted, no cell inverts


def test_the_optimiser_checks_its_hooks_by_their_declared_protocols(bar1):
    from diffsolids.optimize import RemeshCheckpoints, RemeshHook
    from diffsolids.optimize.hooks import condition_name

    rf, _ = bar1

    class HalfRemesher:
        def needs_remesh(self, rf, q):
            return False

    with pytest.raises(OptimizationError, match=r"HalfRemesher needs .*RemeshHook"):
        LBFGS(rf, remesher=HalfRemesher())
    assert isinstance(_RefiningRemesher(), RemeshHook)
    assert not isinstance(_RefiningRemesher(), RemeshCheckpoints)
    assert isinstance(_CheckpointingRemesher(), RemeshCheckpoints)

    def enough(rec, opt):
        return False

    class Budget:
        def __call__(self, rec, opt):
            return False

    assert condition_name(enough) == "enough" and condition_name(Budget()) == "Budget"
