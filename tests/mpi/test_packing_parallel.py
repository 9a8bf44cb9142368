"""Run under ``mpiexec -n 2``: the shared coefficient packing equals DOLFINx's on every rank
(ghost cells and facets of a partitioned mesh, P1 and P2, 2D and 3D)."""

import pytest
from mpi4py import MPI
from test_packing import test_shared_packing_equals_dolfinx


@pytest.mark.parametrize(("dim", "degree"), [(2, 2), (3, 1)])
def test_shared_packing_equals_dolfinx_on_ranks(dim, degree):
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    test_shared_packing_equals_dolfinx(dim, degree)
