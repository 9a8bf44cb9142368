"""The paper's experiments on the paper's data, timed next to the paper's Table 4.

Scenes read from their PolyFEM JSON (``diffsolids.polyfem.scene``; data in
``$DIFFSOLIDS_DATA/diffipc`` or ``--data``), each with the paper's objective and control:

- ``puzzle`` (Fig. 14): run-new.json, 30 BDF1 steps, 740 dofs; the piece's initial velocity;
  10 x the uniform time integral of int_Gamma1 |u - u_target|^2 ds (target: target-new.json).
- ``kangaroo`` (Fig. 20): run-new.json, 60 steps, 462 dofs; log E and nu of the kangaroo; the
  same objective (target: target-new.json).
- ``throw`` (Fig. 1, 3D): run.json, pool + two bunnies, 6 183 dofs; the thrown bunny's initial
  velocity; the squared distance of the second bunny's final centre of mass (x, z) to
  (3.67854, 0.137261). ``--throw-steps`` of the paper's 40 (default 8: a partial run; the
  per-Newton-iteration cost is what it measures; 0 skips it).
- ``sliding_bunny`` (Fig. 21, 3D): run-new.json, the bunny on a slide (a kinematic obstacle),
  2 799 dofs; opt.json's problem as the demo builds it (``paper_sliding_bunny.
  friction_problem``: mu; 100 |c(T) - c_target(T)|^2, target at mu = 0.1) over
  ``--sliding-steps`` of the paper's 40 (default 10, the demo's default; 0 skips it).

Per scene: forward seconds (wall and process CPU: the machine is shared; the objective's forward
run at the scene's parameters, on a warm JIT cache), Newton iterations, seconds per Newton
iteration, the Newton matrix's entries (the contact pattern's size), its rebuilds and the Newton
solves restarted for missing entries, gradient seconds (the adjoint sweep; its first call, and
``repeat_*``: forward and gradient again at a neighbouring q, as in an optimisation, without the
sweep's one-time set-up; wall and CPU seconds), gradient / forward (wall and CPU), the gradients
themselves (to compare two versions), the paper's Table 4 solve and gradient seconds, where the
gradient goes (``gradient_phases_s``: the sweep's objective partials, linear solves, pushes into
earlier steps, parameter partials and the rest; its Krylov iterations and factorisations;
``gradient_contact_s``: the contact term's timers in the sweep, (wall s, CPU s, calls)), and the
top entries of a cProfile of forward + gradient (``--profile``; clocked by the thread's CPU
time, so work in other threads, e.g. TBB's in ipctk, is not in it). The barrier stiffness is
``suggest_barrier_stiffness``'s (``--kappa scene``: the scenes' 1e5 as PolyFEM means it).

Run ``python tests/benchmarks/bench_paper.py [--scenes puzzle kangaroo throw]``. The last line
printed is a JSON object with the numbers.
"""

import argparse
import cProfile
import io
import json
import os
import pstats
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[2]
TABLE4 = {  # the paper's Table 4: solve / gradient seconds
    "puzzle": (1.5877, 0.2129),
    "kangaroo": (1.6704, 0.1624),
    "sliding_bunny": (547.36, 1.6478),
    "throw": (209.30, 4.3731),
}
# PolyFEM's Newton iterations per step (the paper's Table 4: all Newton iterations over all
# Newton solves of the optimisation's forward runs, free-flight steps included)
TABLE4_NEWTON_PER_STEP = {"puzzle": 4.6, "kangaroo": 4.5, "throw": 15.3, "sliding_bunny": 70.0}
FOLDERS = {
    "puzzle": "fig14_puzzle_piece",
    "kangaroo": "fig20_kangaroo",
    "throw": "fig1_bunnies",
    "sliding_bunny": "fig21_friction_bunny",
}
FACTOR_MEMORY_MB = 1000.0  # per rank, for the 2D scenes' stored forward factorisations


def _parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["puzzle", "kangaroo", "throw", "sliding_bunny"])
    p.add_argument("--data", type=Path, default=None, help="folder of the paper's scene data")
    p.add_argument("--kappa", default="suggest", help="'suggest', 'scene' or a number")
    p.add_argument("--throw-steps", type=int, default=8, help="BDF1 steps of fig1 (paper: 40)")
    p.add_argument("--sliding-steps", type=int, default=10, help="steps of fig21 (paper: 40)")
    p.add_argument("--profile", action="store_true", help="cProfile forward + gradient")
    p.add_argument("--top", type=int, default=8, help="profile entries printed")
    return p.parse_args(argv)


