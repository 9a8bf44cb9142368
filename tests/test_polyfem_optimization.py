"""PolyFEM optimisation files (opt.json) run by diffsolids.polyfem: each variable kind and form
the runner maps, checked by Taylor tests in a random direction and along the gradient, the
errors that name what is unsupported, and the command line in a subprocess.

Scenes of our own (tests/polyfem_own_scenes.py: a block thrown onto a clamped ground);
tests/mpi runs the same on 2 ranks; the paper's experiments in test_paper_optimization.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from polyfem_own_scenes import TARGET, write_experiment

import diffsolids as ds
from diffsolids.polyfem import read_polyfem_optimization
from diffsolids.verification import RATE_WINDOW

ROOT = Path(__file__).resolve().parents[1]
TAYLOR_MIN_RATE = 2.0 - RATE_WINDOW  # taylor_test's own criterion of second order


def _check(taylor) -> None:
    """Second order: every rate above 2 - window, the last within the window around 2."""
    rates = taylor.rates_second
    assert rates.min() >= TAYLOR_MIN_RATE and abs(rates[-1] - 2.0) <= RATE_WINDOW, str(taylor)


def _taylor_both(problem, seed: int = 0, h0: float | None = None) -> list:
    """Taylor tests at q0 in a random direction and along -g (unit directions with ``h0``)."""
    rf, q0 = problem.rf, problem.q0
    g = rf.gradient(q0)
    d = np.random.default_rng(seed).standard_normal(q0.size)
    if h0 is None:
        return [ds.taylor_test(rf, q0, d / np.linalg.norm(d)), ds.taylor_test(rf, q0, -g)]
    return [ds.taylor_test(rf, q0, v / np.linalg.norm(v), h0=h0, num=3) for v in (d, -g)]


@pytest.mark.parametrize("kind", ["initial", "friction", "elastic"])
def test_variables_give_verified_gradients(tmp_path, kind):
    problem = read_polyfem_optimization(write_experiment(tmp_path, kind)).build()
    J = problem.rf(problem.q0)
    assert np.isfinite(J) and J > 0
    for taylor in _taylor_both(problem):
        _check(taylor)


def test_follow_branch_starts_from_the_initial_parameters_run(tmp_path):
    path = write_experiment(tmp_path, "friction")
    plain = read_polyfem_optimization(path).build()
    problem = read_polyfem_optimization(path).build(follow_branch=True)
    assert plain.rf.branch_reference is None
    assert np.array_equal(problem.rf.branch_reference, problem.q0)
    J, J_plain = problem.rf(problem.q0), plain.rf(plain.q0)
    assert abs(J - J_plain) <= 1e-8 * abs(J_plain)
    assert problem.rf.reference_run is not None
    for taylor in _taylor_both(problem):
        _check(taylor)


def test_initial_velocity_layout_follows_geometry_order(tmp_path):
    """x = [ground (vx, vy), block (vx, vy)]: the block's entries start it at (1, -0.5)."""
    problem = read_polyfem_optimization(write_experiment(tmp_path, "initial")).build()
    sim = problem.simulation
    problem.controls[0].assign(np.array([0.0, 0.0, 0.7, -0.3]))
    block = ds.RigidVelocity(sim, 1, angular=False)
    v = sim.v0.reshape(-1, 2)[block.nodes]
    assert np.allclose(v, [0.7, -0.3])
    assert np.all(sim.u0 == 0.0)


def test_elastic_parameters_are_polyfem_lame(tmp_path):
    """Without ``initial``, x0 is log(lambda), log(mu) per body from E, nu (2D: plane stress)."""
    problem = read_polyfem_optimization(write_experiment(tmp_path, "elastic")).build()
    E, nu = np.array([1e5, 2e4]), 0.3
    lmbda, mu = E * nu / (1 - nu**2), E / (2 * (1 + nu))
    assert np.allclose(problem.q0, np.log(np.concatenate([lmbda, mu])), rtol=1e-12)
    assert not problem.model.plane_stress


