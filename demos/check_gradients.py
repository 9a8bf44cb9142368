"""Check adjoint gradients against finite differences and Taylor tests on a built-in scene.

For every control block of the scene's reduced functional J(q) the script draws a random
direction dq (seeded) that moves only that block, compares the adjoint directional derivative
dJ.dq with central differences (J(q + h dq) - J(q - h dq)) / 2h over a sweep of steps h (the
best one is reported) and runs a Taylor test: the remainder |J(q + h dq) - J(q) - h dJ.dq|
must fall like h^2 (rate 2) when the gradient is right. A last row does the same along the
gradient itself (all blocks at once), where a sign or scale error cannot hide. The table:

    control | parameters | adjoint dJ.dq | best FD | rel. error | Taylor rate

Scenes (``--scene``):

* ``static-shape``: the bridge of ``meshes/bridge.geo`` (linear elasticity, three tractions)
  with the objective of demos/bridge_stress.py (L8 stress, two-sided volume penalty, boundary
  smoothing) and boundary mesh-motion shape controls, plus the traction magnitude.
* ``dynamic-material``: a damped Neo-Hookean bar of two bodies (BDF2, 8 steps) pulled down at
  its tip; Young's modulus per cell (log), Poisson's ratio per body, damping per body and the
  density per cell (log); objective: misfit of the final state plus kinetic energy over time.
* ``contact-friction``: a soft block sliding down a slab on a 20 degree incline (IPC contact
  with lagged friction, BDF2); the friction coefficient, the block's Young's modulus (log), its
  initial rigid velocity and the rest positions of its vertices; objective: the final
  position of the block plus its kinetic energy over time.

Run ``python demos/check_gradients.py --scene contact-friction`` (``--tiny`` for a smaller run,
``--json out.json`` to save the rows), also under ``mpiexec -n 2``. The exit code is 1 when a
relative error exceeds ``--tolerance`` or a Taylor rate falls below ``--min-rate``.
"""

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import ufl
from mpi4py import MPI

import diffsolids as ds
from diffsolids.parallel import collective_comm
from diffsolids.verification import finite_difference_check, taylor_test

ROOT = Path(__file__).resolve().parents[1]
SCENES = ("static-shape", "dynamic-material", "contact-friction")

__all__ = ["SCENES", "Row", "build_scene", "check", "main"]


@dataclass
class Row:
    """One line of the table."""

    control: str
    parameters: int
    adjoint: float
    finite_difference: float
    relative_error: float
    step: float
    taylor_rate: float


# -- scenes --------------------------------------------------------------------------------------
def _static_shape(comm, tiny: bool):
    from dolfinx import fem

    from diffsolids.controls import ParameterControl
    from diffsolids.mesh import from_geo
    from diffsolids.objectives import (
        BoundarySmoothing,
        final_value,
        stress_lp_norm,
        volume_penalty,
    )
    from diffsolids.optimize import MeshMotionControl
    from diffsolids.reduced_functional import ReducedFunctional

    fixed, loads = ["fixed_left", "fixed_right"], ["load_1", "load_2", "load_3"]
    domain = from_geo(ROOT / "meshes" / "bridge.geo", comm, numbers={"h": 0.4 if tiny else 0.2})
    model = ds.Model(domain, ds.LinearElastic(E=1.0e3, nu=0.3), degree=1, plane_stress=True)
    for side in fixed:
        model.add_dirichlet(side, 0.0)
    for k, load in enumerate(loads):
        model.add_traction(load, [0.2 * k, -1.0], name=f"load_{k + 1}")
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-12), progress=False)
    shape = MeshMotionControl(model, exclude_facets=fixed + loads)
    # a volume target 2 % below the initial one: the penalty is active and differentiable
    area = collective_comm(comm).allreduce(
        fem.assemble_scalar(fem.form(1.0 * model.fields.dx)), op=MPI.SUM
    )
    V = 0.98 * area
    J = (
        final_value(stress_lp_norm(model, 8, "von_mises"))
        + 10.0 * volume_penalty(model, V, "upper")
        + 10.0 * volume_penalty(model, V, "lower")
        + 0.1 * BoundarySmoothing(model, 2, exclude_facets=fixed)
    )
    load = ParameterControl(model, "load_2", "scale")
    rf = ReducedFunctional(sim, J, [shape, load])
    return rf, {shape.name: 0.02, load.name: 0.05}


