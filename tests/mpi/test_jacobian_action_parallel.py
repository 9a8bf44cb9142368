"""Run under ``mpiexec -n 2``: the matrix-free Jacobian with coefficients packed once per solve
(ghost values of the direction included) equals the assembled exact Jacobian on 2 ranks."""

import numpy as np
import pytest
from mpi4py import MPI
from test_jacobian_action import actions, damped_newton, exact_products


@pytest.mark.parametrize("degree", [1, 2])
def test_packed_once_action_equals_assembled_jacobian(degree):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    newton = damped_newton(comm, degree)
    x = newton.create_matrix().createVecRight()
    start, _ = x.getOwnershipRange()
    rng = np.random.default_rng(7)
    directions = []
    for _ in range(2):
        d = rng.standard_normal(x.getSize())  # the same global vector on every rank
        directions.append(d[start : start + x.getLocalSize()])
    fixed, _ = actions(newton, directions, fixed=True)
    for yf, ye in zip(fixed, exact_products(newton, directions), strict=True):
        err, size = (comm.allreduce(np.sum(v**2), op=MPI.SUM) ** 0.5 for v in (yf - ye, ye))
        assert err <= 1e-12 * size
