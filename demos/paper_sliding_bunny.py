"""The paper's Fig. 21 on the paper's data: identify the friction coefficient of a sliding bunny.

Scene ``fig21_friction_bunny`` of the paper's data (``--data DIR``): ``run-new.json`` (a
Neo-Hookean Stanford bunny, ``stanford-bunny.obj_.msh`` scaled 4, E = 1e5 Pa, nu = 0.48,
rho = 1000, thrown at v0 = (0, 0, 2) m/s along a slide ``slide.msh`` (an obstacle: here a body
whose boundary is clamped) under gravity along -y; BDF1, 40 steps of 0.05 s; IPC contact with
dhat 1e-3, eps_v 1e-3 and friction 0.5), ``target.json`` (the same scene with friction 0.1) and
``opt.json`` (the objective: 100 |c(T) - c_target(T)|^2, c the bunny's centre of mass at the
final time; L-BFGS, grad_norm 1e-4).

The control is the logarithm of the friction coefficient of the bunny-slide pair (the paper's
single friction parameter; the other pairs, self-contact of the bunny and of the clamped slide,
never touch).
The outcome checked (``--check``): mu = 0.1 recovered from 0.5 to 1e-3 relative, and no
intersection or inverted element in the target, initial and final runs.

The barrier stiffness is ``suggest_barrier_stiffness``'s (``--kappa scene``: the scene's 1e4 as
PolyFEM means it, see ``diffsolids.contact.polyfem``: pairs rest ~2e-9 m apart and the first
step already needs more than 50 Newton iterations, most of them cut by the collision check).

Sizes: ``--tiny`` (3 steps, 1 iteration: a smoke test), default (10 steps of the paper's 40: the
bunny lands and slides for 0.5 s; ~40 s per step on a loaded 2-core machine) and ``--full`` (the
paper's 40 steps, ~30 min per forward run).
Output in ``output/paper_sliding_bunny/``: ``history.jsonl``, ``result.json``,
``paper_sliding_bunny.png``.
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
    paper_functional,
    paper_report,
    paper_setup,
    recovery_figures,
)

import diffsolids as ds
from diffsolids.controls import FrictionControl
from diffsolids.io.polyfem_scene import read_polyfem_scene
from diffsolids.objectives import center_of_mass, final_value, series_values
from diffsolids.reduced_functional import ReducedFunctional

FOLDER = "fig21_friction_bunny"
BUNNY, SLIDE = 1, 3  # body ids (volume_selection)
RECOVERY_RTOL = 1e-3
SIZES = by_size(steps=(3, 10, None), iterations=(1, 20, 20))


def parse_args(argv, comm: MPI.Comm) -> DemoRun:
    """The run with its arguments."""
    parser = DemoRun.parser(__doc__.splitlines()[0], "paper_sliding_bunny")
    add_data_argument(parser)
    return DemoRun(parser, argv, comm, SIZES)


def paper_objective(model, opt: dict, target_centre: np.ndarray):
    """opt.json's objective: weight x |c(T) - c_target(T)|^2 (``center-target``, ``final``).

    Raises:
        ds.ParameterError: opt.json holds another objective.
    """
    functional, _ = paper_functional(opt, "final", "center-target", volume_selection=[BUNNY])
    com = center_of_mass(model, BUNNY)
    misfit = sum((com[k] - float(target_centre[k])) ** 2 for k in range(model.dim))
    return final_value(misfit) * float(functional.get("weight", 1.0))


def setup(args, comm):
    """Scene, simulation, control and the paper's objective (target centre computed)."""
    path, opt = experiment(args.data, FOLDER)
    run_scene, target_scene = (
        read_polyfem_scene(path / s["path"], obstacles="clamp") for s in opt["states"]
    )
    if not run_scene.same_geometry(target_scene):
        raise ds.ParameterError(f"{target_scene.path}: other meshes than {run_scene.path}")
    model, contact, sim = build(run_scene, comm, args.steps, args.kappa)
    control = FrictionControl(contact, pairs=[(BUNNY, SLIDE)], log=True)
    true = np.array([float(target_scene.raw["contact"]["friction_coefficient"])])
    q0 = np.array([float(run_scene.raw["contact"]["friction_coefficient"])])
    control.assign(np.log(true))
    target = sim.run()
    com = center_of_mass(model, BUNNY)
    centre = series_values(sim, com, target, steps=[-1])[0]
    control.assign(np.log(q0))
    rf = ReducedFunctional(sim, paper_objective(model, opt, centre), control)
    return model, contact, sim, rf, target, true, q0, opt


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Identify the bunny's friction coefficient; returns the report (printed on rank 0)."""
    run = parse_args(argv, comm)
    args = run.args
    model, contact, sim, rf, target, true, q0, opt = paper_setup(run, setup)
    options = gradient_stop_options(opt, args.iterations, initial_step=0.5, max_change=0.5)
    result, keeper, trajs = optimise_paths(run, rf, np.log(q0), options, target)
    com = center_of_mass(model, BUNNY)
    # the slide runs along z, gravity along -y: the paths in the (z, y) plane
    paths = {k: series_values(sim, com, t)[:, [2, 1]] for k, t in trajs.items()}
    mu = float(np.exp(result.q[0]))
    error0 = float(abs(q0[0] - true[0]) / true[0])
    error1 = float(abs(mu - true[0]) / true[0])

    text = f"({q0[0]:g} -> {mu:.6f}, true {true[0]:g})"
    report = paper_report(run, result, sim, trajs, contact, ("mu", error1, RECOVERY_RTOL, text))
    values = (float(true[0]), float(q0[0]), mu, (error0, error1))
    figures = recovery_figures("mu", *values, contact, keeper.last)
    figures["eps_v"] = contact.eps_v
    headline = (
        f"paper_sliding_bunny (Fig. 21): mu {q0[0]:g} -> {mu:.5f} (true {true[0]:g}); "
        f"relative error {error0:.3f} -> {error1:.2e}; {args.steps} steps, "
        f"kappa {contact.stiffness:.3g}"
    )
    title = "Fig. 21 sliding bunny: centre-of-mass paths (z, y)"
    return finish_paper(run, report, model, result, figures, headline, paths, title)


if __name__ == "__main__":
    run_demo(main)
