"""Material optimisation: a bar bent into a sine by its material alone (paper Fig. 16).

A linear-elastic bar with rest shape [-4, 4] x [-0.3, 0.3] is compressed and sheared by its
ends: the end faces x = -+4 are prescribed u_x = -sign(x) (= +-1) and u_y = 0.7 sin(x + u_x),
and no body force acts. With a homogeneous material the bar deforms into a nearly straight
strip; the optimisation changes the Lame parameters of every cell (log lambda and log mu as
DG0 fields) so that the deformed long boundaries follow the sine, i.e. u_y = 0.7 sin(x + u_x)
along the whole bar: the top edge should lie on y = 0.3 + 0.7 sin x and the bottom edge on
y = -0.3 + 0.7 sin x (``boundary_graph_fit``). A small material smoothing term (paper eq. 38)
keeps the fields from becoming noisy, and a penalty on cells compressed below half their area
(det(I + grad u) < 0.5) keeps the deformed mesh from folding: linear elasticity has no
inversion barrier, and without the penalty the optimum crushes the soft cells at the ends.

The outcome checked: the fit error (the graph misfit of both edges) falls at least 10-fold.

Run ``python demos/sine_bar.py`` (default size, a few seconds), ``--tiny`` (smoke test) or
``--full`` (finer mesh, more iterations), also under ``mpiexec -n 2``. Output in
``output/sine_bar/``: ``sine_bar_initial.bp`` / ``sine_bar_final.bp`` (displacement, von
Mises stress, lambda and mu), ``history.jsonl`` and plots of the optimiser, ``sine_bar.png``
and ``result.json``.
"""

import numpy as np
import ufl
from common import DemoReport, DemoRun, plot_history, run_demo, save_figure
from invariants import check_invariants
from material_common import cell_values, finish_material
from mpi4py import MPI

import diffsolids as ds
from diffsolids import forms
from diffsolids.controls import ParameterControl
from diffsolids.io import deformed_triangles
from diffsolids.mesh import create_rectangle
from diffsolids.objectives import Integral, MaterialSmoothing, boundary_graph_fit, final_value
from diffsolids.objectives.terms import objective_terms
from diffsolids.optimize import LBFGSOptions, check_trajectories, min_volume_ratio
from diffsolids.reduced_functional import ReducedFunctional

HALF_LENGTH, HALF_WIDTH, AMPLITUDE = 4.0, 0.3, 0.7
LAMBDA0, MU0 = 100.0, 50.0  # homogeneous start (only their ratio matters: no body force)
SMOOTHING = 1e-4  # weight of the material smoothing term
MIN_AREA_RATIO, COMPRESSION_PENALTY = 0.5, 100.0  # penalise det(I + grad u) < 0.5 with this weight
MIN_REDUCTION = 10.0  # --check: the fit error must fall at least this much
SIZES = {
    "tiny": {"cells": (32, 3), "iterations": 6},
    "default": {"cells": (80, 6), "iterations": 60},
    "full": {"cells": (240, 18), "iterations": 300},
}


def end_displacement(x: np.ndarray, t: float) -> np.ndarray:
    """Dirichlet value at the ends: u_x = -sign(x), u_y = 0.7 sin(x + u_x)."""
    ux = -np.sign(x[0])
    return np.vstack([ux, AMPLITUDE * np.sin(x[0] + ux)])


def build(comm: MPI.Comm, cells):
    """The bar, its static simulation, the objective (fit + smoothing) and the fit alone."""
    facets = {
        1: lambda x: np.isclose(np.abs(x[0]), HALF_LENGTH),
        2: lambda x: np.isclose(x[1], HALF_WIDTH),
        3: lambda x: np.isclose(x[1], -HALF_WIDTH),
    }
    domain = create_rectangle(
        comm,
        [[-HALF_LENGTH, -HALF_WIDTH], [HALF_LENGTH, HALF_WIDTH]],
        cells,
        facets=facets,
        names={"ends": 1, "top": 2, "bottom": 3},
    )
    model = ds.Model(domain, ds.LinearElastic(lmbda=LAMBDA0, mu=MU0))
    model.add_dirichlet("ends", end_displacement)
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-10), progress=False)
    fit = final_value(
        boundary_graph_fit(model, "top", lambda x: HALF_WIDTH + AMPLITUDE * ufl.sin(x))
        + boundary_graph_fit(model, "bottom", lambda x: -HALF_WIDTH + AMPLITUDE * ufl.sin(x))
    )
    compression = Integral(
        lambda f: forms.penalty(MIN_AREA_RATIO - ufl.det(forms.deformation_gradient(f.u))) * f.dx,
        "compression",
    )
    objective = (
        fit
        + SMOOTHING * MaterialSmoothing(model, ("lmbda", "mu"))
        + COMPRESSION_PENALTY * final_value(compression)
    )
    controls = [
        ParameterControl(model, "lmbda", "field", log=True),
        ParameterControl(model, "mu", "field", log=True),
    ]
    return model, ReducedFunctional(sim, objective, controls), fit


