"""PolyFEM scene files as written: side selections, first-match order, expression-valued
boundary conditions, static scenes, PolyFEM's defaults, plane strain on request.

Scenes of our own on a 2 x 1 rectangle (tests/mpi: the same on 2 ranks); the paper's scenes
load in test_paper_scenes.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI
from polyfem_own_scenes import write_rectangle

import diffsolids as ds
from diffsolids.parallel import collective_comm
from diffsolids.polyfem import read_polyfem_scene


def static_scene(folder: Path, **geometry) -> Path:
    """A static linear-elastic scene: left side clamped by a side selection, the right side
    moved by an expression of y; no ``time``, no ``rho``, no ``volume_selection``."""
    write_rectangle(folder)
    scene = {
        "geometry": [
            {"mesh": "rectangle.msh", "surface_selection": {"threshold": 1e-6}, **geometry}
        ],
        "space": {"discr_order": 1},
        "boundary_conditions": {
            "rhs": [0, 0],
            "dirichlet_boundary": [
                {"id": 1, "value": [0, 0]},
                {"id": 3, "value": ["0.1*cos(0)", "0.05*y"]},
            ],
        },
        "materials": {"type": "LinearElasticity", "E": 100.0, "nu": 0.3},
    }
    path = folder / "static.json"
    path.write_text(json.dumps(scene))
    return path


def right_side_displacement(setup) -> tuple[np.ndarray, np.ndarray]:
    """(y, u) at the dofs on x = 2 of the solved static scene, gathered on every rank."""
    traj = setup.simulation.run()
    V = setup.model.V
    owned = V.dofmap.index_map.size_local
    X = V.tabulate_dof_coordinates()[:owned]
    u = traj.u[-1].reshape(-1, 2)[:owned]
    right = np.isclose(X[:, 0], 2.0)
    parts = collective_comm(setup.domain.comm).allgather((X[right, 1], u[right]))
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def test_static_scene_with_side_selection_and_expressions(tmp_path):
    scene = read_polyfem_scene(static_scene(tmp_path))
    assert scene.static and scene.materials[0].rho == 1.0  # PolyFEM's defaults
    setup = scene.build(MPI.COMM_WORLD)
    assert isinstance(setup.integrator, ds.Static) and setup.model.plane_stress
    y, u = right_side_displacement(setup)
    assert len(y) == 5
    assert np.allclose(u[:, 0], 0.1, atol=1e-12) and np.allclose(u[:, 1], 0.05 * y, atol=1e-12)
    tags = setup.domain.facet_tags
    assert set(np.unique(tags.values)) <= {1, 2, 3, 4}


def _facet_tag_at(domain, point) -> int:
    import dolfinx

    mesh = domain.mesh
    tags = domain.facet_tags
    mid = dolfinx.mesh.compute_midpoints(mesh, mesh.topology.dim - 1, tags.indices)[:, :2]
    hit = np.flatnonzero(np.linalg.norm(mid - point, axis=1) < 1e-9)
    local = int(tags.values[hit[0]]) if hit.size else -1
    return collective_comm(domain.comm).allreduce(local, op=MPI.MAX)


def test_the_first_matching_selection_names_a_facet_and_sides_are_numbered(tmp_path):
    selections = [
        {"id": 5, "box": [[1.9, -1.0], [3.0, 2.0]]},  # the right side
        {"id": 6, "box": [[-10.0, -10.0], [10.0, 10.0]]},  # a catch-all, last
    ]
    path = static_scene(tmp_path)
    raw = json.loads(path.read_text())
    raw["geometry"][0]["surface_selection"] = selections
    raw["boundary_conditions"]["dirichlet_boundary"] = [{"id": 6, "value": [0, 0]}]
    path.write_text(json.dumps(raw))
    domain = read_polyfem_scene(path).domain(MPI.COMM_WORLD)
    assert _facet_tag_at(domain, [2.0, 0.125]) == 5  # not overwritten by the catch-all
    assert _facet_tag_at(domain, [0.0, 0.125]) == 6
    raw["geometry"][0]["surface_selection"] = {"threshold": 1e-6, "id_offset": 10}
    path.write_text(json.dumps(raw))
    domain = read_polyfem_scene(path).domain(MPI.COMM_WORLD)
    sides = {(0.0, 0.125): 11, (0.125, 0.0): 12, (2.0, 0.125): 13, (0.125, 1.0): 14}
    for point, tag in sides.items():
        assert _facet_tag_at(domain, point) == tag


def test_plane_strain_on_request_and_refused_expressions(tmp_path):
    scene = read_polyfem_scene(static_scene(tmp_path))
    domain = scene.domain(MPI.COMM_WORLD)
    assert not scene.model(domain, plane_stress=False).plane_stress
    raw = json.loads((tmp_path / "static.json").read_text())
    raw["boundary_conditions"]["neumann_boundary"] = [{"id": 4, "value": ["x", 0]}]
    (tmp_path / "static.json").write_text(json.dumps(raw))
    scene = read_polyfem_scene(tmp_path / "static.json")
    with pytest.raises(ds.ParameterError, match=r"neumann_boundary id 4: value .*depends on x"):
        scene.build(MPI.COMM_WORLD)
    raw["boundary_conditions"]["neumann_boundary"] = [{"id": 4, "value": ["sin(", 0]}]
    (tmp_path / "static.json").write_text(json.dumps(raw))
    with pytest.raises(ds.ParameterError, match=r"neumann_boundary\[0\]\.value\[0\]"):
        read_polyfem_scene(tmp_path / "static.json")
