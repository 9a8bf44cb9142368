"""Central differences verify the adjoint friction gradient of the paper's Fig. 21 sliding bunny.

The scene ``fig21_friction_bunny`` (a Stanford bunny thrown along a slide, 2 799 dofs with the
slide as a kinematic obstacle) as the demo builds it from opt.json
(``demos/paper_sliding_bunny.friction_problem``, the runner's problem with ``follow_branch``:
100 |c(T) - c_target(T)|^2 of the bunny's centre of mass, the target run at mu = 0.1; the
control opt.json's friction coefficient mu) over
the first ``STEPS`` steps at mu = 0.5: the bunny lands in step 1 (20 pairs), friction acts from
step 2, step 3 is the impact (79 pairs) and the bunny slides in steps 4-5.

Step 3 has two strict local minima of the incremental potential (78 and 79 pairs, energies
7.4e-3 apart); Newton from u^2 ends in either after a change of mu by 1e-4, so J(mu) computed
from scratch has two branches (J jumps by 1.4% over 8 steps) and central differences compare
them. The demo's functional has a branch reference at the initial mu
(``ReducedFunctional(..., branch_reference=...)``): every run starts each step's Newton
iteration at the reference run's state, so the perturbed runs stay on its branch.

Checked here: the perturbed runs keep the base run's contact pattern, central differences in
mu agree with the adjoint to ``TOLERANCE`` at h = 1e-5 and 1e-6 along a random direction
and along the gradient, and from h = 1e-4 to 1e-5 the error falls like h^2 (by more than
30x); the base parameters again reproduce J to the last bit.
"""

import os
from pathlib import Path

import pytest
from contact_checks import central_differences
from mpi4py import MPI

COMM = MPI.COMM_WORLD
DATA = Path(
    os.environ.get("DIFFSOLIDS_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)
DIFFIPC = DATA / "diffipc"

STEPS = 5  # landing, friction, the impact step with two local minima, sliding
TOLERANCE = 1e-6
SMALL_H = (1e-5, 1e-6)  # central-difference steps of mu checked against TOLERANCE
TRUNCATION_H = 1e-4  # the error from TRUNCATION_H to SMALL_H[0] must fall like h^2


def friction(steps: int, comm: MPI.Comm = COMM):
    """(rf, q0, contact, sim) of the demo's problem over ``steps`` steps (skips without data)."""
    from demo_modules import load_demo

    demo = load_demo("paper_sliding_bunny")
    if not (DIFFIPC / demo.FOLDER / "opt.json").is_file():
        pytest.skip(f"the paper's data is not at {DIFFIPC} (set DIFFSOLIDS_DATA)")
    _, problem = demo.friction_problem(DIFFIPC, comm, steps, follow_branch=True)
    return problem.rf, problem.q0, problem.contact, problem.simulation


@pytest.mark.slow
def test_sliding_friction_gradient_against_central_differences():
    rf, q, contact, _ = friction(STEPS)
    J0, g = rf.value_and_gradient(q)
    pairs0 = [r.num_collisions for r in contact.records]
    assert max(pairs0) > 0 and abs(g[0]) > 0, f"pairs per step {pairs0}, gradient {g}"

    assert rf.reference_run is not None
    steps = (TRUNCATION_H, *SMALL_H)
    results, report = central_differences(rf, q, g, contact, steps, 21)
    errors = {(r.direction, r.h): r.error for r in results}
    for name in ("random", "gradient"):
        for h in SMALL_H:
            assert errors[name, h] <= TOLERANCE, report
        assert errors[name, TRUNCATION_H] >= 30 * errors[name, SMALL_H[0]], report
    for r in results:
        assert r.pairs == (pairs0, pairs0), report
    # the base parameters again from scratch (the last run was at q - h dq)
    J_again = rf(q)
    assert J_again == J0, (J_again, J0)