def test_composite_forms_and_stopping_condition(tmp_path):
    """soft_constraint(divide(final position, volume)), power, plus-const; the stop rule."""
    mean_x = {
        "type": "divide",
        "objective": [
            {
                "type": "transient_integral",
                "state": 0,
                "integral_type": "final",
                "static_objective": {
                    "type": "position",
                    "state": 0,
                    "dim": 0,
                    "volume_selection": [1],
                },
            },
            {"type": "volume", "state": 0, "volume_selection": [1]},
        ],
    }
    functionals = [
        {"type": "soft_constraint", "soft_bound": [0.2, 0.2], "objective": mean_x, "weight": 3},
        {
            "type": "power",
            "power": 2,
            "objective": {**TARGET, "integral_type": "steps", "steps": [4, 8]},
        },
    ]
    stop = [{"type": "plus-const", "value": -1e-12, "objective": functionals[0]}]
    opt = read_polyfem_optimization(
        write_experiment(tmp_path, "initial", functionals=functionals, stopping_conditions=stop)
    )
    problem = opt.build()
    J = problem.rf(problem.q0)
    terms = problem.rf.term_values()
    traj = problem.rf.trajectory
    # the block's mean x at the end, by its nodes (uniform P1 mesh: the centroid of the cells)
    (value,) = problem.stopping.evaluate(traj)
    assert value == pytest.approx(next(iter(terms.values())) - 1e-12, rel=1e-12)
    assert pytest.approx(sum(terms.values()), rel=1e-12) == J
    for taylor in _taylor_both(problem):
        _check(taylor)


def test_bounds_and_options(tmp_path):
    solver = {
        "nonlinear": {
            "solver": "L-BFGS-B",
            "max_iterations": 7,
            "grad_norm": 1e-5,
            "box_constraints": {"bounds": [-3, 3], "max_change": 0.5},
            "line_search": {"method": "Backtracking"},
        }
    }
    opt = read_polyfem_optimization(write_experiment(tmp_path, "initial", solver=solver))
    options = opt.lbfgs_options()
    assert (options.max_iterations, options.gradient_atol, options.max_change) == (7, 1e-5, 0.5)
    options = opt.lbfgs_options(max_iterations=3, grad_norm=1e-12)
    assert (options.max_iterations, options.gradient_atol) == (3, 1e-12)
    with pytest.raises(ds.ParameterError, match="grad_norm must be >= 0, got -1"):
        opt.lbfgs_options(grad_norm=-1.0)
    assert opt.build(steps=2, grad_norm=1e-11).options.gradient_atol == 1e-11
    problem = opt.build(steps=4)
    lo, hi = problem.rf.bounds()
    assert np.all(lo == -3) and np.all(hi == 3)
    assert problem.simulation.integrator.num_steps == 4


def test_minimize_decreases_J(tmp_path):
    problem = read_polyfem_optimization(write_experiment(tmp_path, "initial", steps=8)).build()
    result = ds.optimize.minimize(problem.rf, problem.q0, problem.options, progress=False)
    assert result.objective < 0.1 * result.history[0].objective


@pytest.mark.parametrize(
    "edit, match",
    [
        ({"colour": 1}, r"unsupported keys \['colour'\]"),
        (
            {"variable_to_simulation": [{"type": "shape", "composite_map_type": "interior"}]},
            "composite_map_type 'interior' is not supported",
        ),
        ({"variable_to_simulation": [{"type": "damping"}]}, "variable type 'damping'"),
        ({"parameters": [{"number": 5}]}, "the per-body vector has 5 entries; 2 bodies x 2"),
        ({"functionals": [{"type": "AMIPS", "state": 0}]}, "unsupported static objective 'AMIPS'"),
        (
            {
                "functionals": [
                    {
                        **TARGET,
                        "static_objective": {**TARGET["static_objective"], "target_state": 4},
                    }
                ]
            },
            r"target_state \[4\] is not a target state",
        ),
        ({"solver": {"nonlinear": {"solver": "Newton"}}}, "solver 'Newton' is not supported"),
        (
            {"functionals": [{**TARGET, "integral_type": "simpson"}]},
            "integral_type 'simpson' is not supported",
        ),
    ],
)
def test_unsupported_entries_are_named(tmp_path, edit, match):
    path = write_experiment(tmp_path, "initial")
    spec = json.loads(path.read_text())
    spec.update(edit)
    path.write_text(json.dumps(spec))
    with pytest.raises(ds.ParameterError, match=match):
        read_polyfem_optimization(path).build()


def test_missing_and_invalid_files(tmp_path):
    with pytest.raises(ds.ParameterError, match="does not exist"):
        read_polyfem_optimization(tmp_path / "opt.json")
    (tmp_path / "opt.json").write_text("{")
    with pytest.raises(ds.ParameterError, match="not valid JSON"):
        read_polyfem_optimization(tmp_path / "opt.json")


