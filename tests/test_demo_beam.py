"""Smoke test of the flagship demo (demos/beam_swing.py) and of its gmsh geometry."""

import importlib.util
import json
from pathlib import Path

import dolfinx
import numpy as np
import pytest
from mpi4py import MPI

from diffsolids.mesh import from_geo

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--tiny"]


def _demo():
    spec = importlib.util.spec_from_file_location("beam_swing", ROOT / "demos" / "beam_swing.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_beam_geo_tags_and_parameters():
    dom = from_geo(ROOT / "meshes" / "beam.geo", MPI.COMM_SELF, numbers={"L": 2.0, "h": 0.2})
    lo, hi = dom.bounding_box()
    assert np.allclose(lo, 0.0)
    assert np.allclose(hi, [2.0, 0.1, 0.1])  # the override of L reached gmsh
    assert dom.names == {"beam": 1, "clamp": 1, "tip": 2}
    fdim = dom.mesh.topology.dim - 1
    for name, x0 in (("clamp", 0.0), ("tip", 2.0)):
        facets = dom.facets_of(name)
        assert facets.size > 0
        mid = dolfinx.mesh.compute_midpoints(dom.mesh, fdim, facets)
        assert np.allclose(mid[:, 0], x0)


@pytest.mark.parametrize("fmt", ["vtx", "xdmf"])
def test_beam_swings_down_and_up(tmp_path, fmt):
    demo = _demo()
    argv = [*TINY, "--out", str(tmp_path)] + (["--xdmf"] if fmt == "xdmf" else [])
    summary = demo.main(argv)

    for f in summary["files"]:
        assert Path(f).exists(), f
    if fmt == "vtx":
        for name in ("beam_swing.bp", "beam_swing_cells.bp"):
            assert (tmp_path / name / "data.0").stat().st_size > 0
    else:
        assert (tmp_path / "beam_swing.xdmf").stat().st_size > 0
        assert (tmp_path / "beam_swing.h5").stat().st_size > 0
    assert (tmp_path / "tip_trajectory.png").stat().st_size > 0

    tip_z = summary["tip"][:, 2]
    csv = np.loadtxt(tmp_path / "tip_trajectory.csv", delimiter=",")
    assert csv.shape == (summary["steps"] + 1, 4)
    assert np.allclose(csv[:, 3], tip_z)
    assert tip_z[0] == 0.0
    low = int(np.argmin(tip_z))
    assert 0 < low < len(tip_z) - 1
    assert tip_z[low] < -0.3  # it falls far (large deformation) ...
    assert tip_z[low:].max() > tip_z[low] + 0.3  # ... and swings back up
    assert np.all(np.diff(tip_z[: low + 1]) < 0)  # monotone fall from rest
    assert summary["newton_its"] >= summary["steps"]
    assert summary["swung_down_and_up"]
    assert json.loads((tmp_path / "result.json").read_text())["newton_its"] == summary["newton_its"]
