"""Smoke tests of the material optimisation demos (sine bar, bridge, bouncing ball, kangaroo).

Each demo runs in-process at its ``--tiny`` size: the objective must decrease and the
invariants hold (no inverted element; no intersection in the contact scenes); the outcome
thresholds of the default size (e.g. the 10-fold fit reduction) are not asserted here.
"""

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from demo_modules import load_demo
from mpi4py import MPI
from scipy.sparse.csgraph import connected_components

from diffsolids.mesh import from_geo

ROOT = Path(__file__).resolve().parents[1]
INVARIANTS = {
    "sine_bar": ["objective decreased", "no inverted element"],
    "bridge_material": ["objective decreased", "no inverted element"],
    "bouncing_ball_height": ["objective decreased", "no inverted element", "no intersection"],
    "kangaroo_material": ["objective decreased", "no inverted element", "no intersection"],
}


@pytest.mark.parametrize("name", sorted(INVARIANTS))
def test_material_demo_tiny(name, tmp_path):
    report = load_demo(name).main(["--tiny", "--out", str(tmp_path), "--no-plot"])
    outcomes = {o.name: o for o in report.outcomes}
    for required in INVARIANTS[name]:
        assert outcomes[required].passed, outcomes[required]
    assert report.final_objective < report.initial_objective
    assert report.iterations >= 1
    # the initial and final states were written (VTX) and the summary file agrees
    for path in report.extra["files"]:
        assert Path(path).exists(), path
    assert any("final" in Path(p).name for p in report.extra["files"])
    saved = json.loads((tmp_path / "result.json").read_text())
    assert saved["final_objective"] == pytest.approx(report.final_objective)
    assert (tmp_path / "history.jsonl").exists()


def test_kangaroo_geo_is_one_body_above_the_ground():
    domain = from_geo(ROOT / "meshes" / "kangaroo.geo", MPI.COMM_SELF, numbers={"h": 0.07})
    assert domain.names == {"ground": 1, "kangaroo": 2, "ground_bottom": 1}
    mesh = domain.mesh
    cells = mesh.geometry.dofmaps[0][domain.cells_of("kangaroo")]
    x = mesh.geometry.x
    assert x[np.unique(cells), 1].min() > 0.0  # the feet start above the ground (y = 0)
    # head, neck, arm, tail and legs are fused into one connected piece
    rows = np.repeat(np.arange(len(cells)), cells.shape[1])
    incidence = sp.csr_matrix((np.ones(rows.size), (rows, cells.ravel())))
    count, _ = connected_components(incidence @ incidence.T)
    assert count == 1


@pytest.mark.parametrize("dim", [2, 3])
def test_bouncing_ball_geo_tags(dim):
    numbers = {"D": dim, "h": 0.06, "hp": 0.1}
    domain = from_geo(
        ROOT / "meshes" / "bouncing_ball.geo", MPI.COMM_SELF, dim=dim, numbers=numbers
    )
    assert domain.body_ids == [1, 2] and domain.names["ball"] == 2
    mesh = domain.mesh
    ball = np.unique(mesh.geometry.dofmaps[0][domain.cells_of("ball")])
    z = mesh.geometry.x[ball, dim - 1]
    assert z.min() > 0.0 and z.max() <= 0.23 + 1e-9  # radius 0.1 above a gap of 0.03
    assert domain.facets_of("plank_ends").size > 0
