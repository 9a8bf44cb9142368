"""Run under ``mpiexec -n 2``: a paper scene read from its PolyFEM JSON on 2 ranks equals serial.

The fig14 puzzle scene (a few steps with contact, the paper's objective, the piece's initial
velocity as control; see test_paper_scenes.paper_gradient_scene) is built on COMM_WORLD and on
COMM_SELF in the same process: objective, gradient and Newton iterations must agree.
"""

import numpy as np
from mpi4py import MPI
from test_paper_scenes import paper_gradient_scene

RTOL = 1e-8


def _value_and_gradient(comm):
    rf, q, contact = paper_gradient_scene("puzzle", comm)
    J = rf(q)
    iterations = rf.trajectory.newton_iterations()
    gaps = [r.min_distance for r in contact.records[-6:]]
    return J, rf.gradient(q), iterations, gaps


def test_puzzle_scene_world_equals_self():
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    J_par, g_par, its_par, gaps_par = _value_and_gradient(comm)
    J_ser, g_ser, its_ser, gaps_ser = _value_and_gradient(MPI.COMM_SELF)
    assert np.isfinite(gaps_ser).sum() >= 3
    assert its_par == its_ser
    assert np.allclose(gaps_par, gaps_ser, rtol=1e-6)
    assert abs(J_par - J_ser) <= RTOL * abs(J_ser)
    assert np.allclose(g_par, g_ser, rtol=RTOL, atol=0.0), (g_par, g_ser)
