"""PolyFEM scenes with kinematic obstacles: ``is_obstacle`` geometry and fixed bodies.

``read_polyfem_scene(path)`` makes ``is_obstacle`` entries kinematic obstacles of the contact
term (no dofs); ``fixed_bodies="obstacles"`` does the same for bodies whose whole boundary is
clamped to zero (the paper's grounds and pool). The bodies that move see the same contact
surface in both set-ups, so their trajectories must agree to rounding.
"""

import json
import os
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import RigidVelocity
from diffsolids.objectives import Integral, final_value
from diffsolids.polyfem import PolyFEMBoundaryValue, read_polyfem_scene
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.verification import finite_difference_check

COMM = MPI.COMM_WORLD
DIFFIPC = (
    Path(os.environ.get("DIFFSOLIDS_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    / "diffipc"
)
PUZZLE = DIFFIPC / "fig14_puzzle_piece" / "run-new.json"
BUNNY = DIFFIPC / "fig21_friction_bunny" / "run-new.json"
STEPS = 6  # the piece thrown at (1, -4) m/s touches the wave from step 3


def _require(path: Path) -> Path:
    if not path.is_file():
        pytest.skip(f"paper data not found: {path} (set DIFFSOLIDS_DATA)")
    return path


def puzzle_setup(fixed_bodies: str, comm: MPI.Comm = COMM, stiffness=None):
    """fig14's piece thrown at (1, -4) m/s onto the wave: (scene, model, contact, simulation)."""
    scene = read_polyfem_scene(_require(PUZZLE), fixed_bodies=fixed_bodies)
    scene.initial_velocity = [PolyFEMBoundaryValue(1, (1.0, -4.0))]
    model = scene.model(scene.domain(comm))
    integrator = ds.BDF(scene.bdf_order, scene.dt, STEPS)
    contact = scene.contact_term(model, integrator, "suggest" if stiffness is None else stiffness)
    sim = scene.simulation(model, integrator, ds.SolverOptions(rtol=1e-10))
    return scene, model, contact, sim


def _piece_displacements(model: ds.Model, u: np.ndarray) -> np.ndarray:
    """The piece's (body 1) nodal displacements sorted by rest position (serial)."""
    V = model.V
    nodes = np.unique(V.dofmap.list[model.domain.cells_of(1)])
    X = V.tabulate_dof_coordinates()[nodes, :2]
    order = np.lexsort((X[:, 1].round(9), X[:, 0].round(9)))
    return u.reshape(-1, 2)[nodes][order]


def test_a_fixed_body_as_obstacle_gives_the_same_motion_with_fewer_dofs():
    if COMM.size > 1:
        pytest.skip("compares nodal arrays of one process")
    _, model_o, contact_o, sim_o = puzzle_setup("obstacles")
    _, model_b, contact_b, sim_b = puzzle_setup("bodies", stiffness=contact_o.stiffness)
    assert contact_b.stiffness == contact_o.stiffness and not contact_b.obstacles
    assert model_o.domain.body_ids == [1] and model_b.domain.body_ids == [1, 3]
    assert not model_o.dirichlet and len(contact_o.obstacles) == 1
    size = [m.V.dofmap.index_map.size_global * 2 for m in (model_o, model_b)]
    assert size[0] < size[1]
    traj_o, traj_b = sim_o.run(), sim_b.run()
    gaps = [r.min_distance for r in contact_o.records]
    assert np.isfinite(gaps).sum() >= 3  # in contact over half of the steps
    u_o = _piece_displacements(model_o, traj_o.u[-1])
    u_b = _piece_displacements(model_b, traj_b.u[-1])
    assert np.abs(u_b).max() > 0.1
    assert np.abs(u_o - u_b).max() <= 1e-9 * np.abs(u_b).max()


def puzzle_functional(comm: MPI.Comm = COMM) -> tuple[ReducedFunctional, np.ndarray]:
    """The piece's final height and spread against its initial velocity, the wave an obstacle."""
    sim = puzzle_setup("obstacles", comm)[-1]

    def spread(f):
        return (f.X[1] + f.u[1]) * f.dx(1) + 10.0 * f.u[0] ** 2 * f.dx(1)

    rf = ReducedFunctional(sim, final_value(Integral(spread)), RigidVelocity(sim, 1, angular=False))
    return rf, np.array([1.0, -4.0])


@pytest.mark.parametrize("direction", ["random", "gradient"])
def test_velocity_gradient_against_an_obstacle_scene(direction):
    rf, q = puzzle_functional()
    J, g = rf.value_and_gradient(q)
    assert np.isfinite(J) and np.linalg.norm(g) > 1e-8
    d = np.random.default_rng(21).standard_normal(2) if direction == "random" else g
    fd = finite_difference_check(rf, q, d / np.linalg.norm(d), [1e-3, 1e-4, 1e-5], gradient=g)
    assert fd.relative_error < 1e-6, str(fd)


def test_an_is_obstacle_entry_is_kinematic_by_default():
    scene = read_polyfem_scene(_require(BUNNY))
    slide, bunny = scene.geometry
    assert slide.is_obstacle and slide.kinematic and not bunny.kinematic
    assert scene.body_ids == [1]
    (obstacle,) = scene.obstacles(3)
    assert obstacle.name == "obstacle3" and len(obstacle.faces) > 0
    # the slide's surface, placed as the scene places it (no transformation: as in the file)
    lo, hi = obstacle.rest_positions.min(axis=0), obstacle.rest_positions.max(axis=0)
    slide_mesh = ds.mesh.read_mesh(slide.mesh, MPI.COMM_SELF)
    box = slide_mesh.bounding_box()
    assert np.allclose(lo, box[0]) and np.allclose(hi, box[1])


def _scene_with(tmp_path: Path, edit) -> Path:
    raw = json.loads(_require(PUZZLE).read_text())
    for g in raw["geometry"]:
        g["mesh"] = str(PUZZLE.parent / g["mesh"])
    edit(raw)
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(raw))
    return path


def test_obstacle_errors_are_named(tmp_path):
    def obstacle(raw):
        raw["geometry"][0]["is_obstacle"] = True

    with pytest.raises(ds.ParameterError, match=r"geometry\[0\]\.is_obstacle: refused"):
        read_polyfem_scene(_scene_with(tmp_path, obstacle), obstacles="error")

    def moving(raw):
        obstacle(raw)
        raw["boundary_conditions"]["dirichlet_boundary"][0]["value"] = [0.1, 0]

    # PolyFEM's rule: a dirichlet_boundary value on an obstacle's surface id is its displacement
    (wave,) = read_polyfem_scene(_scene_with(tmp_path, moving)).obstacles(2)
    assert wave.moving and np.array_equal(wave.motion(0.5), [0.1, 0.0])

    def thrown(raw):
        obstacle(raw)
        raw["initial_conditions"]["velocity"].append({"id": 3, "value": [1, 0]})

    with pytest.raises(ds.ParameterError, match=r"initial_conditions\.velocity"):
        read_polyfem_scene(_scene_with(tmp_path, thrown))

    def all_obstacles(raw):
        for g in raw["geometry"]:
            g["is_obstacle"] = True
        raw["initial_conditions"]["velocity"] = []

    with pytest.raises(ds.ParameterError, match="no body"):
        read_polyfem_scene(_scene_with(tmp_path, all_obstacles))
    with pytest.raises(ds.ParameterError, match="fixed_bodies"):
        read_polyfem_scene(PUZZLE, fixed_bodies="ground")
