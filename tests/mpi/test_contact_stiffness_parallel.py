"""Run under ``mpiexec -n 2``: the kappa a contact term chooses and its run equal serial ones."""

import numpy as np
import pytest
from mpi4py import MPI
from test_contact_stiffness import _scene

import diffsolids as ds


def _run(comm):
    model, contact, sim = _scene(comm=comm)
    traj = sim.run()
    com = ds.series_values(sim, ds.center_of_mass(model, [2])[1], traj)
    return contact.stiffness, np.asarray(com)


def test_chosen_stiffness_world_equals_self():
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    kappa_par, com_par = _run(MPI.COMM_WORLD)
    kappa_ser, com_ser = _run(MPI.COMM_SELF)
    assert kappa_par == pytest.approx(kappa_ser, rel=1e-12)
    assert np.allclose(com_par, com_ser, rtol=1e-10, atol=1e-14)
    assert np.ptp(com_ser) > 1e-6  # the block moved
