"""Run under ``mpiexec -n 2``: node targets on P2 nodes (edge nodes by a locator, any node by
canonical index) give the serial per-step values, objective and gradient (E field, shape, v0)."""

import numpy as np
import pytest
from gradient_scenes import CONTROLS, SCENES, build_model, model_simulation
from mpi4py import MPI
from test_node_target_p2 import SCENE, _edge_nodes_right, p2_objective, top_right_nodes

import diffsolids as ds
from diffsolids.objectives import node_target, series_values
from diffsolids.reduced_functional import ReducedFunctional

KEYS = ["young-field-log", "shape-all", "initial-v0"]


def _run(comm):
    sim = model_simulation(build_model(SCENES[SCENE], comm), ds.BDF(2, 0.05, 3))
    model = sim.model
    top = top_right_nodes()  # canonical indices: the same on every rank and partition
    traj = sim.run()
    series = [
        node_target(model, _edge_nodes_right, [0.02, -0.05], match="displacement"),
        node_target(
            model, top, np.arange(2 * len(top)).reshape(-1, 2) * 0.01, numbering="canonical"
        ),
    ]
    values = [np.asarray(series_values(sim, s, traj)) for s in series]
    rf = ReducedFunctional(sim, p2_objective(model, top), [CONTROLS[k](sim) for k in KEYS])
    J, g = rf.value_and_gradient(rf.initial_parameters())
    return values, J, g


def test_p2_node_target_world_equals_self():
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    values_par, J_par, g_par = _run(MPI.COMM_WORLD)
    values_ser, J_ser, g_ser = _run(MPI.COMM_SELF)
    for a, b in zip(values_par, values_ser, strict=True):
        assert np.allclose(a, b, rtol=1e-10, atol=1e-14 * np.abs(b).max())
    assert J_par == pytest.approx(J_ser, rel=1e-10)
    assert np.allclose(g_par, g_ser, rtol=1e-7, atol=1e-10 * np.abs(g_ser).max())