def _dynamic_material(comm, tiny: bool):
    from diffsolids.controls import ParameterControl
    from diffsolids.mesh import create_rectangle
    from diffsolids.objectives import Integral, final_value, target_displacement, time_integral
    from diffsolids.reduced_functional import ReducedFunctional

    n = (8, 2) if tiny else (16, 4)
    facets = {1: lambda x: np.isclose(x[0], 0.0), 2: lambda x: np.isclose(x[0], 2.0)}
    domain = create_rectangle(
        comm, [[0, 0], [2, 0.5]], list(n), facets=facets, bodies={2: lambda x: x[0] > 1.0}
    )
    materials = {
        1: ds.NeoHookean(E=200.0, nu=0.3, density=2.0, damping_psi=0.2, damping_phi=0.1),
        2: ds.NeoHookean(E=300.0, nu=0.35, density=1.5, damping_psi=0.3, damping_phi=0.1),
    }
    model = ds.Model(domain, materials, degree=1)
    model.add_traction(2, [0.0, -12.0])
    model.add_dirichlet(1, 0.0)
    steps = 4 if tiny else 8
    sim = ds.Simulation(model, ds.BDF(2, 0.05, steps), ds.SolverOptions(rtol=1e-12), progress=False)
    rho = model.coefficients["density"]
    kinetic = Integral(lambda f: 0.5 * rho * ufl.dot(f.v, f.v) * f.dx, "kinetic")
    target = final_value(target_displacement(model, [0.0, -0.2], facets=2))
    J = target + 0.1 * time_integral(kinetic, "trapezoidal")
    controls = [
        ParameterControl(model, "E", "field", log=True),
        ParameterControl(model, "nu", "bodies"),
        ParameterControl(model, "damping_psi", "bodies"),
        ParameterControl(model, "density", "field", log=True),
    ]
    return ReducedFunctional(sim, J, controls), {}


def _contact_friction(comm, tiny: bool):
    from diffsolids.contact import ContactTerm
    from diffsolids.controls import FrictionControl, ParameterControl, RigidVelocity, ShapeControl
    from diffsolids.mesh.scene import combine_meshes, simplex_box
    from diffsolids.objectives import Integral, final_value, time_integral
    from diffsolids.reduced_functional import ReducedFunctional

    dhat = 1e-2
    theta = np.deg2rad(20.0)
    slab = simplex_box([[0.0, 0.0], [3.0, 0.1]], [15, 1])
    # off the slab's vertex grid: a block vertex starting exactly above a slab vertex puts a kink
    # into the lagged point-edge friction of the first step (see tests/test_gradients_contact.py)
    shift = 0.0137
    block = simplex_box([[0.2 + shift, 0.1 + 0.5 * dhat], [0.5 + shift, 0.25 + 0.5 * dhat]], [3, 2])
    domain = combine_meshes(comm, [slab, block], names={"slab": 1, "block": 2})
    material = ds.NeoHookean(E=1e5, nu=0.3, density=1000.0, damping_psi=10.0, damping_phi=1.0)
    model = ds.Model(domain, material, degree=1)
    model.add_body_force(9.81 * np.array([np.sin(theta), -np.cos(theta)]), name="gravity")
    model.add_dirichlet(lambda x: x[1] < 0.1 + 1e-9, 0.0)
    integrator = ds.BDF(2, 0.01, 6 if tiny else 12)
    contact = ContactTerm(model, dhat=dhat, friction={("slab", "block"): 0.2}, eps_v=1e-2)
    model.add_numeric_term(contact)
    sim = ds.Simulation(model, integrator, ds.SolverOptions(rtol=1e-12), progress=False)
    x_end = Integral(lambda f: (f.X[0] + f.u[0]) * f.dx(2), "block x")
    motion = Integral(lambda f: ufl.dot(f.v, f.v) * f.dx(2), "block v^2")
    J = final_value(x_end) + time_integral(motion)
    controls = [
        FrictionControl(contact, pairs=[("slab", "block")]),
        ParameterControl(model, "E", "bodies", bodies=["block"], log=True),
        RigidVelocity(sim, "block"),
        ShapeControl(model, lambda x: x[1] > 0.1 + 1e-9),
    ]
    rf = ReducedFunctional(sim, J, controls)
    return rf, {controls[2].name: 0.05, controls[3].name: 2e-3}


_BUILDERS = {
    "static-shape": _static_shape,
    "dynamic-material": _dynamic_material,
    "contact-friction": _contact_friction,
}


def build_scene(name: str, comm: MPI.Comm = MPI.COMM_WORLD, tiny: bool = False):
    """The reduced functional of a built-in scene and the perturbation size of some blocks.

    Returns:
        (rf, sizes) with ``sizes[control name]`` the norm of that block's random direction
        (absolute, for displacement-like controls); other blocks use 5 % of |q_block| (at least
        1e-3 per parameter).
    """
    if name not in _BUILDERS:
        raise SystemExit(f"check_gradients: unknown scene {name!r}; choose from {SCENES}")
    return _BUILDERS[name](comm, tiny)


