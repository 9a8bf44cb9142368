"""Run a PolyFEM optimisation JSON: ``python -m diffsolids.polyfem OPT_JSON [options]``.

Reads ``OPT_JSON`` and its scenes (:func:`~diffsolids.polyfem.read_polyfem_optimization`),
builds the problem, optionally checks the gradient by central differences, and minimises J
with opt.json's optimiser settings. Writes to ``--out`` (default ``output/<folder of
OPT_JSON>``): ``history.jsonl`` (one record per iterate, with q), ``log.csv`` (the log
printed), ``objective.png`` and ``gradient_norm.png``, ``initial.bp`` and ``final.bp`` (the
trajectories of the first and the last iterate, for ParaView) and ``result.json``. Runs under
``mpiexec -n N`` with the same numbers.
"""

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from mpi4py import MPI

if TYPE_CHECKING:
    from diffsolids.polyfem import PolyFEMProblem

__all__ = ["main", "parser"]


def parser() -> argparse.ArgumentParser:
    """The command line."""
    p = argparse.ArgumentParser(
        prog="python -m diffsolids.polyfem", description=__doc__.splitlines()[0]
    )
    p.add_argument("opt_json", type=Path, help="PolyFEM optimisation JSON (opt.json)")
    p.add_argument("--out", type=Path, default=None, help="output folder")
    p.add_argument("--max-iterations", type=int, default=None, help="replace max_iterations")
    p.add_argument(
        "--grad-norm", type=float, default=None, help="replace solver.nonlinear.grad_norm"
    )
    p.add_argument("--steps", type=int, default=None, help="run only the first N time steps")
    p.add_argument(
        "--kappa",
        default="suggest",
        help="barrier stiffness: 'suggest' (default), 'scene' (as PolyFEM means the scene's) "
        "or a number",
    )
    p.add_argument(
        "--area-weighting",
        action="store_true",
        help="weight contact pairs by area (the convergent formulation's barrier; PolyFEM's "
        "scenes without use_convergent_formulation do not)",
    )
    p.add_argument(
        "--follow-branch",
        action="store_true",
        help="start every step's Newton solve at the initial parameters' run where admissible "
        "(J smooth where contact steps have several local minima)",
    )
    p.add_argument(
        "--check-gradient",
        action="store_true",
        help="compare the gradient with central differences at the start and stop",
    )
    return p


def _stiffness(value: str) -> float | str | None:
    if value == "scene":
        return None
    if value == "suggest":
        return value
    return float(value)


def _say(comm: MPI.Comm, *args: object) -> None:
    if comm.rank == 0:
        print(*args, flush=True)


def _check_gradient(problem: "PolyFEMProblem", comm: MPI.Comm) -> dict:
    """Central differences of J along a random direction and along -g, at three step sizes."""
    from diffsolids.parallel import collective_comm

    rf, q0 = problem.rf, problem.q0
    g = rf.gradient(q0)
    rng = np.random.default_rng(0)
    out = {}
    for name, d in (("random", rng.standard_normal(q0.size)), ("gradient", -g)):
        d = collective_comm(comm).bcast(d / max(np.linalg.norm(d), 1e-300), root=0)
        for h in (1e-3, 1e-4, 1e-5):
            fd = (rf(q0 + h * d) - rf(q0 - h * d)) / (2 * h)
            exact = float(g @ d)
            err = abs(fd - exact) / max(abs(exact), 1e-300)
            out[f"{name} h={h:g}"] = err
            _say(
                comm,
                f"  {name:8s} h = {h:.0e}: central difference {fd:.9e}, "
                f"adjoint {exact:.9e}, relative error {err:.2e}",
            )
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    from diffsolids.errors import DiffsolidsError
    from diffsolids.io.output import write_trajectory
    from diffsolids.optimize import TrajectoryKeeper, minimize
    from diffsolids.polyfem import read_polyfem_optimization

    args = parser().parse_args(argv)
    comm = MPI.COMM_WORLD
    out = args.out or Path("output") / args.opt_json.resolve().parent.name
    try:
        opt = read_polyfem_optimization(args.opt_json)
        t0 = time.perf_counter()
        problem = opt.build(
            comm,
            steps=args.steps,
            max_iterations=args.max_iterations,
            grad_norm=args.grad_norm,
            stiffness=_stiffness(args.kappa),
            contact_options={"area_weighting": True} if args.area_weighting else None,
            follow_branch=args.follow_branch,
        )
    except DiffsolidsError as error:
        _say(comm, f"error: {error}")
        return 2
    _say(
        comm,
        f"{args.opt_json}: {problem.q0.size} parameters, objective "
        f"{' + '.join(problem.labels)}; built in {time.perf_counter() - t0:.1f} s",
    )
    report: dict = {"opt_json": str(args.opt_json), "parameters": int(problem.q0.size)}
    if args.check_gradient:
        _say(comm, "gradient check (central differences):")
        report["gradient_check"] = _check_gradient(problem, comm)
    keeper = TrajectoryKeeper()
    result = minimize(
        problem.rf,
        problem.q0,
        problem.options,
        inner_product=problem.inner_product,
        stop_conditions=[problem.stopping],
        on_accept=keeper,
        output_dir=out,
        log=True,
        log_file=out / "log.csv",
        plot_every=1,
    )
    model = result.functional.simulation.model
    for name, traj in (("initial", keeper.first), ("final", keeper.last)):
        if traj is not None:
            write_trajectory(model, traj, out / f"{name}.bp")
    report.update(
        reason=result.reason,
        message=result.message,
        iterations=result.iterations,
        initial_objective=result.history[0].objective,
        objective=result.objective,
        q=[float(v) for v in result.q],
        num_forward=result.num_forward,
        num_gradient=result.num_gradient,
        stopping_conditions=problem.stopping.values,
    )
    if comm.rank == 0:
        (out / "result.json").write_text(json.dumps(report, indent=1))
    _say(
        comm,
        f"{result.reason}: J {report['initial_objective']:.6e} -> {result.objective:.6e} "
        f"in {result.iterations} iterations; output in {out}",
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
