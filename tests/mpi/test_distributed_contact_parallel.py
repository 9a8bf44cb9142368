"""Run under ``mpiexec -n 2`` (and 3): distributed contact equals serial contact.

Each rank evaluates its share of the collisions
(:class:`~diffsolids.contact.partition.CollisionPartition`). Scenes are built on COMM_WORLD and
on COMM_SELF in the same process and compared: (a) contact energy, gradient, Hessian action and
the assembled Hessian (entries added by other ranks into the owner's preallocated rows) of a
three-body 2D scene with friction and a two-body 3D scene with friction; (b) the gradient of a
short optimisation objective (friction, shape, initial velocity controls); (c) the work is
split, not replicated: each collision is on exactly one rank with its serial weight (the
per-rank collision counts sum to the serial count, every rank has some).
"""

import dolfinx.fem.petsc as fem_petsc
import numpy as np
import pytest
import ufl
from contact_checks import box_falling_on_box, crate_on_incline
from dolfinx import fem
from mpi4py import MPI
from parallel_checks import assert_world_equals_self, value_and_gradient

import diffsolids as ds
from diffsolids.contact.partition import collision_keys
from diffsolids.controls import FrictionControl, InitialCondition, ShapeControl
from diffsolids.objectives import Integral, final_value, time_integral
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.solvers.sparsity import matrix_with_pattern, sorted_unique
from diffsolids.states import Phase, StepContext

RTOL = 1e-10


def _scene_2d(comm, steps: int = 4):
    """A slab, a crate sliding on it and a lid on the crate (friction on both contacts)."""
    return crate_on_incline(comm, 1e-3, [6, 3], [3, 2], steps)


def _scene_3d(comm, steps: int = 3):
    """A free box falling flat (slightly turned) onto a clamped box, friction 0.3."""
    model, contact, v0 = box_falling_on_box(
        comm, 1e-3, [4, 4, 1], [3, 3, 1], 1e11, [0.05, 0.0, -0.3], degrees=2.0
    )
    integ = ds.BDF(2, 0.004, steps)
    sim = ds.Simulation(model, integ, ds.SolverOptions(rtol=1e-10), v0=v0, progress=False)
    return model, contact, sim


SCENES = {"2d": _scene_2d, "3d": _scene_3d}


def _sorted_nodal(V, arr: np.ndarray, d: int) -> np.ndarray:
    """Owned nodal values of all ranks, ordered by node coordinates (partition independent)."""
    comm = V.mesh.comm
    n = V.dofmap.index_map.size_local
    x = np.round(V.tabulate_dof_coordinates()[:n, :d], 12)
    xs = np.concatenate(comm.allgather(x))
    vs = np.concatenate(comm.allgather(np.asarray(arr).reshape(-1, d)[:n]))
    return vs[np.lexsort(xs.T[::-1])]


def _field(V, d: int, seed: int) -> fem.Function:
    """A smooth partition-independent field on V."""
    f = fem.Function(V)
    a = np.random.default_rng(seed).uniform(1.0, 3.0, size=(d, d))

    def values(x):
        return np.vstack([np.sin(a[i] @ x[:d] + i) for i in range(d)])

    f.interpolate(values)
    return f


def _kernels(build, comm) -> dict:
    """Contact kernels at the last state of a short run (lagged from the state before)."""
    model, contact, sim = build(comm)
    traj = sim.run()
    d = model.dim
    V = model.V
    i = sim.integrator.num_steps
    contact.begin_step(StepContext.of(sim.integrator, i, traj, Phase.BACKWARD))
    u = fem.Function(V)
    u.x.array[:] = traj.u[i]
    bc = model.dirichlet_dofs()
    out = {"records": [r.num_collisions for r in contact.records]}
    out["energy"] = contact.energy(u)
    b = fem_petsc.create_vector(V)
    b.set(0.0)
    contact.add_residual(u, b)
    out["gradient"] = _sorted_nodal(V, b.array_r, d)
    direction = _field(V, d, 1)
    direction.x.array[bc] = 0.0
    y = fem_petsc.create_vector(V)
    y.set(0.0)
    contact.add_hessian_action(u, direction.x.array, y)
    out["hessian_action"] = _sorted_nodal(V, y.array_r, d)
    # the assembled exact Hessian: other ranks' entries land in the owner's preallocated rows
    A = sim.solver.A
    N = A.getSize()[1]
    rows, cols = contact.matrix_pattern(u, bc)
    r0, r1 = A.getOwnershipRange()
    diag = np.arange(r0, r1, dtype=np.int64)
    keys = sorted_unique(np.asarray(rows, dtype=np.int64) * N + cols, diag * N + diag)
    B = matrix_with_pattern(A, keys)
    contact.add_jacobian(u, B, bc)
    B.assemble()
    x = B.createVecRight()
    x.array[:] = direction.x.array[: len(x.array)]
    z = B.createVecLeft()
    B.mult(x, z)
    out["matrix_action"] = _sorted_nodal(V, z.array_r, d)
    B.destroy()
    # adjoint products at the same state
    lam = _field(V, d, 2)
    lam.x.array[bc] = 0.0
    out["history"] = [_sorted_nodal(V, g, d) for g in contact.adjoint_history(u, lam).values()]
    out["friction"] = contact.adjoint_friction(u, lam)
    out["shape"] = _sorted_nodal(model.shape_space, contact.adjoint_shape(u, lam), d)
    # one fresh build at the state: this rank's share of candidates and collisions
    ev = contact._evaluate(u)
    C = contact.builder.build(ev.x)
    out["share"] = {
        "collisions": len(C),
        "keys": collision_keys(C),
        "weights": _weights(C),
    }
    return out


