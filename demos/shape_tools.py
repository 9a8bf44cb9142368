"""Helpers shared by the static shape-optimisation demos (bridges, 3D beam, interlocking parts).

The stress problem the three stress demos share (L8 von Mises stress, volume term and boundary
smoothing, normalised by the first mesh), a run that writes and looks at the initial and final
states around L-BFGS while ``diffsolids.optimize.InvariantMonitor`` checks every accepted
iterate, the checks every run reports, and the
before/after figures. All functions are collective over the mesh communicator and return the
same value on every rank.
"""

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from common import DemoReport, DemoRun, check_decrease
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.io import boundary_edges, write_trajectory
from diffsolids.io.output import von_mises_field
from diffsolids.objectives import BoundarySmoothing, final_value, stress_lp_norm, volume_penalty
from diffsolids.optimize import (
    InvariantMonitor,
    LBFGSOptions,
    OptimizationResult,
    Remesher,
    ShapeInnerProduct,
    minimize,
)
from diffsolids.parallel import collective_comm
from diffsolids.reduced_functional import ReducedFunctional

__all__ = [
    "ShapeRun",
    "StressProblem",
    "check_iterates",
    "check_stress_reduction",
    "design_vertex_coordinates",
    "max_von_mises",
    "optimise_shape",
    "plot_shapes_2d",
    "plot_shapes_3d",
    "run_extra",
    "shape_run",
    "vertex_coordinates",
    "volume",
    "write_state",
]


def shape_run(
    description: str, name: str, argv: Sequence[str] | None, comm: MPI.Comm, sizes: dict
) -> DemoRun:
    """A shape demo's run: the arguments of every demo and ``--h``, the mesh size."""
    parser = DemoRun.parser(description, name)
    parser.add_argument("--h", type=float, help="mesh size")
    return DemoRun(parser, argv, comm, sizes)


def vertex_coordinates(domain) -> np.ndarray:
    """Vertex positions (num_vertices, dim) in canonical (input) order, on every rank."""
    mesh = domain.mesh
    dim = mesh.geometry.dim
    n = mesh.geometry.index_map().size_local
    out = np.zeros((mesh.geometry.index_map().size_global, dim))
    out[mesh.geometry.input_global_indices[:n]] = mesh.geometry.x[:n, :dim]
    return collective_comm(domain.comm).allreduce(out, op=MPI.SUM)


def design_vertex_coordinates(control) -> np.ndarray:
    """Reference positions of the design vertices of a MeshMotionControl (parameter order)."""
    motion = control.motion
    X = motion.reference[:, : motion.dim]
    mesh = motion.domain.mesh
    n = mesh.geometry.index_map().size_local
    out = np.zeros((motion.num_vertices, motion.dim))
    out[mesh.geometry.input_global_indices[:n]] = X[:n]
    return collective_comm(motion.comm).allreduce(out, op=MPI.SUM)[motion.design]


def volume(model) -> float:
    """Rest volume (area in 2D) of the model's mesh."""
    local = fem.assemble_scalar(fem.form(1.0 * model.fields.dx))
    return collective_comm(model.domain.comm).allreduce(local, op=MPI.SUM)


def max_von_mises(model, u: np.ndarray) -> float:
    """Largest cellwise (midpoint) von Mises stress of a displacement array."""
    field = von_mises_field(model, u)
    local = field.x.array.max() if field.x.array.size else -np.inf
    return collective_comm(model.domain.comm).allreduce(float(local), op=MPI.MAX)


def write_state(model, path: Path, u: np.ndarray) -> list[Path]:
    """Write one state (displacement and von Mises stress) as VTX ``.bp`` or XDMF; the files."""
    return write_trajectory(model, ds.Trajectory([0.0], [u], [np.zeros_like(u)]), path)


