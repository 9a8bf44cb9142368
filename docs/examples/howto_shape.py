"""Optimise a shape: a clamped plate carrying a load at its tip, with less peak stress.

The top and bottom edges of a 3 x 1 plate move (a MeshMotionControl: the interior follows an
elasticity extension); the objective is the L8 norm of the von Mises stress (a smooth stand-in
for its maximum) over its initial value, a one-sided volume bound and a boundary smoothing.
``python docs/examples/howto_shape.py [--out DIR] [--iterations N]`` (also under mpiexec).
"""

import argparse
from pathlib import Path

import numpy as np
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.io import write_trajectory
from diffsolids.objectives import BoundarySmoothing, stress_lp_norm, volume_penalty
from diffsolids.optimize import (
    InvariantMonitor,
    LBFGSOptions,
    MeshMotionControl,
    OptimizationResult,
    ShapeInnerProduct,
    minimize,
)
from diffsolids.parallel import collective_comm

CLAMP, LOAD = 1, 2


def build(comm: MPI.Comm, n: tuple[int, int] = (24, 8)) -> ds.ReducedFunctional:
    """The plate, its design boundary and the objective J(q)."""
    # [scene]
    facets = {
        CLAMP: lambda x: np.isclose(x[0], 0.0),
        LOAD: lambda x: np.isclose(x[0], 3.0) & (x[1] > 0.3) & (x[1] < 0.7),
    }
    domain = ds.mesh.create_rectangle(comm, [[0, 0], [3, 1]], list(n), facets=facets)
    model = ds.Model(domain, ds.NeoHookean(E=1e3, nu=0.3), plane_stress=True)
    model.add_dirichlet(CLAMP, 0.0)
    model.add_traction(LOAD, [0.0, -40.0])
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-10), progress=False)
    # [design]
    # every boundary vertex moves except the clamped side and the loaded segment; a shape
    # whose boundary would fold over itself is refused (an invalid trial: the step halves)
    control = MeshMotionControl(model, exclude_facets=[CLAMP, LOAD], refuse_intersections=True)
    # [objective]
    stress = ds.final_value(stress_lp_norm(model, 8, "von_mises"))
    s0 = ds.ReducedFunctional(sim, stress, control)(np.zeros(control.size))
    V0 = collective_comm(comm).allreduce(
        fem.assemble_scalar(fem.form(1.0 * model.fields.dx)), op=MPI.SUM
    )
    J = (
        (1.0 / s0) * stress  # 1 at the initial shape
        + (1e3 / V0**2) * volume_penalty(model, V0, "upper")  # the plate may not grow
        + 1e-2 * BoundarySmoothing(model, exclude_facets=[CLAMP, LOAD])
    )
    return ds.ReducedFunctional(sim, J, control)
    # [end objective]


def main(argv: list[str] | None = None) -> OptimizationResult:
    """Optimise, check every iterate, write the initial and final states."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("output/howto_shape"))
    parser.add_argument("--iterations", type=int, default=15)
    args = parser.parse_args(argv)
    # [optimise]
    rf = build(MPI.COMM_WORLD)
    q0 = np.zeros(rf.size)
    rf(q0)
    initial = rf.trajectory
    monitor = InvariantMonitor()  # counts iterates with inverted cells or folded boundaries
    result = minimize(
        rf,
        q0,
        LBFGSOptions(max_iterations=args.iterations, gradient_rtol=1e-4),
        inner_product=ShapeInnerProduct(rf),  # the mesh motion's H1 Riesz map
        on_accept=monitor,
        log=True,
        log_file=args.out / "log.csv",
    )
    # each trajectory is written on its own rest shape
    write_trajectory(rf.model, initial, args.out / "initial.bp")
    write_trajectory(result.functional.model, result.functional.trajectory, args.out / "final.bp")
    # [end optimise]
    assert monitor.inverted == monitor.intersecting == 0
    return result


if __name__ == "__main__":
    main()
