"""The potential the Newton solver reports (remembered from its line search) is the true one."""

import numpy as np
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import create_box


def test_recorded_energy_is_the_potential_of_the_step_state():
    dom = create_box(
        MPI.COMM_WORLD,
        [[0, 0, 0], [4, 0.5, 0.5]],
        [8, 2, 2],
        facets={1: lambda x: np.isclose(x[0], 0)},
    )
    model = ds.Model(dom, ds.NeoHookean(E=1e5, nu=0.3, density=100.0))
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    sim = ds.Simulation(model, ds.BDF(2, 0.02, 4), ds.SolverOptions(rtol=1e-10))
    traj = sim.run()
    solver = sim.solver
    energies = [r.energy for r in traj.records]
    assert len(set(energies)) == len(energies)  # every step has its own potential
    for i in range(1, traj.num_steps + 1):
        sim.load_step(i, traj)
        model.fields.u.x.array[:] = traj.u[i]
        fresh = solver.energy()
        assert abs(fresh - traj.records[i - 1].energy) <= 1e-12 * abs(fresh)
