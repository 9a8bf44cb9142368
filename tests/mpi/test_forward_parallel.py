"""Run under ``mpiexec -n 2``: the distributed solve equals a serial solve of the same problem."""

import numpy as np
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import create_box


def _tip_and_energy(comm):
    dom = create_box(
        comm, [[0, 0, 0], [4, 0.5, 0.5]], [8, 2, 2], facets={1: lambda x: np.isclose(x[0], 0)}
    )
    model = ds.Model(dom, ds.NeoHookean(E=1e5, nu=0.3, density=100.0))
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    traj = ds.Simulation(model, ds.BDF(2, 0.02, 5), ds.SolverOptions(rtol=1e-12)).run()
    x = model.V.tabulate_dof_coordinates()
    u = traj.u[-1].reshape(-1, 3)
    tip = np.isclose(x[:, 0], 4.0) & np.isclose(x[:, 1], 0.0) & np.isclose(x[:, 2], 0.0)
    local = u[tip][0] if tip.any() else None
    vals = [v for v in comm.allgather(local) if v is not None]
    return vals[0], traj.records[-1].energy


def test_parallel_matches_serial():
    comm = MPI.COMM_WORLD
    tip_par, e_par = _tip_and_energy(comm)
    tip_ser, e_ser = _tip_and_energy(MPI.COMM_SELF)
    assert np.allclose(tip_par, tip_ser, rtol=1e-10, atol=1e-14)
    assert abs(e_par - e_ser) <= 1e-10 * abs(e_ser)