def _weights(C) -> np.ndarray:
    groups = (C.vv_collisions, C.ev_collisions, C.ee_collisions, C.fv_collisions)
    return np.array([c.weight for g in groups for c in g], dtype=float)


def _close(a, b, rtol=RTOL) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    scale = max(np.abs(b).max(initial=0.0), 1e-300)
    if a.shape != b.shape:
        return False
    err = np.abs(a - b).max(initial=0.0) / scale
    if err > rtol:
        print(f"relative difference {err:.2e} > {rtol:.0e}")
    return err <= rtol


@pytest.mark.parametrize("scene", sorted(SCENES))
def test_kernels_equal_serial(scene):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2 (or 3)"
    par = _kernels(SCENES[scene], comm)
    ser = _kernels(SCENES[scene], MPI.COMM_SELF)
    assert par["records"] == ser["records"] and max(ser["records"]) > 0
    assert abs(par["energy"] - ser["energy"]) <= RTOL * abs(ser["energy"])
    for name in ("gradient", "hessian_action", "matrix_action", "shape"):
        assert np.abs(ser[name]).max() > 0, name
        assert _close(par[name], ser[name]), name
    assert np.abs(ser["friction"]).max() > 0
    assert _close(par["friction"], ser["friction"])
    # d g / d u^{i-j} on the scale of all j (the velocity part alone can be round-off)
    assert _close(np.stack(par["history"]), np.stack(ser["history"]))
    # (c) each collision on exactly one rank, whole: the ranks' shares partition the serial set
    shares = comm.allgather(par["share"])
    keys = np.concatenate([s["keys"] for s in shares])
    weights = np.concatenate([s["weights"] for s in shares])
    pieces = [s["collisions"] for s in shares]
    if comm.rank == 0:
        print(f"{scene}: collisions per rank {pieces} (serial {ser['share']['collisions']})")
    assert sum(pieces) == ser["share"]["collisions"] == len(np.unique(keys))
    assert min(pieces) > 0  # every rank has work
    order, serial_order = np.argsort(keys), np.argsort(ser["share"]["keys"])
    assert np.array_equal(keys[order], ser["share"]["keys"][serial_order])
    assert _close(weights[order], ser["share"]["weights"][serial_order], 1e-14)


def _rf(build, comm):
    model, contact, sim = build(comm, steps=3)
    d = model.dim
    on_top = 3 if d == 2 else 2
    density = model.coefficients["density"]
    objective = final_value(
        Integral(lambda f: (f.X[0] + f.u[0]) * f.dx(on_top), "x")
    ) + time_integral(
        Integral(lambda f: 0.5 * density * ufl.dot(f.v, f.v) * f.dx(on_top), "kinetic")
    )
    controls = [
        FrictionControl(contact),
        ShapeControl(model, "all"),
        InitialCondition(sim, "velocity"),
    ]
    return ReducedFunctional(sim, objective, controls)


@pytest.mark.parametrize("scene", sorted(SCENES))
def test_gradient_equals_serial(scene):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2 (or 3)"
    world, serial = (value_and_gradient(_rf(SCENES[scene], c)) for c in (comm, MPI.COMM_SELF))
    assert_world_equals_self(world, serial, RTOL, scene)
