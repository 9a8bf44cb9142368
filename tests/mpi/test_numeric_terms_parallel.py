"""Run under ``mpiexec -n 2``: a user's NumericTerm gives the serial value and gradient."""

import numpy as np
from mpi4py import MPI
from test_numeric_terms import _check, _reduced, _spring_simulation


def test_ground_spring_on_two_ranks_equals_serial():
    world = _reduced(_spring_simulation(MPI.COMM_WORLD)[0])
    serial = _reduced(_spring_simulation(MPI.COMM_SELF)[0])
    q = world.initial_parameters()
    assert np.allclose(q, serial.initial_parameters(), rtol=0, atol=0)
    assert abs(world(q) - serial(q)) <= 1e-10 * abs(serial(q))
    gw, gs = world.gradient(q), serial.gradient(q)
    assert np.allclose(gw, gs, rtol=1e-8, atol=1e-8 * np.abs(gs).max())
    _check(world)
