"""Flat and wavy grounds on 2 ranks: the drop on a two-triangle ground (both formulations),
the box thrown along a wavy polyline and the disk rolling down a slope (Newton steps held at
stick), as serial."""

import numpy as np
import pytest
from mpi4py import MPI
from smoothness_scenes import drop, roll, wavy

COMM = MPI.COMM_WORLD


def _as_serial(build, *args, **kwargs):
    """The scene on COMM and on one rank: J to 1e-10 and the gradient to 1e-8 of serial."""
    parallel = build(*args, comm=COMM, **kwargs)
    J, g = parallel.rf.value_and_gradient(parallel.q0)
    serial = build(*args, comm=MPI.COMM_SELF, **kwargs)
    Js, gs = serial.rf.value_and_gradient(serial.q0)
    assert abs(J - Js) <= 1e-10 * abs(Js)
    assert np.allclose(g, gs, rtol=1e-8, atol=0)
    pairs = [r.num_collisions for r in parallel.contact.records]
    assert COMM.allreduce(sum(pairs), op=MPI.SUM) > 0
    return parallel, serial


@pytest.mark.parametrize("formulation", ["ipc", "convergent"])
def test_drop_on_two_triangles_equals_serial(formulation):
    _as_serial(drop, 2, steps=8, formulation=formulation)


def test_wavy_ground_equals_serial():
    _as_serial(wavy, steps=12)


def test_rolling_disk_equals_serial():
    parallel, serial = _as_serial(roll, steps=14)
    its = [r.iterations for r in parallel.rf.trajectory.records]
    assert its == [r.iterations for r in serial.rf.trajectory.records]
    revised = parallel.rf.simulation.solver.revised_steps
    assert revised == serial.rf.simulation.solver.revised_steps > 0
