"""The paper's Fig. 21 on the paper's data: identify the friction coefficient of a sliding bunny.

Scene ``fig21_friction_bunny`` of the paper's data (``--data DIR``): ``run-new.json`` (a
Neo-Hookean Stanford bunny, ``stanford-bunny.obj_.msh`` scaled 4, E = 1e5 Pa, nu = 0.48,
rho = 1000, thrown at v0 = (0, 0, 2) m/s along a slide ``slide.msh`` (an obstacle: here a
kinematic obstacle, ``obstacle3``, no dofs: 2 799 instead of 17 046 with the slide as a
clamped body, the same trajectory) under gravity along -y; BDF1, 40 steps of 0.05 s; IPC
contact with dhat 1e-3, eps_v 1e-3 and friction 0.5), ``target.json`` (the same scene with
friction 0.1) and ``opt.json`` (the objective: 100 |c(T) - c_target(T)|^2, c the bunny's
centre of mass at the final time; L-BFGS, grad_norm 1e-4).

The problem is opt.json's as the runner builds it (``python -m diffsolids.polyfem``;
:func:`friction_problem`): the control is its friction variable, mu of every pair (the bunny's
self-contact never touches), the slide a kinematic obstacle; the demo keeps opt.json's
objective and gradient stop and replaces its iteration limit (5) with ``--iterations`` and
limits a step of mu to 0.2. The outcome checked (``--check``): mu = 0.1 recovered from 0.5 to
1e-3 relative, and no intersection or inverted element in the target, initial and final
runs. Measured (default size, serial, 2026-12-07, a second job on the machine): mu 0.5 -> 0.3
-> 0.1 (relative error 2.8e-16, J 7.7 -> 7.7e-29) in 2 iterations and 3 forward solves, CPU
86 s.

The barrier stiffness is ``suggest_barrier_stiffness``'s (``--kappa scene``: the scene's 1e4 as
PolyFEM means it, see ``diffsolids.polyfem.contact``: pairs rest ~2e-9 m apart and the first
step already needs more than 50 Newton iterations, most of them cut by the collision check).

Two branches of J(mu), and the branch reference that keeps J on one (measured, suggested kappa):
the impact step 3 has two strict local minima of its incremental potential, 78 and 79 contact
pairs, energies -13.0192 and -13.0118 at mu = 0.4999 (7.4e-3 apart at every mu in 0.5 +- 1e-4,
an energy ridge between them, the exact Hessian positive definite at both: smallest
eigenvalue 5.9). Newton from u^2 (every other guess is refused by the collision check of its
straight path) ends in either: the projected phase's first 14 iterations are all cut by the
collision-free step bound, and the paths for mu = 0.4999 and 0.5 part at iteration 11. Neither
the Newton tolerance nor the Hessian (CLAMP or ABS projection, exact from the start: a third
stationary point) decides it deterministically, so J jumps by 1.4% (J = 3.392 at
mu = 0.4999, 3.440 at 0.5 and 0.5001 over 8 steps). The functional therefore follows the
branch of the initial mu (``ReducedFunctional(..., branch_reference=mu0)``): each step's
Newton iteration starts at the reference run's state when that state is admissible, and J is
one smooth function of mu whatever was evaluated before. Central differences then agree with
the adjoint (5 steps, in mu: 5.8e-9 at h = 1e-6, 6.5e-8 at 1e-5, 6.4e-6 at 1e-4, 3.8e-3 at
1e-3: the O(h^2) truncation; ``tests/test_paper_sliding_gradient.py`` builds
``friction_problem(..., follow_branch=True)``, the runner's ``--follow-branch``).

The demo optimises without the branch reference: J's branches differ by 1.4% near mu = 0.5,
which the optimiser's first steps (0.2) pass over, and near the target the plain J is the
target run's own computation (J(0.1) = 0). Following the branch of mu = 0.5 instead, the runs
at mu <= 0.25 do not converge from the reference's states in steps 8-10 and are solved again
from the usual guesses, and J(0.1) = 6.9e-4 (the target run took the other branch at the
impact step): the optimiser drifted to mu = 0.0950 (J 8.1e-5) in 5 iterations and 1 170 s
(2026-12-07; the paper reports 0.0974).

Sizes: ``--tiny`` (3 steps, 1 iteration: a smoke test), default (10 steps of the paper's 40: the
bunny lands and slides for 0.5 s) and ``--full`` (the paper's 40 steps, with the default
solver options: measured once, the target run at mu = 0.1 takes at most 89 Newton iterations
per step, mean 44.3, 164 s CPU (2026-12-07; step 5 took 151 before the first Newton attempt
stopped near a saddle); the run at mu = 0.5 at most 50, mean 26.1, 299 s).
Output in ``output/paper_sliding_bunny/``: ``history.jsonl``, ``result.json``,
``paper_sliding_bunny.png``.
"""

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

from diffsolids.polyfem import PolyFEMOptimization, PolyFEMProblem

FOLDER = "fig21_friction_bunny"
BUNNY = 1  # the bunny's body id (volume_selection)
RECOVERY_RTOL = 1e-3
SIZES = by_size(steps=(3, 10, None), iterations=(1, 20, 20))


def parse_args(argv, comm: MPI.Comm) -> DemoRun:
    """The run with its arguments."""
    parser = DemoRun.parser(__doc__.splitlines()[0], "paper_sliding_bunny")
    add_data_argument(parser)
    return DemoRun(parser, argv, comm, SIZES)


def friction_problem(
    data, comm: MPI.Comm, steps: int | None, kappa="suggest", follow_branch: bool = False
) -> tuple[PolyFEMOptimization, PolyFEMProblem]:
    """opt.json's problem as ``python -m diffsolids.polyfem`` builds it.

    ``follow_branch``: the run at the initial mu is the branch reference of every forward
    (the runner's ``--follow-branch``, see the module docstring). The slide is a kinematic
    obstacle.

    Returns:
        (the opt.json read, the problem: q is mu, ``targets[1]`` the target run)
    """
    return polyfem_problem(data, comm, FOLDER, steps, kappa, follow_branch=follow_branch)


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Identify the bunny's friction coefficient; returns the report (printed on rank 0)."""
    run = parse_args(argv, comm)
    args = run.args
    optimization, problem = friction_problem(args.data, comm, args.steps, args.kappa)
    record_time_grid(run, problem.simulation)
    sim, contact, q0 = problem.simulation, problem.contact, problem.q0
    true = float(optimization.states[1].raw["contact"]["friction_coefficient"])
    options = gradient_stop_options(optimization.raw, args.iterations, max_change=0.2)
    result, _, trajs = optimise_paths(run, problem.rf, q0, options, problem.targets[1])
    mu = float(result.q[0])
    values = (true, q0[0], mu, contact)
    report, figures, (error0, error1) = recovery_outcome(
        run, result, sim, trajs, "mu", values, RECOVERY_RTOL
    )
    figures["eps_v"] = contact.eps_v
    headline = (
        f"paper_sliding_bunny (Fig. 21): mu {q0[0]:g} -> {mu:.5f} (true {true:g}); "
        f"relative error {error0:.3f} -> {error1:.2e}; {args.steps} steps, "
        f"kappa {contact.stiffness:.3g}"
    )
    # the slide runs along z, gravity along -y: the paths in the (z, y) plane
    figure = "Fig. 21 sliding bunny"
    return finish_paper(
        run, report, sim, result, figures, headline, trajs, BUNNY, figure, axes=("z", "y")
    )


if __name__ == "__main__":
    run_demo(main)
