"""Run under ``mpiexec -n 2``: steps solved through a stiffness continuation equal serial ones.

Newton rtol 1e-12. The soft barrier makes the step Jacobians ill-conditioned (barrier Hessians
~kappa dhat^2 / d^2 at d = 5e-8 m): the ranks' other summation order moves the friction
coefficient's gradient by 1.6e-10 relative with direct solves, 4.7e-10 with continued ones.
"""

import numpy as np
import pytest
from mpi4py import MPI
from test_stiffness_continuation import DATA, STEPS, _run

RTOL = 1e-9


def test_continued_block_world_equals_self():
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    _, q_par, J_par, g_par, continued_par, gaps_par = _run(1, comm, rtol=1e-12)
    _, q_ser, J_ser, g_ser, continued_ser, gaps_ser = _run(1, MPI.COMM_SELF, rtol=1e-12)
    assert continued_par == continued_ser >= STEPS // 2
    assert np.array_equal(q_par, q_ser)
    assert np.allclose(gaps_par, gaps_ser, rtol=1e-6)
    assert J_par == pytest.approx(J_ser, rel=RTOL)
    diff = np.abs(g_par - g_ser).max() / np.abs(g_ser).max()
    assert diff <= RTOL, diff
    for value in comm.allgather(J_par):
        assert value == J_par


def _ball(comm: MPI.Comm, steps: int):
    """Fig. 22's ball at its own kappa 1e4 for ``steps`` steps (its impact from step 2)."""
    from diffsolids.polyfem import read_polyfem_optimization

    opt_json = DATA / "diffipc" / "fig22_bounce_ball" / "opt.json"
    if not opt_json.is_file():
        pytest.skip(f"the paper's data is not at {opt_json.parent.parent} (set DIFFSOLIDS_DATA)")
    problem = read_polyfem_optimization(opt_json).build(comm, steps=steps, stiffness=None)
    problem.rf.controls.assign(problem.q0)
    traj = problem.rf.simulation.run()
    return problem.rf.simulation.solver, traj.records


def test_floor_continuations_world_equal_self():
    """The pair pressed to the gap floor starts the same continuations on 2 ranks as serially."""
    solver_par, records_par = _ball(MPI.COMM_WORLD, 3)
    solver_ser, records_ser = _ball(MPI.COMM_SELF, 3)
    assert solver_par.floor_continuations == solver_ser.floor_continuations == 2
    assert solver_par.continued_steps == solver_ser.continued_steps == 2
    energies_par = [r.energy for r in records_par]
    assert np.allclose(energies_par, [r.energy for r in records_ser], rtol=1e-9, atol=0)
    for values in MPI.COMM_WORLD.allgather(energies_par):
        assert values == energies_par
    # its pairs rest at round-off: the steps accepted there are the same, on every rank
    round_off = [s[0] for s in solver_par.round_off_steps]
    assert round_off == [s[0] for s in solver_ser.round_off_steps] != []
    assert MPI.COMM_WORLD.allgather(solver_par.round_off_steps)[0] == solver_par.round_off_steps
