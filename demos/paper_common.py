"""Helpers of the demos that run the paper's experiments on the paper's own data.

The paper's data repository (``Huangzizhou/DiffIPC-data``, folder ``json_scripts/``) holds one
folder per experiment with the meshes, the PolyFEM scene of the run (``run*.json``), of the
target (``target*.json``) and the optimisation (``opt.json``: parameters, objective,
optimiser). The demos take ``--data DIR`` (a checkout, its ``json_scripts/`` or a folder
holding ``diffipc/``, the subset the tests use; default: the environment variable
``DIFFSOLIDS_DATA``, else ``../shared/data`` next to the repository, as the tests do) and
never copy the data.

Here: the data folder, the scenes of an experiment (run and target must place the same
meshes), opt.json's objective checked (``paper_functional``) and its ``transient_integral`` of a
``target`` as our objective, a Simulation that loads the target of each step, and the steps
the demos' ``main`` share: setup with the time grid recorded, the optimisation with its three
trajectories, the report with the invariants and the recovery outcome, the figures of
``report.extra`` and the closing figure and summary.
"""

import json
import os
from pathlib import Path

import numpy as np
from common import ROOT
from dynamic_common import finish_transient
from invariants import check_invariants

import diffsolids as ds
from diffsolids.objectives import center_of_mass, series_values, target_trajectory, time_integral
from diffsolids.optimize import LBFGSOptions, check_trajectories
from diffsolids.polyfem import PolyFEMOptimization, PolyFEMProblem, read_polyfem_optimization
from diffsolids.polyfem.scene import PolyFEMScene, read_polyfem_scene

__all__ = [
    "DEFAULT_DATA",
    "add_data_argument",
    "build",
    "contact_figures",
    "experiment",
    "finish_paper",
    "gradient_stop_options",
    "kappa_argument",
    "optimise_paths",
    "paper_functional",
    "paper_report",
    "paper_setup",
    "plot_paths",
    "polyfem_problem",
    "record_time_grid",
    "recovery_outcome",
    "scenes",
    "target_objective",
]

# the folder holding the paper's data (its diffipc/ or json_scripts/, see DATA_LAYOUTS)
DEFAULT_DATA = Path(os.environ.get("DIFFSOLIDS_DATA", ROOT.parent / "shared" / "data"))


def add_data_argument(parser) -> None:
    """``--data DIR`` (the folder holding the experiments' folders) and ``--kappa``."""
    parser.add_argument(
        "--data",
        type=Path,
        default=DEFAULT_DATA,
        help=f"folder of the paper's scene data (default {DEFAULT_DATA})",
    )
    parser.add_argument(
        "--kappa",
        default="suggest",
        help="barrier stiffness: 'suggest' (suggest_barrier_stiffness, the default), 'scene' "
        "(the scene's barrier_stiffness as PolyFEM means it) or a number",
    )


# where an experiment's folder may sit under --data: the folder itself, a checkout of the
# paper's data repository (json_scripts/), the parent of the shared subset (diffipc/)
DATA_LAYOUTS = (".", "json_scripts", "diffipc")


def experiment(data: Path, folder: str) -> tuple[Path, dict]:
    """The folder of an experiment (under ``data`` as in :data:`DATA_LAYOUTS`) and its ``opt.json``.

    Raises:
        FileNotFoundError: The folder or its opt.json is missing (names ``--data``).
    """
    for layout in DATA_LAYOUTS:
        path = Path(data) / layout / folder
        if (path / "opt.json").is_file():
            return path.resolve(), json.loads((path / "opt.json").read_text())
    raise FileNotFoundError(
        f"no {folder}/opt.json under {data} (nor under its json_scripts/ or diffipc/): pass "
        "--data DIR, the folder of the paper's scene data (a checkout of "
        "Huangzizhou/DiffIPC-data, or its json_scripts/), or set DIFFSOLIDS_DATA"
    )


