"""The paper's Fig. 20 on the paper's data: recover a jumping kangaroo's E and nu.

Scene ``fig20_kangaroo`` of the paper's data (``--data DIR``): ``run-new.json`` (a Neo-Hookean
kangaroo, ``kangaroo-coarse.msh`` scaled 0.25, thrown at (3.2, 1) m/s onto a ground made of
``square.obj`` scaled to 3 x 0.02 m with its boundary clamped; plane stress, rho = 100; BDF1,
60 steps of 0.01 s; IPC contact with dhat = 1e-3, friction 0.5, eps_v = 1e-3) at E = 3e6 Pa,
nu = 0.5, ``target-new.json`` (the same at E = 1e7 Pa, nu = 0.3) and ``opt.json`` (objective:
10 x the time integral, uniform, of int_Gamma1 |u^i - u^i_target|^2 ds over the kangaroo's
boundary; L-BFGS-B, max_change 1, 20 iterations, grad_norm 1e-3). The target trajectory is our
own forward run of ``target-new.json``: J is 0 at the truth (3.6e-23 measured).

The controls are the kangaroo's log E and nu, nu in [0, 0.5], started from run-new.json's
E = 3e6, nu = 0.5. (opt.json's parameters are PolyFEM's per-body log lambda, log mu laid out
[lambda_ground, lambda_kangaroo, mu_ground, mu_kangaroo] = [12, 14.5, 12, 13.8]: the kangaroo's
lambda = e^14.5 = nu E / (1 - nu^2), mu = e^13.8 = E / (2 (1 + nu)) are E = 3e6, nu = 0.5 in
plane stress, the same start; the ground's cells have only clamped nodes, their material has
no effect.)

Why not L-BFGS: nu is barely seen by this trajectory. At the truth the Hessian of J in (log E,
nu) has eigenvalues 4.9e-2 and 2.7e-7 (condition 1.8e5; in the paper's log lambda, log mu
2.2e6), and the valley of J is bent: its floor E*(nu) (J minimal over E at fixed nu) peaks at
the truth (E* = 9.82e6 at nu = 0.5, 9.94e6 at 0.2), while J on the floor is at most 6e-9
between nu = 0.13 and 0.5 (3.7e-2 at the start). L-BFGS reaches the floor in four iterations
(E within 1.5%) and then crawls along it: 20 iterations took nu from 0.5 to 0.433 (J 1.3e-9,
|g| 4e-8), 30 with nu rescaled to balance the Hessian's diagonal ended at 0.23; Newton with a
finite-difference Hessian of the adjoint gradient moves 0.007 per iteration (15 iterations:
0.417), because every straight step along the bent floor leaves it and the walls (curvature
4.9e-2) cap the next one. The adjoint gradient itself is right (central differences agree to
1e-4 relative on the floor). So E is projected out (``diffsolids.optimize.FloorSearch``): J
is minimised over log E at fixed nu (Newton with secant curvature), and nu follows the floor's
slope dJ/dnu + (dlogE*/dnu) dJ/dlogE (secant steps of at most 0.15, kept inside the bracket
where the slope changes sign), each new nu starting from the floor's tangent. Measured
(default, 60 steps): 21 evaluations (one forward and one adjoint solve each; CPU 38 s),
E = 1.0000007e7, nu = 0.300053, J 3.6e-16 (from 3.7e-2), |g| 1.4e-11; ``--tiny`` (35 steps):
17 evaluations (CPU 15 s), nu = 0.300002.

The outcome checked (``--check``, every size): E and nu within 1% of 1e7 and 0.3, no
intersection or inverted element in the three runs. The search stops when its next step would
change log E by less than 1e-7 and nu by less than 1e-4 (L-BFGS stopped at opt.json's
grad_norm 1e-3 would have ended at its third iterate, E 9.9e6, nu 0.485; the gradient's noise
at the truth is ~2e-12).

Sizes: ``--tiny`` (35 steps, reaching the first impact; the test), default and ``--full``
(the paper's 60 steps), at most 24, 40 and 60 evaluations (``--iterations`` sets the limit). The
barrier stiffness is ``suggest_barrier_stiffness``'s (``--kappa scene``: the scene's 1e5 as
PolyFEM means it; see ``paper_puzzle`` for what it does). Output in ``output/paper_kangaroo/``:
``history.jsonl`` (one line per evaluation), ``result.json``, ``paper_kangaroo.png``.
"""

