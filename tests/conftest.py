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
