"""Friction optimisation (paper Fig. 21): the friction coefficient that slides a block to a line.

A soft rounded block (Neo-Hookean) starts at rest on a 30 degree ramp and slides down under
gravity (BDF2, IPC contact with lagged smoothed friction between block and ramp). The control is
the friction coefficient of the block-ramp pair (``FrictionControl``, parametrised by its
logarithm); the objective the squared
distance of the block's centre of mass at the final time from a vertical target line, (c_x(T) -
x_line)^2. The line is where the block ends with mu = 0.1; the optimisation starts from mu = 0.5
(the block then barely moves) and must recover 0.1.

Sizes: ``--tiny`` (smoke test), default (2D, ``meshes/sliding.geo``, well under 2 minutes),
``--full`` (finer mesh and time step, longer slide).

Writes into ``output/sliding_friction/`` (``--out``): ``sliding_initial.bp`` /
``sliding_final.bp`` (VTX, or ``.xdmf`` with ``--xdmf``), ``sliding_friction.png`` (block at
rest, at the end of the initial and the optimised run, the line; centre-of-mass x(t); objective
and mu per iteration), ``history.jsonl`` and ``result.json``.

Run ``python demos/sliding_friction.py`` or ``mpiexec -n 2 python demos/sliding_friction.py``.
"""

import numpy as np
from common import MESHES, DemoReport, DemoRun, plot_history, run_demo, save_figure
from dynamic_common import body_nodes, finish_transient, write_runs
from invariants import check_invariants
from mpi4py import MPI

import diffsolids as ds
from diffsolids.contact import ContactTerm, suggest_barrier_stiffness
from diffsolids.controls import FrictionControl
from diffsolids.io import boundary_edges
from diffsolids.mesh import from_geo
from diffsolids.objectives import center_of_mass, final_value, series_values
from diffsolids.optimize import LBFGSOptions, check_trajectories
from diffsolids.reduced_functional import ReducedFunctional

GEO = MESHES / "sliding.geo"
THETA = 30.0  # slope [degrees]; tan(30 deg) = 0.577: the block slides for mu < 0.577
MU_TRUE, MU_START = 0.1, 0.5
E, NU, DENSITY, DAMPING = 1e5, 0.3, 1000.0, 100.0
DHAT, EPS_V = 1e-3, 0.01
SIZES = {
    "tiny": {"h": 0.05, "dt": 0.02, "steps": 25, "iterations": 3},
    "default": {"h": 0.025, "dt": 0.01, "steps": 60, "iterations": 15},
    "full": {"h": 0.01, "dt": 0.005, "steps": 160, "iterations": 20},
}
# the run must recover mu within this relative error
MU_RTOL = 0.02


def parse_args(argv, comm: MPI.Comm) -> DemoRun:
    """The run with its arguments."""
    p = DemoRun.parser(__doc__.splitlines()[0], "sliding_friction")
    p.add_argument("--mu-true", type=float, default=MU_TRUE, help="coefficient of the target")
    p.add_argument("--mu-start", type=float, default=MU_START, help="initial coefficient")
    return DemoRun(p, argv, comm, SIZES)


def build_scene(args, comm):
    """Model, contact term and simulation of the block on the ramp; u0 = the block at rest."""
    domain = from_geo(GEO, comm, numbers={"h": args.h, "theta": THETA})
    material = ds.NeoHookean(E=E, nu=NU, density=DENSITY, damping_psi=DAMPING)
    model = ds.Model(domain, material, degree=1)
    model.add_gravity(9.81)
    t = np.deg2rad(THETA)
    top = 2.0 * np.tan(t) * np.cos(t)  # the slope is the line n.x = top, n = (sin t, cos t)
    model.add_dirichlet(lambda x: np.sin(t) * x[0] + np.cos(t) * x[1] < top + 1e-9, 0.0)
    integrator = ds.BDF(2, args.dt, args.steps)
    # kappa of the sliding run's integrator (the settling run below would otherwise choose it)
    kappa = suggest_barrier_stiffness(ContactTerm(model, dhat=DHAT, stiffness=1.0), integrator)
    friction = {("ramp", "block"): args.mu_start}
    contact = model.add_numeric_term(
        ContactTerm(model, DHAT, stiffness=kappa, friction=friction, eps_v=EPS_V)
    )
    options = ds.SolverOptions(rtol=1e-8)
    u0 = settle(model, contact, args.dt, options)
    sim = ds.Simulation(model, integrator, options, u0=u0, progress=False)
    return model, contact, sim


def settle(model, contact, dt: float, options, steps: int = 15) -> np.ndarray:
    """The block at rest on the slope: a few dissipative steps with sticking friction."""
    mu = contact.friction_coefficients
    contact.set_friction("ramp", "block", 5.0)
    try:
        traj = ds.Simulation(model, ds.BDF(1, dt, steps), options, progress=False).run()
    finally:
        contact.friction_coefficients = mu
    u0 = np.zeros_like(traj.u[-1])
    nodes = body_nodes(model, "block")
    u0.reshape(-1, model.dim)[nodes] = traj.u[-1].reshape(-1, model.dim)[nodes]
    return u0


