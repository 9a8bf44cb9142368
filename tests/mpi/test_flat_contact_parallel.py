"""Flat and wavy grounds on 2 ranks: the drop on a two-triangle ground (both formulations) and
the box thrown along a wavy polyline, as serial."""

import numpy as np
import pytest
from mpi4py import MPI
from smoothness_scenes import drop, wavy

COMM = MPI.COMM_WORLD


@pytest.mark.parametrize("formulation", ["ipc", "convergent"])
def test_drop_on_two_triangles_equals_serial(formulation):
    parallel = drop(2, comm=COMM, steps=8, formulation=formulation)
    J, g = parallel.rf.value_and_gradient(parallel.q0)
    serial = drop(2, comm=MPI.COMM_SELF, steps=8, formulation=formulation)
    Js, gs = serial.rf.value_and_gradient(serial.q0)
    assert abs(J - Js) <= 1e-10 * abs(Js)
    assert np.allclose(g, gs, rtol=1e-8, atol=0)
    pairs = [r.num_collisions for r in parallel.contact.records]
    assert COMM.allreduce(sum(pairs), op=MPI.SUM) > 0


def test_wavy_ground_equals_serial():
    parallel = wavy(comm=COMM, steps=12)
    J, g = parallel.rf.value_and_gradient(parallel.q0)
    serial = wavy(comm=MPI.COMM_SELF, steps=12)
    Js, gs = serial.rf.value_and_gradient(serial.q0)
    assert abs(J - Js) <= 1e-10 * abs(Js)
    assert np.allclose(g, gs, rtol=1e-8, atol=0)
    pairs = [r.num_collisions for r in parallel.contact.records]
    assert COMM.allreduce(sum(pairs), op=MPI.SUM) > 0
