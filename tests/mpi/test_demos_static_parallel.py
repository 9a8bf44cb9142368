"""Run under ``mpiexec -n 2``: the scenes of demos/check_gradients.py on 2 ranks equal serial ones.

contact-friction clamps the whole slab, so on 2 ranks one rank can hold only prescribed dofs
(lambda = 0 there): the adjoint must still call the contact kernels, which are collective, on
every rank (it used to skip them on that rank and deadlock in the first gradient).
"""

import pytest
from demo_modules import load_demo
from mpi4py import MPI
from parallel_checks import assert_world_equals_self, value_and_gradient

RTOL = 1e-8


@pytest.mark.parametrize("scene", ["static-shape", "contact-friction"])
def test_check_gradients_scene_world_equals_self(scene):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    module = load_demo("check_gradients")
    world, serial = (
        value_and_gradient(module.build_scene(scene, c, tiny=True)[0])
        for c in (comm, MPI.COMM_SELF)
    )
    assert_world_equals_self(world, serial, RTOL, scene)
