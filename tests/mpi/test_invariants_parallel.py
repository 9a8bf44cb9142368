"""Run under ``mpiexec -n 2``: the post-processing tools are collective and rank-independent.

Centres of mass along a trajectory, volume ratios, inverted states and cells, outlines and
triangles of figures: each check of ``tests/state_checks.py`` holds on 2 ranks, and its numbers
equal those of a COMM_SELF run; the contact checks count the same states.
"""

import numpy as np
from mpi4py import MPI
from optimize_script import contact_problem
from state_checks import (
    check_centres_of_mass,
    check_figure_geometry,
    check_volume_ratios_and_inversions,
)

import diffsolids as ds
from diffsolids.optimize import BoundaryIntersection, check_trajectories


def test_checks_on_two_ranks_equal_serial_ones():
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run under mpiexec -n 2"
    for check in (check_centres_of_mass, check_volume_ratios_and_inversions, check_figure_geometry):
        world, serial = np.asarray(check(comm)), np.asarray(check(MPI.COMM_SELF))
        assert np.allclose(world, serial, rtol=1e-13, atol=1e-14), check.__name__
        assert all(np.array_equal(world, w) for w in comm.allgather(world))  # on every rank


def test_contact_checks_on_two_ranks():
    comm = MPI.COMM_WORLD
    rf, contact = contact_problem(comm)
    rf(rf.initial_parameters())
    traj = rf.trajectory
    X = rf.model.V.tabulate_dof_coordinates()[:, 1]
    down = np.zeros((len(X), 2))
    down[X > 0.3 + 1e-9, 1] = -0.2  # the block into the slab
    sunk = ds.Trajectory([0.0], [down.ravel()], [np.zeros(down.size)])
    checks = check_trajectories(rf.simulation, [traj, sunk], contact)
    assert (checks.inverted, checks.intersecting) == (0, 1)
    assert 0.0 < checks.min_distance == comm.bcast(checks.min_distance, root=0)
    boundary = BoundaryIntersection(rf.model)
    assert not boundary.intersects() and boundary.intersects(down.ravel())
