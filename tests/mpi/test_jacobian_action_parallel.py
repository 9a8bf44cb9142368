"""Run under ``mpiexec -n 2``: the matrix-free Jacobian with coefficients packed once per solve
(ghost values of the direction included) equals the assembled exact Jacobian on 2 ranks."""

import numpy as np
import pytest
from mpi4py import MPI
from test_jacobian_action import actions, damped_newton


@pytest.mark.parametrize("degree", [1, 2])
def test_packed_once_action_equals_assembled_jacobian(degree):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    newton = damped_newton(comm, degree)
    A = newton.create_matrix()
    newton.assemble_jacobian(A, exact=True)
    x, y = A.createVecs()
    start, _ = x.getOwnershipRange()
    rng = np.random.default_rng(7)
    directions = []
    for _ in range(2):
        d = rng.standard_normal(x.getSize())  # the same global vector on every rank
        directions.append(d[start : start + x.getLocalSize()])
    fixed, _ = actions(newton, directions, fixed=True)
    for d, yf in zip(directions, fixed, strict=True):
        x.array_w[:] = d
        A.mult(x, y)
        err = comm.allreduce(np.sum((yf - y.array_r) ** 2), op=MPI.SUM) ** 0.5
        assert err <= 1e-12 * y.norm()