@dataclass
class ShapeRun:
    """An optimisation run of :func:`optimise_shape`.

    Attributes:
        result: The OptimizationResult.
        monitor: The InvariantMonitor that checked every accepted iterate.
        files: The files of the initial and final states.
        initial: What ``look`` returned for the initial state.
        final: What ``look`` returned for the final state.
    """

    result: OptimizationResult
    monitor: InvariantMonitor
    files: list[Path]
    initial: object
    final: object


def optimise_shape(
    rf,
    q0: np.ndarray,
    options: LBFGSOptions,
    args: argparse.Namespace,
    look: Callable[[object, np.ndarray], object],
    deformed: bool = False,
    **kwargs,
) -> ShapeRun:
    """L-BFGS on a shape problem; the initial and final states are written and looked at.

    The initial state is solved first; ``look(model, u)`` measures it (outlines, stresses,
    coordinates) before the shape changes, and the final state after the run. Every accepted
    iterate is checked by an InvariantMonitor (``deformed``: also the deformed boundary).

    Args:
        rf: The ReducedFunctional.
        q0: Initial parameters.
        options: L-BFGS options.
        args: Parsed arguments (``out``, ``xdmf``, ``no_plot``).
        look: Measurements of a state on the model it belongs to.
        deformed: Check the deformed boundaries of the iterates too.
        **kwargs: Further arguments of ``minimize`` (inner product, remesher, observers).
    """
    suffix = ".xdmf" if args.xdmf else ".bp"
    rf(q0)
    u0 = rf.trajectory.u[-1].copy()
    initial = look(rf.model, u0)
    files = write_state(rf.model, args.out / f"initial{suffix}", u0)
    monitor = InvariantMonitor(deformed)
    kwargs["on_accept"] = [monitor, *kwargs.get("on_accept", ())]
    result = minimize(
        rf,
        q0,
        options,
        progress=False,
        output_dir=args.out,
        plot_every=0 if args.no_plot else max(options.max_iterations, 1),  # at the end only
        **kwargs,
    )
    model = result.functional.model
    u1 = result.functional.trajectory.u[-1]
    final = look(model, u1)
    files += write_state(model, args.out / f"final{suffix}", u1)
    return ShapeRun(result, monitor, files, initial, final)


def check_iterates(
    report, monitor: InvariantMonitor, rest: str = "iterates with self-intersecting boundaries"
) -> None:
    """Record: objective decreased, no iterate with inverted cells or intersecting boundaries.

    Args:
        report: The DemoReport.
        monitor: The run's InvariantMonitor.
        rest: Name of the outcome "no iterate with an intersecting rest boundary".
    """
    check_decrease(report)
    report.check("iterates with inverted cells", monitor.inverted, 0, monitor.inverted == 0)
    report.check(rest, monitor.intersecting, 0, monitor.intersecting == 0)
    if monitor.deformed:
        report.check(
            "iterates with intersecting deformed shapes",
            monitor.intersecting_deformed,
            0,
            monitor.intersecting_deformed == 0,
        )


def check_stress_reduction(report, stress0: float, stress1: float, minimum: float) -> None:
    """Record the stress demos' outcome: the maximum von Mises stress fell ``minimum``-fold."""
    reduction = stress0 / stress1
    report.check(
        "max von Mises reduction",
        reduction,
        minimum,
        reduction >= minimum,
        f"({stress0:.4g} -> {stress1:.4g})",
    )


def run_extra(run: DemoRun, opt: ShapeRun, domain, **values) -> dict:
    """``report.extra`` of a shape run: the demo's values, then remeshes, size, cost, files."""
    return {
        **values,
        "remeshes": sum(r.remeshed for r in opt.result.history),
        "vertices": domain.mesh.geometry.index_map().size_global,
        "ranks": run.comm.size,
        "cpu_seconds": run.cpu_seconds(),
        "files": [str(f) for f in opt.files],
    }


