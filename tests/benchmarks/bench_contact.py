"""Contact benchmark: cost of the IPC contact term per Newton iteration.

A free box (friction 0.3) falls flat onto a larger box clamped at its bottom: flat-on-flat 3D
contact between two free bodies, P1, BDF2. Reported per Newton iteration: collision-set build,
barrier/friction energy, gradient and Hessian, matrix insertion, pattern check, CCD step bound
(AdditiveCCD, LBVH broad phase), and the total Newton iteration time for comparison; the cost of a
sparsity-pattern change (matrix rebuild with the union pattern, and MUMPS symbolic+numeric versus
numeric-only factorisation); and both narrow phases on the same flat-on-flat Newton step.

Then the adjoint gradient of an objective of the falling box (final height of its centre of mass
plus the time integral of its kinetic energy) with respect to the rest positions of all
vertices, a log Young's modulus per cell and the friction coefficient, timed on a warm JIT cache
(an untimed sweep first), as a ratio to the forward run (``ratio``; goal <= 0.10), the share of
the contact adjoint kernels (``adjoint_history``, ``adjoint_shape``, ``adjoint_friction``, with
the contact evaluations they trigger) in it (``adjoint_contact_kernels_share``; goal <= 0.20),
and the share of contact work in a Newton iteration (``contact_share``: contact operations plus
the solver's pattern check; goal <= 0.30).

Last, the paper's fig1 scene (two bunnies thrown into a coarse pool whose faces are up to 3.2 m
long, BDF1, the paper's material and dhat; data in ``$DIFFSOLIDS_DATA/diffipc/fig1_bunnies``)
and the same bunnies on a fine slab of about the same size: seconds per Newton iteration and the
vertex pairs the contact sparsity pattern holds (``coarse_obstacle_*`` and ``fine_obstacle_*``;
a coarse obstacle must cost about what the scene's size suggests).

Run ``python tests/benchmarks/bench_contact.py [--cells N]``, also under ``mpiexec -n 2``:
contact is distributed (each collision evaluated on one rank,
:mod:`diffsolids.contact.partition`), and ``per_rank`` lists each rank's contact timers (wall
and CPU per Newton iteration), the partition's counts (collision sets built, collisions kept)
and its own cost (``share``: dropping the other ranks' collisions, inside ``build``).

``--ranks 1,2`` runs the benchmark once per rank count (``mpiexec -n k``, one session, the same
arguments, the fig1 scenes skipped; a small untimed run first warms the JIT cache) and prints
the speedups of the forward, the gradient, the Newton iteration and the contact part (wall and
CPU, the slowest rank), and a projection of the contact part to ``--project`` ranks from the
measured costs: the distributed contact work per collision, the replicated part (collision
set build, CCD, gather, reach pattern), the partition's own cost per collision and the
communication volume per evaluation (the gathered surface vector plus one allreduce of it per
reduced vector; a link of ``--bandwidth`` GB/s and ``--latency`` us per collective step,
log2 P steps).
The last line printed is a JSON object with the numbers.

Measured with ``--ranks 1,2`` (one session each, 2 shared cores at load ~9, so CPU times are
the steadier figures): default case (11 049 dofs, 134 Newton iterations on 1 and 2 ranks),
forward 95.3 -> 82.1 s (1.16x), gradient 4.79 -> 3.97 s (1.21x), contact CPU per Newton
iteration 119 -> 91 ms per rank (1.31x; Hessians 30 + 35 -> 14 + 17 ms), 508 144 / 504 121
collisions per rank; ``--cells 20 --steps 2`` (44 811 dofs): forward 89.6 -> 79.8 s (1.12x),
gradient 1.11x, contact CPU 350 -> 272 ms per rank (1.28x), but the MUMPS factorisation takes
3.2 s of the 4.5 s Newton iteration on 1 and on 2 ranks (contact: 12%), so the linear solver,
not contact, bounds the speedup. Projected contact speedup at 64 ranks: 2.7x (replicated
collision set build, CCD and reach pattern ~25%, splitting ~1.5 us per collision).

``--pc gamg`` solves the Newton steps by GMRES + GAMG and the adjoint systems by GMRES with the
same preconditioner (no factorisations; ``"pc": "gamg"`` in the JSON). Measured with ``--cells
28 --steps 2 --ranks 1,2`` (115 821 dofs, 21 Newton iterations, one session, idle machine):
MUMPS LU forward 257.6 -> 153.8 s (1.68x), gradient 3.19 -> 2.66 s (1.20x); GAMG forward 94.9
-> 50.2 s (1.89x), gradient 14.6 -> 9.29 s (1.57x).
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")


def _parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cells", type=int, default=12, help="cells per side of the upper box")
    p.add_argument("--steps", type=int, default=8, help="BDF2 steps")
    p.add_argument("--dt", type=float, default=0.004, help="time step")
    p.add_argument(
        "--pc",
        choices=["lu", "gamg"],
        default="lu",
        help="Newton steps: MUMPS LU (adjoint: stored factors) or GMRES + GAMG (adjoint: GMRES)",
    )
    p.add_argument("--scene-steps", type=int, default=3, help="fig1 BDF1 steps (0: skip)")
    p.add_argument("--ranks", default=None, help="e.g. 1,2: one mpiexec run per rank count")
    p.add_argument("--project", type=int, default=64, help="ranks of the projection")
    p.add_argument("--bandwidth", type=float, default=5.0, help="GB/s of the projection")
    p.add_argument("--latency", type=float, default=5.0, help="us per collective step")
    return p.parse_args(argv)


FIG1 = (
    Path(os.environ.get("DIFFSOLIDS_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))
    / "diffipc"
    / "fig1_bunnies"
)


def bunnies_scene(comm, obstacle: str = "pool", steps: int = 3, stiffness: float | None = None):
    """Fig1 of the paper (run.json): a pool and two bunnies, the first thrown at (2, 0.5, 0) m/s.

    Args:
        comm: Communicator.
        obstacle: "pool" (the paper's flat-pool.msh, 195 vertices, 3.2 m edges) or "fine" (a
            slab under the bunnies with about as many vertices, 0.1-0.2 m edges).
        steps: BDF1 steps of dt = 0.05.
        stiffness: Barrier stiffness (default: :func:`suggest_barrier_stiffness`).

    Returns:
        (simulation, contact term).
    """
    from dolfinx import fem
    from mpi4py import MPI

    import diffsolids as ds
    from diffsolids.contact import ContactTerm, suggest_barrier_stiffness
    from diffsolids.mesh import combine_meshes, read_mesh
    from diffsolids.mesh.scene import simplex_box

    bunny = FIG1 / "stanford-bunny.obj_.msh"
    if obstacle == "pool":
        ground = read_mesh(FIG1 / "flat-pool.msh", MPI.COMM_SELF)
    else:
        ground = simplex_box([[-0.8, 0.05, -0.5], [1.6, 0.15, 0.5]], [20, 1, 8])
    meshes = [ground] + [
        read_mesh(bunny, MPI.COMM_SELF, scale=6.0, translation=t) for t in ([0, 0, 0], [1, 0, 0])
    ]
    domain = combine_meshes(comm, meshes)
    model = ds.Model(domain, ds.NeoHookean(E=1e6, nu=0.48, density=1240.0))
    model.add_gravity(9.81, axis=1)
    model.add_dirichlet(lambda x: x[1] < 0.17, 0.0)  # the ground (bunnies start at y > 0.199)
    integ = ds.BDF(1, 0.05, steps)
    if stiffness is None:
        stiffness = suggest_barrier_stiffness(ContactTerm(model, dhat=1e-3, stiffness=1.0), integ)
    contact = ContactTerm(model, dhat=1e-3, stiffness=stiffness)
    model.add_numeric_term(contact)
    v0 = fem.Function(model.V)
    thrown = model.V.dofmap.list[domain.cell_tags.find(2)]
    v0.x.array.reshape(-1, 3)[thrown] = [2.0, 0.5, 0.0]
    return ds.Simulation(model, integ, ds.SolverOptions(rtol=1e-8), v0=v0.x.array), contact


def newton_cost(comm, obstacle: str, steps: int, stiffness: float | None = None) -> dict:
    """Seconds per Newton iteration and contact pattern pairs of :func:`bunnies_scene`."""
    import numpy as np
    from petsc4py import PETSc

    from diffsolids.states import Phase, StepContext

    sim, contact = bunnies_scene(comm, obstacle, steps, stiffness)
    t0, c0 = time.perf_counter(), time.process_time()
    traj = sim.run()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    its = max(traj.newton_iterations(), 1)
    surf = contact.surface
    nv = surf.num_vertices
    free = ~surf.static
    pairs, free_pairs = [], []
    for i in range(1, steps + 1):  # each step's pattern again, as the run made it
        contact.begin_step(StepContext.of(sim.integrator, i, traj, Phase.BACKWARD))
        a, b = np.divmod(contact.pattern.reach(contact._step), nv)
        pairs.append(int(np.count_nonzero(a < b)))
        free_pairs.append(int(np.count_nonzero((a < b) & free[a] & free[b])))
    patterns = sim.solver.patterns
    return {
        "stiffness": contact.stiffness,
        "dofs": sim.model.V.dofmap.index_map.size_global * 3,
        "surface_vertices": nv,
        "surface_vertex_pairs": nv * (nv - 1) // 2,
        "newton_iterations": [r.iterations for r in traj.records],
        "newton_s": wall / its,
        "newton_cpu_s": cpu / its,
        "pattern_pairs": max(pairs),
        "pattern_pairs_per_step": pairs,
        "pattern_free_pairs": max(free_pairs),
        "pattern_check_s": patterns.seconds / its,
        "pattern_misses": getattr(patterns, "misses", None),
        "pattern_rebuilds": patterns.rebuilds,
        "matrix_nonzeros": int(sim.solver.A.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)["nz_used"]),
        "contact_s": {k: v["seconds"] for k, v in contact.timing_summary().items()},
    }


def _per_rank(comm, contact, its: int) -> list[dict]:
    """Each rank's contact timers, partition counts and repeated parts (gathered to all)."""
    from diffsolids.parallel import collective_comm

    ev = contact._eval
    mine = {
        "contact_ms_per_newton_iteration": {
            k: 1e3 * v["seconds"] / its for k, v in contact.timing_summary().items()
        },
        "contact_cpu_ms_per_newton_iteration": {
            k: 1e3 * v["cpu_seconds"] / its for k, v in contact.timing_summary().items()
        },
        "counts": dict(contact.partition.counts),
        "partition_ms_per_newton_iteration": {
            k: 1e3 * v[0] / its for k, v in contact.partition.timings.items()
        },
        "partition_cpu_ms_per_newton_iteration": {
            k: 1e3 * v[2] / its for k, v in contact.partition.timings.items()
        },
        "collisions_last": len(ev.collisions) if ev is not None else 0,
    }
    return collective_comm(comm).allgather(mine)


