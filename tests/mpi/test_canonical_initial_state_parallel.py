"""Run under ``mpiexec -n 2``: canonical initial states (CanonicalValues) give the serial run."""

import test_papercuts
from mpi4py import MPI


def test_canonical_initial_state_is_the_nodal_field_and_the_control_order_on_two_ranks():
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    test_papercuts.test_canonical_initial_state_is_the_nodal_field_and_the_control_order()


def test_canonical_initial_state_gives_the_serial_run_on_two_ranks():
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    test_papercuts.test_canonical_initial_state_gives_the_serial_run_on_every_rank_count()
