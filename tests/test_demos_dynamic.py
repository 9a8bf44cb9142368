"""Smoke tests of the transient contact demos (throw, sliding friction, puzzle, shock protection).

Each demo runs in-process at its ``--tiny`` size: the objective must decrease and the
invariants hold (no inverted element, no intersection in any reported state); the outcome
thresholds of the default size (e.g. the target circle reached) are not asserted here.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from demo_modules import load_demo
from mpi4py import MPI

from diffsolids.mesh import from_geo

ROOT = Path(__file__).resolve().parents[1]
INVARIANTS = ["objective decreased", "no inverted element", "no intersection"]
DEMO_NAMES = ["puzzle_initial_velocity", "shock_protection", "sliding_friction", "throw"]


@pytest.mark.parametrize("name", DEMO_NAMES)
def test_dynamic_demo_tiny(name, tmp_path):
    report = load_demo(name).main(["--tiny", "--out", str(tmp_path), "--no-plot"])
    outcomes = {o.name: o for o in report.outcomes}
    for required in INVARIANTS:
        assert outcomes[required].passed, outcomes[required]
    assert report.final_objective < report.initial_objective
    assert report.iterations >= 1
    for path in report.extra["files"]:
        assert Path(path).exists(), path
    saved = json.loads((tmp_path / "result.json").read_text())
    assert saved["final_objective"] == pytest.approx(report.final_objective)


def test_throw_scene_geometry():
    """Bodies and tags of both throw scenes; the ground's top is one edge (2D) / triangle (3D)."""
    for geo, dim, top_vertices in (("throw2d.geo", 2, 2), ("throw3d.geo", 3, 3)):
        domain = from_geo(ROOT / "meshes" / geo, MPI.COMM_SELF, numbers={"h": 0.06})
        assert domain.names == {"ground": 1, "A": 2, "B": 3, "ground_top": 1}
        mesh = domain.mesh
        x = mesh.geometry.x[:, :dim]
        dofmap = mesh.geometry.dofmaps[0]
        ground = np.unique(dofmap[domain.cells_of("ground")])
        bodies = np.unique(dofmap[np.concatenate([domain.cells_of("A"), domain.cells_of("B")])])
        assert np.all(x[ground, -1] <= 1e-12)  # the ground lies below z = 0 ...
        assert x[bodies, -1].min() > 1e-4  # ... and the bodies above it, with a gap
        assert np.sum(np.isclose(x[ground, -1], 0.0)) == top_vertices
