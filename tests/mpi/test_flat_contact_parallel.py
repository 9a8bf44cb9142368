"""Flat and wavy grounds on 2 ranks: the drop on a two-triangle ground (both formulations),
the box thrown along a wavy polyline and the disk rolling down a slope (Newton steps held at
stick), as serial."""

import numpy as np
import pytest
from mpi4py import MPI
from smoothness_scenes import drop, roll, wavy

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


def test_rolling_disk_equals_serial():
    parallel = roll(comm=COMM, steps=14)
    J, g = parallel.rf.value_and_gradient(parallel.q0)
    serial = roll(comm=MPI.COMM_SELF, steps=14)
    Js, gs = serial.rf.value_and_gradient(serial.q0)
    assert abs(J - Js) <= 1e-10 * abs(Js)
    assert np.allclose(g, gs, rtol=1e-8, atol=0)
    its = [r.iterations for r in parallel.rf.trajectory.records]
    assert its == [r.iterations for r in serial.rf.trajectory.records]
    revised = parallel.rf.simulation.solver.revised_steps
    assert revised == serial.rf.simulation.solver.revised_steps > 0
