"""Run under ``mpiexec -n 2``: the shared coefficient packing equals DOLFINx's on every rank
(ghost cells and facets of a partitioned mesh, P1 and P2, 2D and 3D; values compared as bytes
and with np.array_equal)."""

import pytest
from mpi4py import MPI
from test_packing import test_shared_packing_equals_dolfinx


@pytest.mark.parametrize("compare_bytes_below", [0, 2**40])
@pytest.mark.parametrize(("dim", "degree"), [(2, 2), (3, 1)])
def test_shared_packing_equals_dolfinx_on_ranks(dim, degree, compare_bytes_below, monkeypatch):
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    test_shared_packing_equals_dolfinx(dim, degree, compare_bytes_below, monkeypatch)
