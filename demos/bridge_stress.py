"""Static shape optimisation of a 2D bridge: lower the peak stress at constant volume (Fig. 6).

The bridge (``meshes/bridge.geo``: span 10, height 2, a lower beam and an upper chord joined by
verticals around three openings with rounded corners) is clamped at both ends and carries
three tractions on the underside of its lower beam, one under each opening. Linear elasticity
(plane stress), one static solve per evaluation.

Objective (paper eqs. 30, 35, 37), normalised by its initial stress value:

    J = ||sigma_vM||_L8 / s0 + w_V ((V - V0) / V0)^2 + w_S * boundary smoothing

Controls: every boundary vertex except the clamped sides and the loaded segments (so the total
load stays fixed) moves freely; the interior follows through the linear-elasticity extension
(MeshMotionControl); the Riesz map of that extension is the initial inverse Hessian of L-BFGS
(ShapeInnerProduct); the interior is remeshed when the mesh quality drops. A trial shape whose
boundary intersects itself (possible without inverted cells) is refused like an inverted one.

Checked outcome (default and --full): the maximum cellwise von Mises stress falls by at least a
factor 2 while the volume stays within 1 % of V0; in every run: the objective decreased, no
accepted iterate has inverted cells or a self-intersecting boundary.

Run ``python demos/bridge_stress.py`` (default size), ``--tiny`` (smoke test), ``--full``
(paper-like resolution), or ``mpiexec -n 2 python demos/bridge_stress.py``.
"""

import logging
import time

import numpy as np
from common import MESHES, DemoReport, demo_parser, finish, report_from, run_demo, size_name
from mpi4py import MPI
from shape_tools import (
    GuardedMeshMotion,
    Invariants,
    facet_polygons_2d,
    max_von_mises,
    plot_shapes_2d,
    volume,
    write_state,
)

import diffsolids as ds
from diffsolids.io import configure_logging
from diffsolids.mesh import from_geo
from diffsolids.objectives import BoundarySmoothing, final_value, stress_lp_norm, volume_penalty
from diffsolids.optimize import (
    LBFGSOptions,
    Remesher,
    ShapeInnerProduct,
    minimize,
)
from diffsolids.parallel import collective_comm
from diffsolids.reduced_functional import ReducedFunctional

GEO = MESHES / "bridge.geo"
FIXED = ("fixed_left", "fixed_right")
LOADS = ("load_1", "load_2", "load_3")
TRACTION = 1.0  # downward traction on each loaded segment (force per length)
E, NU = 1.0e3, 0.3
SIZES = {
    "tiny": {"h": 0.25, "iterations": 4, "max_change": 0.05},
    "default": {"h": 0.1, "iterations": 60, "max_change": 0.05},
    "full": {"h": 0.035, "iterations": 300, "max_change": 0.02},
}
WEIGHT_VOLUME = 1.0e3
WEIGHT_SMOOTHING = 1.0
MIN_REDUCTION = 2.0  # checked: max von Mises before / after
VOLUME_TOLERANCE = 0.01  # checked: |V - V0| / V0


