"""Central differences verify the adjoint friction gradient of the paper's Fig. 21 sliding bunny.

The scene ``fig21_friction_bunny`` (a Stanford bunny thrown along a slide, 2 799 dofs with the
slide as a kinematic obstacle) with the demo's objective and control
(``demos/paper_sliding_bunny.friction_problem``: 100 |c(T) - c_target(T)|^2 of the bunny's
centre of mass, the target run at mu = 0.1; the control log mu of the bunny-slide pair) over
the first ``STEPS`` steps at mu = 0.5: the bunny lands in step 1 (20 pairs), friction acts from
step 2, step 3 is the impact (79 pairs) and the bunny slides in steps 4-5.

Step 3 has two strict local minima of the incremental potential (78 and 79 pairs, energies
7.4e-3 apart); Newton from u^2 ends in either after a change of mu by 1e-4, so J(mu) computed
from scratch has two branches (J jumps by 1.4% over 8 steps) and central differences compare
them. The demo's ContinuationSimulation starts each step's Newton iteration at the base run's
state (the warm start), so the perturbed runs stay on the base run's branch: measured on 5
steps (one run, h in mu), relative errors 1.7e-9 (h = 1e-6), 6.7e-7 (1e-5), 6.7e-5 (1e-4),
1.8e-3 (5e-4), 1.2e-2 (1e-3): the O(h^2) truncation of a J whose curvature is set by contact
pairs entering and leaving dhat (at mu - 1e-3 one pair of step 3 has left).

Checked here: the warm-started perturbed runs reuse the base run's contact pattern, central
differences in log mu agree with the adjoint to ``TOLERANCE`` at h = 1e-5 and 1e-6 along a
random direction and along the gradient, and from h = 1e-4 to 1e-5 the error falls like h^2
(by more than 30x); a cold run at the base parameters reproduces J to round-off.
"""

import os
from pathlib import Path

import numpy as np
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
SMALL_H = (1e-5, 1e-6)  # central-difference steps of log mu checked against TOLERANCE
TRUNCATION_H = 1e-4  # the error from TRUNCATION_H to SMALL_H[0] must fall like h^2


def friction(steps: int, comm: MPI.Comm = COMM):
    """(rf, q0, contact, sim) of the demo's problem over ``steps`` steps (skips without data)."""
    from demo_modules import load_demo

    demo = load_demo("paper_sliding_bunny")
    if not (DIFFIPC / demo.FOLDER / "opt.json").is_file():
        pytest.skip(f"the paper's data is not at {DIFFIPC} (set DIFFSOLIDS_DATA)")
    _, contact, sim, rf, _, _, q0, _ = demo.friction_problem(DIFFIPC, comm, steps)
    return rf, np.log(q0), contact, sim


@pytest.mark.slow
def test_sliding_friction_gradient_against_central_differences():
    rf, q, contact, sim = friction(STEPS)
    J0, g = rf.value_and_gradient(q)
    base = rf.trajectory
    pairs0 = [r.num_collisions for r in contact.records]
    assert max(pairs0) > 0 and abs(g[0]) > 0, f"pairs per step {pairs0}, gradient {g}"

    def warm_start():  # continuation: stay on the base run's branch
        sim.warm_start = base

    steps = (TRUNCATION_H, *SMALL_H)
    results, report = central_differences(rf, q, g, contact, steps, 21, warm_start)
    sim.warm_start = None
    errors = {(r.direction, r.h): r.error for r in results}
    for name in ("random", "gradient"):
        for h in SMALL_H:
            assert errors[name, h] <= TOLERANCE, report
        assert errors[name, TRUNCATION_H] >= 30 * errors[name, SMALL_H[0]], report
    for r in results:
        assert r.pairs == (pairs0, pairs0), report
    # the base parameters again from scratch (no warm start; the last run was at q - h dq)
    J_again = rf(q)
    assert J_again == pytest.approx(J0, rel=1e-12, abs=0.0), (J_again, J0)
