"""The branch reference on 2 ranks: the same J and gradient as serial, history-independent."""

import numpy as np
from mpi4py import MPI
from smoothness_scenes import ridge

COMM = MPI.COMM_WORLD
OFFSET = 0.004  # the block tips to the side of its offset on any number of ranks


def test_ridge_with_reference_equals_serial():
    parallel = ridge(COMM, steps=9, offset=OFFSET)
    q = parallel.q0 + np.array([0.003, -0.002])
    J, g = parallel.rf.value_and_gradient(q)
    assert parallel.rf.simulation.branch_reference is not None
    serial = ridge(MPI.COMM_SELF, steps=9, offset=OFFSET)
    Js, gs = serial.rf.value_and_gradient(q)
    assert abs(J - Js) <= 1e-10 * abs(Js), (J, Js)
    assert np.allclose(g, gs, rtol=1e-8, atol=0), (g, gs)
    # the same q after another point gives the same J to the last bit
    parallel.rf(parallel.q0 - 0.01)
    assert parallel.rf(q) == J
    pairs = [r.num_collisions for r in parallel.contact.records]
    assert COMM.allreduce(sum(pairs), op=MPI.SUM) > 0
