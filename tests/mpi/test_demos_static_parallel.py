"""Run under ``mpiexec -n 2``: the scenes of demos/check_gradients.py on 2 ranks equal serial ones.

contact-friction clamps the whole slab, so on 2 ranks one rank can hold only prescribed dofs
(lambda = 0 there): the adjoint must still call the contact kernels, which are collective, on
every rank (it used to skip them on that rank and deadlock in the first gradient).
"""

import numpy as np
import pytest
from demo_modules import load_demo
from mpi4py import MPI

RTOL = 1e-8


@pytest.mark.parametrize("scene", ["static-shape", "contact-friction"])
def test_check_gradients_scene_world_equals_self(scene):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    module = load_demo("check_gradients")
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