def scenes(path: Path, opt: dict) -> tuple[PolyFEMScene, PolyFEMScene | None]:
    """The run scene (``states[0]``) and the target scene (``states[1]``, if any).

    Raises:
        ds.ParameterError: The target places other meshes than the run.
    """
    states = [read_polyfem_scene(path / s["path"]) for s in opt["states"]]
    run = states[0]
    target = states[1] if len(states) > 1 else None
    if target is not None and not run.same_geometry(target):
        raise ds.ParameterError(f"{target.path}: the target places other meshes than {run.path}")
    return run, target


def kappa_argument(value: str | None):
    """``--kappa`` as the ``stiffness`` argument of PolyFEMScene.contact_term.

    "scene" (or None): the scene's own barrier stiffness; "suggest"; or a number.
    """
    if value is None or value == "scene":
        return None
    if value == "suggest":
        return value
    return float(value)


def paper_functional(
    opt: dict,
    integral_type: str,
    static_type: str,
    default_integral: str | None = None,
    **static_fields,
) -> tuple[dict, dict]:
    """opt.json's one functional and its static objective, checked for the expected kind.

    Args:
        opt: The opt.json.
        integral_type: The expected ``integral_type`` of the ``transient_integral``.
        static_type: The expected ``type`` of its ``static_objective``.
        default_integral: ``integral_type`` when opt.json gives none (None: it must be given).
        **static_fields: Further entries the static objective must have, e.g.
            ``volume_selection=[1]``.

    Returns:
        (functional, static objective) as dicts.

    Raises:
        ds.ParameterError: opt.json holds another objective (named in the message).
    """
    (functional,) = opt["functionals"]
    static = functional.get("static_objective", {})
    if (
        functional.get("type") != "transient_integral"
        or functional.get("integral_type", default_integral) != integral_type
        or static.get("type") != static_type
        or any(static.get(k) != v for k, v in static_fields.items())
    ):
        raise ds.ParameterError(
            f"opt.json objective {functional!r} is not a {integral_type} {static_type}"
        )
    return functional, static


def target_objective(sim: ds.Simulation, opt: dict, target: ds.Trajectory):
    """The paper's objective of opt.json: ``transient_integral`` of a ``target`` term.

    PolyFEM's ``target`` with ``surface_selection`` is int_Gamma |x - x_target|^2 ds over the
    selected boundary (same meshes: |u - u_target|^2); its ``transient_integral`` (uniform)
    skips t = 0 and weights each later step by dt; ``weight`` multiplies the whole.

    Args:
        sim: The simulation the objective is evaluated on.
        opt: opt.json's contents.
        target: The target run (same mesh and steps).

    Raises:
        ds.ParameterError: opt.json holds another objective.
    """
    functional, static = paper_functional(opt, "uniform", "target", default_integral="uniform")
    facets = static["surface_selection"]
    misfit = target_trajectory(sim, target, facets=facets, match="displacement")
    return time_integral(misfit, "uniform") * float(functional.get("weight", 1.0))


def build(
    scene: PolyFEMScene,
    comm,
    steps: int | None,
    kappa=None,
    rtol: float = 1e-9,
    area_weighting: bool = False,
    contact_options: dict | None = None,
    **solver_options: float | str,
):
    """The scene's model, contact term and a Simulation of its first ``steps`` steps.

    Args:
        scene: The run scene.
        comm: Communicator.
        steps: Number of steps (None: the scene's).
        kappa: ``--kappa`` ("scene" or None: the scene's barrier stiffness as written).
        rtol: Newton tolerance.
        area_weighting: Weight contact pairs by area (PolyFEM: no; the 3D throw converges
            with the suggested kappa only with it, see bench_paper).
        contact_options: Further ContactTerm arguments (e.g. ``hessian_projection``).
        **solver_options: Further :class:`~diffsolids.SolverOptions` (e.g.
            ``exact_hessian_below``).

    Returns:
        (model, contact, simulation)
    """
    domain = scene.domain(comm)
    model = scene.model(domain)
    integrator = ds.BDF(scene.bdf_order, scene.dt, steps or scene.num_steps)
    # the scenes' soft barriers (kappa 1e5) rest pairs ~1e-11 m apart: only closer than
    # 1e-10 dhat counts as touching in the invariant checks (check_trajectories)
    contact = scene.contact_term(
        model,
        integrator,
        kappa_argument(kappa),
        min_gap=1e-10,
        area_weighting=area_weighting,
        **(contact_options or {}),
    )
    sim = ds.Simulation(
        model,
        integrator,
        ds.SolverOptions(rtol=rtol, **solver_options),
        u0=scene.nodal_values(model, scene.initial_displacement),
        v0=scene.nodal_values(model, scene.initial_velocity),
        progress=False,
    )
    return model, contact, sim


