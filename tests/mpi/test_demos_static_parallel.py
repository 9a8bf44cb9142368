"""Run under ``mpiexec -n 2``: the scenes of demos/check_gradients.py on 2 ranks equal serial ones.

contact-friction clamps the whole slab, so on 2 ranks one rank can hold only prescribed dofs
(lambda = 0 there): the adjoint must still call the contact kernels, which are collective, on
every rank (it used to skip them on that rank and deadlock in the first gradient).
"""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

DEMOS = Path(__file__).resolve().parents[2] / "demos"
RTOL = 1e-8


def _check_gradients():
    if str(DEMOS) not in sys.path:
        sys.path.insert(0, str(DEMOS))
    spec = importlib.util.spec_from_file_location("check_gradients", DEMOS / "check_gradients.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("scene", ["static-shape", "contact-friction"])
def test_check_gradients_scene_world_equals_self(scene):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    module = _check_gradients()
    results = []
    for c in (comm, MPI.COMM_SELF):
        rf, _ = module.build_scene(scene, c, tiny=True)
        q = rf.initial_parameters()
        results.append((q, *rf.value_and_gradient(q)))
    (q_par, J_par, g_par), (q_ser, J_ser, g_ser) = results
    assert np.array_equal(q_par, q_ser)
    assert J_par == pytest.approx(J_ser, rel=RTOL)
    assert np.abs(g_ser).max() > 0
    diff = np.abs(g_par - g_ser).max() / np.abs(g_ser).max()
    print(f"{scene}: value {abs(J_par / J_ser - 1):.1e}, gradient {diff:.1e}")
    assert diff <= RTOL
    for gradient in comm.allgather(g_par):
        assert np.array_equal(gradient, g_par)
