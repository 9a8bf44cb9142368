"""PolyFEM scenes' contact parameters, read as PolyFEM reads them."""

import json

import numpy as np
import pytest
from mpi4py import MPI
from test_mesh_input import _paper_file, _paper_mesh

import diffsolids as ds
from diffsolids.contact import Obstacle
from diffsolids.mesh import boundary_facets, combine_meshes, simplex_box
from diffsolids.polyfem.contact import (
    polyfem_contact_options,
    shortest_boundary_edge,
    shortest_obstacle_edge,
)

COMM = MPI.COMM_WORLD


def _puzzle_scene():
    scene = json.loads(_paper_file("fig14_puzzle_piece/run-new.json").read_text())
    wave = _paper_mesh("fig14_puzzle_piece/wave.msh", scale=[2, 1])
    piece = _paper_mesh("fig14_puzzle_piece/puzzle.msh", scale=0.001, translation=[-1, 0.2])
    return scene, combine_meshes(COMM, [wave, piece], bodies=[3, 1])


def _numpy_shortest_edge(domain) -> float:
    """Independent of DOLFINx's facet topology: edges on one cell only, from the cell array."""
    cells = domain.mesh.geometry.dofmaps[0]
    edges = boundary_facets(cells)
    x = domain.mesh.geometry.x[:, :2]
    return float(np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1).min())


def test_the_puzzle_scene_gets_polyfems_dhat_rule_and_kappa_as_written():
    scene, domain = _puzzle_scene()
    edge = shortest_boundary_edge(domain)
    if COMM.size == 1:
        assert edge == pytest.approx(_numpy_shortest_edge(domain), rel=1e-12)
    assert edge == pytest.approx(4.24e-4, rel=5e-3)  # < 1e-3: PolyFEM uses 0.8 of it
    options = polyfem_contact_options(scene, domain)
    assert options == {
        "dhat": pytest.approx(0.8 * edge, rel=1e-12),
        "stiffness": 1e5,
        "friction": 0.5,
        "eps_v": 1e-3,
        "area_weighting": False,
    }


def test_given_dhat_adaptive_kappa_and_unsupported_options():
    scene, domain = _puzzle_scene()
    scene["contact"]["dhat"] = 2e-3
    scene["solver"]["contact"]["barrier_stiffness"] = "adaptive"
    options = polyfem_contact_options(scene, domain)
    assert options["dhat"] == 2e-3 and options["stiffness"] is None
    for bad in (-1.0, "soft", float("nan")):
        scene["solver"]["contact"]["barrier_stiffness"] = bad
        with pytest.raises(ds.ParameterError, match="barrier_stiffness"):
            polyfem_contact_options(scene, domain)
    with pytest.raises(ds.ParameterError, match="no contact"):
        polyfem_contact_options({"contact": {"enabled": False}}, domain)


def test_convergent_formulation_maps_the_physical_barrier_stiffness():
    scene, domain = _puzzle_scene()
    scene["contact"]["dhat"] = 2e-3
    scene["solver"]["contact"]["barrier_stiffness"] = 1e5
    plain = polyfem_contact_options(scene, domain)
    assert plain["stiffness"] == 1e5 and not plain["area_weighting"]
    assert "formulation" not in plain
    scene["contact"]["use_convergent_formulation"] = True
    options = polyfem_contact_options(scene, domain)
    assert options["formulation"] == "convergent" and options["area_weighting"]
    assert options["stiffness"] == pytest.approx(1e5 / 2e-3**3, rel=1e-14)
    scene["contact"]["use_physical_barrier"] = False
    assert polyfem_contact_options(scene, domain)["stiffness"] == 1e5
    for key in ("use_area_weighting", "use_improved_max_operator"):
        scene["contact"][key] = False
        with pytest.raises(ds.ParameterError, match=f"contact.{key} = false"):
            polyfem_contact_options(scene, domain)
        scene["contact"][key] = True


def test_dhat_default_sees_obstacle_edges_and_dhat_percentage():
    """PolyFEM's rule: 0.8 (``dhat_percentage``) x the shortest collision-mesh edge, obstacles'
    edges included, only when 1e-3 is longer than that edge; a given dhat as written."""
    scene, domain = _puzzle_scene()
    edge = shortest_boundary_edge(domain)
    short = 0.25 * edge  # an obstacle segment shorter than every body edge
    ground = Obstacle(np.array([[-5.0, -1.0], [-5.0 + short, -1.0], [5.0, -1.0]]))
    assert shortest_obstacle_edge([ground]) == pytest.approx(short, rel=1e-12)
    assert shortest_obstacle_edge([]) == np.inf
    options = polyfem_contact_options(scene, domain, [ground])
    assert options["dhat"] == pytest.approx(0.8 * short, rel=1e-12)
    scene["contact"]["dhat_percentage"] = 0.5
    assert polyfem_contact_options(scene, domain, [ground])["dhat"] == pytest.approx(
        0.5 * short, rel=1e-12
    )
    assert polyfem_contact_options(scene, domain)["dhat"] == pytest.approx(0.5 * edge, rel=1e-12)
    # every collision-mesh edge longer than 1e-3: the default 1e-3 stays
    coarse = combine_meshes(COMM, [simplex_box([[0, 0], [1, 1]], [4, 4])], bodies=[1])
    assert shortest_boundary_edge(coarse) > 1e-3
    assert polyfem_contact_options(scene, coarse, [ground])["dhat"] == pytest.approx(
        0.5 * short, rel=1e-12
    )
    assert polyfem_contact_options(scene, coarse)["dhat"] == 1e-3
    scene["contact"]["dhat"] = 2e-3  # given: as written, even above the shortest edge
    assert polyfem_contact_options(scene, domain, [ground])["dhat"] == 2e-3
    scene["contact"].pop("dhat")
    for bad in (0.0, -1.0, float("nan")):
        scene["contact"]["dhat_percentage"] = bad
        with pytest.raises(ds.ParameterError, match="dhat_percentage"):
            polyfem_contact_options(scene, domain)
