import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

# Test modules may import dolfinx before diffsolids; diffsolids loads the MPI library of the PyPI
# DOLFINx wheel first (dolfinx_solver), which the DOLFINx bindings need.
import diffsolids  # noqa: F401
