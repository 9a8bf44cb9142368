"""Run under ``mpiexec -n 2``: kinematic obstacles on 2 ranks give the serial results.

The obstacle scenes of test_obstacles.py are built on COMM_WORLD and on COMM_SELF in the same
process; collision counts, trajectories, values and gradients (shape, friction coefficient,
initial velocity; parameters in canonical order) must agree, and every rank holds the same
obstacle.
"""

import numpy as np
import pytest
from mpi4py import MPI
from parallel_checks import assert_world_equals_self, value_and_gradient
from test_obstacles import (
    belt_scene,
    block_positions,
    block_scene,
    ground,
    slide_scene,
)

import diffsolids as ds
from diffsolids.contact import Obstacle
from diffsolids.controls import FrictionControl, InitialCondition, ShapeControl
from diffsolids.mesh import create_box
from diffsolids.reduced_functional import ReducedFunctional

RTOL = 1e-10


def _slide(comm):
    model, contact, sim, objective = slide_scene(2, comm=comm)
    return ReducedFunctional(sim, objective, ShapeControl(model, "all")), contact


def _belt(comm):
    _, contact, sim, objective = belt_scene(comm=comm)
    controls = [
        FrictionControl(contact, pairs=[("block", "belt")]),
        InitialCondition(sim, "velocity"),
    ]
    return ReducedFunctional(sim, objective, controls), contact


def _value_and_gradient(build, comm):
    rf, contact = build(comm)
    return value_and_gradient(rf), [r.num_collisions for r in contact.records]


@pytest.mark.parametrize("build", [_slide, _belt], ids=["shape-fixed", "friction-v0-moving"])
def test_obstacle_gradient_world_equals_self(build):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    world, counts_par = _value_and_gradient(build, comm)
    serial, counts_ser = _value_and_gradient(build, MPI.COMM_SELF)
    assert counts_par == counts_ser and min(counts_ser) > 0
    assert_world_equals_self(world, serial, RTOL)


def test_elevator_world_equals_self():
    """A moving obstacle whose move is made with the guess: the same trajectory on 2 ranks."""
    runs = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        lift = ground(motion=lambda t: np.array([0.0, 0.5 * t]), name="lift")
        block = [[0.2, 1e-3], [0.5, 0.151]]
        _, contact, sim = block_scene(
            lift, ds.BDF(1, 0.01, 4), block=block, gravity=(0, 0), comm=comm, v0=np.array([0, 0.5])
        )
        traj = sim.run()
        runs.append(
            ([block_positions(contact, u, 1) for u in traj.u], list(contact.moved_with_guess))
        )
    (par, moved_par), (ser, moved_ser) = runs
    assert moved_par == moved_ser and moved_ser
    for a, b in zip(par, ser, strict=True):
        assert np.abs(a - b).max() <= 1e-10


def test_obstacle_from_distributed_mesh():
    """The boundary of a mesh distributed over the ranks: the same obstacle as from a serial one."""
    corners = [[0, 0, -0.2], [1, 1, 0]]
    par = Obstacle.from_domain(create_box(MPI.COMM_WORLD, corners, [3, 2, 1]))
    ser = Obstacle.from_domain(create_box(MPI.COMM_SELF, corners, [3, 2, 1]))
    assert np.array_equal(par.rest_positions, ser.rest_positions)
    assert np.array_equal(par.faces, ser.faces)
    for faces in MPI.COMM_WORLD.allgather(par.faces):
        assert np.array_equal(faces, par.faces)