def build(name: str, data: Path, kappa, steps: int | None, comm):
    """(ReducedFunctional, q) of a scene with its paper objective and control."""
    import numpy as np
    from paper_common import build as build_scene
    from paper_common import experiment, scenes, target_objective

    from diffsolids.controls import ControlSet, ParameterControl, RigidVelocity
    from diffsolids.reduced_functional import ReducedFunctional

    if name == "sliding_bunny":
        from paper_sliding_bunny import friction_problem

        _, problem = friction_problem(data, comm, steps, kappa)
        return problem.rf, problem.q0, problem.simulation
    if name == "throw":
        # the demo's problem (paper_throw_bunnies.throw_problem): opt.json through the runner,
        # area-weighted pairs (with PolyFEM's unweighted pairs the suggested kappa is 3.9e13)
        from paper_throw_bunnies import throw_problem

        _, problem = throw_problem(data, comm, steps, kappa)
        return problem.rf, problem.q0, problem.simulation
    path, opt = experiment(data, FOLDERS[name])
    run, target = scenes(path, opt)
    model, _contact, sim = build_scene(run, comm, steps, kappa)
    if name == "puzzle":
        controls = RigidVelocity(sim, 1, angular=False)
        truth = np.array(target.initial_velocity[0].value)
        q = np.array(run.initial_velocity[0].value)
    else:
        controls = [
            ParameterControl(model, "E", "bodies", [1], log=True),
            ParameterControl(model, "nu", "bodies", [1]),
        ]
        truth = np.array([np.log(target.materials[1].E), target.materials[1].nu])
        q = np.array([np.log(run.materials[1].E), run.materials[1].nu])
    # a fixed budget for the forward's factorisations (the default, the node's spare memory,
    # keeps none when other jobs fill the node: the adjoint then refactorises, measured 21
    # factorisations and 546 Krylov iterations instead of 1 and 96 on the puzzle, 0.47 instead
    # of 0.14 of the forward)
    ControlSet(controls, sim).assign(truth)
    target = sim.run()
    rf = ReducedFunctional(
        sim, target_objective(sim, opt, target), controls, factor_memory_mb=FACTOR_MEMORY_MB
    )
    return rf, q, sim


def measure(name: str, args, comm) -> dict:
    """Forward and gradient seconds of one scene (after an untimed warm-up of 2 steps)."""
    from diffsolids.contact import ContactTerm

    steps = {"throw": args.throw_steps, "sliding_bunny": args.sliding_steps}.get(name)
    warm, q_warm, _ = build(name, args.data, args.kappa, 2, comm)
    warm(q_warm)
    warm.gradient(q_warm)
    rf, q, sim = build(name, args.data, args.kappa, steps, comm)
    # CPU time of this thread as the profiler's clock: on a loaded machine a wall-clock profile
    # charges the time spent waiting for a core to whatever runs when the process is descheduled
    # (system calls above all: time.process_time showed 8 of 18 s in a kangaroo profile)
    profiler = cProfile.Profile(time.thread_time) if args.profile else None
    if profiler:
        profiler.enable()
    t0, c0 = time.perf_counter(), time.process_time()
    J = rf(q)
    forward, forward_cpu = time.perf_counter() - t0, time.process_time() - c0
    contact = next(t for t in sim.model.numeric_terms if isinstance(t, ContactTerm))
    per_step = [r.iterations for r in rf.trajectory.records]
    if rf.reference_run is not None:  # this forward solved the reference run first
        reference = [r.iterations for r in rf.reference_run.records]
        per_step = [a + b for a, b in zip(per_step, reference, strict=True)]
    its = sum(per_step)
    in_contact = [n for n, c in zip(per_step, contact.records, strict=True) if c.num_collisions]
    in_contact = in_contact or per_step
    # steps that ended at round-off above 1e-7 f_char: the precision of this J
    round_off = [r / f for _, r, _, f in sim.solver.reported_round_off_steps()]
    contact.timings.clear()  # from here: the contact work of the gradient only
    t0, c0 = time.perf_counter(), time.process_time()
    g = rf.gradient(q)
    gradient, gradient_cpu = time.perf_counter() - t0, time.process_time() - c0
    stats = rf.adjoint_stats
    store = rf.factor_store
    timers = contact.timing_summary()
    if profiler:
        profiler.disable()
    # the same again at a neighbouring q (a new forward run): the gradient as in an
    # optimisation, without the sweep's one-time set-up (its adjoint forms, the KSPs)
    q2 = q * (1.0 + 1e-9)
    t0, c0 = time.perf_counter(), time.process_time()
    rf(q2)
    forward2, forward2_cpu = time.perf_counter() - t0, time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    g2 = rf.gradient(q2)
    gradient2, gradient2_cpu = time.perf_counter() - t0, time.process_time() - c0
    paper_solve, paper_grad = TABLE4[name]
    out = {
        "dofs": sim.model.V.dofmap.index_map.size_global * sim.model.dim,
        "steps": sim.integrator.num_steps,
        "kappa": contact.stiffness,
        "objective": float(J),
        "gradient_norm": float((g @ g) ** 0.5),
        "gradient": [float(x) for x in g],  # to compare gradients before/after a change
        "repeat_gradient": [float(x) for x in g2],
        "forward_s": forward,
        "forward_cpu_s": forward_cpu,
        "newton_iterations": its,
        # per step with contact pairs (this rank's count), next to PolyFEM's per-step mean
        "newton_per_contact_step_max": max(in_contact),
        "newton_per_contact_step_mean": sum(in_contact) / len(in_contact),
        "paper_newton_per_step": TABLE4_NEWTON_PER_STEP[name],
        "round_off_steps": len(round_off),
        "round_off_worst_relative_residual": max(round_off, default=0.0),
        # Table 4's own measure: all Newton iterations over all steps (free flight included)
        "newton_per_step_mean": its / sim.integrator.num_steps,
        "s_per_newton_iteration": forward / max(its, 1),
        "gradient_s": gradient,
        "gradient_cpu_s": gradient_cpu,
        "gradient_over_forward": gradient / forward,
        "gradient_over_forward_cpu": gradient_cpu / forward_cpu,
        "repeat_forward_s": forward2,
        "repeat_forward_cpu_s": forward2_cpu,
        "repeat_gradient_s": gradient2,
        "repeat_gradient_cpu_s": gradient2_cpu,
        "repeat_gradient_over_forward": gradient2 / forward2,
        "repeat_gradient_over_forward_cpu": gradient2_cpu / forward2_cpu,
        "paper_solve_s": paper_solve,
        "paper_gradient_s": paper_grad,
        "forward_over_paper": forward / paper_solve,
        # where the gradient goes: the sweep's phases (wall s), its Krylov iterations and LU
        # factorisations, and the contact term's operations in it (wall and CPU s)
        "gradient_phases_s": {k: round(v, 4) for k, v in stats["phase_seconds"].items()},
        "gradient_krylov_iterations": stats.get("krylov_iterations"),
        "gradient_factorisations": stats.get("factorisations"),
        "forward_factors_kept": None if store is None else len(store.factors),
        # the Newton matrix at the end of the run: its entries (the contact pattern's size),
        # its rebuilds and the Newton solves restarted for missing entries
        "matrix_nonzeros": int(sim.solver.A.getInfo()["nz_used"]),
        "pattern_rebuilds": sim.solver.patterns.rebuilds,
        "pattern_misses": sim.solver.patterns.misses,
        "gradient_contact_s": {
            k: (round(v["seconds"], 4), round(v["cpu_seconds"], 4), v["calls"])
            for k, v in sorted(timers.items(), key=lambda kv: -kv[1]["seconds"])
        },
    }
    if profiler and comm.rank == 0:
        stream = io.StringIO()
        stats = pstats.Stats(profiler, stream=stream).sort_stats("tottime")
        stats.print_stats(args.top)
        print(f"--- {name}: cProfile (thread CPU time) of forward + gradient, by own time ---")
        print(stream.getvalue().split("ncalls", 1)[-1][:4000])
        total = sum(v[2] for v in stats.stats.values())
        top = sorted(stats.stats.items(), key=lambda kv: -kv[1][2])[: args.top]
        out["profile_top_own_s"] = {
            f"{Path(k[0]).name}:{k[1]}:{k[2]}": round(v[2], 3) for k, v in top
        }
        out["profile_total_s"] = total
    return out


