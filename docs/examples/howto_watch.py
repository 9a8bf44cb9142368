"""Watch an optimisation: the log per iteration, the log file, its plot, an observer.

A cantilever of two materials sags under gravity; L-BFGS recovers the Young's moduli of its
two halves from a measured deflection. ``python docs/examples/howto_watch.py [--out DIR]``
(``mpiexec -n 2`` prints the same log once).
"""

import argparse
from pathlib import Path

import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.optimize.monitor import plot_log, read_log

E_TRUE = (2.0e5, 5.0e4)  # the moduli that made the "measurement"


def build(comm: MPI.Comm) -> ds.ReducedFunctional:
    """The beam, the misfit to the measured deflection, the log-moduli of its two halves."""
    domain = ds.mesh.create_rectangle(
        comm,
        [[0, 0], [2, 0.2]],
        [20, 2],
        facets={1: lambda x: np.isclose(x[0], 0)},
        bodies={2: lambda x: x[0] > 1.0},  # body 1 the clamped half, body 2 the free half
    )
    model = ds.Model(domain, ds.NeoHookean(E=1e5, nu=0.3, density=10.0))
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-10), progress=False)
    measured = fem.Function(model.V)
    misfit = ds.Integral(lambda f: ufl.inner(f.u - measured, f.u - measured) * f.dx, "misfit")
    control = ds.ParameterControl(model, "E", "bodies", log=True)
    rf = ds.ReducedFunctional(sim, ds.final_value(misfit), control)
    q0 = rf.initial_parameters()
    rf(np.log(E_TRUE))  # the measurement: the deflection with the true moduli
    measured.x.array[:] = rf.trajectory.u[-1]
    rf.controls.assign(q0)
    return rf


def main(argv: list[str] | None = None) -> None:
    """Optimise with the log on, then read the log file back and plot it."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("output/howto_watch"), help="output folder")
    p.add_argument("--iterations", type=int, default=20, help="L-BFGS iterations")
    args = p.parse_args(argv)
    rf = build(MPI.COMM_WORLD)
    comm = rf.comm
    # [observer]
    moduli = []  # E of both halves at every accepted iterate

    def keep_moduli(record: ds.optimize.IterationRecord, optimizer: ds.optimize.LBFGS) -> None:
        """An on_accept observer: called once per accepted iterate, on every rank."""
        moduli.append(np.exp(optimizer.point.q))

    # [minimize]
    options = ds.LBFGSOptions(max_iterations=args.iterations, gradient_rtol=1e-8)
    result = ds.minimize(
        rf,
        options=options,
        log=True,  # one line per accepted iterate on stdout (rank 0)
        log_file=args.out / "log.csv",  # the same records, one CSV row each (or .jsonl)
        on_accept=keep_moduli,
    )
    # [read]
    history = read_log(args.out / "log.csv")  # IterationRecord per row, all digits
    assert [r.objective for r in history] == [r.objective for r in result.history]
    if comm.rank == 0:
        figure = plot_log(history, args.out / "log.svg", title="cantilever: E of two halves")
        print(f"E = {np.exp(result.q).round(1)} (true {E_TRUE}), {result.reason}")
        print(f"{len(history)} records in {args.out / 'log.csv'}, plot {figure}")
        print(f"E at iteration 1 {moduli[1].round(1)}, at {len(moduli) - 1} {moduli[-1].round(1)}")
    # [done]


if __name__ == "__main__":
    main()
