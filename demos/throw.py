"""Flagship demo (paper Fig. 1): optimise a throw so that the hit body ends in a target circle.

Body A (a soft disk) is thrown at body B (a soft rounded block) resting on a static ground; B
is pushed along the ground by the impact and slides to a stop under friction. The control is the
initial velocity of A (a rigid translation, ``--angular`` adds a spin), the objective the squared
distance of B's centre of mass at the final time from the centre of a target circle (paper eq.
32). Physics: Neo-Hookean bodies with a little viscous damping, BDF2, IPC contact between all
bodies (barrier stiffness from ``suggest_barrier_stiffness``) with lagged smoothed friction.
Gradients: the discrete adjoint of exactly these steps; optimiser: L-BFGS.

Sizes: ``--tiny`` (smoke test), default (2D, ``meshes/throw2d.geo``, under 2 minutes on 2
cores), ``--full`` (3D, ``meshes/throw3d.geo``: a ball thrown at a puck, target circle on the
ground plane off the line of the throw).

Writes into ``output/throw/`` (``--out``): ``throw_initial.bp`` and ``throw_final.bp`` (VTX,
or ``.xdmf`` with ``--xdmf``: the trajectories of the initial and the optimised throw),
``throw.png`` (paths of both centres of mass before/after, the target circle, the objective
history), ``com_paths.csv``, the optimiser's ``history.jsonl`` and ``result.json``.

Run ``python demos/throw.py`` or ``mpiexec -n 2 python demos/throw.py``.
"""

import numpy as np
from common import MESHES, DemoReport, DemoRun, plot_history, run_demo, save_figure
from dynamic_common import body_nodes, finish_transient, write_runs
from invariants import check_invariants
from mpi4py import MPI

import diffsolids as ds
from diffsolids.contact import ContactTerm
from diffsolids.controls import RigidVelocity
from diffsolids.io import boundary_edges
from diffsolids.mesh import from_geo
from diffsolids.objectives import (
    center_of_mass,
    center_of_mass_trajectory,
    final_value,
    series_values,
)
from diffsolids.optimize import LBFGSOptions, check_trajectories
from diffsolids.reduced_functional import ReducedFunctional

# scene and run sizes: mesh size of the bodies (h) and of the ground (hg), time step, steps,
# optimisation iterations
SIZES = {
    "tiny": {"dim": 2, "h": 0.06, "dt": 0.02, "steps": 40, "iterations": 3},
    "default": {"dim": 2, "h": 0.03, "dt": 0.01, "steps": 80, "iterations": 12},
    "full": {"dim": 3, "h": 0.035, "dt": 0.01, "steps": 60, "iterations": 10},
}
# the initial throw (velocity of A [m/s]) and the target (centre of the circle on the ground,
# radius) per dimension. 3D: the initial throw leaves B 0.28 m short of and beside the target;
# B (3.1 kg) must slide ~0.65 m at ~9 degrees off the line of the throw, which A (5.3 kg)
# reaches with an off-centre hit at ~3.3 m/s. Oblique hits pass little momentum to B, so
# targets much further off the line need far faster throws (0.7 m at 0.2 m off the line: an
# estimated 5 m/s; runs towards it stalled ~0.1 m short, and fast throws make the forward
# solves slow).
THROW = {2: [2.5, 0.2], 3: [2.0, 0.0, 0.2]}
TARGET = {2: ([1.3], 0.05), 3: ([1.05, 0.1], 0.05)}
# materials: soft Neo-Hookean with a little viscous damping (relaxation time psi / E ~ 2 ms)
E, NU, DAMPING = 1e5, 0.3, 200.0
DENSITY = {"ground": 1000.0, "A": 3000.0, "B": 1000.0}
# friction coefficients of the pairs, barrier distance, friction smoothing velocity
FRICTION = {("ground", "A"): 0.3, ("ground", "B"): 0.5, ("A", "B"): 0.2}
DHAT, EPS_V = 1e-3, 0.02
# the optimisation stops when B ends within this fraction of the radius from the centre
STOP_FRACTION = 0.5
# times [s] of the snapshots of the optimised throw in the figure (2D)
SNAPSHOT_TIMES = (0.1, 0.2, 0.3)


def parse_args(argv, comm: MPI.Comm) -> DemoRun:
    """The run with its arguments: the initial throw and the target of the dimension."""
    p = DemoRun.parser(__doc__.splitlines()[0], "throw")
    p.add_argument("--angular", action="store_true", help="also optimise the spin of A")
    p.add_argument("--v0", type=float, nargs="+", help="initial velocity of A (dim numbers)")
    p.add_argument("--target", type=float, nargs="+", help="target centre on the ground")
    p.add_argument("--radius", type=float, help="target radius (default 0.05 m)")
    p.add_argument("--steps", type=int, help="number of time steps")
    p.add_argument("--dt", type=float, help="time step")
    run = DemoRun(p, argv, comm, SIZES)
    args = run.args
    args.v0 = np.array(args.v0 if args.v0 is not None else THROW[args.dim], dtype=float)
    target, radius = TARGET[args.dim]
    args.target = np.array(args.target if args.target is not None else target, dtype=float)
    args.radius = args.radius if args.radius is not None else radius
    return run


