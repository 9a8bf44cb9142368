"""A first Newton attempt that nears a saddle of the step's potential stops early.

The paper's Fig. 21 sliding bunny at its target friction mu = 0.1 (opt.json's problem through
``demos/paper_sliding_bunny.friction_problem``, 5 steps, default ``SolverOptions``): in step 5
the projected Newton phase reaches a residual of 2.5e-3 (rtol x f_char is 9e-8) where the
exact contact Hessian is indefinite: its Newton step is no descent direction, and the
projected steps that replace it leave the saddle at a linear rate (the residual grows for 70
iterations and the attempt fails at the iteration limit). After ``SADDLE_STREAK`` such steps in
a row the attempt stops and the step is solved again with exact steps from the start: the same
state, and no step above the default iteration limit.
"""

import numpy as np
import pytest
from mpi4py import MPI
from test_paper_sliding_gradient import DIFFIPC

import diffsolids as ds
import diffsolids.solvers.newton as newton

STEPS = 5
TARGET_MU = 0.1


@pytest.mark.slow
def test_saddle_stop_keeps_the_state_within_the_iteration_limit(monkeypatch):
    from demo_modules import load_demo

    demo = load_demo("paper_sliding_bunny")
    if not (DIFFIPC / demo.FOLDER / "opt.json").is_file():
        pytest.skip(f"the paper's data is not at {DIFFIPC} (set DIFFSOLIDS_DATA)")
    _, problem = demo.friction_problem(DIFFIPC, MPI.COMM_WORLD, STEPS)
    target = problem.targets[1]  # mu = 0.1 with the default options
    limit = ds.SolverOptions().max_iterations
    its = [r.iterations for r in target.records]
    assert max(its) <= limit, its

    monkeypatch.setattr(newton, "SADDLE_STREAK", 10**9)  # no saddle stop: the limit comes first
    problem.rf(np.array([TARGET_MU]))
    plain = problem.rf.trajectory
    plain_its = [r.iterations for r in plain.records]
    assert problem.simulation.solver.saddle_stops == 0
    assert max(plain_its) > limit, plain_its
    assert sum(its) < sum(plain_its)
    for u, up in zip(target.u, plain.u, strict=True):
        assert np.abs(u - up).max() <= 1e-10
