"""Run under ``mpiexec -n 2``: a PolyFEM scene with its ground as a kinematic obstacle gives
the serial value and velocity gradient."""

import numpy as np
import pytest
from mpi4py import MPI
from test_polyfem_obstacles import puzzle_functional


def test_obstacle_scene_world_equals_self():
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    out = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        rf, q = puzzle_functional(comm)
        out.append(rf.value_and_gradient(q))
    (J_par, g_par), (J_ser, g_ser) = out
    assert J_par == pytest.approx(J_ser, rel=1e-9)
    assert np.allclose(g_par, g_ser, rtol=1e-7, atol=0)
