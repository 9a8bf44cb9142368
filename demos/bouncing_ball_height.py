"""Material optimisation: make a ball bounce higher by changing its stiffness field (Fig. 22).

A Neo-Hookean ball (a disk in 2D, plane strain; a sphere with ``--full``) of radius 0.1 m,
E = 1e5 Pa, nu = 0.48, density 1000 kg/m^3, is thrown down at 2 m/s from 3 cm above a stiff
plank (E = 1e9 Pa, clamped at both ends; ``meshes/bouncing_ball.geo``). It falls under
gravity, hits the plank (IPC contact, BDF2) and bounces back up. The control is Young's
modulus of every cell of the ball (log E as a DG0 field, between 2e4 and 1e6 Pa; the plank's
cells are held fixed by their bounds); the objective is the negative height of the ball's
centre of mass at the final time (paper eqs. 33-34) plus a material smoothing term (eq. 38).

The outcome checked: the final height increases. Invariants: no intersection in any state of
the initial and final runs, no inverted element.

Run ``python demos/bouncing_ball_height.py`` (default size, well under 2 minutes), ``--tiny``
(smoke test) or ``--full`` (3D ball), also under ``mpiexec -n 2``. Output in
``output/bouncing_ball_height/``: ``bouncing_ball_height_initial.bp`` / ``..._final.bp``
(trajectories with the E field), ``history.jsonl``, ``bouncing_ball_height.png`` and
``result.json``.
"""

import numpy as np
from common import MESHES, DemoReport, DemoRun, run_demo, save_figure
from invariants import check_invariants
from material_common import body_cell_mask, cell_values, finish_material
from mpi4py import MPI

import diffsolids as ds
from diffsolids.contact import ContactTerm
from diffsolids.controls import ParameterControl
from diffsolids.io import deformed_triangles
from diffsolids.mesh import from_geo
from diffsolids.mesh.ordering import CanonicalLayout
from diffsolids.objectives import (
    MaterialSmoothing,
    center_of_mass,
    final_value,
    height_objective,
    series_values,
)
from diffsolids.optimize import LBFGSOptions, check_trajectories, min_volume_ratio
from diffsolids.reduced_functional import ReducedFunctional

GEO = MESHES / "bouncing_ball.geo"
BALL = {"E": 1e5, "nu": 0.48, "density": 1000.0}
PLANK = {"E": 1e9, "nu": 0.48, "density": 1000.0}
E_BOUNDS = (2e4, 1e6)  # bounds of the ball's Young's modulus [Pa]
SPEED = 2.0  # initial downward speed of the ball [m/s]
DHAT = 1e-3  # barrier distance [m]: about 1e-3 of the scene (plank length 0.6 m)
SMOOTHING = 1e-4  # weight of the material smoothing term
SIZES = {
    "tiny": {"dim": 2, "h": 0.04, "hp": 0.06, "dt": 0.008, "steps": 20, "iterations": 2},
    "default": {"dim": 2, "h": 0.02, "hp": 0.04, "dt": 0.004, "steps": 40, "iterations": 15},
    "full": {"dim": 3, "h": 0.03, "hp": 0.05, "dt": 0.004, "steps": 40, "iterations": 30},
}


def build(comm: MPI.Comm, args):
    """The scene, its BDF2 simulation with contact, and the reduced functional."""
    dim = args.dim
    domain = from_geo(GEO, comm, dim=dim, numbers={"D": dim, "h": args.h, "hp": args.hp})
    materials = {"plank": ds.NeoHookean(**PLANK), "ball": ds.NeoHookean(**BALL)}
    model = ds.Model(domain, materials)
    model.add_gravity(9.81)
    model.add_dirichlet("plank_ends", 0.0)
    integrator = ds.BDF(2, args.dt, args.steps)
    contact = model.add_numeric_term(ContactTerm(model, DHAT))
    # the ball lies above the plank's top face (height 0): throw it down
    X = model.V.tabulate_dof_coordinates()[:, :dim]
    v0 = np.zeros_like(X)
    v0[X[:, dim - 1] > 1e-9, dim - 1] = -SPEED
    sim = ds.Simulation(
        model, integrator, ds.SolverOptions(rtol=1e-8), v0=v0.ravel(), progress=False
    )
    # log E per cell; the plank's cells are pinned by equal bounds
    E = model.coefficients["E"]
    layout = CanonicalLayout(E.function_space)
    plank = body_cell_mask(model, layout, "plank")
    q_now = np.log(layout.gather(E.x.array))
    lower = np.where(plank, q_now, np.log(E_BOUNDS[0]))
    upper = np.where(plank, q_now, np.log(E_BOUNDS[1]))
    control = ParameterControl(model, "E", "field", log=True, lower=lower, upper=upper)
    objective = final_value(height_objective(model, bodies="ball"))
    objective = objective + SMOOTHING * MaterialSmoothing(model, ("E",))
    rf = ReducedFunctional(sim, objective, control)
    return model, contact, rf, ~plank


