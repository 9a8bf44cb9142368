"""Inputs a user gets wrong: each refused with an error that names the file, entity and value.

Every case runs in a child process too (a crash cannot fail an in-process test); the
checkpoint-directory case also on 2 ranks, where an error on rank 0 alone would hang the run.
"""

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from child_process import assert_child_raises
from mpi4py import MPI

import diffsolids as ds
from diffsolids.contact import Obstacle
from diffsolids.controls import ControlError, ParameterControl
from diffsolids.errors import MeshError
from diffsolids.optimize import OptimizationError
from diffsolids.optimize.checkpoint import Checkpoint

MPIEXEC = Path(sys.executable).parent / "mpiexec"

NAN_MSH = """$MeshFormat
2.2 0 8
$EndMeshFormat
$Nodes
4
1 0 0 0
2 1 0 0
3 nan 1 0
4 1 1 0
$EndNodes
$Elements
2
1 2 2 1 1 1 2 3
2 2 2 1 1 2 4 3
$EndElements
"""

BAD_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0.5\nv 1 1 0.5\nf 1 2 3\nf 2 4 5\n"


@pytest.fixture
def files(tmp_path):
    (tmp_path / "nan.msh").write_text(NAN_MSH)
    (tmp_path / "bad.obj").write_text(BAD_OBJ)
    (tmp_path / "taken").write_text("a file where a directory is wanted\n")
    return tmp_path


def test_a_non_finite_coordinate_is_named(files):
    with pytest.raises(MeshError, match=r"nan\.msh: 1 vertices have non-finite .*indices 2\b"):
        ds.mesh.read_mesh(files / "nan.msh", MPI.COMM_SELF)
    assert_child_raises(
        "import diffsolids as ds\nds.mesh.read_mesh('nan.msh')",
        "diffsolids.errors.MeshError: nan.msh: 1 vertices have non-finite",
        files,
    )


def test_a_face_index_out_of_range_is_named(files):
    message = r"bad\.obj: triangle cell 1 refers to vertex 4 \(0-based\), but the file has 4"
    with pytest.raises(MeshError, match=message):
        Obstacle.from_file(files / "bad.obj")
    assert_child_raises(
        "from diffsolids.contact import Obstacle\nObstacle.from_file('bad.obj')",
        "diffsolids.errors.MeshError: obstacle file bad.obj: triangle cell 1 refers to vertex 4",
        files,
    )


def test_a_checkpoint_directory_that_is_a_file_is_named(files):
    with pytest.raises(OptimizationError, match=r"checkpoint directory .*taken is a file"):
        Checkpoint(files / "taken", MPI.COMM_WORLD)
    script = textwrap.dedent(
        """
        from mpi4py import MPI
        from diffsolids.optimize.checkpoint import Checkpoint
        Checkpoint("taken", MPI.COMM_WORLD)
        """
    )
    assert_child_raises(script, "diffsolids.optimize.options.OptimizationError:", files)
    if MPI.COMM_WORLD.size == 1 and MPIEXEC.exists():
        run = subprocess.run(
            [str(MPIEXEC), "-n", "2", sys.executable, "-c", script],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=files,
        )
        assert run.returncode != 0 and run.stderr.count("taken is a file") == 2, run.stderr


def _model():
    box = ds.mesh.simplex_box([[0.0, 0.0], [1.0, 1.0]], [2, 2])
    domain = ds.combine_meshes(MPI.COMM_WORLD, [box], names={"box": 1})
    return ds.Model(domain, ds.LinearElastic(E=1e3, nu=0.3))


@pytest.mark.parametrize(
    ("bounds", "message"),
    [
        ({"lower": 2.0, "upper": 1.0}, r"lower bound above .* lower 2 > upper 1"),
        ({"lower": [1.0, 2.0, 3.0]}, r"bounds of shapes \(3,\) and \(\) for 1 parameters"),
        ({"upper": np.nan}, "bounds contain NaN"),
    ],
)
def test_malformed_bounds_are_refused_where_the_control_is_made(bounds, message):
    with pytest.raises(ControlError, match=message):
        ParameterControl(_model(), "E", "uniform", **bounds)


def test_a_lame_control_of_a_young_model_says_how_to_get_one():
    with pytest.raises(ControlError, match=r"'lmbda'.*give them as lmbda=\.\.\., mu=\.\.\."):
        ParameterControl(_model(), "lmbda", "uniform")
