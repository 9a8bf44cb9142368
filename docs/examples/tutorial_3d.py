"""Tutorial (3D): the same slide on a plate, the target a point on the plate.

Only the scene changes from the 2D tutorial: boxes of tetrahedra, gravity along -z, and the
objective is the squared distance of the block's centre of mass (x and y) from a target point.
"""

import argparse
from pathlib import Path

import numpy as np
from mpi4py import MPI

import diffsolids as ds

TARGET = np.array([0.35, 0.2])  # where the block's centre of mass should stop (x, y) [m]


def build(steps: int = 15, dt: float = 0.02, comm: MPI.Comm = MPI.COMM_WORLD):
    """The scene, its simulation and the reduced functional J(v0)."""
    plate = ds.mesh.simplex_box([[0, 0, 0], [0.6, 0.4, 0.05]], [6, 4, 1])
    block = ds.mesh.simplex_box([[0.05, 0.05, 0.05 + 5e-4], [0.2, 0.2, 0.15]], [2, 2, 2])
    domain = ds.combine_meshes(comm, [plate, block], names={"plate": 1, "block": 2})
    materials = {
        "plate": ds.NeoHookean(E=1e6, nu=0.3, density=1000.0),
        "block": ds.NeoHookean(E=2e4, nu=0.3, density=500.0),
    }
    model = ds.Model(domain, materials)
    model.add_gravity(9.81)  # along -z, the last axis
    model.add_dirichlet(lambda x: x[2] < 1e-9, 0.0)  # the plate's underside
    integrator = ds.BDF(2, dt, steps)
    probe = ds.ContactTerm(model, dhat=1e-3, stiffness=1.0)
    kappa = ds.suggest_barrier_stiffness(probe, integrator)
    model.add_numeric_term(ds.ContactTerm(model, dhat=1e-3, stiffness=kappa, friction=0.3))
    sim = ds.Simulation(model, integrator, ds.SolverOptions(rtol=1e-9), progress=False)
    # [objective]
    # |c(T) - target|^2 over the horizontal components of the block's centre of mass
    volume = 0.15 * 0.15 * 0.1
    c = [
        ds.Integral(lambda f, k=k: (f.X[k] + f.u[k]) / volume * f.dx(2), f"c_{k}") for k in range(2)
    ]
    objective = ds.final_value((c[0] - TARGET[0]) ** 2 + (c[1] - TARGET[1]) ** 2)
    # [end]
    control = ds.RigidVelocity(sim, "block", angular=False)
    return ds.ReducedFunctional(sim, objective, control)


def main(argv: list[str] | None = None) -> None:
    """Check the gradient, optimise, write the final trajectory."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=15, help="time steps")
    p.add_argument("--iterations", type=int, default=5, help="L-BFGS iterations")
    p.add_argument("--out", type=Path, default=Path("output/tutorial_3d"), help="output folder")
    args = p.parse_args(argv)
    rf = build(args.steps)
    comm = rf.model.domain.comm
    q0 = np.array([0.6, 0.3, 0.0])
    dq = np.random.default_rng(0).standard_normal(3)
    rate = ds.taylor_test(rf, q0, dq, h0=0.01, num=3).min_rate
    options = ds.LBFGSOptions(max_iterations=args.iterations, initial_step=0.2)
    result = ds.minimize(rf, q0, options)
    rf(result.q)
    ds.io.write_trajectory(rf.model, rf.trajectory, args.out / "final.bp")
    if comm.rank == 0:
        print(f"Taylor rate {rate:.2f}")
        J0 = result.history[0].objective
        print(f"J {J0:.4e} -> {result.objective:.4e} in {result.iterations} iterations")
        print(f"optimised throw {np.round(result.q, 3)} m/s")


if __name__ == "__main__":
    main()
