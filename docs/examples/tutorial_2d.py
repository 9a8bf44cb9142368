"""Tutorial (2D): slide a block along a slab so that it stops at a target.

A soft block resting on a clamped slab is given an initial velocity; friction stops it. We
choose the initial velocity with L-BFGS so that the block's centre of mass stops at x = X_TARGET.
Run ``python docs/examples/tutorial_2d.py`` (or under ``mpiexec -n 2``); the gradient is
checked by ``docs/examples/test_tutorial_2d.py`` (``python -m pytest docs/examples``).
"""

import argparse
from pathlib import Path

import numpy as np
from mpi4py import MPI

import diffsolids as ds

X_TARGET = 0.5  # where the block's centre of mass should stop [m]


def build(steps: int = 25, dt: float = 0.02, comm: MPI.Comm = MPI.COMM_WORLD):
    """The scene, its simulation and the reduced functional J(v0)."""
    # [mesh]
    # Two bodies, meshed separately (serial meshes) and combined into one Domain that is
    # partitioned over `comm`. The block starts 0.5 mm above the slab: within the contact
    # distance dhat, so that it rests on the barrier from the first step.
    slab = ds.mesh.simplex_box([[0.0, 0.0], [1.5, 0.1]], [15, 1])
    block = ds.mesh.simplex_box([[0.1, 0.1 + 5e-4], [0.4, 0.25]], [6, 3])
    domain = ds.combine_meshes(comm, [slab, block], names={"slab": 1, "block": 2})
    # [material]
    # One material per body (or one for all). Neo-Hookean, plane strain in 2D.
    materials = {
        "slab": ds.NeoHookean(E=1e6, nu=0.3, density=1000.0),
        "block": ds.NeoHookean(E=2e4, nu=0.3, density=500.0),
    }
    model = ds.Model(domain, materials)
    # [loads]
    # Gravity along -y and a clamp: every node of the slab's underside is held at zero.
    model.add_gravity(9.81)
    model.add_dirichlet(lambda x: x[1] < 1e-9, 0.0)
    # [contact]
    # IPC contact between all boundaries, with friction 0.3. The barrier stiffness kappa is
    # chosen from the masses and the time step by suggest_barrier_stiffness, which needs a
    # contact term to look at: a probe with any stiffness.
    integrator = ds.BDF(2, dt, steps)
    probe = ds.ContactTerm(model, dhat=1e-3, stiffness=1.0)
    kappa = ds.suggest_barrier_stiffness(probe, integrator)
    contact = ds.ContactTerm(model, dhat=1e-3, stiffness=kappa, friction=0.3, eps_v=1e-3)
    model.add_numeric_term(contact)
    # [time]
    # BDF2 time stepping: every step minimises the incremental potential with Newton's method.
    # Creating the Simulation freezes the model (no add_* after this line).
    sim = ds.Simulation(model, integrator, ds.SolverOptions(rtol=1e-9), progress=False)
    # [objective]
    # The block's centre of mass in x, written in UFL over the block's cells (dx(2)), and the
    # objective J = (c_x(T) - X_TARGET)^2 at the final time.
    area = 0.3 * 0.15
    c_x = ds.Integral(lambda f: (f.X[0] + f.u[0]) / area * f.dx(2), "centre of mass x")
    objective = ds.final_value((c_x - X_TARGET) ** 2)
    # [control]
    # The control: the block's initial velocity, a rigid translation (angular=False).
    control = ds.RigidVelocity(sim, "block", angular=False)
    rf = ds.ReducedFunctional(sim, objective, control)
    # [end]
    return rf, contact


def main(argv: list[str] | None = None) -> None:
    """Evaluate, optimise, write the trajectories."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=25, help="time steps")
    p.add_argument("--dt", type=float, default=0.02, help="time step [s]")
    p.add_argument("--iterations", type=int, default=8, help="L-BFGS iterations")
    p.add_argument("--out", type=Path, default=Path("output/tutorial_2d"), help="output folder")
    args = p.parse_args(argv)
    rf, contact = build(args.steps, args.dt)
    sim, model = rf.simulation, rf.model
    comm = model.domain.comm
    # [forward]
    q0 = np.array([0.5, 0.0])  # thrown at 0.5 m/s along x
    J0 = rf(q0)
    first = rf.trajectory  # the trajectory of the last evaluation
    if comm.rank == 0:
        print(f"initial throw {q0}: J = {J0:.6e}")
    # [optimise]
    options = ds.LBFGSOptions(max_iterations=args.iterations, gradient_rtol=1e-6, initial_step=0.2)
    # one line per accepted iterate on stdout, and the same numbers in a CSV file
    result = ds.minimize(rf, q0, options, log=True, log_file=args.out / "log.csv")
    if comm.rank == 0:
        print(f"optimised throw {np.round(result.q, 4)}: J = {result.objective:.3e}")
        print(f"{result.iterations} iterations, stopped by {result.reason}")
    # [output]
    rf(result.q)  # re-run the optimum (minimize leaves the last trial in rf)
    for label, traj in (("initial", first), ("final", rf.trajectory)):
        files = ds.io.write_trajectory(model, traj, args.out / f"{label}.bp")
        if comm.rank == 0:
            print(f"wrote {label}: {', '.join(str(p) for p in files)}")
    # [invariants]
    checks = ds.optimize.check_trajectories(sim, [rf.trajectory], contact)
    if comm.rank == 0:
        print(f"inverted states {checks.inverted}, intersecting {checks.intersecting}")
    # [done]


if __name__ == "__main__":
    main()