def _ranks_driver(args, argv) -> dict:
    """Run the benchmark under ``mpiexec -n k`` for each k of ``--ranks``; speedups, projection."""
    import math
    import subprocess

    counts = [int(k) for k in args.ranks.split(",")]
    passed, skip = [], False
    for a in argv:  # the same arguments, without the driver's own
        if skip:
            skip = False
            continue
        if a in ("--ranks", "--project", "--bandwidth", "--latency", "--scene-steps"):
            skip = True
            continue
        if a.split("=")[0] in ("--ranks", "--project", "--bandwidth", "--latency", "--scene-steps"):
            continue
        passed.append(a)
    mpiexec = Path(sys.executable).with_name("mpiexec")
    launcher = str(mpiexec) if mpiexec.exists() else "mpiexec"
    # a small untimed run first: every measured run then finds its kernels in the JIT cache
    warm = [launcher, "-n", "1", sys.executable, __file__, "--cells", "4", "--steps", "2"]
    subprocess.run([*warm, "--scene-steps", "0"], capture_output=True, text=True, check=True)
    runs = {}
    for k in counts:
        cmd = [launcher, "-n", str(k), sys.executable]
        cmd += [__file__, *passed, "--scene-steps", "0"]
        t0 = time.perf_counter()
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        runs[k] = json.loads(out.strip().splitlines()[-1])
        runs[k]["session_wall_s"] = time.perf_counter() - t0
        print(
            f"ranks {k}: forward {runs[k]['forward_seconds']:.2f} s, gradient "
            f"{runs[k]['gradient_seconds']:.2f} s",
            flush=True,
        )

    def contact_ms(r, cpu=False):
        key = "contact_cpu_ms_per_newton_iteration" if cpu else "contact_ms_per_newton_iteration"
        return max(sum(p[key].values()) for p in r["per_rank"])  # the slowest rank

    base = runs[counts[0]]
    summary = {"benchmark": "contact_ranks", "ranks": counts, "runs": runs}
    for k in counts[1:]:
        r = runs[k]
        summary[f"speedup_{k}"] = {
            "forward": base["forward_seconds"] / r["forward_seconds"],
            "gradient": base["gradient_seconds"] / r["gradient_seconds"],
            "newton_iteration": base["ms_per_newton_iteration"] / r["ms_per_newton_iteration"],
            "contact_wall": contact_ms(base) / contact_ms(r),
            "contact_cpu": contact_ms(base, True) / contact_ms(r, True),
        }
    # projection of the contact part of a Newton iteration to P ranks (CPU times of the serial
    # run; the share's cost per collision from the run on the most ranks)
    ser = base["per_rank"][0]
    evals = max(ser["counts"]["evaluations"], 1)
    its = base["newton_iterations"]
    kept = ser["counts"]["collisions"] / its  # collisions evaluated per Newton iteration
    repeated = {"gather", "reach_pattern", "pattern", "build", "ccd", "ccd_obstacles"}
    forward = {k: v for k, v in ser["contact_cpu_ms_per_newton_iteration"].items()}
    forward = {k: v for k, v in forward.items() if not k.startswith("adjoint_")}
    rep_ms = sum(v for k, v in forward.items() if k in repeated)
    dist_ms = sum(forward.values()) - rep_ms
    per_collision_us = 1e3 * dist_ms / max(kept, 1)
    top = runs[counts[-1]]
    share_ms = max(
        p["partition_cpu_ms_per_newton_iteration"].get("share", 0.0) for p in top["per_rank"]
    )
    share_us = 1e3 * share_ms / max(kept, 1)  # per collision of the whole set
    vec_mb = base["surface_vector_bytes"] / 1e6
    # per Newton iteration: a gather and ~3 reduced vectors (gradient, line-search gradients)
    vectors = 4.0 * evals / its
    P = args.project

    def comm_ms(p):
        if p == 1:
            return 0.0
        steps = math.ceil(math.log2(p))
        return vectors * (steps * args.latency * 1e-3 + 2.0 * vec_mb / args.bandwidth)

    def contact_at(p):
        return dist_ms / p + rep_ms + (share_us * kept * 1e-3 if p > 1 else 0.0) + comm_ms(p)

    summary["projection"] = {
        "ranks": P,
        "per_collision_us": per_collision_us,
        "share_us_per_collision": share_us,
        "collisions_per_newton_iteration": kept,
        "distributed_cpu_ms_serial": dist_ms,
        "replicated_cpu_ms": rep_ms,
        "communication_ms": comm_ms(P),
        "contact_ms_serial": dist_ms + rep_ms,
        "contact_ms_projected": contact_at(P),
        "contact_speedup_projected": (dist_ms + rep_ms) / contact_at(P),
        "contact_speedup_limit": (dist_ms + rep_ms) / (rep_ms + share_us * kept * 1e-3),
        "strong_scaling_contact_ms": {p: contact_at(p) for p in (1, 2, 4, 8, 16, 32, 64)},
        "assumptions": f"{args.bandwidth} GB/s, {args.latency} us per collective step, "
        f"{vectors:.1f} surface vectors per Newton iteration; collision set build, CCD, gather "
        "and reach pattern replicated on every rank; forward contact timers only",
    }
    from diffsolids.parallel import peak_rss_mb

    summary["peak_rss_mb"] = peak_rss_mb()  # this process's
    print(json.dumps(summary))
    return summary


