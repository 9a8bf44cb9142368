"""Run under ``mpiexec -n 2``: output written on 2 ranks equals output written by one rank."""

import importlib.util
import tempfile
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI
from output_checks import model_on, read_vtx, read_xdmf, write_affine

from diffsolids.mesh import create_box, create_rectangle

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def shared_dir():
    comm = MPI.COMM_WORLD
    path = comm.bcast(tempfile.mkdtemp(prefix="diffsolids-out-") if comm.rank == 0 else None)
    return Path(path)


def _domain(dim, comm):
    if dim == 2:
        return create_rectangle(comm, [[0, 0], [1, 2]], [3, 4])
    return create_box(comm, [[0, 0, 0], [1, 1, 2]], [2, 2, 3])


def _by_coordinates(x, values):
    """Rows of values sorted by their (rounded) coordinates, duplicates (ghosts) removed."""
    _, first = np.unique(np.round(x, 12), axis=0, return_index=True)
    return np.round(x[first], 12), values[first]


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("degree", [1, 2])
def test_parallel_output_equals_serial(shared_dir, dim, degree):
    comm = MPI.COMM_WORLD
    for fmt in ("bp", "xdmf"):
        write_affine(model_on(_domain(dim, comm), degree), shared_dir / f"world.{fmt}")
        if comm.rank == 0:
            write_affine(model_on(_domain(dim, MPI.COMM_SELF), degree), shared_dir / f"self.{fmt}")
    comm.barrier()
    if comm.rank != 0:
        return
    par, ser = read_xdmf(shared_dir / "world.xdmf"), read_xdmf(shared_dir / "self.xdmf")
    assert par["geometry"].shape == ser["geometry"].shape
    assert par["topology"].shape == ser["topology"].shape
    for name, steps in ser["fields"].items():
        for t, (center, values) in steps.items():
            other = par["fields"][name][t][1]
            if center == "Node":
                xs, vs = _by_coordinates(ser["geometry"], values)
                xp, vp = _by_coordinates(par["geometry"], other)
                assert np.array_equal(xs, xp)
                assert np.allclose(vs, vp, atol=1e-14)
            else:  # constant stress: compare the cell values as a multiset
                assert np.allclose(np.sort(values.ravel()), np.sort(other.ravel()), rtol=1e-12)

    par, ser = read_vtx(shared_dir / "world.bp"), read_vtx(shared_dir / "self.bp")
    for sp, ss in zip(par["steps"], ser["steps"], strict=True):
        assert sp["time"] == ss["time"]
        for name in ("displacement", "velocity"):
            xs, vs = _by_coordinates(ss["geometry"], ss[name])
            xp, vp = _by_coordinates(sp["geometry"], sp[name])
            assert np.array_equal(xs, xp)
            assert np.allclose(vs, vp, atol=1e-14)
    cells_par = read_vtx(shared_dir / "world_cells.bp")["steps"]
    cells_ser = read_vtx(shared_dir / "self_cells.bp")["steps"]
    for sp, ss in zip(cells_par, cells_ser, strict=True):
        # each rank writes its owned and ghost cells: compare the distinct values
        assert np.allclose(
            np.unique(np.round(sp["von_mises"], 9)), np.unique(np.round(ss["von_mises"], 9))
        )


def test_beam_demo_parallel_equals_serial(shared_dir):
    spec = importlib.util.spec_from_file_location("beam_swing", ROOT / "demos" / "beam_swing.py")
    demo = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo)
    comm = MPI.COMM_WORLD
    par = demo.main(["--tiny", "--out", str(shared_dir / "world")], comm)
    ser = demo.main(
        ["--tiny", "--no-plot", "--out", str(shared_dir / f"self{comm.rank}")], MPI.COMM_SELF
    )
    assert par["ranks"] == comm.size
    assert np.allclose(par["tip"], ser["tip"], rtol=1e-10, atol=1e-13)
    assert par["newton_its"] == ser["newton_its"]
    assert par["swung_down_and_up"]
    for f in par["files"]:
        assert Path(f).exists()