# -- checks --------------------------------------------------------------------------------------
def _block_size(q: np.ndarray, name: str, sizes: dict) -> float:
    if name in sizes:
        return sizes[name]
    return 0.05 * max(float(np.linalg.norm(q)), 1e-3 * np.sqrt(q.size))


def _row(rf, q, g, dq, name: str, size: int, steps) -> Row:
    fd = finite_difference_check(rf, q, dq, steps, gradient=g)
    taylor = taylor_test(rf, q, dq, h0=5e-3, num=4)
    return Row(
        name,
        size,
        fd.adjoint,
        float(fd.finite_differences[fd.best_index]),
        fd.relative_error,
        fd.best_step,
        taylor.min_rate,
    )


def check(rf, sizes: dict, seed: int = 0) -> list[Row]:
    """One row per control block (random direction) and one along the gradient (collective)."""
    q0 = rf.initial_parameters()
    rng = np.random.default_rng(seed)
    steps = np.array([1e-1, 3e-2, 1e-2, 3e-3, 1e-3, 3e-4, 1e-4])
    try:
        g = rf.gradient(q0)
        offsets = rf.controls.offsets
        rows, scaled = [], np.zeros_like(q0)
        for control, a, b in zip(rf.controls.controls, offsets[:-1], offsets[1:], strict=True):
            size = _block_size(q0[a:b], control.name, sizes)
            dq = np.zeros_like(q0)
            r = rng.standard_normal(b - a)
            dq[a:b] = size * r / np.linalg.norm(r)
            rows.append(_row(rf, q0, g, dq, control.name, b - a, steps))
            gb = g[a:b]
            if np.any(gb):
                scaled[a:b] = size * gb / np.linalg.norm(gb)
        rows.append(_row(rf, q0, g, scaled, "along the gradient", q0.size, steps))
        return rows
    finally:
        rf.controls.assign(q0)


def table(rows: list[Row]) -> str:
    """The rows as a text table."""
    header = (
        f"{'control':<26} {'params':>6} {'adjoint dJ.dq':>16} {'best FD':>16} "
        f"{'rel. error':>10} {'h':>8} {'Taylor rate':>11}"
    )
    lines = [header, "-" * len(header)]
    for r in rows:
        lines.append(
            f"{r.control:<26} {r.parameters:>6d} {r.adjoint:>16.9e} {r.finite_difference:>16.9e} "
            f"{r.relative_error:>10.2e} {r.step:>8.1e} {r.taylor_rate:>11.2f}"
        )
    return "\n".join(lines)


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> list[Row]:
    """Run the checks of one scene; prints the table (rank 0) and returns the rows."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", choices=SCENES, default="static-shape", help="built-in scene")
    p.add_argument("--tiny", action="store_true", help="a coarser mesh and fewer steps")
    p.add_argument("--seed", type=int, default=0, help="seed of the random directions")
    p.add_argument("--tolerance", type=float, default=1e-5, help="largest relative FD error")
    p.add_argument("--min-rate", type=float, default=1.8, help="smallest Taylor rate")
    p.add_argument("--json", type=Path, help="also write the rows to this JSON file")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    rf, sizes = build_scene(args.scene, comm, args.tiny)
    rows = check(rf, sizes, args.seed)
    seconds = time.perf_counter() - t0
    if comm.rank == 0:
        print(f"check_gradients: scene {args.scene}, {rf.size} parameters, {comm.size} rank(s)")
        print(table(rows))
        bad = [
            r.control
            for r in rows
            if r.relative_error > args.tolerance or r.taylor_rate < args.min_rate
        ]
        verdict = f"FAILED: {', '.join(bad)}" if bad else "all rows within tolerance"
        print(
            f"{verdict} (tolerance {args.tolerance:g}, min rate {args.min_rate:g}); {seconds:.1f} s"
        )
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps([asdict(r) for r in rows], indent=2))
    return rows


def _failed(rows: list[Row], argv) -> bool:
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--tolerance", type=float, default=1e-5)
    p.add_argument("--min-rate", type=float, default=1.8)
    args, _ = p.parse_known_args(argv)
    return any(r.relative_error > args.tolerance or r.taylor_rate < args.min_rate for r in rows)


if __name__ == "__main__":
    argv = sys.argv[1:]
    sys.exit(1 if _failed(main(argv), argv) else 0)