def polyfem_problem(
    data: Path, comm, folder: str, steps: int | None = None, kappa="suggest", **build
) -> tuple[PolyFEMOptimization, PolyFEMProblem]:
    """An experiment's opt.json built as ``python -m diffsolids.polyfem`` builds it.

    :func:`~diffsolids.polyfem.read_polyfem_optimization` of ``folder``'s opt.json under
    ``data``, built with ``steps`` and the ``--kappa`` value ``kappa``; pairs closer than 1e-10
    dhat count as touching in the invariant checks (as in :func:`build`).

    Args:
        data: ``--data``.
        comm: Communicator.
        folder: The experiment's folder.
        steps: Run the first ``steps`` steps (None: the scenes').
        kappa: ``--kappa`` ("suggest", "scene" or a number).
        **build: Further arguments of :meth:`~diffsolids.polyfem.PolyFEMOptimization.build`
            (``contact_options`` are added to ``min_gap``).

    Returns:
        (the opt.json read, the problem)
    """
    path, _ = experiment(data, folder)
    contact_options = {"min_gap": 1e-10, **build.pop("contact_options", {})}
    optimization = read_polyfem_optimization(path / "opt.json")
    problem = optimization.build(
        comm,
        steps=steps,
        stiffness=kappa_argument(kappa),
        contact_options=contact_options,
        **build,
    )
    return optimization, problem


def record_time_grid(run, simulation: ds.Simulation) -> None:
    """The simulation's steps and time step recorded in ``run.args`` (the report shows them)."""
    integrator = simulation.integrator
    run.args.steps, run.args.dt = integrator.num_steps, integrator.dt


def gradient_stop_options(opt: dict, iterations: int, **kwargs) -> LBFGSOptions:
    """L-BFGS options stopping at opt.json's gradient norm (``grad_norm`` x 1e-3, absolute)."""
    nonlinear = opt["solver"]["nonlinear"]
    atol = float(nonlinear.get("grad_norm", 1e-4)) * 1e-3
    return LBFGSOptions(max_iterations=iterations, gradient_atol=atol, gradient_rtol=0.0, **kwargs)


def paper_setup(run, setup) -> tuple:
    """``setup(args, comm)`` of a paper demo, its steps and time step recorded in ``run.args``.

    Returns:
        What ``setup`` returns: (model, contact, simulation, ...).
    """
    values = setup(run.args, run.comm)
    integrator = values[2].integrator
    run.args.steps, run.args.dt = integrator.num_steps, integrator.dt
    return values


def optimise_paths(run, rf, q0, options: LBFGSOptions, target) -> tuple:
    """``run.optimise`` (q in the history) and the three trajectories of the checks and figure.

    Returns:
        (result, keeper, {"target": target, "initial": ..., "final": ...})
    """
    result, keeper = run.optimise(rf, q0, options, write_parameters=True)
    return result, keeper, {"target": target, "initial": keeper.first, "final": keeper.last}


def paper_report(run, result, sim, trajectories: dict, contact, recovery: tuple | None = None):
    """The DemoReport with the invariants of the trajectories and a recovery outcome.

    Args:
        run: The DemoRun.
        result: The OptimizationResult.
        sim: The Simulation of the trajectories.
        trajectories: The trajectories checked (no inverted element, no intersection).
        contact: The contact term (its collision surface is checked).
        recovery: (what, relative error, tolerance, text): the outcome "relative error of the
            recovered <what>", not checked in ``--tiny`` runs (None: none).
    """
    report = run.report(result)
    check_invariants(report, check_trajectories(sim, list(trajectories.values()), contact))
    if recovery is not None and not run.args.tiny:
        what, error, rtol, text = recovery
        report.check(f"relative error of the recovered {what}", error, rtol, error < rtol, text)
    return report