def build_scene(args, comm):
    """Domain, model, contact term, simulation and reduced functional of the throw."""
    geo = MESHES / ("throw2d.geo" if args.dim == 2 else "throw3d.geo")
    domain = from_geo(geo, comm, numbers={"h": args.h})
    materials = {
        body: ds.NeoHookean(E=E, nu=NU, density=rho, damping_psi=DAMPING)
        for body, rho in DENSITY.items()
    }
    model = ds.Model(domain, materials, degree=1)
    model.add_gravity(9.81)
    up = args.dim - 1
    model.add_dirichlet(lambda x: x[up] < 1e-9, 0.0)  # the ground: every node with z <= 0
    integrator = ds.BDF(2, args.dt, args.steps)
    contact = model.add_numeric_term(ContactTerm(model, DHAT, friction=FRICTION, eps_v=EPS_V))
    options = ds.SolverOptions(rtol=1e-8)
    sim = ds.Simulation(
        model, integrator, options, u0=settle(model, args.dt, options), progress=False
    )
    control = RigidVelocity(sim, "A", angular=args.angular)
    return model, contact, sim, control


def settle(model, dt: float, options, steps: int = 20) -> np.ndarray:
    """Initial displacement with B at rest on the ground (barrier force = weight), A as meshed.

    B is meshed a small gap above the ground; letting it settle for a few (BDF1, dissipative)
    steps gives the resting state, so that the first steps neither drop nor lift B.
    """
    traj = ds.Simulation(model, ds.BDF(1, dt, steps), options, progress=False).run()
    u0 = np.zeros_like(traj.u[-1])
    nodes = body_nodes(model, "B")
    dim = model.dim
    u0.reshape(-1, dim)[nodes] = traj.u[-1].reshape(-1, dim)[nodes]
    return u0


def body_segments(model, u=None) -> np.ndarray:
    """Boundary edges of the bodies A and B (2D, collective): the ground's are left out."""
    segs = boundary_edges(model, u)
    return segs[segs[:, :, 1].min(axis=1) > 1e-7]  # the ground lies in y <= 0