def plot(path, args, model, traj0, traj1, paths, line, result, mus, comm) -> None:
    """Block at rest and at the end of both runs, target line, x(t), objective and mu."""
    import matplotlib

    matplotlib.use("Agg")
    from dynamic_common import scene_figure
    from matplotlib.collections import LineCollection

    t = np.deg2rad(THETA)
    normal, top = np.array([np.sin(t), np.cos(t)]), 2.0 * np.sin(t)
    segs = []
    for u in (None, traj0.u[-1], traj1.u[-1]):
        s = boundary_edges(model, u)
        segs.append(s[(s @ normal).max(axis=1) > top + 1e-7])  # the block's edges
    if comm.rank != 0:
        return
    fig, ax, (ax_x, ax_h, ax_mu) = scene_figure(6.0, (1.3, 1), None, 3)
    styles = [("0.55", "-", "rest"), ("tab:blue", "--", f"end, mu = {mus[0]:.3g}")]
    styles.append(("tab:red", "-", f"end, mu = {mus[-1]:.4g} (optimised)"))
    ax.fill([0, 2.0, 0], [0, 0, 2.0 * np.tan(t)], color="0.85", zorder=0, label="ramp")
    for s, (color, ls, label) in zip(segs, styles, strict=True):
        ax.add_collection(LineCollection(s, colors=color, linestyles=ls, lw=1.0, label=label))
    ax.axvline(line, color="k", lw=1.5, label=f"target line x = {line:.3f} m")
    ax.plot(paths[0][:, 0], paths[0][:, 1], color="tab:blue", lw=1.0, ls=":")
    ax.plot(paths[1][:, 0], paths[1][:, 1], color="tab:red", lw=1.0, ls=":")
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlim(-0.05, 2.05)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(fontsize=8, loc="upper right")
    ax.set_title(
        f"block sliding down a {THETA:g} degree ramp for {args.steps * args.dt:g} s: "
        "friction coefficient found so that it ends on the line",
        fontsize=9,
    )
    times = np.asarray(traj1.times)
    ax_x.plot(times, paths[0][:, 0], color="tab:blue", label="initial mu")
    ax_x.plot(times, paths[1][:, 0], color="tab:red", label="optimised mu")
    ax_x.axhline(line, color="k", lw=1.0)
    ax_x.set_xlabel("time [s]")
    ax_x.set_ylabel("x of the centre of mass [m]")
    ax_x.legend(fontsize=8)
    ax_x.grid(alpha=0.3)
    plot_history(ax_h, result, "J", "objective (c_x(T) - x_line)^2", fontsize=9)
    ax_mu.plot(range(len(mus)), mus, "o-", ms=3)
    ax_mu.axhline(args.mu_true, color="k", lw=1.0, ls="--", label=f"true mu = {args.mu_true:g}")
    ax_mu.set_xlabel("iteration")
    ax_mu.set_ylabel("friction coefficient")
    ax_mu.legend(fontsize=8)
    ax_mu.grid(alpha=0.3)
    save_figure(fig, path, comm)


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    run = parse_args(argv, comm)
    args = run.args
    model, contact, sim = build_scene(args, comm)
    com = center_of_mass(model, "block")
    control = FrictionControl(contact, pairs=[("ramp", "block")], log=True)

    # the target: where the block ends with the true coefficient
    control.assign(np.log([args.mu_true]))
    target_traj = sim.run()
    line = float(series_values(sim, com[0], target_traj, steps=[-1])[0])
    control.assign(np.log([args.mu_start]))

    rf = ReducedFunctional(sim, final_value((com[0] - line) ** 2), control)
    options = LBFGSOptions(
        max_iterations=args.iterations, gradient_rtol=1e-6, initial_step=0.5, max_change=0.5
    )
    q0 = np.log([args.mu_start])
    result, keeper = run.optimise(rf, q0, options, write_parameters=True)
    traj0, traj1 = keeper.first, keeper.last
    paths = [series_values(sim, com, traj) for traj in (traj0, traj1)]
    files = write_runs(model, {"initial": traj0, "final": traj1}, args, "sliding")
    files += [args.out / "history.jsonl", args.out / "result.json"]

    report = run.report(result)
    mu = float(np.exp(result.q[0]))
    mus = [float(np.exp(r.q[0])) for r in result.history]
    check_invariants(report, check_trajectories(sim, [traj0, traj1], contact))
    error = abs(mu - args.mu_true) / args.mu_true
    if not args.tiny:
        report.check(
            "relative error of the recovered mu",
            error,
            MU_RTOL,
            error < MU_RTOL,
            f"(mu {args.mu_start:g} -> {mu:.5f}, true {args.mu_true:g})",
        )
    figures = {
        "mu_start": args.mu_start,
        "mu_true": args.mu_true,
        "mu_final": mu,
        "mu_history": mus,
        "line_x": line,
        "final_x_initial": float(paths[0][-1, 0]),
        "final_x_final": float(paths[1][-1, 0]),
    }
    headline = (
        f"sliding_friction: mu {args.mu_start:g} -> {mu:.5f} (true {args.mu_true:g}, "
        f"error {100 * error:.2f}%); the block ends {abs(paths[0][-1, 0] - line):.3f} m -> "
        f"{abs(paths[1][-1, 0] - line):.2e} m from the line"
    )

    def figure(path):
        plot(path, args, model, traj0, traj1, paths, line, result, mus, comm)

    return finish_transient(run, report, model, result, files, figures, headline, figure)


if __name__ == "__main__":
    run_demo(main)
