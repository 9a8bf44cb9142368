"""Run under ``mpiexec -n 2``: a static PolyFEM scene with a side selection and expression
values gives the serial displacement."""

import numpy as np
from mpi4py import MPI
from test_polyfem_scene_reader import right_side_displacement, static_scene

from diffsolids.polyfem import read_polyfem_scene


def test_static_scene_world_equals_self(tmp_path):
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    path = static_scene(tmp_path)
    out = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        setup = read_polyfem_scene(path).build(comm)
        y, u = right_side_displacement(setup)
        order = np.argsort(y)
        traj = setup.simulation.trajectory
        owned = setup.model.V.dofmap.index_map.size_local * 2
        peak = comm.allreduce(np.abs(traj.u[-1][:owned]).max(), op=MPI.MAX)
        out.append((y[order], u[order], peak))
    (y_par, u_par, peak_par), (y_ser, u_ser, peak_ser) = out
    assert np.allclose(y_par, y_ser) and np.allclose(u_par, u_ser, atol=1e-12)
    assert abs(peak_par - peak_ser) <= 1e-10 * peak_ser
