"""The paper's Fig. 14 on the paper's data: recover the initial velocity of a puzzle piece.

Scene ``fig14_puzzle_piece`` of the paper's data (``--data DIR``): ``run-new.json`` (a Neo-Hookean
puzzle piece, ``puzzle.msh`` scaled 1e-3, thrown at v0 = (0.5, 0) m/s over a wavy ground
``wave.msh`` whose boundary is clamped; plane stress E = 1e6 Pa, nu = 0.3, rho = 1000; BDF1,
30 steps of 0.02 s; IPC contact with dhat = 0.8 x the shortest boundary edge, friction 0.5,
eps_v = 1e-3), ``target-new.json`` (the same scene thrown at v0 = (2, 1))
and ``opt.json`` (the objective: 10 x the time integral, uniform, of the squared distance of the
piece's boundary to its target, int_Gamma1 |u^i - u^i_target|^2 ds; L-BFGS, grad_norm 1e-4).

The control is the piece's initial velocity (PolyFEM's per-body velocity; the paper's four
parameters also hold the ground's, whose nodes are clamped but for its interior, which
the objective does not see: we leave it at zero). The outcome checked (``--check``): v0 =
(2, 1) recovered from (0.5, 0) to 1e-3 relative, no intersection or inverted element in the
target, initial and final runs.

The barrier stiffness is ``suggest_barrier_stiffness``'s (``--kappa scene``: the scene's 1e5 as
PolyFEM means it, see ``diffsolids.polyfem.contact``; pairs then rest ~1e-12 m apart, where the
collision check cuts every Newton step at the harder impacts of optimiser iterates, e.g. v0 =
(2, -0.4) at step 12: the solver then reaches the step's minimiser through a stiffness
continuation (``SolverOptions.continuation_after``); measured 2026-12-02: v0 recovered to 2.3e-8
in 29 iterations, 46 forward solves, 302 s CPU, where before the optimisation failed at such
an iterate; the objective is noisy at ~1e-8 relative there: the distance of points ~1 m from
the origin has that roundoff at 1e-12 m).

Sizes: ``--tiny`` (10 steps, 2 iterations: a smoke test), default and ``--full`` (the paper's
30 steps).
Output in ``output/paper_puzzle/``: ``history.jsonl``, ``result.json``, ``paper_puzzle.png``.
"""

import numpy as np
from common import DemoReport, DemoRun, by_size, run_demo
from mpi4py import MPI
from paper_common import (
    add_data_argument,
    build,
    experiment,
    finish_paper,
    gradient_stop_options,
    optimise_paths,
    paper_setup,
    recovery_outcome,
    scenes,
    target_objective,
)

from diffsolids.controls import RigidVelocity
from diffsolids.reduced_functional import ReducedFunctional

FOLDER = "fig14_puzzle_piece"
PIECE = 1  # the piece's body id (volume_selection)
RECOVERY_RTOL = 1e-3
SIZES = by_size(steps=(10, None, None), iterations=(2, 50, 50))


def parse_args(argv, comm: MPI.Comm) -> DemoRun:
    """The run with its arguments."""
    parser = DemoRun.parser(__doc__.splitlines()[0], "paper_puzzle")
    add_data_argument(parser)
    return DemoRun(parser, argv, comm, SIZES)


def velocity_of(scene, body: int) -> np.ndarray:
    """The initial velocity a scene gives a body."""
    (entry,) = [v for v in scene.initial_velocity if v.id == body]
    return np.array(entry.value)


def setup(args, comm):
    """Scene, simulation, control and the paper's objective (target trajectory loaded)."""
    path, opt = experiment(args.data, FOLDER)
    run_scene, target_scene = scenes(path, opt)
    model, contact, sim = build(run_scene, comm, args.steps, args.kappa)
    control = RigidVelocity(sim, PIECE, angular=False)
    true = velocity_of(target_scene, PIECE)
    q0 = velocity_of(run_scene, PIECE)
    control.assign(true)
    target = sim.run()
    control.assign(q0)
    rf = ReducedFunctional(sim, target_objective(sim, opt, target), control)
    return model, contact, sim, rf, target, true, q0, opt


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Recover the piece's initial velocity; returns the report (printed on rank 0)."""
    run = parse_args(argv, comm)
    args = run.args
    _, contact, sim, rf, target, true, q0, opt = paper_setup(run, setup)
    options = gradient_stop_options(opt, args.iterations, max_change=2.0)
    result, _, trajs = optimise_paths(run, rf, q0, options, target)
    values = (true, q0, result.q, contact)
    report, figures, (error0, error1) = recovery_outcome(
        run, result, sim, trajs, "v0", values, RECOVERY_RTOL
    )
    headline = (
        f"paper_puzzle (Fig. 14): v0 {q0.tolist()} -> {np.round(result.q, 5).tolist()} "
        f"(true {true.tolist()}); relative error {error0:.3f} -> {error1:.2e}; "
        f"kappa {contact.stiffness:.3g}"
    )
    figure = "Fig. 14 puzzle piece"
    return finish_paper(run, report, sim, result, figures, headline, trajs, PIECE, figure)


if __name__ == "__main__":
    run_demo(main)
