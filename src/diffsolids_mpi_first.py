"""Make ``import dolfinx`` (or ``petsc4py``) work as the first import of a script.

The PyPI DOLFINx wheel (``dolfinx-solver-real``) links its bindings against ``libmpi.so.12``
of the PyPI ``mpich`` wheel, which the dynamic loader finds only after ``mpi4py.MPI`` has loaded
it; ``import dolfinx_solver`` does that in the right order. A script that starts with
``import dolfinx`` fails with ``ImportError: libmpi.so.12: cannot open shared object file``.

This module installs a meta-path finder that imports ``dolfinx_solver`` the first time one of
the MPI-linked packages is imported, and does nothing where no ``dolfinx_solver`` exists
(a conda, spack or docker DOLFINx). ``python -m diffsolids_mpi_first --install`` writes a
``.pth`` file into the environment's site-packages so that every interpreter of the environment
installs the finder at start-up (``make setup`` does this for the README's venv); the finder
costs nothing until one of those packages is imported.
"""

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import sysconfig
import types
from collections.abc import Sequence
from pathlib import Path

__all__ = ["PTH_NAME", "MPIFirstFinder", "install_finder", "install_pth"]

#: Top-level packages whose compiled modules link the wheel's MPI.
MPI_LINKED = frozenset({"dolfinx", "petsc4py", "slepc4py"})

#: Name of the start-up file in site-packages.
PTH_NAME = "diffsolids-mpi-first.pth"


class MPIFirstFinder(importlib.abc.MetaPathFinder):
    """Imports ``dolfinx_solver`` before the first MPI-linked package, then steps aside."""

    def find_spec(  # noqa: D102
        self,
        fullname: str,
        path: Sequence[str] | None = None,
        target: types.ModuleType | None = None,
    ) -> importlib.machinery.ModuleSpec | None:
        if fullname.partition(".")[0] in MPI_LINKED:
            sys.meta_path[:] = [f for f in sys.meta_path if not isinstance(f, MPIFirstFinder)]
            if "dolfinx_solver" not in sys.modules and importlib.util.find_spec("dolfinx_solver"):
                importlib.import_module("dolfinx_solver")
        return None  # the regular finders import the package itself


def install_finder() -> None:
    """Put the finder first on ``sys.meta_path`` (once)."""
    if not any(isinstance(f, MPIFirstFinder) for f in sys.meta_path):
        sys.meta_path.insert(0, MPIFirstFinder())


def install_pth() -> Path:
    """Write the start-up ``.pth`` file into this interpreter's site-packages.

    Returns:
        The path written.
    """
    path = Path(sysconfig.get_paths()["purelib"]) / PTH_NAME
    path.write_text("import diffsolids_mpi_first; diffsolids_mpi_first.install_finder()\n")
    return path


if __name__ == "__main__":
    if sys.argv[1:] != ["--install"]:
        sys.exit("usage: python -m diffsolids_mpi_first --install")
    print(f"wrote {install_pth()}")
