"""Static shape optimisation with a fabricated solution: recover a bridge's rest shape (Fig. 5).

The bridge of ``meshes/bridge.geo`` (clamped at both ends) sags under gravity; linear
elasticity (plane stress). A forward solve on the unperturbed shape gives the target
displacement u* and with it the target configuration x* = X + u*, a P1 field attached to the
mesh vertices (it moves with the material points: x^trg defined on the reference domain,
paper eq. 31). The rest shape is then perturbed by a smooth displacement of every boundary
vertex except the clamped ones, extended into the interior by the mesh motion, and L-BFGS
minimises (paper eqs. 31, 37)

    J = int |X + u - x*|^2 dx / J(perturbed) + w_S * boundary smoothing

over the same boundary displacements (MeshMotionControl; ShapeInnerProduct as the initial
inverse Hessian). The optimiser never sees the perturbation: it has to find the original
shape from the sag alone.

Checked outcome (default and --full): the largest vertex error of the recovered rest shape is
below 1 % of the largest vertex displacement of the perturbation; in every run: the objective
decreased, no accepted iterate has inverted cells or a self-intersecting boundary.

Run ``python demos/bridge_fabricated.py`` (default size), ``--tiny`` (smoke test), ``--full``
(paper-like resolution), or ``mpiexec -n 2 python demos/bridge_fabricated.py``.
"""

import logging
import time

import numpy as np
from common import MESHES, DemoReport, demo_parser, finish, report_from, run_demo, size_name
from dolfinx import fem
from mpi4py import MPI
from shape_tools import (
    GuardedMeshMotion,
    Invariants,
    design_vertex_coordinates,
    facet_polygons_2d,
    plot_shapes_2d,
    vertex_coordinates,
    write_state,
)

import diffsolids as ds
from diffsolids.io import configure_logging
from diffsolids.mesh import from_geo
from diffsolids.objectives import BoundarySmoothing, final_value, target_positions
from diffsolids.optimize import LBFGSOptions, ShapeInnerProduct, minimize
from diffsolids.parallel import collective_comm
from diffsolids.reduced_functional import ReducedFunctional

GEO = MESHES / "bridge.geo"
FIXED = ("fixed_left", "fixed_right")
LENGTH, HEIGHT = 10.0, 2.0  # of meshes/bridge.geo
E, NU, DENSITY, GRAVITY = 1.0e3, 0.3, 1.0, 1.0
AMPLITUDE = 0.15  # largest displacement of the perturbation (about 1.5 default cells)
SIZES = {
    "tiny": {"h": 0.25, "iterations": 4},
    "default": {"h": 0.1, "iterations": 200},
    "full": {"h": 0.035, "iterations": 300},
}
WEIGHT_SMOOTHING = 1.0e-8  # small: the smoothing term is not zero at the true shape
MAX_ERROR = 0.01  # checked: max vertex error / max perturbation


def perturbation(x: np.ndarray) -> np.ndarray:
    """A smooth displacement field (n, 2) at positions x (n, 2), largest value ~AMPLITUDE."""
    s, t = np.pi * x[:, 0] / LENGTH, np.pi * x[:, 1] / HEIGHT
    d = np.column_stack(
        [
            0.6 * np.sin(2 * s) * np.cos(t),
            np.sin(s) * (0.7 + 0.3 * np.cos(3 * s)) * np.cos(0.5 * t),
        ]
    )
    return AMPLITUDE * d / np.abs(d).max()


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Run the demo on ``comm``; returns the report (printed on rank 0)."""
    parser = demo_parser(__doc__.splitlines()[0], "bridge_fabricated")
    parser.add_argument("--h", type=float, help="mesh size")
    args = parser.parse_args(argv)
    size = size_name(args)
    setup = SIZES[size]
    h = args.h or setup["h"]
    iterations = args.iterations if args.iterations is not None else setup["iterations"]
    configure_logging(logging.INFO if args.verbose else logging.WARNING, comm)
    t0 = time.perf_counter()
    cpu0 = time.process_time()

    domain = from_geo(GEO, comm, numbers={"h": h})
    material = ds.LinearElastic(E=E, nu=NU, density=DENSITY)
    model = ds.Model(domain, material, degree=1, plane_stress=True)
    model.add_gravity(GRAVITY)
    for side in FIXED:
        model.add_dirichlet(side, 0.0)
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-12), progress=False)
    control = GuardedMeshMotion(model, exclude_facets=list(FIXED))
    X_true = vertex_coordinates(domain)
    suffix = ".xdmf" if args.xdmf else ".bp"

    # the fabricated solution: the deformed unperturbed bridge, attached to the vertices
    u_true = sim.run().u[-1]
    files = write_state(model, args.out / f"target{suffix}", u_true)
    target_shape = facet_polygons_2d(model)
    target = fem.Function(model.V, name="target")
    dofs_x = model.V.tabulate_dof_coordinates()[:, :2]
    target.x.array[:] = dofs_x.ravel() + u_true

    misfit = final_value(target_positions(model, target))
    smooth = BoundarySmoothing(model, 2, exclude_facets=list(FIXED))
    scale = ReducedFunctional(sim, misfit, control)
    q_perturbed = perturbation(design_vertex_coordinates(control)).ravel()
    J_perturbed = scale(q_perturbed)
    rf = ReducedFunctional(sim, (1.0 / J_perturbed) * misfit + WEIGHT_SMOOTHING * smooth, control)
    rf(q_perturbed)
    files += write_state(model, args.out / f"initial{suffix}", rf.trajectory.u[-1])
    before = facet_polygons_2d(model)
    X_perturbed = vertex_coordinates(domain)
    perturbation_size = float(np.linalg.norm(X_perturbed - X_true, axis=1).max())

    invariants = Invariants()
    options = LBFGSOptions(max_iterations=iterations, gradient_rtol=1e-9)
    result = minimize(
        rf,
        q_perturbed,
        options,
        inner_product=ShapeInnerProduct(rf, mass_weight=1.0 / HEIGHT**2),
        stop_conditions=[invariants],
        progress=False,
        output_dir=args.out,
        plot_every=0 if args.no_plot else max(iterations, 1),  # at the end only
    )
    error = float(np.linalg.norm(vertex_coordinates(domain) - X_true, axis=1).max())
    files += write_state(model, args.out / f"final{suffix}", rf.trajectory.u[-1])
    after = facet_polygons_2d(model)

    report = report_from("bridge_fabricated", args, result, t0)
    relative = error / perturbation_size
    report.extra = {
        "max_perturbation": perturbation_size,
        "max_vertex_error": error,
        "relative_error": relative,
        "vertices": domain.mesh.geometry.index_map().size_global,
        "parameters": rf.size,
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
            "max vertex error / perturbation",
            relative,
            MAX_ERROR,
            relative < MAX_ERROR,
            f"({error:.3g} of {perturbation_size:.3g})",
        )
    if not args.no_plot:
        title = (
            f"rest shape: perturbed by up to {perturbation_size:.3g}, recovered to "
            f"{error:.2g} ({100 * relative:.2g} %)"
        )
        plot_shapes_2d(
            args.out / "bridge_fabricated.png",
            before,
            after,
            result,
            title,
            comm,
            target=target_shape,
            labels=("perturbed", "recovered", "original"),
        )
    return finish(report, args, comm)


if __name__ == "__main__":
    run_demo(main)