def main(argv=None) -> dict:
    """Run the benchmark and return the numbers."""
    args = _parse(argv)
    if args.ranks:
        return _ranks_driver(args, list(sys.argv[1:] if argv is None else argv))
    import ipctk
    import numpy as np
    import ufl
    from mpi4py import MPI
    from petsc4py import PETSc

    import diffsolids as ds
    from diffsolids.controls import FrictionControl, ParameterControl, ShapeControl
    from diffsolids.objectives import Integral, final_value, time_integral
    from diffsolids.reduced_functional import ReducedFunctional
    from diffsolids.solvers.sparsity import matrix_with_pattern

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: contact_checks
    from contact_checks import box_falling_on_box

    comm = MPI.COMM_WORLD
    n = args.cells
    dhat = 1e-3
    cells = ([2 * n, 2 * n, max(2, n // 4)], [n, n, max(2, n // 2)])
    model, contact, v0 = box_falling_on_box(comm, dhat, *cells, 1e12, [0.0, 0.0, -0.5])
    integ = ds.BDF(2, args.dt, args.steps)
    petsc_options = {} if args.pc == "lu" else {"pc_type": args.pc}
    sim = ds.Simulation(
        model, integ, ds.SolverOptions(rtol=1e-8, petsc_options=petsc_options), v0=v0
    )
    solver = sim.solver
    density = model.coefficients["density"]
    objective = final_value(Integral(lambda f: (f.X[2] + f.u[2]) * f.dx(2), "height")) + (
        time_integral(Integral(lambda f: 0.5 * density * ufl.dot(f.v, f.v) * f.dx(2), "kinetic"))
    )
    controls = [
        ShapeControl(model, "all"),
        ParameterControl(model, "E", "field", log=True),
        FrictionControl(contact),
    ]
    rf = ReducedFunctional(sim, objective, controls)  # keeps each step's factors for the adjoint
    q0 = rf.initial_parameters()

    t0, c0 = time.perf_counter(), time.process_time()
    rf.forward(q0)
    total, total_cpu = time.perf_counter() - t0, time.process_time() - c0
    traj = rf.trajectory
    its = max(traj.newton_iterations(), 1)
    timings = contact.timing_summary()
    per_iteration = {k: 1e3 * v["seconds"] / its for k, v in timings.items()}
    per_iteration_cpu = {k: 1e3 * v["cpu_seconds"] / its for k, v in timings.items()}
    pattern_check_ms = 1e3 * solver.patterns.seconds / its
    contact_ms = sum(per_iteration.values()) + pattern_check_ms
    contact_cpu_ms = sum(per_iteration_cpu.values())

    # FE Jacobian assembly at the final state, for scale
    t0 = time.perf_counter()
    solver.assemble_jacobian(solver.A)
    fe_jacobian_ms = 1e3 * (time.perf_counter() - t0)

    # a pattern change: rebuild with the union pattern; symbolic+numeric vs numeric-only LU
    A = solver.A
    indptr, cols, _ = A.getValuesCSR()
    rstart, rend = A.getOwnershipRange()
    N = A.getSize()[1]
    rows = np.repeat(np.arange(rstart, rend, dtype=np.int64), np.diff(indptr))
    keys = rows * N + cols.astype(np.int64)
    t0 = time.perf_counter()
    B = matrix_with_pattern(A, keys)
    rebuild_ms = 1e3 * (time.perf_counter() - t0)
    A.copy(B, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)

    def factor_ms(M, ksp=None):
        ksp = ksp or PETSc.KSP().create(comm)
        ksp.setOperators(M)
        ksp.setType("preonly")
        ksp.getPC().setType("lu")
        ksp.getPC().setFactorSolverType("mumps")
        t = time.perf_counter()
        ksp.setUp()
        return 1e3 * (time.perf_counter() - t), ksp

    symbolic_ms, ksp = factor_ms(B)
    B.scale(1.0 + 1e-12)  # same pattern, new values
    numeric_ms, _ = factor_ms(B, ksp)

    # narrow phases on one flat-on-flat Newton step of the final state
    surf = contact.surface
    x0 = surf.rest_positions + surf.gather(traj.u[-1])
    x1 = x0.copy()
    x1[:, 2] -= np.where(surf.body == 2, 2 * dhat, 0.0)
    ccd = {}
    for name, narrow in (
        ("additive", ipctk.AdditiveCCD()),
        ("tight_inclusion_1e-6_1000", ipctk.TightInclusionCCD(1e-6, 1000)),
    ):
        t = time.perf_counter()
        toi = ipctk.compute_collision_free_stepsize(
            surf.mesh, np.asfortranarray(x0), np.asfortranarray(x1), 0.0, ipctk.LBVH(), narrow
        )
        ccd[name] = {"ms": 1e3 * (time.perf_counter() - t), "toi": toi}

    # adjoint gradient (shape, E field, friction) on a warm JIT cache
    rf.derivative()  # compiles the adjoint forms
    before = contact.timing_summary()
    t0, c0 = time.perf_counter(), time.process_time()
    gradient = rf.derivative()
    gradient_s, gradient_cpu = time.perf_counter() - t0, time.process_time() - c0
    after = contact.timing_summary()
    adjoint_contact_ms = {
        k: 1e3 * (v["seconds"] - before.get(k, {"seconds": 0.0})["seconds"]) / args.steps
        for k, v in after.items()
        if v["seconds"] > before.get(k, {"seconds": 0.0})["seconds"]
    }
    # the contact adjoint kernels (their own timers; the evaluations they trigger are inside)
    kernels_s = (
        1e-3
        * args.steps
        * sum(v for k, v in adjoint_contact_ms.items() if k.startswith("adjoint_"))
    )

    result = {
        "benchmark": "contact",
        "ranks": comm.size,
        "pc": args.pc,
        "dofs": model.V.dofmap.index_map.size_global * 3,
        "surface_vertices": surf.num_vertices,
        "active_pairs_last": contact.records[-1].num_collisions,
        "steps": args.steps,
        "newton_iterations": its,
        "seconds_total": total,
        "ms_per_newton_iteration": 1e3 * total / its,
        "cpu_ms_per_newton_iteration": 1e3 * total_cpu / its,
        "contact_ms_per_newton_iteration": per_iteration,
        "contact_cpu_ms_per_newton_iteration": per_iteration_cpu,
        "contact_ms_per_call": {k: v["mean_ms"] for k, v in timings.items()},
        "fe_jacobian_assembly_ms": fe_jacobian_ms,
        "pattern_rebuilds": solver.patterns.rebuilds,
        "pattern_check_ms_per_newton_iteration": pattern_check_ms,
        "contact_share": contact_ms / (1e3 * total / its),
        "contact_share_cpu": contact_cpu_ms / (1e3 * total_cpu / its),
        "pattern_rebuild_seconds_total": solver.patterns.rebuild_seconds,
        "matrix_rebuild_ms": rebuild_ms,
        "lu_symbolic_plus_numeric_ms": symbolic_ms,
        "lu_numeric_only_ms": numeric_ms,
        "projected_newton_steps": solver.projected_steps,
        "ccd_flat_on_flat": ccd,
        "min_distance_over_dhat_last": contact.records[-1].min_distance / dhat,
        "gradient_parameters": int(gradient.size),
        "forward_seconds": total,
        "gradient_seconds": gradient_s,
        "ratio": gradient_s / total,
        "ratio_cpu": gradient_cpu / total_cpu,
        "adjoint_contact_ms_per_step": adjoint_contact_ms,
        "adjoint_shape_s_per_step": adjoint_contact_ms.get("adjoint_shape", 0.0) / 1e3,
        "adjoint_contact_kernels_seconds": kernels_s,
        "adjoint_contact_kernels_share": kernels_s / gradient_s,
        "adjoint_stats": {k: v for k, v in rf.adjoint_stats.items() if k != "krylov_per_step"},
    }
    result["per_rank"] = _per_rank(comm, contact, its)
    result["collisions_per_rank_last"] = [r["collisions_last"] for r in result["per_rank"]]
    result["contact_evaluations"] = result["per_rank"][0]["counts"]["evaluations"]
    result["surface_vector_bytes"] = surf.num_vertices * 3 * 8
    if args.scene_steps > 0 and FIG1.is_dir():  # fig1: a coarse pool, then a fine slab
        coarse = newton_cost(comm, "pool", args.scene_steps)
        fine = newton_cost(comm, "fine", args.scene_steps, coarse["stiffness"])
        result.update({f"coarse_obstacle_{k}": v for k, v in coarse.items()})
        result.update({f"fine_obstacle_{k}": v for k, v in fine.items()})
    if comm.rank == 0:
        from diffsolids.parallel import peak_rss_mb

        result["peak_rss_mb"] = peak_rss_mb()  # this process's
        print(json.dumps(result))
    return result


if __name__ == "__main__":
    import diffsolids  # noqa: F401  (loads the MPI of the PyPI DOLFINx wheel first)

    main(sys.argv[1:])
