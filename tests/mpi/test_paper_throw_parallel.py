"""Run under ``mpiexec -n 2``: the paper's 3D throw (Fig. 1) gives the serial value and
velocity gradient (2 steps, the bunnies colliding in the first)."""

import numpy as np
import pytest
from mpi4py import MPI
from test_paper_throw_gradient import throw


@pytest.mark.slow
def test_throw_world_equals_self():
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    out = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        rf, q, contact = throw(2, comm)
        out.append((*rf.value_and_gradient(q), [r.num_collisions for r in contact.records]))
    (J_par, g_par, pairs_par), (J_ser, g_ser, pairs_ser) = out
    assert pairs_par == pairs_ser and pairs_ser[-1] > 0
    assert J_par == pytest.approx(J_ser, rel=1e-8)
    assert np.allclose(g_par, g_ser, rtol=1e-6, atol=1e-8 * np.abs(g_ser).max())
