"""SolverOptions: the absolute residual tolerance and the validated initial-guess choice."""

import numpy as np
import pytest

import diffsolids as ds
from diffsolids.solvers.newton import INITIAL_GUESSES


def _static_run(model, **options):
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(**options), progress=False)
    traj = sim.run()
    return traj.records[0], sim


def test_atol_stops_newton_earlier(cantilever):
    """A large atol ends the solve at the first residual below it: fewer iterations."""
    strict, sim = _static_run(cantilever, rtol=1e-10)
    f_char = sim.solver._f_char
    assert strict.iterations >= 3  # a nonlinear solve: room to stop earlier
    assert strict.residual <= 1e-10 * f_char

    cantilever.fields.u.x.array[:] = 0.0
    atol = 1e-3 * f_char  # far above rtol * f_char = 1e-10 f_char
    loose, _ = _static_run(cantilever, rtol=1e-10, atol=atol)
    assert loose.iterations < strict.iterations
    assert loose.residual <= atol
    assert loose.residual > 1e-10 * f_char  # stopped by atol, not by rtol

    # an atol below rtol * f_char changes nothing
    cantilever.fields.u.x.array[:] = 0.0
    same, _ = _static_run(cantilever, rtol=1e-10, atol=1e-3 * 1e-10 * f_char)
    assert same.iterations == strict.iterations
    assert same.residual == pytest.approx(strict.residual, rel=1e-6, abs=1e-14 * f_char)


def test_atol_alone_converges(cantilever):
    """rtol = 0 with atol > 0 is a valid absolute-only criterion."""
    _, sim = _static_run(cantilever, rtol=1e-10)
    atol = 1e-6 * sim.solver._f_char
    cantilever.fields.u.x.array[:] = 0.0
    rec, _ = _static_run(cantilever, rtol=0.0, atol=atol)
    assert rec.residual <= atol
    assert np.isfinite(rec.energy)


def test_defaults():
    o = ds.SolverOptions()
    assert o.atol == 0.0
    assert o.initial_guess == "predictor"
    assert o.exact_hessian_below == 1e-3  # projected contact Newton steps, then exact ones
    assert set(INITIAL_GUESSES) == {"predictor", "previous", "zero"}
    for guess in INITIAL_GUESSES:
        assert ds.SolverOptions(initial_guess=guess).initial_guess == guess


@pytest.mark.parametrize("guess", ["extrapolate", "Previous", "", None])
def test_bad_initial_guess_names_the_choices(guess):
    with pytest.raises(ValueError, match="initial_guess") as err:
        ds.SolverOptions(initial_guess=guess)
    for name in INITIAL_GUESSES:
        assert repr(name) in str(err.value)


@pytest.mark.parametrize(
    "kwargs", [{"atol": -1.0}, {"atol": "1e-8"}, {"atol": np.nan}, {"rtol": -1e-9}, {"atol": True}]
)
def test_bad_tolerances_raise(kwargs):
    name = next(iter(kwargs))
    with pytest.raises(ValueError, match=f"{name}="):
        ds.SolverOptions(**kwargs)


def test_no_tolerance_at_all_raises():
    with pytest.raises(ValueError, match="rtol and atol are both 0"):
        ds.SolverOptions(rtol=0.0, atol=0.0)


def test_failed_projected_phase_is_retried_with_the_exact_hessian():
    """A step whose projected Newton phase fails is solved again with the exact Hessian.

    The box-on-slab contact scene (tests/test_friction_smoothness.py) takes 19 and 31 Newton
    iterations in steps 1 and 3 with projected steps only (exact_hessian_below=0) and at most
    17 with the exact Hessian from the start: with a limit of 18 those steps fail their first
    attempt and converge on the retry from the same initial guess.
    """
    from test_friction_smoothness import box_on_slab

    limit = 18
    _, sim, _ = box_on_slab(ds.SolverOptions(exact_hessian_below=0.0, max_iterations=limit))
    traj = sim.run()
    solver = sim.solver
    its = [r.iterations for r in traj.records]
    assert solver.retried_steps >= 1, its
    assert max(its) > limit  # iterations of both attempts are counted (no error raised)

    # exact Hessian from the start: nothing to retry
    _, sim, _ = box_on_slab(ds.SolverOptions(exact_hessian_below=np.inf, max_iterations=limit))
    sim.run()
    assert sim.solver.retried_steps == 0

    # and a limit that the exact Hessian cannot meet either fails, naming both attempts
    _, sim, _ = box_on_slab(ds.SolverOptions(exact_hessian_below=0.0, max_iterations=8))
    with pytest.raises(ds.errors.NewtonConvergenceError, match="and so did the step again"):
        sim.run()


def test_contact_hessian_projection_names():
    """The names "abs" and "clamp" map to ipctk's methods; any other name is refused by name."""
    import ipctk

    from diffsolids.contact.energy.contact_potential import projection_method
    from diffsolids.errors import ParameterError

    assert projection_method("abs") == ipctk.PSDProjectionMethod.ABS
    assert projection_method("clamp") == ipctk.PSDProjectionMethod.CLAMP
    with pytest.raises(ParameterError, match="hessian_projection 'none'"):
        projection_method("none")