def contact_figures(contact, final) -> dict:
    """The contact's kappa and dhat and the Newton iterations of the final run (report.extra)."""
    return {
        "kappa": contact.stiffness,
        "dhat": contact.dhat,
        "newton_iterations_final_run": final.newton_iterations(),
    }


def recovery_outcome(run, result, sim, trajectories: dict, name: str, values: tuple, rtol: float):
    """The report and report.extra of the recovery of a parameter ``name`` (true, initial, final).

    The relative errors of the initial and the final value (vector norms), the outcome "relative
    error of the recovered <name>" below ``rtol`` (:func:`paper_report`), and the figures
    ``<name>_true``, ``_initial``, ``_final``, ``_error_initial``, ``_error_final`` with
    :func:`contact_figures` of the final run.

    Args:
        run: The DemoRun.
        result: The OptimizationResult.
        sim: The Simulation of the trajectories.
        trajectories: ``optimise_paths``'s trajectories (checked; "final" is the last run).
        name: The parameter's name in the report.
        values: (true, initial, final, contact): the parameter's values (floats or arrays)
            and the contact term.
        rtol: The relative error the recovery must reach.

    Returns:
        (report, figures, (initial error, final error))
    """
    contact = values[3]
    true, initial, final = (np.atleast_1d(np.asarray(v, dtype=float)) for v in values[:3])
    errors = tuple(float(np.linalg.norm(v - true) / np.linalg.norm(true)) for v in (initial, final))
    scalar = true.size == 1
    shown = [f"{v[0]:.7g}" if scalar else str(np.round(v, 6).tolist()) for v in (initial, final)]
    shown.append(f"{true[0]:g}" if scalar else str(true.tolist()))
    text = f"({shown[0]} -> {shown[1]}, true {shown[2]})"
    report = paper_report(run, result, sim, trajectories, contact, (name, errors[1], rtol, text))
    listed = {"true": true, "initial": initial, "final": final}
    figures = {f"{name}_{k}": float(v[0]) if scalar else v.tolist() for k, v in listed.items()}
    figures.update({f"{name}_error_initial": errors[0], f"{name}_error_final": errors[1]})
    figures.update(contact_figures(contact, trajectories["final"]))
    return report, figures, errors


def finish_paper(
    run,
    report,
    sim,
    result,
    figures: dict,
    headline: str,
    trajectories: dict,
    body: int,
    name: str,
    axes=("x", "y"),
):
    """``finish_transient`` with the figure of :func:`plot_paths`: a body's centre-of-mass paths.

    The paths of the centre of mass of ``body`` in ``trajectories`` (target, initial, final, as
    :func:`optimise_paths` returns them), coordinates ``axes``, titled ``"<name>: centre-of-mass
    paths"`` (with the axes when they are not x, y), next to the objective per iteration.
    """
    com = center_of_mass(sim.model, body)
    columns = ["xyz".index(a) for a in axes]
    paths = {k: series_values(sim, com, t)[:, columns] for k, t in trajectories.items()}
    title = f"{name}: centre-of-mass paths"
    if tuple(axes) != ("x", "y"):
        title += f" ({', '.join(axes)})"

    def figure(path):
        plot_paths(path, paths, result, title, run.comm, axes)

    return finish_transient(run, report, sim.model, result, [], figures, headline, figure)


def plot_paths(path, paths: dict, result, title: str, comm, axes=("x", "y")) -> None:
    """Centre-of-mass paths (target, initial, final) and the objective per iteration.

    ``axes`` names the two coordinates of the paths (the axis labels).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from common import plot_history, save_figure

    if comm.rank != 0:
        return
    fig, (ax, ax_h) = plt.subplots(1, 2, figsize=(11, 4), width_ratios=[2, 1])
    styles = {"target": ("k", "-"), "initial": ("tab:blue", "--"), "final": ("tab:red", ":")}
    for key, xy in paths.items():
        color, ls = styles[key]
        ax.plot(xy[:, 0], xy[:, 1], color=color, ls=ls, label=key)
    ax.set_xlabel(f"{axes[0]} [m]")
    ax.set_ylabel(f"{axes[1]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    plot_history(ax_h, result, "J", "objective", fontsize=9)
    save_figure(fig, path, comm)
