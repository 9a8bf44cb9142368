"""The branch reference: J one smooth function of q where a contact step has two local minima.

The scene (``smoothness_scenes.ridge``): a block lands on a roof ridge under its diagonal and
tips to one side or the other; which one Newton finds from u^{i-1} is decided by round-off,
so J (the side it tipped to) jumps under tiny changes of q. With
``ReducedFunctional(..., branch_reference=q_ref)`` every step starts at the reference run's
state: J and its gradient are the same whatever was evaluated before, smooth near q_ref, and
central differences verify the adjoint.
"""

import numpy as np
import pytest
from contact_checks import central_differences
from smoothness_scenes import ridge

import diffsolids as ds
from diffsolids.verification import line_scan

STEPS = 9  # the block lands in step 5 and tips over the next steps


@pytest.fixture(scope="module")
def scene():
    return ridge(steps=STEPS)


def test_reference_run_starts_every_step(scene):
    rf = scene.rf
    J0, g = rf.value_and_gradient(scene.q0)
    assert rf.reference_run is not None
    assert rf.reference_run.num_steps == STEPS
    assert rf.simulation.branch_reference is None  # the functional's only while it runs
    # at q_ref each step starts at its own converged state
    its = [r.iterations for r in rf.trajectory.records]
    assert max(its) <= 1, its
    assert abs(J0) > 0 and np.all(np.isfinite(g))


def test_gradient_against_central_differences(scene):
    rf, q = scene.rf, scene.q0
    _, g = rf.value_and_gradient(q)
    rows, report = central_differences(rf, q, g, scene.contact, (1e-3, 1e-4), seed=3)
    errors = {(r.direction, r.h): r.error for r in rows}
    for direction in ("random", "gradient"):
        assert errors[direction, 1e-4] <= 1e-5, report


def test_value_independent_of_history(scene):
    rf, q = scene.rf, scene.q0
    dq = np.array([0.004, -0.003])
    J1 = rf(q + dq)
    for step in (0.02, -0.015, 0.007):  # other points in between
        rf(q + step * np.array([1.0, 0.5]))
    rf.simulation.warm_start = rf.trajectory  # an optimiser's warm start is not used
    try:
        J2 = rf(q + dq)
    finally:
        rf.simulation.warm_start = None
    assert pytest.approx(J1, rel=1e-12, abs=0.0) == J2
    fresh = ridge(steps=STEPS)
    assert fresh.rf(q + dq) == J1


def test_no_jump_along_a_line(scene):
    scan = line_scan(scene.rf, scene.q0, np.array([1.0, 0.0]), 0.02, 9)
    assert scan.jumps.size == 0, (scan.values, scan.deviations)
    # the block tipped to the same side everywhere
    assert len({np.sign(v) for v in scan.values}) == 1, scan.values


def test_another_functional_on_the_simulation_has_no_reference(scene):
    rf = scene.rf
    rf(scene.q0)
    plain = ds.ReducedFunctional(rf.simulation, rf.objective, rf.controls.controls)
    assert plain.branch_reference is None
    plain(scene.q0 + 0.001)
    assert plain.reference_run is None
    rf(scene.q0 - 0.001)
    assert rf.reference_run is not None and rf.simulation.branch_reference is None


def test_a_plain_run_after_the_functional_follows_no_reference(scene):
    """The reference is the functional's: at q_ref the functional's run starts every step
    converged, a plain run of its simulation afterwards solves every step from its own guess
    (it used to follow the functional's branch)."""
    rf = scene.rf
    rf(scene.q0)
    assert max(r.iterations for r in rf.trajectory.records) <= 1
    plain = rf.simulation.run()  # the controls are still at q_ref
    assert rf.simulation.branch_reference is None
    its = [r.iterations for r in plain.records]
    assert max(its) > 1, its


@pytest.mark.parametrize("q_ref", [[1.0], [1.0, np.nan], [[1.0, 2.0, 3.0]]])
def test_bad_reference_refused(scene, q_ref):
    rf = scene.rf
    with pytest.raises(ds.ParameterError, match="branch_reference must be 2 finite"):
        ds.ReducedFunctional(
            rf.simulation, rf.objective, rf.controls.controls, branch_reference=q_ref
        )


def _fail_once(sim, monkeypatch, step: int) -> list:
    """Make the solver's first solve of ``step`` fail; the list records the forced failures."""
    real, forced = sim.solver.solve, []

    def solve(i, retries=True):
        if i == step and not forced:
            forced.append((i, retries))
            raise ds.NewtonConvergenceError(i, 1000, 1.0, 1e-9, "forced by the test")
        return real(i, retries)

    monkeypatch.setattr(sim.solver, "solve", solve)
    return forced


def test_failed_solve_from_the_reference_solved_again_from_the_default_guess(
    scene, monkeypatch, caplog
):
    rf, q = scene.rf, scene.q0 + np.array([0.004, -0.003])
    J_reference_route = rf(q)
    its_reference_route = [r.iterations for r in rf.trajectory.records]
    reference = rf.reference_run
    rf(scene.q0)  # another point: the next call at q runs again
    forced = _fail_once(rf.simulation, monkeypatch, 7)
    with caplog.at_level("WARNING", logger="diffsolids"):
        J = rf(q)
    assert forced == [(7, False)]  # one attempt from the reference's state, no retries
    assert "step 7: no convergence from the branch reference's state" in caplog.text
    assert np.isfinite(J) and rf.reference_run is reference
    # step 7 started at the predictor, not at the reference's u^7: more Newton iterations
    # (the failed solve's 1000 counted too), the same minimum here (the block has tipped to
    # the reference's side by step 7)
    its = [r.iterations for r in rf.trajectory.records]
    assert its[6] > 1000 + its_reference_route[6], (its, its_reference_route)
    assert pytest.approx(J, rel=1e-6) == J_reference_route


def test_failed_solve_without_a_reference_raises(scene, monkeypatch):
    rf = scene.rf
    plain = ds.ReducedFunctional(rf.simulation, rf.objective, rf.controls.controls)
    forced = _fail_once(plain.simulation, monkeypatch, 7)
    with pytest.raises(ds.NewtonConvergenceError, match="forced by the test"):
        plain(scene.q0)
    assert forced == [(7, True)]
