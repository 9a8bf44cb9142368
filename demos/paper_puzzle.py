"""The paper's Fig. 14 on the paper's data: recover the initial velocity of a puzzle piece.

Scene ``fig14_puzzle_piece`` of the paper's data (``--data DIR``): ``run-new.json`` (a Neo-Hookean
puzzle piece, ``puzzle.msh`` scaled 1e-3, thrown at v0 = (0.5, 0) m/s over a wavy ground
``wave.msh`` whose boundary is clamped; plane stress E = 1e6 Pa, nu = 0.3, rho = 1000; BDF1,
30 steps of 0.02 s; IPC contact with dhat = 0.8 x the shortest boundary edge, friction 0.5,
eps_v = 1e-3), ``target-new.json`` (the same scene thrown at v0 = (2, 1))
and ``opt.json`` (the objective: 10 x the time integral, uniform, of the squared distance of the
piece's boundary to its target, int_Gamma1 |u^i - u^i_target|^2 ds; L-BFGS, grad_norm 1e-4).

The problem is opt.json's as ``python -m diffsolids.polyfem`` builds it
(:func:`~diffsolids.polyfem.read_polyfem_optimization`): the four parameters are both bodies'
initial velocities (the ground's first; its nodes are clamped but for its interior), the
target run is our forward run of ``target-new.json``. The demo stops at 1e-3 of opt.json's
grad_norm (the recovery it checks needs it) with steps of at most 2 m/s. The outcome checked
(``--check``): both bodies' v0 recovered (the piece's (2, 1) from (0.5, 0), the ground's 0) to
1e-3 relative, no intersection or inverted element in the target, initial and final runs.

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
    finish_paper,
    gradient_stop_options,
    optimise_paths,
    polyfem_problem,
    record_time_grid,
    recovery_outcome,
)

from diffsolids.polyfem import PolyFEMScene

FOLDER = "fig14_puzzle_piece"
PIECE = 1  # the piece's body id (volume_selection)
RECOVERY_RTOL = 1e-3
SIZES = by_size(steps=(10, None, None), iterations=(2, 50, 50))


def parse_args(argv, comm: MPI.Comm) -> DemoRun:
    """The run with its arguments."""
    parser = DemoRun.parser(__doc__.splitlines()[0], "paper_puzzle")
    add_data_argument(parser)
    return DemoRun(parser, argv, comm, SIZES)


def velocities(scene: PolyFEMScene) -> np.ndarray:
    """The bodies' initial velocities as opt.json's parameters lay them out (geometry[] order)."""
    given = {v.id: v.value for v in scene.initial_velocity}
    return np.concatenate([np.asarray(given.get(b, [0.0, 0.0]), float) for b in scene.body_ids])


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Recover the piece's initial velocity; returns the report (printed on rank 0)."""
    run = parse_args(argv, comm)
    args = run.args
    optimization, problem = polyfem_problem(args.data, comm, FOLDER, args.steps, args.kappa)
    record_time_grid(run, problem.simulation)
    sim, contact, q0 = problem.simulation, problem.contact, problem.q0
    true = velocities(optimization.states[1])
    options = gradient_stop_options(optimization.raw, args.iterations, max_change=2.0)
    result, _, trajs = optimise_paths(run, problem.rf, q0, options, problem.targets[1])
    values = (true, q0, result.q, contact)
    report, figures, (error0, error1) = recovery_outcome(
        run, result, sim, trajs, "v0", values, RECOVERY_RTOL
    )
    piece = 2 * optimization.states[0].body_ids.index(PIECE) + np.arange(2)
    headline = (
        f"paper_puzzle (Fig. 14): piece's v0 {q0[piece].tolist()} -> "
        f"{np.round(result.q[piece], 5).tolist()} (true {true[piece].tolist()}); relative error "
        f"of both bodies' v0 {error0:.3f} -> {error1:.2e}; "
        f"kappa {contact.stiffness:.3g}"
    )
    figure = "Fig. 14 puzzle piece"
    return finish_paper(run, report, sim, result, figures, headline, trajs, PIECE, figure)


if __name__ == "__main__":
    run_demo(main)
