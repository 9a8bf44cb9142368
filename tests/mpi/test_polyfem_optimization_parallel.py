"""Run under ``mpiexec -n 2``: PolyFEM optimisation files of our own give the serial J and
gradient for each variable kind."""

import numpy as np
import pytest
from mpi4py import MPI
from polyfem_own_scenes import write_experiment

from diffsolids.polyfem import read_polyfem_optimization


@pytest.mark.parametrize("kind", ["initial", "friction", "elastic"])
def test_runner_world_equals_self(tmp_path, kind):
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    opt = read_polyfem_optimization(write_experiment(tmp_path, kind, steps=8))
    out = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        problem = opt.build(comm)
        out.append(problem.rf.value_and_gradient(problem.q0))
    (J_par, g_par), (J_ser, g_ser) = out
    assert J_par == pytest.approx(J_ser, rel=1e-9)
    assert np.allclose(g_par, g_ser, rtol=1e-7, atol=1e-12 * np.abs(g_ser).max())
