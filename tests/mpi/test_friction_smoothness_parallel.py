"""Run under ``mpiexec -n 2``: the friction gradient of test_friction_smoothness on 2 ranks.

The box thrown onto the slab is built on COMM_WORLD and on COMM_SELF in the same process: J
and dJ/dmu agree, and on 2 ranks central differences verify the gradient to 1e-6 in a random
direction and along the gradient (as serially).
"""

import numpy as np
from mpi4py import MPI
from test_friction_smoothness import FD_TOLERANCE, MU, SMOOTH, box_on_slab, friction_checks

from diffsolids.controls import FrictionControl
from diffsolids.reduced_functional import ReducedFunctional

RTOL = 1e-8


def _value_and_gradient(comm):
    contact, sim, objective = box_on_slab(SMOOTH, comm)
    rf = ReducedFunctional(sim, objective, FrictionControl(contact, pairs=[("slab", "block")]))
    q = np.array([MU])
    return rf(q), rf.gradient(q)


def test_friction_gradient_parallel_equals_serial():
    assert MPI.COMM_WORLD.size > 1, "run under mpiexec -n 2"
    J, g = _value_and_gradient(MPI.COMM_WORLD)
    J_self, g_self = _value_and_gradient(MPI.COMM_SELF)
    assert abs(J - J_self) <= RTOL * abs(J_self)
    assert np.allclose(g, g_self, rtol=RTOL, atol=0.0), (g, g_self)


def test_friction_gradient_parallel_central_differences():
    for name, res in friction_checks(SMOOTH, MPI.COMM_WORLD).items():
        assert abs(res.adjoint) > 1e-5, f"{name}: friction does not act\n{res}"
        assert res.relative_error <= FD_TOLERANCE, f"{name}\n{res}"