def main(argv=None) -> dict:
    args = _parse(argv)
    sys.path.insert(0, str(ROOT / "demos"))
    from mpi4py import MPI
    from paper_common import DEFAULT_DATA

    args.data = args.data or DEFAULT_DATA
    comm = MPI.COMM_WORLD
    results = {}
    for name in args.scenes:
        if {"throw": args.throw_steps, "sliding_bunny": args.sliding_steps}.get(name) == 0:
            continue
        results[name] = measure(name, args, comm)
        if comm.rank == 0:
            r = results[name]
            print(
                f"{name}: {r['dofs']} dofs, {r['steps']} steps, forward {r['forward_s']:.2f} s "
                f"(CPU {r['forward_cpu_s']:.2f} s) "
                f"({r['newton_iterations']} Newton its, {r['s_per_newton_iteration']:.4f} s "
                f"each; per contact step max {r['newton_per_contact_step_max']} mean "
                f"{r['newton_per_contact_step_mean']:.1f}, PolyFEM {r['paper_newton_per_step']}), "
                f"gradient {r['gradient_s']:.3f} s ({r['gradient_over_forward']:.3f} "
                f"of forward; again at a neighbouring q: {r['repeat_gradient_s']:.3f} s, "
                f"{r['repeat_gradient_over_forward']:.3f}); "
                f"paper {r['paper_solve_s']} / {r['paper_gradient_s']} s; "
                f"{r['round_off_steps']} steps ended at round-off (worst residual "
                f"{r['round_off_worst_relative_residual']:.2g} f_char)",
                flush=True,
            )
    results["ranks"] = comm.size
    results["kappa_option"] = args.kappa
    if comm.rank == 0:
        from diffsolids.parallel import peak_rss_mb

        results["peak_rss_mb"] = peak_rss_mb()  # this process's
        print(json.dumps(results), flush=True)
    return results


if __name__ == "__main__":
    main()
