"""Post-processing every user needs: centres of mass along a trajectory (series_values), the
invariant checks (inverted elements, intersections), observers of accepted iterates, the
geometry of figures and the files of written trajectories."""

import numpy as np
import pytest
from mpi4py import MPI
from optimize_script import contact_problem, shape_problem
from state_checks import (
    check_centres_of_mass,
    check_figure_geometry,
    check_volume_ratios_and_inversions,
)

import diffsolids as ds
from diffsolids.io import silhouette_edges, write_trajectory
from diffsolids.mesh import create_box
from diffsolids.optimize import (
    BoundaryIntersection,
    InvariantMonitor,
    LBFGSOptions,
    TrajectoryKeeper,
    check_trajectories,
    minimize,
)


def test_centres_of_mass_of_affine_states():
    check_centres_of_mass(MPI.COMM_WORLD)


def test_volume_ratios_and_inverted_states():
    check_volume_ratios_and_inversions(MPI.COMM_WORLD)


def test_boundary_edges_and_deformed_triangles():
    check_figure_geometry(MPI.COMM_WORLD)


def test_silhouettes_of_a_box():
    domain = create_box(MPI.COMM_WORLD, [[0, 0, 0], [1, 2, 3]], [2, 2, 3])
    model = ds.Model(domain, ds.NeoHookean(E=1.0, nu=0.3))
    sides = {1: (0, 2), 2: (0, 1)}  # seen along y: the x-z outline; along z: the x-y outline
    for axis, edges in zip((1, 2), silhouette_edges(model, axes=(1, 2)), strict=True):
        a, b = sides[axis]
        projected = edges[:, :, [a, b]]
        length = np.linalg.norm(projected[:, 1] - projected[:, 0], axis=1).sum()
        extent = np.array([1.0, 2.0, 3.0])[[a, b]]
        # the outlines of the faces towards and away from the viewer: twice the perimeter
        assert length == pytest.approx(2 * 2 * extent.sum(), rel=1e-12)


def test_contact_states_and_boundary_intersections():
    rf, contact = contact_problem(MPI.COMM_WORLD)  # a block 0.1 above a slab, dhat = 0.02
    sim, model = rf.simulation, rf.model
    rf(rf.initial_parameters())
    traj = rf.trajectory
    checks = check_trajectories(sim, [traj], contact)
    assert (checks.states, checks.inverted, checks.intersecting) == (len(traj.u), 0, 0)
    closest = min(r.min_distance for r in contact.records)
    assert checks.min_distance == pytest.approx(closest, rel=1e-12)
    # the block moved down by twice the gap: into the slab
    X = model.V.tabulate_dof_coordinates()[:, 1]
    down = np.zeros((len(X), 2))
    down[X > 0.3 + 1e-9, 1] = -0.2
    sunk = ds.Trajectory([0.0], [down.ravel()], [np.zeros(down.size)])
    assert check_trajectories(sim, [traj, sunk], contact).intersecting == 1
    boundary = BoundaryIntersection(model)
    assert not boundary.intersects() and not boundary.intersects(traj.u[-1])
    assert boundary.intersects(down.ravel())


def test_observers_keep_trajectories_and_check_every_iterate():
    rf, _ = shape_problem(MPI.COMM_WORLD)
    keeper, monitor = TrajectoryKeeper(), InvariantMonitor(deformed=True)
    seen = []
    result = minimize(
        rf,
        options=LBFGSOptions(max_iterations=4),
        on_accept=[keeper, monitor, lambda rec, opt: seen.append(opt.point.trajectory)],
    )
    n = len(result.history)
    assert keeper.accepted == monitor.checked == n == len(seen)
    assert keeper.first is seen[0] and keeper.last is seen[-1]
    assert keeper.last is result.functional.trajectory  # the final iterate, no extra solve
    assert (monitor.inverted, monitor.intersecting, monitor.intersecting_deformed) == (0, 0, 0)


@pytest.mark.parametrize("suffix", [".bp", ".xdmf"])
def test_write_trajectory_returns_its_files(tmp_path, suffix):
    from dolfinx import fem

    model = ds.Model(
        create_box(MPI.COMM_WORLD, [[0, 0, 0], [1, 1, 1]], [1, 1, 1]), ds.NeoHookean(E=1.0, nu=0.3)
    )
    u = np.zeros_like(model.fields.u.x.array)
    traj = ds.Trajectory([0.0, 0.5], [u, u + 0.01], [u, u])
    P2 = fem.Function(fem.functionspace(model.domain.mesh, ("Lagrange", 2)), name="p2")
    files = write_trajectory(model, traj, tmp_path / f"run{suffix}", extra=[P2])
    expected = {".bp": ["run.bp", "run_cells.bp", "run_p2.bp"], ".xdmf": ["run.xdmf", "run.h5"]}
    assert [f.name for f in files] == expected[suffix]
    assert all(f.exists() for f in files)
