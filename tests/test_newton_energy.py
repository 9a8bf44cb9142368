"""The potential the Newton solver reports (remembered from its line search) is the true one."""

import diffsolids as ds


def test_recorded_energy_is_the_potential_of_the_step_state(cantilever):
    model = cantilever
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