class StressProblem:
    """A stress demo: its functional on a mesh (also after remeshing) and the run around it.

    J = ||sigma_vM||_L8 / s0 + w_V * volume term / V0^2 + w_S * boundary smoothing, with the
    L8 stress s0 and the volume V0 of the first mesh, so that J is the same function on every
    mesh. A subclass gives the model and the control and sets the class attributes; the other
    methods are the defaults of the bridge and the beam (one-sided volume bound of eq. 35,
    ShapeInnerProduct, boundary outlines in 2D).

    Attributes:
        weight_volume: w_V.
        weight_smoothing: w_S.
        smoothing_exclude: Facet tags left out of the boundary smoothing.
        remesh_threshold: Minimum scaled Jacobian below which the interior is remeshed.
        min_reduction: The outcome: the maximum von Mises stress falls this many times.
        rest_check: Name of the outcome "no iterate with an intersecting rest boundary".
        deformed: Also check the deformed boundary of every iterate.
        s0: L8 stress of the initial shape (set by the first call).
        V0: Initial volume (set by the first call).
    """

    weight_volume = 1.0e3
    weight_smoothing = 5.0e-2
    smoothing_exclude: Sequence[str] = ()
    remesh_threshold = 0.1
    min_reduction = 2.0
    rest_check = "iterates with self-intersecting boundaries"
    deformed = False

    def __init__(self) -> None:
        self.s0: float | None = None
        self.V0: float | None = None

    # -- the scene ---------------------------------------------------------------------------
    def model(self, domain) -> ds.Model:
        """The scene's model on a mesh."""
        raise NotImplementedError

    def control(self, model, sim):
        """The shape control of the scene's model."""
        raise NotImplementedError

    def volume_term(self, model, V0: float):
        """The volume term (default: one-sided, V may not grow)."""
        return volume_penalty(model, V0, "upper")

    def solver_options(self) -> ds.SolverOptions:
        """Newton options of the static solve."""
        return ds.SolverOptions(rtol=1e-10)

    def __call__(self, domain) -> ReducedFunctional:
        """The reduced functional on a mesh (the first call fixes s0 and V0)."""
        model = self.model(domain)
        sim = ds.Simulation(model, ds.Static(), self.solver_options(), progress=False)
        control = self.control(model, sim)
        stress = final_value(stress_lp_norm(model, 8, "von_mises"))
        if self.s0 is None:
            self.V0 = volume(model)
            self.s0 = ReducedFunctional(sim, stress, control)(np.zeros(control.size))
        V0 = self.V0
        smooth = BoundarySmoothing(model, 2, exclude_facets=list(self.smoothing_exclude))
        J = (
            (1.0 / self.s0) * stress
            + (self.weight_volume / V0**2) * self.volume_term(model, V0)
            + self.weight_smoothing * smooth
        )
        return ReducedFunctional(sim, J, control)

    # -- the story -----------------------------------------------------------------------------
    def outline(self, model):
        """What the figure shows of a rest shape (default: the boundary edges of a 2D mesh)."""
        return boundary_edges(model)

    def inner_product(self, rf):
        """The initial inverse Hessian of L-BFGS (default: the Riesz map of the mesh motion)."""
        return ShapeInnerProduct(rf)

    def observers(self) -> list:
        """Further ``on_accept`` observers of the run."""
        return []

    def extra(self, result: OptimizationResult) -> dict:
        """The demo's own values in ``report.extra``."""
        return {}

    def check(self, report, V1: float) -> None:
        """The demo's own outcomes of the default and full sizes (the final volume V1)."""

    def title(self, stress0: float, stress1: float, V1: float) -> str:
        """Title of the figure."""
        return (
            f"max von Mises {stress0:.3g} -> {stress1:.3g} ({stress0 / stress1:.2f}x), "
            f"volume {self.V0:.4g} -> {V1:.4g}"
        )

    def plot(self, path: Path, before, after, result, title: str, comm) -> None:
        """The figure (default: 2D outlines, see :func:`plot_shapes_2d`)."""
        plot_shapes_2d(path, before, after, result, title, comm)

    def look(self, model, u: np.ndarray) -> tuple:
        """Maximum von Mises stress, volume and outline of a state."""
        return max_von_mises(model, u), volume(model), self.outline(model)

    def run(self, run: DemoRun, domain) -> "DemoReport":
        """Optimise the shape on ``domain``, check the outcomes, write the figure and report."""
        args = run.args
        rf = self(domain)
        options = LBFGSOptions(
            max_iterations=args.iterations,
            gradient_rtol=1e-6,
            max_change=args.max_change,
            initial_step=args.max_change,
        )
        opt = optimise_shape(
            rf,
            rf.initial_parameters(),
            options,
            args,
            self.look,
            deformed=self.deformed,
            inner_product=self.inner_product(rf),
            remesher=Remesher(self, threshold=self.remesh_threshold),
            on_accept=self.observers(),
        )
        (stress0, _, before), (stress1, V1, after) = opt.initial, opt.final
        report = run.report(opt.result)
        report.extra = run_extra(
            run,
            opt,
            domain,
            max_von_mises_initial=stress0,
            max_von_mises_final=stress1,
            reduction=stress0 / stress1,
            volume_initial=self.V0,
            volume_final=V1,
            **self.extra(opt.result),
        )
        check_iterates(report, opt.monitor, self.rest_check)
        if not args.tiny:
            check_stress_reduction(report, stress0, stress1, self.min_reduction)
            self.check(report, V1)
        if not args.no_plot:
            title = self.title(stress0, stress1, V1)
            self.plot(args.out / f"{args.demo}.png", before, after, opt.result, title, run.comm)
        return run.finish(report)


