"""The paper's Fig. 20 on the paper's data: recover a jumping kangaroo's E and nu.

Scene ``fig20_kangaroo`` of the paper's data (``--data DIR``): ``run-new.json`` (a Neo-Hookean
kangaroo, ``kangaroo-coarse.msh`` scaled 0.25, thrown at (3.2, 1) m/s onto a ground made of
``square.obj`` scaled to 3 x 0.02 m with its boundary clamped; plane stress, rho = 100; BDF1,
60 steps of 0.01 s; IPC contact with dhat = 1e-3, friction 0.5, eps_v = 1e-3) at E = 3e6 Pa,
nu = 0.5, ``target-new.json`` (the same at E = 1e7 Pa, nu = 0.3) and ``opt.json`` (objective:
10 x the time integral, uniform, of int_Gamma1 |u^i - u^i_target|^2 ds over the kangaroo's
boundary; L-BFGS-B, max_change 1, 20 iterations, grad_norm 1e-3).

The controls are the kangaroo's log E and nu (the paper's parameters are log lambda, log mu
per body, started from opt.json's [12, 13.8], which is not the E, nu of run-new.json; we start
from run-new.json's E = 3e6, nu = 0.5, the outcome the paper states; the ground's cells have
only clamped nodes, their material has no effect). nu is bounded to [0, 0.5], the range of a
3D material: plane stress admits nu up to 1, and there L-BFGS slid into a valley at E = 8.6e6,
nu = 0.81 where the trajectory matches the target to 2e-5 m (J 6e-9 from 3.7e-2). Within
[0, 0.5] E comes within 1.5% in four iterations; nu is weakly determined by this trajectory (J
changes by ~1e-9 between nu = 0.48 and 0.30) and creeps toward 0.3. The outcome checked
(``--check``): E and nu within 1% of 1e7 and 0.3, no intersection or inverted element in the
three runs.

Sizes: ``--tiny`` (35 steps, reaching the first impact; 2 iterations), default and ``--full``
(the paper's 60 steps). The barrier stiffness is ``suggest_barrier_stiffness``'s (``--kappa
scene``: the scene's 1e5 as PolyFEM means it; see ``paper_puzzle`` for what it does). Output in
``output/paper_kangaroo/``: ``history.jsonl``, ``result.json``, ``paper_kangaroo.png``.
"""

import numpy as np
from common import DemoReport, DemoRun, by_size, run_demo
from dynamic_common import check_invariants, finish_transient
from material_common import check_recovered
from mpi4py import MPI
from paper_common import (
    add_data_argument,
    build,
    experiment,
    plot_paths,
    scenes,
    target_objective,
)

from diffsolids.controls import ParameterControl
from diffsolids.objectives import center_of_mass, series_values
from diffsolids.optimize import LBFGSOptions, check_trajectories
from diffsolids.reduced_functional import ReducedFunctional

FOLDER = "fig20_kangaroo"
KANGAROO = 1  # body id (volume_selection)
MAX_ERROR = 0.01
SIZES = by_size(steps=(35, None, None), iterations=(2, 20, 30))


def parse_args(argv, comm: MPI.Comm) -> DemoRun:
    """The run with its arguments."""
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
    objective = target_objective(sim, opt)
    rf = ReducedFunctional(sim, objective, controls)
    true, q0 = parameters_of(target_scene), parameters_of(run_scene)
    rf.controls.assign(true)
    target = sim.run()
    sim.targets = [u.copy() for u in target.u]
    rf.controls.assign(q0)
    return model, contact, sim, rf, target, true, q0, opt


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Recover the kangaroo's E and nu; returns the report (printed on rank 0)."""
    run = parse_args(argv, comm)
    args = run.args
    model, contact, sim, rf, target, true, q0, opt = setup(args, comm)
    args.steps, args.dt = sim.integrator.num_steps, sim.integrator.dt
    box = opt["solver"]["nonlinear"].get("box_constraints", {})
    options = LBFGSOptions(
        max_iterations=args.iterations,
        gradient_rtol=1e-8,
        max_change=[float(box.get("max_change", 1.0)), 0.1],
    )
    result, keeper = run.optimise(rf, q0, options, write_parameters=True)
    trajs = {"target": target, "initial": keeper.first, "final": keeper.last}
    com = center_of_mass(model, KANGAROO)
    paths = {k: series_values(sim, com, t) for k, t in trajs.items()}

    report = run.report(result)
    check_invariants(report, check_trajectories(sim, list(trajs.values()), contact))
    found = {"E": float(np.exp(result.q[0])), "nu": float(result.q[1])}
    start = {"E": float(np.exp(q0[0])), "nu": float(q0[1])}
    truth = {"E": float(np.exp(true[0])), "nu": float(true[1])}
    if not args.tiny:
        check_recovered(report, start, found, truth, MAX_ERROR)
    figures = {
        "true": truth,
        "initial": start,
        "recovered": found,
        "kappa": contact.stiffness,
        "dhat": contact.dhat,
        "newton_iterations_final_run": keeper.last.newton_iterations(),
    }
    headline = (
        f"paper_kangaroo (Fig. 20): E {start['E']:.3g} -> {found['E']:.6g} (true "
        f"{truth['E']:.3g}), nu {start['nu']:.3g} -> {found['nu']:.5f} (true {truth['nu']:.3g}); "
        f"kappa {contact.stiffness:.3g}"
    )

    def figure(path):
        plot_paths(path, paths, result, "Fig. 20 kangaroo: centre-of-mass paths", comm)

    return finish_transient(run, report, model, result, [], figures, headline, figure)


if __name__ == "__main__":
    run_demo(main)
