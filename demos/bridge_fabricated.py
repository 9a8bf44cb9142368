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

import numpy as np
from common import MESHES, DemoReport, run_demo
from dolfinx import fem
from mpi4py import MPI
from shape_tools import (
    check_iterates,
    design_vertex_coordinates,
    optimise_shape,
    plot_shapes_2d,
    run_extra,
    shape_run,
    vertex_coordinates,
    write_state,
)

import diffsolids as ds
from diffsolids.io import boundary_edges
from diffsolids.mesh import from_geo
from diffsolids.objectives import BoundarySmoothing, final_value, target_positions
from diffsolids.optimize import LBFGSOptions, MeshMotionControl, ShapeInnerProduct
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


def look(model, u) -> tuple:
    """Outline and vertex positions of a rest shape."""
    return boundary_edges(model), vertex_coordinates(model.domain)


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Run the demo on ``comm``; returns the report (printed on rank 0)."""
    run = shape_run(__doc__.splitlines()[0], "bridge_fabricated", argv, comm, SIZES)
    args = run.args
    domain = from_geo(GEO, comm, numbers={"h": args.h})
    material = ds.LinearElastic(E=E, nu=NU, density=DENSITY)
    model = ds.Model(domain, material, degree=1, plane_stress=True)
    model.add_gravity(GRAVITY)
    for side in FIXED:
        model.add_dirichlet(side, 0.0)
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-12), progress=False)
    control = MeshMotionControl(model, exclude_facets=list(FIXED), refuse_intersections=True)
    X_true = vertex_coordinates(domain)
    suffix = ".xdmf" if args.xdmf else ".bp"

    # the fabricated solution: the deformed unperturbed bridge, attached to the vertices
    u_true = sim.run().u[-1]
    files = write_state(model, args.out / f"target{suffix}", u_true)
    target_shape = boundary_edges(model)
    target = fem.Function(model.V, name="target")
    dofs_x = model.V.tabulate_dof_coordinates()[:, :2]
    target.x.array[:] = dofs_x.ravel() + u_true

    misfit = final_value(target_positions(model, target))
    smooth = BoundarySmoothing(model, 2, exclude_facets=list(FIXED))
    scale = ReducedFunctional(sim, misfit, control)
    q_perturbed = perturbation(design_vertex_coordinates(control)).ravel()
    J_perturbed = scale(q_perturbed)
    rf = ReducedFunctional(sim, (1.0 / J_perturbed) * misfit + WEIGHT_SMOOTHING * smooth, control)
    opt = optimise_shape(
        rf,
        q_perturbed,
        LBFGSOptions(max_iterations=args.iterations, gradient_rtol=1e-9),
        args,
        look,
        inner_product=ShapeInnerProduct(rf, mass_weight=1.0 / HEIGHT**2),
    )
    (before, X_perturbed), (after, X_final) = opt.initial, opt.final
    perturbation_size = float(np.linalg.norm(X_perturbed - X_true, axis=1).max())
    error = float(np.linalg.norm(X_final - X_true, axis=1).max())

    report = run.report(opt.result)
    relative = error / perturbation_size
    opt.files[:0] = files  # the target first
    report.extra = run_extra(
        run,
        opt,
        domain,
        max_perturbation=perturbation_size,
        max_vertex_error=error,
        relative_error=relative,
        parameters=rf.size,
    )
    check_iterates(report, opt.monitor)
    if not args.tiny:
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
            opt.result,
            title,
            comm,
            target=target_shape,
            labels=("perturbed", "recovered", "original"),
        )
    return run.finish(report)


if __name__ == "__main__":
    run_demo(main)