import numpy as np
from common import DemoReport, DemoRun, by_size, run_demo
from material_common import check_recovered
from mpi4py import MPI
from paper_common import (
    add_data_argument,
    build,
    contact_figures,
    experiment,
    finish_paper,
    paper_report,
    paper_setup,
    scenes,
    target_objective,
)

from diffsolids.adjoint.checkpointing import Checkpointing
from diffsolids.controls import ControlSet, ParameterControl
from diffsolids.optimize import FloorSearch, OptimizationOutput
from diffsolids.reduced_functional import ReducedFunctional

FOLDER = "fig20_kangaroo"
KANGAROO = 1  # body id (volume_selection)
MAX_ERROR = 0.01
STEP_TOL = (1e-7, 1e-4)  # next Newton step of log E and nu at which the search stops
MAX_CHANGE = (1.0, 0.15)  # largest step of log E (opt.json's max_change) and of nu
SIZES = by_size(steps=(35, None, None), iterations=(24, 40, 60))


def parse_args(argv, comm: MPI.Comm) -> DemoRun:
    """The run with its arguments (``--iterations``: the evaluation limit)."""
    parser = DemoRun.parser(__doc__.splitlines()[0], "paper_kangaroo")
    add_data_argument(parser)
    return DemoRun(parser, argv, comm, SIZES)


def parameters_of(scene) -> np.ndarray:
    """(log E, nu) of the kangaroo in a scene."""
    m = scene.materials[KANGAROO]
    return np.array([np.log(m.E), m.nu])


def setup(args, comm):
    """Scene, simulation, controls and the paper's objective (target trajectory loaded)."""
    path, opt = experiment(args.data, FOLDER)
    run_scene, target_scene = scenes(path, opt)
    model, contact, sim = build(run_scene, comm, args.steps, args.kappa)
    controls = [
        ParameterControl(model, "E", "bodies", [KANGAROO], log=True, lower=np.log(1e4)),
        ParameterControl(model, "nu", "bodies", [KANGAROO], lower=0.0, upper=0.5),
    ]
    true, q0 = parameters_of(target_scene), parameters_of(run_scene)
    ControlSet(controls, sim).assign(true)
    target = sim.run()
    # 61 states of 462 dofs: all in memory (the "auto" policy checkpoints on a loaded node, and
    # the figure and the invariant checks read every state of the kept trajectories)
    objective = target_objective(sim, opt, target)
    rf = ReducedFunctional(sim, objective, controls, checkpointing=Checkpointing("all"))
    rf.controls.assign(q0)
    return model, contact, sim, rf, target, true, q0, opt


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Recover the kangaroo's E and nu; returns the report (printed on rank 0)."""
    run = parse_args(argv, comm)
    args = run.args
    _, contact, sim, rf, target, true, q0, opt = paper_setup(run, setup)
    box = opt["solver"]["nonlinear"].get("box_constraints", {})
    max_change = (float(box.get("max_change", MAX_CHANGE[0])), MAX_CHANGE[1])
    output = OptimizationOutput(args.out, comm, write_parameters=True, plot_every=0)
    search = FloorSearch(rf, max_change, STEP_TOL, args.iterations + 1, output)
    result = search.run(q0)
    keeper = search.keeper
    trajs = {"target": target, "initial": keeper.first, "final": keeper.last}

    report = paper_report(run, result, sim, trajs, contact)
    found = {"E": float(np.exp(result.q[0])), "nu": float(result.q[1])}
    start = {"E": float(np.exp(q0[0])), "nu": float(q0[1])}
    truth = {"E": float(np.exp(true[0])), "nu": float(true[1])}
    check_recovered(report, start, found, truth, MAX_ERROR)
    figures = {
        "true": truth,
        "initial": start,
        "recovered": found,
        "final_gradient_norm": float(result.history[-1].gradient_norm),
        "best_gradient": [float(x) for x in result.gradient],
        **contact_figures(contact, keeper.last),
    }
    headline = (
        f"paper_kangaroo (Fig. 20): E {start['E']:.3g} -> {found['E']:.6g} (true "
        f"{truth['E']:.3g}), nu {start['nu']:.3g} -> {found['nu']:.5f} (true {truth['nu']:.3g}); "
        f"J {result.objective:.3g}, |g| {np.linalg.norm(result.gradient):.3g}; "
        f"kappa {contact.stiffness:.3g}"
    )
    figure = "Fig. 20 kangaroo"
    return finish_paper(run, report, sim, result, figures, headline, trajs, KANGAROO, figure)


if __name__ == "__main__":
    run_demo(main)
