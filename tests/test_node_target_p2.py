"""node_target on P2: every Lagrange node is selectable, the edge nodes included (issue 13).

The clamped two-body bar of the gradient scenes with P2 displacements ([0, 2] x [0, 0.5],
4 x 2 cells): its right end has 3 vertices and 2 edge nodes. Values against sums over the
nodal arrays by hand (selection by a locator of node coordinates, by canonical node index, by
input vertex index), errors naming the problem, and gradients (E field, shape, v0) against
central differences along a random direction per control and along the gradient.
"""

from dataclasses import replace

import numpy as np
import pytest
from gradient_scenes import SCENES, build_model, model_simulation, simulation
from test_objectives_library import _fd_check, _run

import diffsolids as ds
from diffsolids.errors import ParameterError
from diffsolids.objectives import final_value, node_target, series_values, time_integral

SCENE = "2d-p2-nh"


def _right_end(x):
    return np.isclose(x[0], 2.0)


def _edge_nodes_right(x):
    """The two edge nodes of the right end (y = 0.125, 0.375), no vertex."""
    return np.isclose(x[0], 2.0) & (np.isclose(x[1], 0.125) | np.isclose(x[1], 0.375))


def _nodes(model):
    """(coordinates, canonical index) of the displacement's nodes (serial)."""
    X = model.V.tabulate_dof_coordinates()[:, :2]
    order = np.lexsort(np.round(X / 1e-10).T[::-1])  # the canonical (lexicographic) order
    canonical = np.empty(len(X), dtype=np.int64)
    canonical[order] = np.arange(len(X))
    return X, canonical


def test_p2_node_target_values_are_exact_sums_over_all_nodes():
    sim = simulation(SCENE, "bdf2")
    model = sim.model
    assert model.V.element.basix_element.degree == 2
    own = _run(sim)
    X, canonical = _nodes(model)
    u = own.u[-1].reshape(-1, 2)
    right = np.flatnonzero(np.isclose(X[:, 0], 2.0))
    assert len(right) == 5  # 3 vertices and 2 edge nodes
    d = np.array([0.1, -0.2])
    s = node_target(model, _right_end, d, match="displacement")
    assert series_values(sim, s, own, steps=[0]) == pytest.approx([5 * d @ d], rel=1e-12)
    by_hand = np.sum((u[right] - d) ** 2)
    assert series_values(sim, s, own, steps=[-1]) == pytest.approx([by_hand], rel=1e-12)
    # the edge nodes only, by a locator: positions X + u against a callable target
    edge = np.flatnonzero(_edge_nodes_right(X.T))
    assert len(edge) == 2
    s = node_target(model, _edge_nodes_right, lambda x: x[:2] + np.array([[0.02], [-0.05]]))
    by_hand = np.sum((u[edge] - [0.02, -0.05]) ** 2)
    assert series_values(sim, s, own, steps=[-1]) == pytest.approx([by_hand], rel=1e-12)
    # by canonical node index (any node): an interior edge node, a vertex, a boundary edge node
    picks = [
        int(np.flatnonzero(np.isclose(X[:, 0], 0.75) & np.isclose(X[:, 1], 0.25))[0]),
        int(np.flatnonzero(np.isclose(X[:, 0], 1.5) & np.isclose(X[:, 1], 0.5))[0]),
        int(edge[1]),
    ]
    targets = X[picks] + np.array([[0.0, 0.1], [0.2, 0.0], [0.0, -0.3]])
    s = node_target(model, canonical[picks], targets, weight=2.0, numbering="canonical")
    assert series_values(sim, s, own, steps=[0]) == pytest.approx([2.0 * 0.14], rel=1e-12)
    by_hand = 2.0 * np.sum((X[picks] + u[picks] - targets) ** 2)
    assert series_values(sim, s, own, steps=[-1]) == pytest.approx([by_hand], rel=1e-12)
    # by input vertex index (the default numbering): vertices of a P2 space still work
    x = model.domain.mesh.geometry.x
    ids = model.domain.mesh.geometry.input_global_indices
    corners = np.flatnonzero(np.isclose(x[:, 0], 2.0) & np.isin(x[:, 1], [0.0, 0.5]))
    s = node_target(model, ids[corners], x[corners, :2] + [0.0, 0.1])
    assert series_values(sim, s, own, steps=[0]) == pytest.approx([2 * 0.01], rel=1e-12)


