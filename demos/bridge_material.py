"""Material identification: recover the Lame parameters of a bridge from its sag (paper Fig. 17).

A 2D bridge (``meshes/bridge.geo``: a deck of span 10 and height 2 with three openings,
clamped at both ends) sags under its own weight. The target displacement u* is the linear
elastic solution for lambda = 160, mu = 80 (density 1, gravity 0.1: scaled units). Starting
from the uniform material lambda = 100, mu = 50, L-BFGS minimises the volume misfit
int |u - u*|^2 dx (paper eq. 31) over log lambda and log mu (one uniform value each) and
recovers both.

The outcome checked: both parameters within 1% of the truth.

Uniform (or per-body) parameters make the problem well posed. Per-cell fields are not
identifiable from a single load case (two unknowns per cell against two equilibrium equations
per vertex, about half as many), and a run with DG0 fields drifts towards other materials with
the same sag instead of the truth.

Run ``python demos/bridge_material.py`` (default size, a few seconds), ``--tiny`` or ``--full``,
also under ``mpiexec -n 2``. Output in ``output/bridge_material/``:
``bridge_material_initial.bp`` / ``bridge_material_final.bp`` / ``bridge_material_target.bp``,
``history.jsonl``, ``bridge_material.png`` and ``result.json``.
"""

import numpy as np
from common import MESHES, DemoReport, DemoRun, plot_history, run_demo, save_figure
from dolfinx import fem
from invariants import check_invariants
from material_common import check_recovered, finish_material
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import ParameterControl
from diffsolids.io import boundary_edges
from diffsolids.mesh import from_geo
from diffsolids.objectives import final_value, target_displacement
from diffsolids.optimize import LBFGSOptions, check_trajectories, min_volume_ratio
from diffsolids.parallel import collective_comm
from diffsolids.reduced_functional import ReducedFunctional

GEO = MESHES / "bridge.geo"
TRUE = {"lmbda": 160.0, "mu": 80.0}
START = {"lmbda": 100.0, "mu": 50.0}
DENSITY, GRAVITY = 1.0, 0.1
MAX_ERROR = 0.01  # --check: relative error of lambda and mu
SIZES = {
    "tiny": {"h": 0.3, "iterations": 6},
    "default": {"h": 0.1, "iterations": 60},
    "full": {"h": 0.035, "iterations": 100},
}


def build(comm: MPI.Comm, h: float):
    """The bridge model (at the true material), its static simulation and the target."""
    domain = from_geo(GEO, comm, numbers={"h": h})
    model = ds.Model(domain, ds.LinearElastic(**TRUE, density=DENSITY))
    model.add_gravity(GRAVITY)
    model.add_dirichlet("fixed_left", 0.0)
    model.add_dirichlet("fixed_right", 0.0)
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-12), progress=False)
    return model, sim


def plot(path, model, states, result, comm) -> None:
    """Deformed outlines (initial, final, target) and the parameter and objective histories."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    outlines = {k: boundary_edges(model, traj.u[-1]) for k, (_, traj) in states.items()}
    rest = boundary_edges(model)
    if comm.rank != 0:
        return
    fig = plt.figure(figsize=(12, 4.2))
    grid = fig.add_gridspec(1, 3, width_ratios=[2.2, 1, 1])
    fig.suptitle("Bridge: recovering lambda and mu from the target displacement (paper Fig. 17)")
    ax = fig.add_subplot(grid[0])
    styles = {
        "rest": ("0.75", 0.6, ":"),
        "initial": ("tab:orange", 0.9, "-"),
        "target": ("k", 2.2, "-"),
        "final": ("tab:blue", 0.9, "--"),
    }
    for label, segments in [("rest", rest), *outlines.items()]:
        color, lw, ls = styles[label]
        ax.add_collection(LineCollection(segments, colors=color, lw=lw, linestyles=ls, label=label))
    ax.autoscale()
    ax.set_aspect("equal")
    ax.legend(loc="upper center", ncol=4, fontsize=8, bbox_to_anchor=(0.5, -0.12))
    ax.set_title("deformed bridge (scaled units, displacement not magnified)")
    qs = np.exp(np.array([r.q for r in result.history]))
    ax = fig.add_subplot(grid[1])
    its = [r.iteration for r in result.history]
    for k, (name, symbol) in enumerate((("lmbda", "lambda"), ("mu", "mu"))):
        line = ax.plot(its, qs[:, k], "o-", ms=3, label=symbol)[0]
        ax.axhline(TRUE[name], color=line.get_color(), ls=":", lw=1)
    ax.set_xlabel("iteration")
    ax.set_title("parameters (dotted: truth)")
    ax.legend()
    ax.grid(alpha=0.3)
    ax = fig.add_subplot(grid[2])
    plot_history(ax, result, title="objective")
    save_figure(fig, path, comm)


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Recover lambda and mu of the bridge; returns the report (printed on rank 0)."""
    run = DemoRun(DemoRun.parser(__doc__.splitlines()[0], "bridge_material"), argv, comm, SIZES)
    args = run.args

    model, sim = build(comm, args.h)
    controls = [
        ParameterControl(model, "lmbda", "uniform", log=True),
        ParameterControl(model, "mu", "uniform", log=True),
    ]
    target = fem.Function(model.V, name="target")
    rf = ReducedFunctional(sim, final_value(target_displacement(model, target)), controls)
    q_true = np.log([TRUE["lmbda"], TRUE["mu"]])
    rf(q_true)  # the synthetic observation u*
    target_traj = rf.trajectory
    target.x.array[:] = target_traj.u[-1]
    q0 = np.log([START["lmbda"], START["mu"]])

    options = LBFGSOptions(max_iterations=args.iterations, gradient_rtol=1e-9)
    result, keeper = run.optimise(rf, q0, options, progress=False, write_parameters=True)
    states = {
        "initial": (q0, keeper.first),
        "target": (q_true, target_traj),
        "final": (result.q, rf.trajectory),
    }
    report = run.report(result)
    found = dict(zip(("lmbda", "mu"), np.exp(result.q), strict=True))
    errors = {k: abs(found[k] / TRUE[k] - 1.0) for k in TRUE}
    volumes = {k: min_volume_ratio(model, traj.u[-1]) for k, (_, traj) in states.items()}
    runs = [traj for _, traj in states.values()]
    check_invariants(report, check_trajectories(rf.simulation, runs), intersections=False)
    check_recovered(report, START, found, TRUE, MAX_ERROR)
    report.extra.update(
        {
            "cells": model.domain.mesh.topology.index_map(2).size_global,
            "dofs": model.V.dofmap.index_map.size_global * model.dim,
            "recovered": found,
            "relative_errors": errors,
            "max_displacement": float(
                collective_comm(comm).allreduce(
                    np.abs(target_traj.u[-1]).max(initial=0.0), op=MPI.MAX
                )
            ),
            "min_volume_ratio": volumes,
            "num_forward": result.num_forward,
        }
    )

    def figure(path):
        plot(path, model, states, result, comm)

    return finish_material(run, report, rf, result, states, ["lmbda", "mu"], figure)


if __name__ == "__main__":
    run_demo(main)
