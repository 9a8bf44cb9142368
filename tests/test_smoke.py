import numpy as np
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import create_box


def test_cantilever_sags_under_gravity():
    dom = create_box(
        MPI.COMM_WORLD,
        [[0, 0, 0], [4, 0.5, 0.5]],
        [8, 2, 2],
        facets={1: lambda x: np.isclose(x[0], 0)},
    )
    model = ds.Model(dom, ds.NeoHookean(E=1e5, nu=0.3, density=100.0))
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    traj = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-10)).run()
    uz = traj.u[-1].reshape(-1, 3)[:, 2]
    assert MPI.COMM_WORLD.allreduce(uz.min(), op=MPI.MIN) < -1e-3
    assert traj.records[-1].residual < 1e-8