def test_p2_node_target_errors():
    model = simulation(SCENE, "bdf2").model
    n = model.V.dofmap.index_map.size_global
    with pytest.raises(
        ParameterError, match=rf"no node has the canonical index \[{n}\].*{n} nodes"
    ):
        node_target(model, [0, n], [0.0, 0.0], numbering="canonical")
    with pytest.raises(ParameterError, match=r"numbering='canonical' selects any node"):
        node_target(model, [10**6], [0.0, 0.0])
    with pytest.raises(ParameterError, match="unknown numbering 'p2'"):
        node_target(model, [0], [0.0, 0.0], numbering="p2")
    with pytest.raises(ParameterError, match="selects no mesh vertex"):
        node_target(model, lambda x: x[0] > 5.0, [0.0, 0.0])
    with pytest.raises(ParameterError, match=r"node target has shape \(3, 2\)"):
        node_target(model, [0, 1], np.zeros((3, 2)), numbering="canonical")


def top_right_nodes() -> np.ndarray:
    """Canonical indices of the top nodes of the right half (from the serial model)."""
    X, canonical = _nodes(simulation(SCENE, "bdf2").model)
    return canonical[np.isclose(X[:, 1], 0.5) & (X[:, 0] > 1.0)]


def p2_objective(model, top_nodes: np.ndarray):
    """Edge nodes (locator, positions) over steps 2, 3 and canonical nodes at the end."""
    edges = node_target(model, _edge_nodes_right, lambda x: x[:2] + np.array([[0.02], [-0.05]]))
    top = node_target(model, top_nodes, [0.01, -0.02], match="displacement", numbering="canonical")
    return time_integral(edges, [2, 3]) + 3.0 * final_value(top)


def test_p2_node_target_gradients():
    sim = simulation(SCENE, "bdf2")
    objective = p2_objective(sim.model, top_right_nodes())
    _fd_check(sim, objective, ["young-field-log", "shape-all", "initial-v0"])


@pytest.mark.parametrize("scene, degree, count", [("2d-p2-nh", 3, 7), ("3d-p2-nh-lame", 2, 9)])
def test_p3_and_3d_p2_node_targets_are_exact_sums(scene, degree, count):
    """P3 (2 nodes per edge, GLL-warped) and 3D P2 (the end face's edge nodes): exact sums."""
    model = build_model(replace(SCENES[scene], degree=degree))
    sim = model_simulation(model, ds.BDF(2, 0.05, 3))
    traj = _run(sim)
    dim = model.dim
    X = model.V.tabulate_dof_coordinates()[:, :dim]
    u = traj.u[-1].reshape(-1, dim)
    sel = np.isclose(X[:, 0], 2.0)
    assert sel.sum() == count
    d = np.full(dim, 0.1)
    s = node_target(model, _right_end, d, match="displacement")
    values = series_values(sim, s, traj)
    assert values[0] == pytest.approx(count * d @ d, rel=1e-12)
    assert values[-1] == pytest.approx(np.sum((u[sel] - d) ** 2), rel=1e-12)


def test_p3_node_target_gradients():
    sim = model_simulation(build_model(replace(SCENES[SCENE], degree=3)), ds.BDF(2, 0.05, 3))
    X = sim.model.V.tabulate_dof_coordinates()[:, :2]
    top = node_target(
        sim.model,
        lambda x: np.isclose(x[1], 0.5) & (x[0] > 1.0),
        lambda x: x[:2] + np.array([[0.01], [-0.02]]),
    )
    assert np.sum(np.isclose(X[:, 1], 0.5) & (X[:, 0] > 1.0)) == 6  # 2 vertices, 4 edge nodes
    _fd_check(sim, time_integral(top, [1, 3]), ["shape-all", "initial-v0"])
