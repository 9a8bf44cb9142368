"""Run under ``mpiexec -n 2``: kernels built on rank 0, loaded by the others, same values."""

import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from dolfinx import fem
from mpi4py import MPI
from test_cold_start import _files, _options, _residual

from diffsolids.parallel import collective_comm
from diffsolids.solvers import jit

pytestmark = [
    pytest.mark.skipif(MPI.COMM_WORLD.size < 2, reason="needs mpiexec -n 2"),
    pytest.mark.skipif(not jit.background_available(), reason="no POSIX C compiler"),
]


@pytest.fixture(autouse=True)
def _background(monkeypatch):
    monkeypatch.setenv("DIFFSOLIDS_JIT_BACKGROUND", "1")


@pytest.fixture
def shared_dir():
    comm = collective_comm(MPI.COMM_WORLD)
    path = Path(comm.bcast(tempfile.mkdtemp(prefix="diffsolids-jit-") if comm.rank == 0 else None))
    yield path
    comm.barrier()
    if comm.rank == 0:
        shutil.rmtree(path, ignore_errors=True)


def test_built_on_rank_zero_same_vector_as_dolfinx(shared_dir):
    comm = MPI.COMM_WORLD
    form = _residual(comm)
    built = jit.build_form(form, _options(shared_dir / "a"))
    assert type(built) is fem.Form  # no lazy forms under MPI: every rank holds the module
    vec = fem.assemble_vector(built)
    reference = fem.assemble_vector(fem.form(form, jit_options=_options(shared_dir / "b")))
    assert np.array_equal(vec.array, reference.array)
    norm = np.sqrt(comm.allreduce(float(vec.array @ vec.array), op=MPI.SUM))
    assert norm > 1e-3
    comm.barrier()
    name = jit.module_name(form, _options(shared_dir / "a"))
    assert {f"{name}.c", f"{name}.c.cached"} <= _files(shared_dir / "a")


def test_a_compiler_error_is_raised_on_every_rank(shared_dir):
    options = _options(shared_dir, ["-O2", "-fno-such-flag-diffsolids"])
    with pytest.raises(RuntimeError, match=r"rank 0 failed.*C compiler failed"):
        jit.build_form(_residual(MPI.COMM_WORLD), options)
