"""Scenes and checks of the post-processing tools (centres of mass, invariants, figure geometry).

Shared by ``tests/test_invariants.py`` (serial) and ``tests/mpi/test_invariants_parallel.py``:
every check takes a communicator and returns the numbers it compared, so the 2-rank test can
also compare them with a COM_SELF run. Affine displacements u = G X + a are represented exactly
by P1, so centres of mass, volume ratios and outlines have closed forms.
"""

import numpy as np
from mpi4py import MPI

import diffsolids as ds
from diffsolids.io import boundary_edges, deformed_triangles, nodal_displacement
from diffsolids.mesh import create_rectangle
from diffsolids.objectives import center_of_mass, series_values
from diffsolids.optimize import check_trajectories, inverted_rest_cells, min_volume_ratio

DENSITY = {1: 1.0, 2: 3.0}  # body 1: [0, 1] x [0, 1], body 2: [1, 2] x [0, 1]
CENTROID = {1: np.array([0.5, 0.5]), 2: np.array([1.5, 0.5])}
G = np.array([[0.1, -0.05], [0.02, 0.08]])
SHIFT = np.array([0.3, -0.2])


def two_body_scene(comm: MPI.Comm) -> tuple[ds.Model, ds.Simulation]:
    """Two Neo-Hookean bodies side by side in [0, 2] x [0, 1], BDF1 with 2 steps."""
    domain = create_rectangle(comm, [[0, 0], [2, 1]], [8, 4], bodies={2: lambda x: x[0] > 1.0})
    materials = {b: ds.NeoHookean(E=100.0, nu=0.3, density=rho) for b, rho in DENSITY.items()}
    model = ds.Model(domain, materials, degree=1)
    model.add_dirichlet(lambda x: np.isclose(x[0], 0.0), 0.0)
    sim = ds.Simulation(model, ds.BDF(1, 0.1, 2), progress=False)
    return model, sim


def affine(model: ds.Model, grad: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """The local displacement array of u = grad X + shift."""
    X = model.V.tabulate_dof_coordinates()[:, : model.dim]
    return (X @ grad.T + shift).ravel()


def affine_trajectory(model: ds.Model, scales=(0.0, 0.5, 1.0)) -> ds.Trajectory:
    """States u^i = s_i (G X + SHIFT), v^i = G X."""
    u = affine(model, G, SHIFT)
    v = affine(model, G, np.zeros(2))
    return ds.Trajectory(
        times=[0.1 * i for i in range(len(scales))],
        u=[s * u for s in scales],
        v=[v.copy() for _ in scales],
    )


def check_centres_of_mass(comm: MPI.Comm) -> np.ndarray:
    """series_values of center_of_mass against (I + s G) X_c + s SHIFT; returns the paths."""
    model, sim = two_body_scene(comm)
    traj = affine_trajectory(model)
    model.fields.u.x.array[:] = 7.0  # restored afterwards
    scales = np.array([0.0, 0.5, 1.0])
    paths = []
    for body in (1, 2, None):
        com = series_values(sim, center_of_mass(model, body), traj)
        if body is None:
            mass = {b: DENSITY[b] for b in (1, 2)}  # both bodies have area 1
            rest = sum(mass[b] * CENTROID[b] for b in mass) / sum(mass.values())
        else:
            rest = CENTROID[body]
        expected = np.array([rest + s * (G @ rest + SHIFT) for s in scales])
        assert com.shape == (3, 2)
        assert np.allclose(com, expected, rtol=0, atol=1e-13), (body, com, expected)
        paths.append(com)
    assert np.all(model.fields.u.x.array == 7.0)
    # one series: one value per state; states chosen, counted from the end
    x = series_values(sim, center_of_mass(model, 2)[0], traj, steps=[-1, 0])
    assert x.shape == (2,) and np.allclose(x, paths[1][[2, 0], 0], rtol=0, atol=1e-15)
    return np.concatenate(paths)


def check_volume_ratios_and_inversions(comm: MPI.Comm) -> tuple[float, int, int]:
    """min_volume_ratio = det(I + G); check_trajectories counts the inverted state."""
    model, sim = two_body_scene(comm)
    ratio = min_volume_ratio(model, affine(model, G, SHIFT))
    assert np.isclose(ratio, np.linalg.det(np.eye(2) + G), rtol=1e-12)
    flip = np.array([[-2.0, 0.0], [0.0, 0.0]])  # F = diag(-1, 1): every cell inverted
    assert np.isclose(min_volume_ratio(model, affine(model, flip, SHIFT)), -1.0, rtol=1e-12)
    good = affine_trajectory(model)
    bad = ds.Trajectory([0.0], [affine(model, flip, SHIFT)], [np.zeros_like(good.u[0])])
    checks = check_trajectories(sim, [good, bad])
    assert (checks.states, checks.inverted, checks.intersecting) == (4, 1, 0)
    assert checks.min_distance == np.inf  # no contact term
    # the rest mesh mirrored: every cell flips against the original orientation
    x = model.domain.mesh.geometry.x
    cells = model.domain.mesh.topology.index_map(2).size_global
    assert inverted_rest_cells(model) == 0
    x[:, 0] *= -1.0
    try:
        flipped = inverted_rest_cells(model)
    finally:
        x[:, 0] *= -1.0
    assert flipped == cells
    return ratio, checks.inverted, flipped


def check_figure_geometry(comm: MPI.Comm) -> tuple[float, float]:
    """boundary_edges and deformed_triangles of the affine state; returns length and area."""
    model, _ = two_body_scene(comm)
    u = affine(model, G, SHIFT)
    x = model.domain.mesh.geometry.x[:, :2]
    assert np.allclose(nodal_displacement(model, u), x @ G.T + SHIFT, rtol=0, atol=1e-14)
    rest = boundary_edges(model)
    length = float(np.linalg.norm(rest[:, 1] - rest[:, 0], axis=1).sum())
    assert len(rest) == 2 * (8 + 4) and np.isclose(length, 6.0, rtol=1e-13)
    moved = boundary_edges(model, u)
    assert np.allclose(moved, rest @ (np.eye(2) + G).T + SHIFT, rtol=0, atol=1e-14)
    owned = model.domain.mesh.topology.index_map(2).size_local
    tris, values = deformed_triangles(model, u, np.full(owned, float(comm.rank)))
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    area = float(0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum())
    assert len(tris) == len(values) == 2 * 8 * 4
    assert np.isclose(area, 2.0 * np.linalg.det(np.eye(2) + G), rtol=1e-13)
    counts = np.bincount(values.astype(int), minlength=comm.size)
    sizes = comm.allgather(owned)
    assert counts.tolist() == sizes  # each rank's values with its own cells, in rank order
    return length, area
