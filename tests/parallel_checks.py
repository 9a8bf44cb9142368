"""Checks shared by the 2-rank tests: a reduced functional on COMM_WORLD equals it on COMM_SELF.

Not collected by pytest (no ``test_`` prefix): tests/mpi/test_*_parallel.py import it. A test
builds the same reduced functional on both communicators in one process, takes
:func:`value_and_gradient` of each and compares them with :func:`assert_world_equals_self`.
"""

import numpy as np
from mpi4py import MPI

from diffsolids.reduced_functional import ReducedFunctional

__all__ = ["assert_world_equals_self", "value_and_gradient"]


def value_and_gradient(rf: ReducedFunctional) -> tuple[np.ndarray, float, np.ndarray]:
    """(q, J(q), dJ/dq) of a reduced functional at its initial parameters q."""
    q = rf.initial_parameters()
    return (q, *rf.value_and_gradient(q))


def assert_world_equals_self(world: tuple, serial: tuple, rtol: float, label: str = "") -> None:
    """The (q, J, g) of a COMM_WORLD run are those of the COMM_SELF run, and on every rank.

    q in the same (canonical) order, J and g to ``rtol`` relative (g: relative to its largest
    entry, which must not be zero), and every rank holds the same J and g to the last bit.
    """
    (q_par, J_par, g_par), (q_ser, J_ser, g_ser) = world, serial
    assert np.array_equal(q_par, q_ser)  # canonical parameter order
    assert abs(J_par - J_ser) <= rtol * abs(J_ser), (J_par, J_ser)
    assert np.abs(g_ser).max() > 0
    diff = np.abs(g_par - g_ser).max() / np.abs(g_ser).max()
    print(f"{label or 'world vs self'}: value {abs(J_par / J_ser - 1):.1e}, gradient {diff:.1e}")
    assert diff <= rtol, diff
    for value in MPI.COMM_WORLD.allgather(J_par):
        assert value == J_par
    for gradient in MPI.COMM_WORLD.allgather(g_par):
        assert np.array_equal(gradient, g_par)
