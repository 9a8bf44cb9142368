"""The branch reference on 2 ranks: the same J and gradient as serial, history-independent."""

import numpy as np
from mpi4py import MPI
from smoothness_scenes import ridge
from test_branch_reference import _fail_once

COMM = MPI.COMM_WORLD
OFFSET = 0.004  # the block tips to the side of its offset on any number of ranks


def test_ridge_with_reference_equals_serial():
    parallel = ridge(COMM, steps=9, offset=OFFSET)
    q = parallel.q0 + np.array([0.003, -0.002])
    J, g = parallel.rf.value_and_gradient(q)
    assert parallel.rf.reference_run is not None
    serial = ridge(MPI.COMM_SELF, steps=9, offset=OFFSET)
    Js, gs = serial.rf.value_and_gradient(q)
    assert abs(J - Js) <= 1e-10 * abs(Js), (J, Js)
    assert np.allclose(g, gs, rtol=1e-8, atol=0), (g, gs)
    # the same q after another point gives the same J to the last bit
    parallel.rf(parallel.q0 - 0.01)
    assert parallel.rf(q) == J
    pairs = [r.num_collisions for r in parallel.contact.records]
    assert COMM.allreduce(sum(pairs), op=MPI.SUM) > 0


def _forced_fallback(comm, q, monkeypatch, step: int = 7):
    """J at q when the solve of ``step`` from the reference's state is made to fail."""
    scene = ridge(comm, steps=9, offset=OFFSET)
    scene.rf(scene.q0)  # the reference run
    forced = _fail_once(scene.rf.simulation, monkeypatch, step)
    J = scene.rf(q)
    assert forced == [(step, False)]
    return J, [r.iterations for r in scene.rf.trajectory.records]


def test_fallback_from_the_reference_equals_serial(monkeypatch):
    q = np.log([6e4, 0.2]) + np.array([0.003, -0.002])  # near the ridge scene's q0
    J, its = _forced_fallback(COMM, q, monkeypatch)
    Js, its_serial = _forced_fallback(MPI.COMM_SELF, q, monkeypatch)
    assert abs(J - Js) <= 1e-10 * abs(Js), (J, Js)
    assert its == its_serial and its[6] > 1000, (its, its_serial)
