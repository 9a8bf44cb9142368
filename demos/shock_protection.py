"""Shape optimisation (paper Fig. 13): a cellular strip that protects a dropped load from stress.

A heavy block (the load) hits a soft cellular strip, a slab with a row of round holes on a fixed
base (``meshes/shock.geo``), at 4.5 m/s. The thin curved ligaments around the holes buckle, the
holes collapse and their walls come into contact (self-contact); the load is decelerated and
bounces back. Physics: Neo-Hookean strip and load with a little viscous damping, BDF2, IPC
contact and self-contact with friction (barrier stiffness from ``suggest_barrier_stiffness``).

The design is low-dimensional (paper sec. 10.2, after Panetta et al. 2015): every hole (an
ellipse at the start) takes the same shape, X = X0 + sum_m q_m Phi_m(X0), with three smooth
displacement fields Phi_m around each hole: its size, its ellipticity and its squareness, faded
out halfway to the strip's faces (which stay flat) and to the next hole (``ShapeControl`` with a
``linear_map``; |q_m| <= 0.25). The objective is the space-time L_p norm of the load's stress,

    J = ( 1 / (T |load|) sum_i dt int_load |sigma(u^i)|_F^p dx )^(1/p),   p = 4,

the paper's eq. 30 integrated over time. The outcome checked: the stress is reduced by at least
10% (and the peak of the per-step L_p stress drops too).

Sizes: ``--tiny`` (smoke test), default (well under 2 minutes of CPU), ``--full`` (finer mesh and
time step). Writes into ``output/shock_protection/`` (``--out``): ``shock_initial.bp`` /
``shock_final.bp`` (VTX, or ``.xdmf`` with ``--xdmf``), ``shock_protection.png``,
``history.jsonl`` and ``result.json``.

Run ``python demos/shock_protection.py`` or under ``mpiexec -n 2``.
"""

from typing import override

import numpy as np
from common import MESHES, DemoReport, DemoRun, plot_history, run_demo, save_figure
from dolfinx import fem
from dynamic_common import body_nodes, finish_transient, write_runs
from invariants import check_invariants
from mpi4py import MPI

import diffsolids as ds
from diffsolids import forms
from diffsolids.contact import ContactTerm
from diffsolids.controls import ShapeControl
from diffsolids.io import boundary_edges
from diffsolids.mesh import from_geo
from diffsolids.objectives import Integral, series_values, time_integral
from diffsolids.optimize import LBFGSOptions, check_trajectories
from diffsolids.parallel import collective_comm
from diffsolids.reduced_functional import ReducedFunctional

GEO = MESHES / "shock.geo"
W, H, HOLES = 0.48, 0.08, 6  # strip width and height, number of holes
RX, RY = 0.032, 0.02  # half axes of the (elliptic) holes
DECAY = 0.5  # the shape fields fade out over this elliptic radius beyond a hole
BOUND = 0.25  # |q_m| <= BOUND (relative changes of the hole)
MODES = ("size", "ellipticity", "squareness")
STRIP = {"E": 3e5, "nu": 0.3, "density": 1000.0, "damping_psi": 20.0}
LOAD = {"E": 1e6, "nu": 0.3, "density": 4000.0, "damping_psi": 20.0}
SPEED = 4.5  # of the load [m/s]
P = 4.0  # exponent of the stress norm
FRICTION, DHAT, EPS_V = 0.2, 1e-3, 0.01
SIZES = {
    "tiny": {"h": 0.016, "hload": 0.03, "dt": 0.002, "steps": 8, "iterations": 2},
    "default": {"h": 0.012, "hload": 0.025, "dt": 0.0015, "steps": 18, "iterations": 8},
    "full": {"h": 0.005, "hload": 0.01, "dt": 0.0005, "steps": 60, "iterations": 20},
}
MIN_REDUCTION = 0.10  # the default run must reduce J by at least this fraction


def parse_args(argv, comm: MPI.Comm) -> DemoRun:
    """The run with its arguments."""
    return DemoRun(DemoRun.parser(__doc__.splitlines()[0], "shock_protection"), argv, comm, SIZES)


