"""Run under ``mpiexec -n 2``: a driven body (``OnBody``) gives the serial value and gradient."""

import numpy as np
import pytest
from mpi4py import MPI
from test_dirichlet_body import driven_body_functional
from test_dirichlet_body import test_every_node_of_the_body_is_constrained as check_node_count


def test_every_node_of_the_body_is_constrained_on_two_ranks():
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    check_node_count()


def test_driven_body_gradient_world_equals_self():
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    out = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        rf = driven_body_functional(comm)
        q = rf.initial_parameters()
        q = q + 0.1 * np.random.default_rng(3).standard_normal(q.size)
        out.append(rf.value_and_gradient(q))
    (J_par, g_par), (J_ser, g_ser) = out
    assert J_par == pytest.approx(J_ser, rel=1e-10)
    assert np.allclose(g_par, g_ser, rtol=1e-8, atol=1e-10 * np.abs(g_ser).max())