def plot_shapes_2d(
    path: Path, before, after, result, title: str, comm, target=None, labels=None
) -> None:
    """Boundary before (grey), after (blue) and optionally a target (dashed); J per iteration."""
    if comm.rank != 0:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from common import plot_history, save_figure
    from matplotlib.collections import LineCollection

    labels = labels or ("initial", "optimised", "target")
    fig, (ax, ax_j) = plt.subplots(1, 2, figsize=(13, 3.6), gridspec_kw={"width_ratios": [2.6, 1]})
    ax.add_collection(LineCollection(before, colors="0.6", lw=0.8, label=labels[0]))
    ax.add_collection(LineCollection(after, colors="C0", lw=1.4, label=labels[1]))
    if target is not None:
        ax.add_collection(
            LineCollection(target, colors="k", lw=0.8, linestyles="--", label=labels[2])
        )
    ax.autoscale()
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize="small")
    ax.set_title(title, fontsize="medium")
    plot_history(ax_j, result)
    save_figure(fig, path, comm)


def plot_shapes_3d(path: Path, before, after, result, title: str, comm) -> None:
    """Side (x-z) and top (x-y) silhouettes before and after (``silhouette_edges``); J history."""
    if comm.rank != 0:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from common import plot_history, save_figure
    from matplotlib.collections import LineCollection

    fig = plt.figure(figsize=(12, 4.6))
    grid = fig.add_gridspec(2, 2, width_ratios=[2.4, 1])
    axes = [fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[1, 0]), fig.add_subplot(grid[:, 1])]
    views = (((0, 2), "side (x-z)"), ((0, 1), "top (x-y)"))
    for ax, ((a, b), name), edges0, edges1 in zip(axes[:2], views, before, after, strict=True):
        ax.add_collection(
            LineCollection(edges0[:, :, [a, b]], colors="0.6", lw=0.8, label="initial")
        )
        ax.add_collection(
            LineCollection(edges1[:, :, [a, b]], colors="C0", lw=1.3, label="optimised")
        )
        ax.autoscale()
        ax.set_aspect("equal")
        ax.set_title(name, fontsize="medium")
    axes[0].legend(loc="upper right", fontsize="small")
    plot_history(axes[2], result)
    fig.suptitle(title, fontsize="medium")
    save_figure(fig, path, comm)