def young_modulus(lmbda: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """E = mu (3 lambda + 2 mu) / (lambda + mu)."""
    return mu * (3 * lmbda + 2 * mu) / (lmbda + mu)


def plot(path, model, states, result, fit_values, comm) -> None:
    """Deformed bar before/after (coloured by log10 E) with the target, and the history."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    controls = result.functional.controls
    panels = []
    for label, (q, traj) in states.items():
        controls.assign(q)
        E = young_modulus(cell_values(model, "lmbda"), cell_values(model, "mu"))
        panels.append((label, *deformed_triangles(model, traj.u[-1], np.log10(E))))
    controls.assign(result.q)
    if comm.rank != 0:
        return
    fig = plt.figure(figsize=(11, 6.5))
    grid = fig.add_gridspec(2, 3)
    xs = np.linspace(-HALF_LENGTH + 1, HALF_LENGTH - 1, 400)
    vmin = min(v.min() for _, _, v in panels)
    vmax = max(v.max() for _, _, v in panels)
    for k, (label, tris, values) in enumerate(panels):
        ax = fig.add_subplot(grid[k, :2])
        coll = PolyCollection(tris, array=values, cmap="viridis", edgecolors="face", lw=0.1)
        coll.set_clim(vmin, vmax)
        ax.add_collection(coll)
        for offset in (HALF_WIDTH, -HALF_WIDTH):
            ax.plot(xs, offset + AMPLITUDE * np.sin(xs), "r--", lw=1.0)
        ax.set_xlim(-HALF_LENGTH + 0.8, HALF_LENGTH - 0.8)
        ax.set_ylim(-1.2, 1.2)
        ax.set_aspect("equal")
        ax.set_title(f"{label}: fit error {fit_values[label]:.3g} (target dashed)")
        fig.colorbar(coll, ax=ax, label="log10 E", shrink=0.8)
    ax = fig.add_subplot(grid[:, 2])
    plot_history(ax, result, title="objective")
    fig.suptitle("Sine bar: material optimisation (paper Fig. 16)")
    save_figure(fig, path, comm)


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Optimise the material field of the bar; returns the report (printed on rank 0)."""
    run = DemoRun(DemoRun.parser(__doc__.splitlines()[0], "sine_bar"), argv, comm, SIZES)
    args = run.args

    model, rf, fit = build(comm, args.cells)
    fit_label = next(t.label for t in objective_terms(rf.objective) if t.node is fit)
    q0 = rf.initial_parameters()
    options = LBFGSOptions(max_iterations=args.iterations, gradient_rtol=1e-8)
    result, keeper = run.optimise(rf, q0, options, progress=False)
    history = result.history
    fit_values = {"initial": history[0].terms[fit_label], "final": history[-1].terms[fit_label]}
    states = {"initial": (q0, keeper.first), "final": (result.q, rf.trajectory)}

    report = run.report(result)
    boundary_length = 4 * HALF_LENGTH  # top and bottom edges at rest
    reduction = fit_values["initial"] / fit_values["final"]
    volumes = {k: min_volume_ratio(model, traj.u[-1]) for k, (_, traj) in states.items()}
    runs = [traj for _, traj in states.values()]
    check_invariants(report, check_trajectories(rf.simulation, runs), intersections=False)
    report.check(
        "fit error reduction",
        reduction,
        MIN_REDUCTION,
        reduction >= MIN_REDUCTION,
        f"graph misfit {fit_values['initial']:.4g} -> {fit_values['final']:.4g}",
    )
    n = rf.controls.controls[0].size
    lmbda, mu = np.exp(result.q[:n]), np.exp(result.q[n:])
    report.extra.update(
        {
            "cells": int(n),
            "parameters": int(rf.size),
            "fit_initial": fit_values["initial"],
            "fit_final": fit_values["final"],
            "rms_distance_initial": float(np.sqrt(fit_values["initial"] / boundary_length)),
            "rms_distance_final": float(np.sqrt(fit_values["final"] / boundary_length)),
            "min_volume_ratio": volumes,
            "lambda_range": [float(lmbda.min()), float(lmbda.max())],
            "mu_range": [float(mu.min()), float(mu.max())],
            "num_forward": result.num_forward,
        }
    )

    def figure(path):
        plot(path, model, states, result, fit_values, comm)

    return finish_material(run, report, rf, result, states, ["lmbda", "mu"], figure)


if __name__ == "__main__":
    run_demo(main)