def hole_modes(X: np.ndarray) -> np.ndarray:
    """Displacement fields of the design (num_points x dim x modes) at rest positions X.

    Around hole k (centre c_k, half axes RX, RY; d = X - c_k, polar angle theta, elliptic
    radius rho = |(d_x / RX, d_y / RY)|, 1 on the hole) the fields are phi(rho) f_m d with
    f = (1, 1) (size), (1, -1) (ellipticity: wider and flatter) and -cos 4theta (1, 1)
    (squareness: out at the diagonals, in at the axes); phi = 1 on the hole and falls linearly
    to 0 at rho = 1 + DECAY, halfway to the strip's faces and to the next hole, so the faces
    stay flat and the fields do not overlap.
    """
    modes = np.zeros((len(X), 2, len(MODES)))
    for k in range(HOLES):
        d = X - np.array([(k + 0.5) * W / HOLES, H / 2])
        rho = np.hypot(d[:, 0] / RX, d[:, 1] / RY)
        phi = np.clip(1.0 - (rho - 1.0) / DECAY, 0.0, 1.0)[:, None]
        theta = np.arctan2(d[:, 1], d[:, 0])
        modes[:, :, 0] += phi * d
        modes[:, :, 1] += phi * d * np.array([1.0, -1.0])
        modes[:, :, 2] -= phi * d * np.cos(4 * theta)[:, None]
    return modes


class HoleShape(ShapeControl):
    """The strip's holes, all shaped alike by the fields of :func:`hole_modes` (bounded)."""

    def __init__(self, model):
        mesh = model.domain.mesh
        comm = mesh.comm
        num = mesh.geometry.index_map().size_global
        local = mesh.geometry.input_global_indices
        # rest positions in canonical (input) order, and the vertices of the strip
        X = np.zeros((num, 2))
        X[np.concatenate(collective_comm(comm).allgather(local))] = np.concatenate(
            collective_comm(comm).allgather(mesh.geometry.x[:, :2])
        )
        nodes = np.unique(mesh.geometry.dofmaps[0][model.domain.cells_of("strip")])
        strip = np.zeros(num, dtype=bool)
        strip[np.concatenate(collective_comm(comm).allgather(local[nodes]))] = True
        modes = hole_modes(X) * strip[:, None, None]
        super().__init__(model, linear_map=modes.reshape(num * 2, len(MODES)))

    @override
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(self.size, -BOUND), np.full(self.size, BOUND)


def build_scene(args, comm):
    """Model, contact term and simulation of the load dropped on the strip."""
    domain = from_geo(
        GEO,
        comm,
        numbers={"W": W, "H": H, "n": HOLES, "R": RX, "Ry": RY, "h": args.h, "hload": args.hload},
    )
    materials = {"strip": ds.NeoHookean(**STRIP), "load": ds.NeoHookean(**LOAD)}
    model = ds.Model(domain, materials, degree=1)
    model.add_gravity(9.81)
    model.add_dirichlet("base", 0.0)
    integrator = ds.BDF(2, args.dt, args.steps)
    contact = model.add_numeric_term(ContactTerm(model, DHAT, friction=FRICTION, eps_v=EPS_V))
    v0 = np.zeros_like(model.fields.u.x.array)
    v0.reshape(-1, 2)[body_nodes(model, "load"), 1] = -SPEED
    options = ds.SolverOptions(rtol=1e-8)
    sim = ds.Simulation(model, integrator, options, v0=v0, progress=False)
    return model, contact, sim


def load_stress_power(model):
    """Integral of |sigma|_F^p over the load per step (the Cauchy stress of its law)."""
    load = model.domain.body_id("load")

    def integrand(f):
        lmbda, mu = model.lame(f)
        sigma = forms.cauchy_stress("neo_hookean", f.u, lmbda, mu)
        return forms.stress_norm_power(sigma, P) * f.dx(load)

    return Integral(integrand, f"load |sigma|^{P:g}")


def stress_history(sim, traj, volume: float) -> np.ndarray:
    """Per-step L_p norm of the load's stress, (int_load |sigma|^p / |load|)^(1/p) [Pa].

    At every state of ``traj``, for the model's current shape.
    """
    power = series_values(sim, load_stress_power(sim.model), traj)
    return (np.maximum(power, 0.0) / volume) ** (1.0 / P)


