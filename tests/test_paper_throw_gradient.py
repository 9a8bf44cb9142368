"""Central differences verify the adjoint gradient of the paper's Fig. 1 throw (3D, paper data).

The scene ``fig1_bunnies`` (pool + two Stanford bunnies, 6 183 dofs) as the demo builds it from
opt.json (``demos/paper_throw_bunnies.throw_problem``, the runner's problem with area-weighted
pairs: the second bunny's final centre of mass (x, z), squared distance to the spot; the
first bunny's initial velocity; default solver options) over the
first ``STEPS`` steps: the bunnies touch in step 2 (17 pairs) and step 3 (56 pairs).

Measured on this scene (2 steps, h = 1e-3 .. 1e-6, random direction and along the gradient):
with the exact Hessian from the first Newton iteration (exact_hessian_below = inf, the solver's
default until 7130d90) the step-2 solve at the scene's v0 = (2, 0.5, 0) ends at a stationary
point with 19 contact pairs and an incremental potential 0.083 above the minimum (17 pairs) that
projected Newton reaches from the same start; for v0 + h d Newton lands on either, J jumps by
1.4e-3 between them, and central differences are off by 0.2 .. 7e4 relative for every h. Neither
rtol (1e-8, 1e-10), the initial guess ("predictor", "previous"), cut-step marching (march_after
0) nor warm starts change that (a warm start is refused: the CCD admits 0.75 of the straight
path from u^1 to the converged u^2). Projected steps only (exact_hessian_below = 0) converge
linearly and leave a bias of 2e-5.

PSD-projected Newton steps while the residual is above 1e-3 f_char and the exact Hessian below
(``SolverOptions.exact_hessian_below = 1e-3``, the demo's and now the solver's default) descend
into the minimum and converge quadratically there; then J is smooth for |h| <= 1e-4 (h = 1e-3
reaches another minimum, 19 pairs, J 1.4e-3 higher) and central differences agree with the
adjoint to better than 1e-6: at h = 1e-4, 3.4e-7 (random direction) and 1.3e-7 (gradient) over
2 steps, 7.6e-8 and 3.1e-8 over 3 steps, 1.3e-7 (random) over 4. On the whole 40 steps (one
run, not a test: 75 s per forward) 1.8e-7 (random) and 5.8e-8 (gradient) at h = 1e-5, 1.7e-5
and 1.2e-5 at h = 1e-4 (truncation), the same contact pairs per step in all runs.
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

STEPS = 3  # contact in steps 2 and 3
H = 1e-4  # central-difference step of the velocity [m/s] (|v0| = 2.06)
TOLERANCE = 1e-6


def throw(steps: int, comm: MPI.Comm = COMM):
    """(rf, q0, contact) of the demo's throw over ``steps`` steps (skips without the data)."""
    from demo_modules import load_demo

    demo = load_demo("paper_throw_bunnies")
    if not (DIFFIPC / demo.FOLDER / "opt.json").is_file():
        pytest.skip(f"the paper's data is not at {DIFFIPC} (set DIFFSOLIDS_DATA)")
    _, problem = demo.throw_problem(DIFFIPC, comm, steps)
    return problem.rf, problem.q0, problem.contact


@pytest.mark.slow
def test_throw_velocity_gradient_against_central_differences():
    rf, q, contact = throw(STEPS)
    g = rf.gradient(q)
    pairs = [r.num_collisions for r in contact.records]
    assert pairs[-1] > 0, f"no contact in the last step: pairs per step {pairs}"
    results, report = central_differences(rf, q, g, contact, [H], 14)
    for r in results:
        assert abs(r.adjoint) > 0, report
        assert r.error <= TOLERANCE, report