def plot(path, model, states, heights, result, times, comm) -> None:
    """Height of the ball over time, the final shapes coloured by log10 E, the history."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    panels = []
    if model.dim == 2:
        for label, (q, traj) in states.items():
            result.functional.controls.assign(q)
            E = np.log10(cell_values(model, "E"))
            low = int(np.argmin(heights[label]))  # deepest point of the bounce
            for k in (low, len(traj.u) - 1):
                panels.append((label, k, *deformed_triangles(model, traj.u[k], E)))
        result.functional.controls.assign(result.q)
    if comm.rank != 0:
        return
    fig = plt.figure(figsize=(13, 4.5))
    grid = fig.add_gridspec(1, 3, width_ratios=[1, 1.6, 1])
    ax = fig.add_subplot(grid[0])
    for label, h in heights.items():
        ax.plot(times, h, label=f"{label}: final {h[-1]:.4f} m")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("centre of mass height [m]")
    ax.legend()
    ax.grid(alpha=0.3)
    ax.set_title("ball height")
    if panels:
        ax = fig.add_subplot(grid[1])
        ball_values = np.concatenate([E[E < 8] for *_, E in panels])  # the plank has 1e9 Pa
        last = len(times) - 1
        for label, k, tris, E in panels:
            shift = np.array([0.0 if label == "initial" else 0.7, 0.0])
            ball = E < 8
            cells = PolyCollection(tris[ball] + shift, array=E[ball], cmap="viridis", lw=0)
            cells.set_clim(ball_values.min(), ball_values.max())
            cells.set_alpha(1.0 if k == last else 0.5)
            ax.add_collection(cells)
            if k == last:
                plank = PolyCollection(tris[~ball] + shift, facecolor="0.6", lw=0)
                ax.add_collection(plank)
                ax.text(shift[0], 0.37, label, ha="center")
        ax.autoscale()
        ax.set_ylim(top=0.42)
        ax.set_aspect("equal")
        fig.colorbar(cells, ax=ax, label="log10 E of the ball [Pa]", shrink=0.8)
        ax.set_title("deepest (faint) and final states")
    ax = fig.add_subplot(grid[2])
    its = [r.iteration for r in result.history]
    ax.plot(its, [-r.objective for r in result.history], "o-", ms=3)
    ax.set_xlabel("iteration")
    ax.set_ylabel("-J (final height - smoothing)")
    ax.grid(alpha=0.3)
    ax.set_title("objective")
    fig.suptitle("Bouncing ball: stiffness field optimised for the final height (paper Fig. 22)")
    save_figure(fig, path, comm)


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Optimise the ball's stiffness field; returns the report (printed on rank 0)."""
    run = DemoRun(
        DemoRun.parser(__doc__.splitlines()[0], "bouncing_ball_height"), argv, comm, SIZES
    )
    args = run.args

    model, contact, rf, ball_cells = build(comm, args)
    sim = rf.simulation
    q0 = rf.initial_parameters()
    options = LBFGSOptions(max_iterations=args.iterations, gradient_rtol=1e-6, max_change=1.0)
    result, keeper = run.optimise(rf, q0, options, progress=False)
    final_traj = rf.trajectory
    min_distance = min((r.min_distance for r in contact.records), default=np.inf)
    states = {"initial": (q0, keeper.first), "final": (result.q, final_traj)}
    vertical = model.dim - 1
    com = center_of_mass(model, "ball")[vertical]
    heights = {k: series_values(sim, com, traj) for k, (_, traj) in states.items()}
    runs = [keeper.first, final_traj]
    volume_ratio = min(min_volume_ratio(model, u) for traj in runs for u in traj.u)

    report = run.report(result)
    gain = heights["final"][-1] - heights["initial"][-1]
    check_invariants(report, check_trajectories(sim, runs, contact))
    report.extra["min_volume_ratio"] = volume_ratio
    report.check(
        "final height increased",
        gain,
        0.0,
        gain > 0,
        f"{heights['initial'][-1]:.5f} m -> {heights['final'][-1]:.5f} m",
    )
    E_ball = np.exp(result.q[ball_cells])
    report.extra.update(
        {
            "dim": model.dim,
            "ball_cells": int(ball_cells.sum()),
            "dofs": model.V.dofmap.index_map.size_global * model.dim,
            "steps": args.steps,
            "dt": args.dt,
            "kappa": contact.stiffness,
            "height_initial": float(heights["initial"][-1]),
            "height_final": float(heights["final"][-1]),
            "min_contact_distance_final_run": float(min_distance),
            "E_ball_range": [float(E_ball.min()), float(E_ball.max())],
            "E_ball_mean": float(E_ball.mean()),
            "num_forward": result.num_forward,
            "newton_iterations_final_run": final_traj.newton_iterations(),
        }
    )
    t = np.asarray(final_traj.times)

    def figure(path):
        plot(path, model, states, heights, result, t, comm)

    return finish_material(run, report, rf, result, states, ["E"], figure)


if __name__ == "__main__":
    run_demo(main)