def plot(path, args, model, traj0, traj1, q0, q1, stress, result, control, comm) -> None:
    """Strip before/after, both at the largest compression, stress over time, J history."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    s0, s1 = stress
    i0, i1 = int(np.argmax(s0)), int(np.argmax(s1))
    control.assign(q0)
    rest0 = boundary_edges(model)
    squeezed0 = boundary_edges(model, traj0.u[i0])
    control.assign(q1)
    rest1 = boundary_edges(model)
    squeezed1 = boundary_edges(model, traj1.u[i1])
    if comm.rank != 0:
        return
    fig = plt.figure(figsize=(11, 6.6))
    grid = fig.add_gridspec(4, 2, width_ratios=[1.9, 1])
    titles = [
        ("initial design", "tab:blue", rest0),
        (
            f"initial design at the largest stress, t = {1e3 * i0 * args.dt:.1f} ms",
            "tab:blue",
            squeezed0,
        ),
        ("optimised design", "tab:red", rest1),
        (
            f"optimised design at the largest stress, t = {1e3 * i1 * args.dt:.1f} ms",
            "tab:red",
            squeezed1,
        ),
    ]
    for row, (title, color, segs) in enumerate(titles):
        ax = fig.add_subplot(grid[row, 0])
        ax.add_collection(LineCollection(segs, colors=color, lw=0.8))
        ax.set_xlim(-0.01, W + 0.01)
        ax.set_ylim(-0.005, H + 0.06)
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=8.5)
        ax.tick_params(labelsize=7)
    ax_s = fig.add_subplot(grid[0:2, 1])
    times = 1e3 * np.asarray(traj1.times)
    ax_s.plot(times, s0 / 1e3, color="tab:blue", label="initial design")
    ax_s.plot(times, s1 / 1e3, color="tab:red", label="optimised design")
    ax_s.set_xlabel("time [ms]")
    ax_s.set_ylabel(f"L{P:g} norm of the load's stress [kPa]")
    ax_s.legend(fontsize=8)
    ax_s.grid(alpha=0.3)
    ax_h = fig.add_subplot(grid[2:4, 1])
    plot_history(ax_h, result, "J", "objective: space-time L4 stress [Pa]", fontsize=9)
    fig.suptitle(
        "load dropped on a cellular strip: hole shape "
        + ", ".join(f"{m} {v:+.3f}" for m, v in zip(MODES, q1, strict=True)),
        fontsize=10,
    )
    save_figure(fig, path, comm)


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    run = parse_args(argv, comm)
    args = run.args
    model, contact, sim = build_scene(args, comm)
    control = HoleShape(model)
    volume = collective_comm(comm).allreduce(
        fem.assemble_scalar(fem.form(1.0 * model.body_measure("load"))), op=MPI.SUM
    )
    T = args.steps * args.dt
    power = time_integral(load_stress_power(model), "uniform") * (1.0 / (T * volume))
    objective = power ** (1.0 / P)
    rf = ReducedFunctional(sim, objective, control)
    options = LBFGSOptions(
        max_iterations=args.iterations,
        gradient_rtol=1e-4,
        objective_rtol=1e-3,
        initial_step=0.1,
        max_change=0.1,
    )
    q0 = np.zeros(control.size)
    result, keeper = run.optimise(rf, q0, options, write_parameters=True)
    # the stress, the checks and the output of each run on its own design
    files, stress, checks = [], [], []
    for label, q, traj in (("initial", q0, keeper.first), ("final", result.q, keeper.last)):
        control.assign(q)
        stress.append(stress_history(sim, traj, volume))
        checks.append(check_trajectories(sim, [traj], contact))
        files += write_runs(model, {label: traj}, args, "shock")
    files += [args.out / "history.jsonl", args.out / "result.json"]
    (traj0, traj1), (stress0, stress1) = (keeper.first, keeper.last), stress

    report = run.report(result)
    reduction = 1.0 - report.final_objective / report.initial_objective
    peak_reduction = 1.0 - stress1.max() / stress0.max()
    check_invariants(report, *checks)
    if not args.tiny:
        report.check(
            "stress reduction (space-time L4)",
            reduction,
            MIN_REDUCTION,
            reduction >= MIN_REDUCTION,
            f"({report.initial_objective:.4g} -> {report.final_objective:.4g} Pa)",
        )
        report.check(
            "peak stress reduction (per-step L4)",
            peak_reduction,
            0.0,
            peak_reduction > 0.0,
            f"({stress0.max():.4g} -> {stress1.max():.4g} Pa)",
        )
    figures = {
        "design": dict(zip(MODES, result.q.tolist(), strict=True)),
        "reduction": reduction,
        "peak_stress_initial": float(stress0.max()),
        "peak_stress_final": float(stress1.max()),
        "invalid_trials": result.num_invalid_trials,
    }
    headline = (
        f"shock_protection: hole shape ({', '.join(MODES)}) -> "
        f"{np.round(result.q, 4).tolist()}; load stress (space-time L4) "
        f"{report.initial_objective:.4g} -> {report.final_objective:.4g} Pa "
        f"({100 * reduction:.1f}% lower), peak per-step L4 {stress0.max():.4g} -> "
        f"{stress1.max():.4g} Pa"
    )

    def figure(path):
        plot(
            path, args, model, traj0, traj1, q0, result.q, (stress0, stress1), result, control, comm
        )

    return finish_transient(run, report, model, result, files, figures, headline, figure)


if __name__ == "__main__":
    run_demo(main)
