"""Run under ``mpiexec -n 2``: the optimiser takes the same iterates on 2 ranks as on 1.

Each test runs the problem on COMM_WORLD and on COMM_SELF in the same process.
"""

import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI
from optimize_script import E_TRUE, bar_problem, check_observed_run, dynamic_problem, observed_run
from petsc4py import PETSc

from diffsolids.optimize import LBFGS, LBFGSOptions

OPTIONS = {"gradient_rtol": 0.0}


@pytest.fixture
def shared_dir():
    """A temporary directory seen by all ranks."""
    comm = MPI.COMM_WORLD
    path = tempfile.mkdtemp(prefix="diffsolids_opt_") if comm.rank == 0 else None
    path = Path(comm.bcast(path, root=0))
    yield path
    comm.barrier()
    if comm.rank == 0:
        shutil.rmtree(path, ignore_errors=True)


def _optimise(comm, iterations, **kwargs):
    rf, _ = dynamic_problem(comm)
    options = LBFGSOptions(max_iterations=iterations, **OPTIONS)
    opt = LBFGS(rf, options, write_parameters=True, plot_every=0, **kwargs)
    return opt, opt.run()


def _compare(a, b, rtol):
    Ja = np.array([r.objective for r in a.history])
    Jb = np.array([r.objective for r in b.history])
    assert len(Ja) == len(Jb)
    assert np.all(np.abs(Ja - Jb) <= rtol * np.abs(Jb)), np.abs(Ja - Jb) / np.abs(Jb)
    qa = np.array([r.q for r in a.history])
    qb = np.array([r.q for r in b.history])
    assert np.all(np.abs(qa - qb) <= rtol * np.abs(qb)), np.abs(qa - qb).max()


def test_same_iterates_on_world_and_self():
    assert MPI.COMM_WORLD.size > 1, "run under mpiexec -n 2"
    _, world = _optimise(MPI.COMM_WORLD, 7)
    _, serial = _optimise(MPI.COMM_SELF, 7)
    _compare(world, serial, 1e-8)
    assert [r.trials for r in world.history] == [r.trials for r in serial.history]
    assert world.history[-1].objective < 1e-2 * world.history[0].objective
    # every rank ends with the same parameters
    assert all(np.array_equal(q, world.q) for q in MPI.COMM_WORLD.allgather(world.q))


def test_resume_from_per_rank_checkpoint(shared_dir):
    comm = MPI.COMM_WORLD
    ckpt = shared_dir / "checkpoint"
    _optimise(comm, 3, checkpoint_dir=ckpt, output_dir=shared_dir / "out")
    comm.barrier()
    files = sorted(p.name for p in ckpt.glob("trajectory_*_rank*.npz"))
    assert files == [f"trajectory_it000003_m000_rank{r:04d}.npz" for r in range(comm.size)]
    _, resumed = _optimise(comm, 6, checkpoint_dir=ckpt, output_dir=shared_dir / "out")
    assert resumed.resumed_from == 3
    _, reference = _optimise(comm, 6)
    _compare(resumed, reference, 1e-10)
    lines = (shared_dir / "out" / "history.jsonl").read_text().splitlines()
    assert len(lines) == 7  # rank 0 writes it once


def test_on_accept_once_per_accepted_iterate_on_every_rank():
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run under mpiexec -n 2"
    rf, _ = bar_problem(comm, bodies=1)
    options = LBFGSOptions(initial_step=3.0, gradient_rtol=1e-8)
    result, trials, calls = observed_run(rf, options, fail_above=2200.0)
    assert result.num_invalid_trials >= 2 and result.converged
    check_observed_run(result, trials, calls)
    # the same calls on every rank
    iterations = [c[1].iteration for c in calls[0::3]]
    assert comm.allgather(iterations) == [iterations] * comm.size


def test_tao_with_a_distributed_vector():
    comm = MPI.COMM_WORLD
    rf, _ = bar_problem(comm, bodies=2)
    q0 = rf.initial_parameters()
    x = PETSc.Vec().createMPI(rf.size, comm=comm)
    start, end = x.getOwnershipRange()
    x.setArray(q0[start:end])
    g = x.duplicate()
    tao = PETSc.TAO().create(comm)
    tao.setType("lmvm")
    tao.setObjectiveGradient(rf.tao_objective_gradient, g)
    tao.setTolerances(gatol=1e-13, grtol=0.0, gttol=0.0)
    tao.setMaximumIterations(200)
    tao.setSolution(x)
    tao.solve()
    assert tao.getConvergedReason() > 0
    scatter, full = PETSc.Scatter.toAll(x)
    scatter.scatter(x, full, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
    assert np.allclose(np.exp(full.getArray()), E_TRUE, rtol=1e-6)
    for obj in (tao, x, g, full, scatter):
        obj.destroy()


def test_floor_search_world_equals_self():
    """FloorSearch takes the same evaluations on 2 ranks as on 1 (the bar's two moduli)."""
    from diffsolids.optimize import FloorSearch

    runs = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        rf, q_true = bar_problem(comm, bodies=2)
        search = FloorSearch(rf, (1.0, 1.0), (1e-8, 1e-6), 60)
        runs.append(search.run(rf.initial_parameters()))
    world, own = runs
    assert world.reason == own.reason == "step"
    assert len(world.history) == len(own.history)
    qw = np.array([r.q for r in world.history])
    qs = np.array([r.q for r in own.history])
    assert np.allclose(qw, qs, rtol=0, atol=1e-8)
    assert np.allclose(world.q, q_true, rtol=0, atol=1e-5)
