"""Smoothness benchmark: is the contact forward a smooth function of its parameters?

Per scene (``tests/smoothness_scenes.py``; the paper's sliding bunny and throw when the data is
present), with the default solver options: J on ``--points`` points of a line through q0
(a random unit direction), the number of jumps (a sample off its neighbours' mean by more
than 5% of J's range, ``diffsolids.line_scan``) and the worst deviation, the central
differences of the gradient at three step sizes along the random direction and along the
gradient (relative errors), and the Newton iterations per contact step of the run at q0 (max
and mean over the steps with contact pairs). For the drop: J and the final state on grounds
of 1, 2 and 4 coplanar triangles (their largest difference).

Run ``python tests/benchmarks/bench_smoothness.py [--scenes drop slide] [--points 41]``. The
last line printed is a JSON object with the numbers. PolyFEM's Newton iterations per step
(the paper's Table 4) for comparison: puzzle 4.6, kangaroo 4.5, throw 15.3, sliding bunny 70.
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")
TESTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS))
DATA = Path(os.environ.get("DIFFSOLIDS_DATA", TESTS.parents[1] / "shared" / "data")) / "diffipc"


def _parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--scenes",
        nargs="+",
        default=[
            "drop",
            "drop_2d",
            "slide",
            "wavy",
            "roll",
            "ridge",
            "ridge_free",
            "damping",
            "damping_polyfem",
            "sliding_bunny",
            "throw",
            "throw_reference",
        ],
        help="scenes to scan",
    )
    p.add_argument("--points", type=int, default=41, help="points of each line scan")
    p.add_argument(
        "--formulation",
        default="ipc",
        choices=["ipc", "convergent"],
        help="contact formulation of the drop, 2D drop, slide and wavy (default: the library's)",
    )
    p.add_argument("--bunny-steps", type=int, default=5, help="steps of the sliding bunny")
    p.add_argument("--throw-steps", type=int, default=3, help="steps of the throw")
    return p.parse_args(argv)


def paper_scene(name: str, args):
    """The sliding bunny (mu) or the throw (v0; with its run at q0 as the branch reference of
    every forward: ``throw_reference``) as a smoothness Scene, or None without the data."""
    from demo_modules import load_demo
    from mpi4py import MPI
    from smoothness_scenes import Scene

    if name == "sliding_bunny":
        demo = load_demo("paper_sliding_bunny")
        if not (DATA / demo.FOLDER / "opt.json").is_file():
            return None
        _, problem = demo.friction_problem(
            DATA, MPI.COMM_WORLD, args.bunny_steps, follow_branch=True
        )
        # radius 0.005 in mu at mu = 0.5 (0.01 in log mu)
        return Scene(problem.rf, problem.q0, 0.005, problem.contact)
    demo = load_demo("paper_throw_bunnies")
    if not (DATA / demo.FOLDER / "opt.json").is_file():
        return None
    if name == "throw_reference":  # the run at q0 as every forward's branch reference
        from paper_common import polyfem_problem

        _, problem = polyfem_problem(
            DATA,
            MPI.COMM_WORLD,
            demo.FOLDER,
            args.throw_steps,
            contact_options={"area_weighting": True},
            follow_branch=True,
        )
    else:
        _, problem = demo.throw_problem(DATA, MPI.COMM_WORLD, args.throw_steps)
    return Scene(problem.rf, problem.q0, 0.01, problem.contact)


def contact_iterations(scene) -> dict:
    """Newton iterations of the steps with contact pairs in the last run, and its precision.

    ``round_off_steps``: the steps that ended at round-off with a residual above 1e-7 f_char
    (the Simulation's warning), the largest of those residuals over f_char.
    """
    records = scene.rf.trajectory.records
    reference = scene.rf.reference_run
    if reference is not None and not any(r.iterations for r in records):
        records = reference.records  # the run at q0 is the reference: its own solve's counts
    pairs = [r.num_collisions for r in scene.contact.records]
    its = [rec.iterations for rec, n in zip(records, pairs, strict=True) if n > 0]
    solver = scene.rf.simulation.solver
    round_off = [r / f for _, r, _, f in solver.reported_round_off_steps()]
    return {
        "contact_steps": len(its),
        "max_iterations": max(its, default=0),
        "mean_iterations": float(np.mean(its)) if its else 0.0,
        "round_off_steps": len(round_off),
        "round_off_worst_relative_residual": max(round_off, default=0.0),
    }


def measure(scene, points: int, seed: int = 7) -> dict:
    """Line scan, central differences and Newton iterations of one scene."""
    import diffsolids as ds

    rng = np.random.default_rng(seed)
    q0 = scene.q0
    t0 = time.perf_counter()
    J0, g = scene.rf.value_and_gradient(q0)
    forward_gradient = time.perf_counter() - t0
    out = {"parameters": len(q0), "J": J0, **contact_iterations(scene)}
    direction = rng.standard_normal(len(q0))
    direction /= np.linalg.norm(direction)
    scan = ds.line_scan(scene.rf, q0, direction, scene.radius, points)
    out.update(
        jumps=len(scan.jumps),
        worst_deviation=float(scan.deviations.max()),
        J_range=scan.value_range,
    )
    steps = scene.radius * np.array([0.1, 0.01, 0.001])
    for label, d in (("random", direction), ("gradient", g / np.linalg.norm(g))):
        fd = ds.finite_difference_check(scene.rf, q0, d, steps=steps, gradient=g)
        out[f"fd_errors_{label}"] = [float(e) for e in fd.relative_errors]
    out["forward_and_gradient_s"] = forward_gradient
    return out


def drop_triangulations(formulation: str) -> dict:
    """J and the final state of the drop on grounds of 1, 2 and 4 coplanar triangles."""
    from smoothness_scenes import drop

    values, states, its = {}, {}, {}
    for triangles in (1, 2, 4):
        scene = drop(triangles, formulation=formulation)
        values[triangles] = scene.rf(scene.q0)
        states[triangles] = scene.rf.trajectory.u[-1].copy()
        its[triangles] = contact_iterations(scene)
    diff = max(float(np.abs(states[k] - states[1]).max()) for k in (2, 4))
    return {
        "J_by_triangles": {str(k): v for k, v in values.items()},
        "final_state_difference_m": diff,
        "iterations_by_triangles": {str(k): v for k, v in its.items()},
    }


def main(argv=None) -> dict:
    from mpi4py import MPI
    from smoothness_scenes import SCENES

    args = _parse(argv)
    comm = MPI.COMM_WORLD
    out = {"points": args.points, "formulation": args.formulation}
    for name in args.scenes:
        t0 = time.perf_counter()
        if name in SCENES:
            scene = SCENES[name](formulation=args.formulation)
        else:
            scene = paper_scene(name, args)
        if scene is None:
            continue
        result = measure(scene, args.points)
        if name == "drop":
            result["triangulations"] = drop_triangulations(args.formulation)
        result["seconds"] = time.perf_counter() - t0
        out[name] = result
        if comm.rank == 0:
            print(
                f"{name}: {result['jumps']} jumps (worst {result['worst_deviation']:.2e} of the "
                f"range), central differences random {result['fd_errors_random']}, gradient "
                f"{result['fd_errors_gradient']}, Newton its per contact step max "
                f"{result['max_iterations']} mean {result['mean_iterations']:.1f}, "
                f"{result['round_off_steps']} steps ended at round-off (worst residual "
                f"{result['round_off_worst_relative_residual']:.2g} f_char) "
                f"({result['seconds']:.0f} s)",
                flush=True,
            )
    if comm.rank == 0:
        from diffsolids.parallel import peak_rss_mb

        out["peak_rss_mb"] = peak_rss_mb()  # this process's
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
