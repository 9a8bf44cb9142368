from mpi4py import MPI

import diffsolids as ds


def test_cantilever_sags_under_gravity(cantilever):
    model = cantilever
    traj = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-10)).run()
    uz = traj.u[-1].reshape(-1, 3)[:, 2]
    assert MPI.COMM_WORLD.allreduce(uz.min(), op=MPI.MIN) < -1e-3
    assert traj.records[-1].residual < 1e-8