def plot(path, args, model, traj0, traj1, paths, q0, q1, result, comm) -> None:
    """Shapes and centre-of-mass paths of both throws, target, B's x(t), objective history."""
    import matplotlib

    matplotlib.use("Agg")
    from dynamic_common import scene_figure
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Circle

    dim = args.dim
    snapshots = []
    if dim == 2:
        rest = body_segments(model)
        before = body_segments(model, traj0.u[-1])
        steps = [round(t / args.dt) for t in SNAPSHOT_TIMES if round(t / args.dt) < args.steps]
        snapshots = [body_segments(model, traj1.u[i]) for i in [*steps, args.steps]]
    if comm.rank != 0:
        return
    fig, ax, (ax_x, ax_h) = scene_figure(6.2, (1.35, 1), [1.6, 1], 2)
    plot_history(ax_h, result, "J", "objective |c_B(T) - target|^2", fontsize=9)
    red, blue = "tab:red", "tab:blue"
    if dim == 2:
        ax.axhspan(-0.04, 0.0, color="0.88", zorder=0)
        ax.add_collection(LineCollection(rest, colors="0.6", lw=0.8))
        ax.add_collection(LineCollection(before, colors=blue, lw=1.0, ls="--"))
        for k, segs in enumerate(snapshots):
            last = k == len(snapshots) - 1
            alpha = 1.0 if last else 0.25 + 0.5 * k / max(len(snapshots) - 1, 1)
            ax.add_collection(
                LineCollection(segs, colors=red, lw=1.2 if last else 0.7, alpha=alpha)
            )
        centre_y = paths["B0"][0, 1]
    else:
        centre_y = args.target[1]
    ax.add_patch(
        Circle((args.target[0], centre_y), args.radius, fc="none", ec="k", lw=1.6, zorder=5)
    )
    for key, color, ls in (
        ("A0", blue, ":"),
        ("B0", blue, "-"),
        ("A1", red, ":"),
        ("B1", red, "-"),
    ):
        ax.plot(paths[key][:, 0], paths[key][:, 1], color=color, ls=ls, lw=1.4)
        ax.plot(*paths[key][-1, :2], "o", ms=3.5, color=color)
    scale = 0.06  # arrow length per m/s
    origin = paths["A0"][0, :2]
    for q, color in ((q0, blue), (q1, red)):
        ax.annotate(
            "",
            xy=origin + scale * q[:2],
            xytext=origin,
            arrowprops={"arrowstyle": "->", "color": color, "lw": 1.6},
        )
    ax.plot([], [], color=blue, ls="--", label=f"initial throw v0 = {np.round(q0[:dim], 2)} m/s")
    ax.plot([], [], color=red, label=f"optimised throw v0 = {np.round(q1[:dim], 2)} m/s")
    ax.plot([], [], color="k", ls=":", label="centre of mass of A (dotted) and B (solid)")
    ax.plot([], [], "o", mfc="none", mec="k", ms=9, label=f"target (radius {args.radius} m)")
    ax.set_aspect("equal")
    ax.autoscale_view()
    lo, hi = ax.get_xlim()
    ax.set_xlim(lo, max(hi, args.target[0] + 2 * args.radius))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]" if dim == 2 else "y [m] (seen from above)")
    ax.legend(fontsize=7.5, loc="upper right" if dim == 2 else "lower left")
    ax.set_title(
        "throw A so that B ends in the circle: shapes at rest (grey), at the end of the initial"
        " throw (blue)\nand during/at the end of the optimised throw (red)"
        if dim == 2
        else "throw A so that B ends in the circle (centre-of-mass paths seen from above)",
        fontsize=9,
    )
    times = np.asarray(traj1.times)
    ax_x.axhspan(args.target[0] - args.radius, args.target[0] + args.radius, color="0.85")
    ax_x.plot(times, paths["B0"][:, 0], color=blue, label="initial throw")
    ax_x.plot(times, paths["B1"][:, 0], color=red, label="optimised throw")
    ax_x.set_xlabel("time [s]")
    ax_x.set_ylabel("x of B's centre of mass [m]")
    ax_x.legend(fontsize=8, loc="upper left")
    ax_x.grid(alpha=0.3)
    save_figure(fig, path, comm)


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    run = parse_args(argv, comm)
    args = run.args
    model, contact, sim, control = build_scene(args, comm)
    com = {body: center_of_mass(model, body) for body in ("A", "B")}
    zero = np.zeros_like(sim.u0)
    rest_B = series_values(sim, com["B"], ds.Trajectory([0.0], [zero], [zero]))[0]
    target = np.append(args.target, rest_B[-1])  # the circle lies on B's resting height
    objective = final_value(center_of_mass_trajectory(model, target, bodies="B"))
    rf = ReducedFunctional(sim, objective, control)
    q0 = np.concatenate([args.v0, np.zeros(control.size - len(args.v0))])

    def target_reached(record, optimizer) -> str | bool:
        # stop once B ends well inside the circle
        end = series_values(sim, com["B"], optimizer.point.trajectory, steps=[-1])[0]
        inside = np.linalg.norm(end - target) < STOP_FRACTION * args.radius
        return "B ends inside the target circle" if inside else False

    options = LBFGSOptions(
        max_iterations=args.iterations,
        gradient_rtol=1e-5,
        initial_step=0.5,
        max_change=1.0,
    )
    result, keeper = run.optimise(rf, q0, options, stop_conditions=[target_reached])
    traj0, traj1 = keeper.first, keeper.last
    paths = {
        f"{body}{k}": series_values(sim, com[body], traj)
        for k, traj in enumerate((traj0, traj1))
        for body in ("A", "B")
    }
    files = write_runs(model, {"initial": traj0, "final": traj1}, args, "throw")

    report = run.report(result)
    distance0 = float(np.linalg.norm(paths["B0"][-1] - target))
    distance1 = float(np.linalg.norm(paths["B1"][-1] - target))
    check_invariants(report, check_trajectories(sim, [traj0, traj1], contact))
    if not args.tiny:
        report.check(
            "final distance of B to the target [m]",
            distance1,
            args.radius,
            distance1 < args.radius,
            f"(initial throw: {distance0:.3f} m)",
        )
    files += [args.out / "com_paths.csv", args.out / "history.jsonl", args.out / "result.json"]
    if comm.rank == 0:
        args.out.mkdir(parents=True, exist_ok=True)
        header = ",".join(f"{k}_{c}" for k in paths for c in "xyz"[: args.dim])
        np.savetxt(
            args.out / "com_paths.csv",
            np.column_stack([paths[k] for k in paths]),
            delimiter=",",
            header=header,
        )
    names = ["v_x", "v_y", "v_z"][: args.dim]
    if args.angular:
        names += ["omega"] if args.dim == 2 else ["omega_x", "omega_y", "omega_z"]
    figures = {
        "dim": args.dim,
        "v0_initial": q0.tolist(),
        "v0_optimised": result.q.tolist(),
        "target": target.tolist(),
        "radius": args.radius,
        "distance_initial": distance0,
        "distance_final": distance1,
        "newton_iterations_final": traj1.newton_iterations(),
    }
    throws = f"{np.round(q0, 3).tolist()} -> {np.round(result.q, 3).tolist()}"
    headline = (
        f"throw: A's initial velocity ({', '.join(names)}) {throws}; B ends {distance0:.3f} m "
        f"-> {distance1:.3f} m from the target (radius {args.radius} m); output in {args.out}/"
    )

    def figure(path):
        plot(path, args, model, traj0, traj1, paths, q0, result.q, result, comm)

    return finish_transient(run, report, model, result, files, figures, headline, figure)


if __name__ == "__main__":
    run_demo(main)
