import gc
import os

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")
# Tests compile hundreds of small forms on a cold cache (CI): unoptimised kernels compile about
# five times faster and run fast enough on test-sized meshes. Benchmarks and demos keep -O2.
os.environ.setdefault("DIFFSOLIDS_JIT_CFLAGS", "-O0 -g0")

# Test modules may import dolfinx before diffsolids; diffsolids loads the MPI library of the PyPI
# DOLFINx wheel first (dolfinx_solver), which the DOLFINx bindings need.
import diffsolids  # noqa: F401


@pytest.fixture(autouse=True, scope="module")
def _collect_garbage():
    """Free the solvers of a module's tests (each holds MUMPS instances and MPI communicators)."""
    yield
    gc.collect()


@pytest.fixture
def cantilever():
    """A Neo-Hookean beam [0, 4] x [0, 0.5]^2 (8 x 2 x 2 cells) clamped at x = 0, under gravity."""
    import numpy as np
    from mpi4py import MPI

    from diffsolids import Model, NeoHookean
    from diffsolids.mesh import create_box

    dom = create_box(
        MPI.COMM_WORLD,
        [[0, 0, 0], [4, 0.5, 0.5]],
        [8, 2, 2],
        facets={1: lambda x: np.isclose(x[0], 0)},
    )
    model = Model(dom, NeoHookean(E=1e5, nu=0.3, density=100.0))
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    return model


@pytest.fixture
def file_from_rank_0(tmp_path):
    """``write(name, text) -> path``: rank 0 writes a file that every rank then reads.

    The path is in rank 0's ``tmp_path``, broadcast; every rank returns after the file exists.
    """
    from pathlib import Path

    from mpi4py import MPI

    def write(name: str, text: str) -> str:
        path = MPI.COMM_WORLD.bcast(str(tmp_path / name))
        if MPI.COMM_WORLD.rank == 0:
            Path(path).write_text(text)
        MPI.COMM_WORLD.barrier()
        return path

    return write


@pytest.fixture(scope="module")
def bar2():
    """The static bar of two bodies whose moduli are recovered (optimize_script.bar_problem)."""
    from mpi4py import MPI
    from optimize_script import bar_problem

    return bar_problem(MPI.COMM_WORLD, bodies=2)