class Problem:
    """Builds the scene on a mesh (also after remeshing) with fixed normalisation constants."""

    def __init__(self, args):
        self.args = args
        self.s0: float | None = None  # L8 stress of the initial shape
        self.V0: float | None = None  # initial volume

    def model(self, domain) -> ds.Model:
        """The clamped, loaded bridge on a mesh."""
        model = ds.Model(domain, ds.LinearElastic(E=E, nu=NU), degree=1, plane_stress=True)
        for side in FIXED:
            model.add_dirichlet(side, 0.0)
        for load in LOADS:
            model.add_traction(load, [0.0, -TRACTION])
        return model

    def __call__(self, domain) -> ReducedFunctional:
        """The reduced functional on a mesh (the first call fixes s0 and V0)."""
        model = self.model(domain)
        sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-10), progress=False)
        control = GuardedMeshMotion(model, exclude_facets=[*FIXED, *LOADS])
        stress = final_value(stress_lp_norm(model, 8, "von_mises"))
        if self.s0 is None:
            self.V0 = volume(model)
            self.s0 = ReducedFunctional(sim, stress, control)(np.zeros(control.size))
        V0 = self.V0
        vol = volume_penalty(model, V0, "upper") + volume_penalty(model, V0, "lower")
        smooth = BoundarySmoothing(model, 2, exclude_facets=list(FIXED))
        J = (1.0 / self.s0) * stress + (WEIGHT_VOLUME / V0**2) * vol + WEIGHT_SMOOTHING * smooth
        return ReducedFunctional(sim, J, control)


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Run the demo on ``comm``; returns the report (printed on rank 0)."""
    parser = demo_parser(__doc__.splitlines()[0], "bridge_stress")
    parser.add_argument("--h", type=float, help="mesh size")
    args = parser.parse_args(argv)
    size = size_name(args)
    setup = SIZES[size]
    h = args.h or setup["h"]
    iterations = args.iterations if args.iterations is not None else setup["iterations"]
    configure_logging(logging.INFO if args.verbose else logging.WARNING, comm)
    t0 = time.perf_counter()
    cpu0 = time.process_time()

    problem = Problem(args)
    domain = from_geo(GEO, comm, numbers={"h": h})
    rf = problem(domain)
    model0 = rf.model
    q0 = rf.initial_parameters()
    rf(q0)
    u0 = rf.trajectory.u[-1].copy()
    stress0 = max_von_mises(model0, u0)
    suffix = ".xdmf" if args.xdmf else ".bp"
    files = write_state(model0, args.out / f"initial{suffix}", u0)
    before = facet_polygons_2d(model0)

    invariants = Invariants()
    options = LBFGSOptions(
        max_iterations=iterations,
        gradient_rtol=1e-6,
        max_change=setup["max_change"],
        initial_step=setup["max_change"],
    )
    result = minimize(
        rf,
        q0,
        options,
        inner_product=ShapeInnerProduct(rf),
        remesher=Remesher(problem, threshold=0.1),
        stop_conditions=[invariants],
        progress=False,
        output_dir=args.out,
        plot_every=0 if args.no_plot else max(iterations, 1),  # at the end only
    )
    rf = result.functional
    model = rf.model
    u1 = rf.trajectory.u[-1]
    stress1 = max_von_mises(model, u1)
    V1 = volume(model)
    files += write_state(model, args.out / f"final{suffix}", u1)
    after = facet_polygons_2d(model)

    report = report_from("bridge_stress", args, result, t0)
    reduction = stress0 / stress1
    change = abs(V1 - problem.V0) / problem.V0
    report.extra = {
        "max_von_mises_initial": stress0,
        "max_von_mises_final": stress1,
        "reduction": reduction,
        "volume_initial": problem.V0,
        "volume_final": V1,
        "remeshes": sum(r.remeshed for r in result.history),
        "vertices": domain.mesh.geometry.index_map().size_global,
        "ranks": comm.size,
        "cpu_seconds": collective_comm(comm).allreduce(time.process_time() - cpu0, op=MPI.SUM),
        "files": [str(f) for f in files],
    }
    report.check(
        "objective decreased",
        report.final_objective,
        report.initial_objective,
        report.final_objective < report.initial_objective,
    )
    report.check("iterates with inverted cells", invariants.inverted, 0, invariants.inverted == 0)
    report.check(
        "iterates with self-intersecting boundaries",
        invariants.intersecting,
        0,
        invariants.intersecting == 0,
    )
    if size != "tiny":
        report.check(
            "max von Mises reduction",
            reduction,
            MIN_REDUCTION,
            reduction >= MIN_REDUCTION,
            f"({stress0:.4g} -> {stress1:.4g})",
        )
        report.check(
            "volume change",
            change,
            VOLUME_TOLERANCE,
            change <= VOLUME_TOLERANCE,
            f"(V {problem.V0:.5g} -> {V1:.5g})",
        )
    if not args.no_plot:
        title = (
            f"max von Mises {stress0:.3g} -> {stress1:.3g} ({reduction:.2f}x), "
            f"volume {problem.V0:.4g} -> {V1:.4g}"
        )
        plot_shapes_2d(args.out / "bridge_stress.png", before, after, result, title, comm)
    return finish(report, args, comm)


if __name__ == "__main__":
    run_demo(main)