def _run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "diffsolids.polyfem", *args],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )


def test_command_line_writes_its_outputs(tmp_path):
    path = write_experiment(tmp_path / "exp", "initial", steps=8)
    out = tmp_path / "out"
    args = ["--out", str(out), "--max-iterations", "2", "--steps", "6", "--area-weighting"]
    args += ["--follow-branch", "--grad-norm", "1e-14"]
    proc = _run_cli(str(path), *args)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["iterations"] == 2 and result["objective"] < result["initial_objective"]
    history = (out / "history.jsonl").read_text().splitlines()
    assert len(history) == 3 and json.loads(history[-1])["q"] == pytest.approx(result["q"])
    for name in ("objective.png", "log.csv", "initial.bp", "final.bp"):
        assert (out / name).exists(), name


def test_command_line_names_a_bad_file(tmp_path):
    proc = _run_cli(str(tmp_path / "missing.json"))
    assert proc.returncode == 2
    assert "missing.json does not exist" in proc.stdout


def test_affine_control_refuses_a_matrix_of_the_wrong_shape(tmp_path):
    problem = read_polyfem_optimization(write_experiment(tmp_path, "friction")).build()
    inner = problem.controls[0].controls
    n = sum(c.size for c in inner)
    with pytest.raises(
        ds.controls.ControlError, match=rf"matrix \({n + 1}, 1\) and offset \({n},\)"
    ):
        ds.controls.AffineControl(inner, np.ones((n + 1, 1)))
    with pytest.raises(ds.controls.ControlError, match="non-finite"):
        ds.controls.AffineControl(inner, np.full((n, 1), np.nan))


@pytest.mark.parametrize(
    "text",
    [
        "(y+0.3-0.7*sin(x))^2",
        "-x^2 + atan2(y, x) - ln(2)*log10(100) + exp(-z)",
        "if(x-0.1, sqrt(y), max(x, y)) + smooth_abs(x - y, 10) + rotate_2D_x(x, y, pi/3)",
    ],
)
def test_expressions_in_ufl_equal_numpy(text):
    from diffsolids.io.expressions import parse_expression

    expression = parse_expression(text)
    x, y, z = 0.3, 0.2, 0.1
    assert float(expression.ufl(x, y, z)) == pytest.approx(float(expression(x, y, z)), rel=1e-14)


@pytest.mark.parametrize("text, name", [("x % 2", "'%'"), ("floor(x)", "'floor'")])
def test_expressions_without_ufl_form_are_named(text, name):
    from diffsolids.io.expressions import ExpressionError, parse_expression

    with pytest.raises(ExpressionError, match=f"{name} has no UFL form"):
        parse_expression(text).ufl(0.3, 0.2)


def test_function_target_gradient(tmp_path):
    """int over the block's boundary of a PolyFEM expression of the deformed position."""
    target = {
        "type": "function-target",
        "state": 0,
        "target_function": "(y - 0.05 - 0.1*sin(3*x))^2",
        "target_function_gradient": ["unused", "unused"],
        "surface_selection": [1],
    }
    functional = {"type": "transient_integral", "state": 0, "static_objective": target}
    path = write_experiment(tmp_path, "elastic", steps=8, functionals=[functional])
    problem = read_polyfem_optimization(path).build()
    assert problem.rf(problem.q0) > 0
    for taylor in _taylor_both(problem):
        _check(taylor)


def test_shape_variable_and_the_hooks_forms(tmp_path):
    from polyfem_own_scenes import write_shape_experiment

    with pytest.warns(UserWarning, match=r"parameters\[0\]\.number is 10, the shape variable has"):
        problem = read_polyfem_optimization(write_shape_experiment(tmp_path)).build()
    assert problem.inner_product is not None and np.all(problem.q0 == 0.0)
    J = problem.rf(problem.q0)
    assert J > 0
    (value,) = problem.stopping.evaluate(problem.rf.trajectory)
    assert value == pytest.approx((2 / 8) * (1 / 4) - 1e-6, rel=1e-12)  # 2 x cell area
    for taylor in _taylor_both(problem):
        _check(taylor)
    result = ds.optimize.minimize(
        problem.rf, problem.q0, problem.options, inner_product=problem.inner_product, progress=False
    )
    assert result.objective < result.history[0].objective
