"""Gradient benchmark: adjoint cost relative to the forward solve, and its accuracy.

A 3D Neo-Hookean beam (box [0, 4] x [0, 0.5]^2, P1, about 30k dofs, the beam of
bench_forward.py) clamped at x = 0 sags under gravity: one static solve, and 50 BDF2 steps with
strain-rate damping. The objective is the L_4 norm of stress plus a target displacement of the
free end (time integrals for the dynamic run). For a DG0 Young's modulus field (log
parametrised, one parameter per cell) and for the shape (all vertices) we time the forward run
and the gradient with a warm JIT cache (each form compiled by an untimed first run) and report
gradient / forward in wall-clock and in CPU time (the latter is robust to other load on the
machine; everything runs single-threaded). The gradient is then compared with central finite
differences for a few parameters (those with the largest gradient entries, and a random
direction), with a tighter Newton tolerance and a sweep of steps (the dynamic check on a
shorter run, --fd-bdf-steps).

The shape partials of the adjoint have two paths (``diffsolids.adjoint.forms.SHAPE_PARTIALS``):
the explicit energy-momentum forms of the built-in terms and objectives ("auto", the default)
and UFL's coordinate derivative ("ufl", the reference). ``--shape-partials both`` (the default)
times the shape gradient of each path after the same forward runs (one sweep object each, the
same trajectory and factorisations) and the per-step cost of their shape-partial forms (CPU
seconds of packing the coefficients and of the kernels, best of ``--kernel-repeat``), and
reports their largest gradient difference; the shape ratio is that of "auto".

The first gradient of each control (a new ReducedFunctional: its forward run, kernel compilation
and adjoint sweep) is timed too. ``--cold`` points the kernel cache at an empty temporary
directory: the model set-up and each control's first gradient then compile their kernels, and
both are timed again with the kernels in the cache (a new model and a new ReducedFunctional).
The JSON reports cold and warm seconds of each, wall-clock and CPU (this process and the C
compiler it ran), and their difference summed over the run: the cost of a cold cache.

Run ``python tests/benchmarks/bench_gradient.py`` (``--help`` for options; ``--profile`` prints
a cProfile of one gradient). Works under ``mpiexec -n 2``. The last line printed is a JSON
object.
"""

import json
import os
import resource
import sys
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

from beam_args import beam_parser


def _parse(argv):
    p = beam_parser(__doc__.splitlines()[0], steps=50)
    p.add_argument("--rtol", type=float, default=1e-9, help="Newton tolerance of the timed runs")
    p.add_argument("--fd-rtol", type=float, default=1e-12, help="Newton tolerance of FD runs")
    p.add_argument("--fd-params", type=int, default=1, help="largest-gradient entries checked")
    p.add_argument(
        "--fd-sweep",
        type=int,
        default=5,
        help="FD step sizes per direction (10^-3, 10^-4, ... relative to (1 + |q|) / |dq|)",
    )
    p.add_argument(
        "--fd-bdf-steps",
        type=int,
        default=10,
        help="BDF2 steps of the dynamic FD check (0 skips it; the timed run uses --steps)",
    )
    p.add_argument(
        "--fd-dynamic-sweep", type=int, default=3, help="FD step sizes per direction (dynamic)"
    )
    p.add_argument("--repeat", type=int, default=2, help="timed repetitions (best is reported)")
    p.add_argument(
        "--factor-memory-mb",
        type=float,
        default=None,
        help="memory per rank for the forward factorisations kept in memory for the adjoint "
        "(ReducedFunctional; default: kept on disk, MUMPS out-of-core)",
    )
    p.add_argument(
        "--only", choices=["static", "dynamic"], default=None, help="run one scenario only"
    )
    p.add_argument(
        "--controls",
        nargs="+",
        choices=["E-field", "shape"],
        default=["E-field", "shape"],
        help="controls timed",
    )
    p.add_argument(
        "--shape-partials",
        choices=["auto", "ufl", "both"],
        default="both",
        help="adjoint shape-partial path(s) timed (both: 'auto' and the 'ufl' reference)",
    )
    p.add_argument(
        "--kernel-repeat", type=int, default=7, help="repetitions of the shape-form timings"
    )
    p.add_argument("--profile", action="store_true", help="cProfile one gradient per case")
    p.add_argument("--skip-fd", action="store_true", help="timings only")
    p.add_argument("--skip-timing", action="store_true", help="finite differences only")
    return p.parse_args(argv)


ARGS = _parse(sys.argv[1:])

import diffsolids as ds  # noqa: E402  (first: it loads the MPI library DOLFINx's wheel needs)

# isort: split
import cProfile  # noqa: E402
import functools  # noqa: E402
import io  # noqa: E402
import pstats  # noqa: E402
import shutil  # noqa: E402
from gc import collect as collect_garbage  # noqa: E402
from pathlib import Path  # noqa: E402

import dolfinx.jit  # noqa: E402
import numpy as np  # noqa: E402
from dolfinx import fem  # noqa: E402
from mpi4py import MPI  # noqa: E402

from diffsolids.adjoint import sweep as adjoint_sweep  # noqa: E402
from diffsolids.adjoint.forms import AdjointForms  # noqa: E402
from diffsolids.adjoint.sensitivities import Targets  # noqa: E402
from diffsolids.controls import ParameterControl, ShapeControl  # noqa: E402
from diffsolids.mesh import create_box  # noqa: E402
from diffsolids.objectives import (  # noqa: E402
    final_value,
    stress_lp_norm,
    target_displacement,
    time_integral,
)
from diffsolids.reduced_functional import ReducedFunctional  # noqa: E402
from diffsolids.verification import finite_difference_check  # noqa: E402

COMM = MPI.COMM_WORLD
COLD_CACHE = None
if ARGS.cold:  # one empty kernel cache for all ranks, read by every later compilation
    COLD_CACHE = COMM.bcast(
        tempfile.mkdtemp(prefix="diffsolids-bench-cache-") if COMM.rank == 0 else None
    )
    dolfinx.jit.DOLFINX_DEFAULT_JIT_OPTIONS["cache_dir"] = (Path(COLD_CACHE), "bench --cold")


def say(*args) -> None:
    if COMM.rank == 0:
        print(*args, flush=True)


def build_model(domain, dynamic: bool) -> ds.Model:
    damping = {"damping_psi": 2e5, "damping_phi": 1e5} if dynamic else {}
    model = ds.Model(domain, ds.NeoHookean(E=1e8, nu=0.3, density=1000.0, **damping), degree=1)
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    return model


def build_objective(model, dynamic: bool):
    # stress of order 1e5..1e6 Pa, tip deflection of order 1e-3 m: both terms of order 1
    stress = stress_lp_norm(model, 4) * 1e-5
    tip = target_displacement(model, [0.0, 0.0, -2e-3], facets=2) * 1e6
    if dynamic:
        return time_integral(stress, "uniform") + time_integral(tip, "uniform")
    return final_value(stress) + final_value(tip)


def make_simulation(model, dynamic: bool, rtol: float, steps: int | None = None) -> ds.Simulation:
    integ = ds.BDF(2, ARGS.dt, steps or ARGS.steps) if dynamic else ds.Static()
    return ds.Simulation(model, integ, ds.SolverOptions(rtol=rtol), progress=False)


def make_control(model, kind: str):
    if kind == "E-field":
        return ParameterControl(model, "E", "field", log=True)
    return ShapeControl(model, "all")


def _max(value: float) -> float:
    return COMM.allreduce(value, op=MPI.MAX)


def _cpu() -> float:
    """CPU seconds of this process and of its waited-for children (the C compiler)."""
    own, children = (
        resource.getrusage(w) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
    )
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def first_gradient(sim: ds.Simulation, objective, control) -> tuple:
    """A new ReducedFunctional and its first gradient (compiling what the cache lacks).

    Returns:
        The ReducedFunctional, its parameters, and wall and CPU seconds (max over ranks) of the
        whole (``s``, ``cpu_s``: set-up, forward run, adjoint sweep) and of its forward run
        (``forward_s``, ``forward_cpu_s``), which compiles nothing.
    """
    COMM.barrier()
    t0, c0 = time.perf_counter(), _cpu()
    rf = ReducedFunctional(sim, objective, [control], factor_memory_mb=ARGS.factor_memory_mb)
    q = rf.initial_parameters()
    t1, c1 = time.perf_counter(), _cpu()
    rf.forward(q)
    t2, c2 = time.perf_counter(), _cpu()
    rf.derivative()
    t3, c3 = time.perf_counter(), _cpu()
    times = {"s": t3 - t0, "cpu_s": c3 - c0, "forward_s": t2 - t1, "forward_cpu_s": c2 - c1}
    return rf, q, {k: _max(v) for k, v in times.items()}


def _variants(kind: str) -> tuple[str, ...]:
    """The shape-partial paths timed for a control ("auto" first: it is the one reported)."""
    if kind != "shape" or ARGS.shape_partials == "auto":
        return ("auto",)
    return ("ufl",) if ARGS.shape_partials == "ufl" else ("auto", "ufl")


def _sweeps(rf: ReducedFunctional, variants: tuple[str, ...]) -> dict:
    """A BackwardSweep per shape-partial path, its forms compiled (untimed).

    The ReducedFunctional keeps one sweep (its first gradient built the "auto" one); the
    benchmark swaps in the sweep of the path wanted, so every path reuses the same trajectory
    and stored factorisations.
    """
    sweeps = {"auto": rf._sweep}
    real = adjoint_sweep.AdjointForms
    for variant in variants:
        if variant in sweeps:
            continue
        adjoint_sweep.AdjointForms = functools.partial(real, shape_partials=variant)
        try:
            sweeps[variant] = adjoint_sweep.BackwardSweep(
                rf.simulation, rf.leaves, rf.controls.targets(), rf.adjoint_options
            )
        finally:
            adjoint_sweep.AdjointForms = real
    return sweeps


def _derivative(rf: ReducedFunctional, sweeps: dict, variant: str) -> np.ndarray:
    """rf.derivative() through the sweep of one shape-partial path."""
    rf._sweep = sweeps[variant]
    return rf.derivative()


def shape_kernel_times(model: ds.Model, objective, dynamic: bool) -> dict:
    """Per-step CPU milliseconds of the shape-partial forms of each path, at the current state.

    For the residual part (lambda . dG/dX) and the objective part (dJ/dX) of the step
    Lagrangian: packing the coefficients and running the kernels (best of --kernel-repeat),
    max over ranks.
    """
    leaves = list(dict.fromkeys(objective.leaves()))
    out = {}
    for variant in ("auto", "ufl"):
        forms = AdjointForms(model, dynamic, leaves, Targets(shape=True), shape_partials=variant)
        forms.lam.x.array[:] = np.random.default_rng(0).standard_normal(forms.lam.x.array.size)
        for const in forms.weights.values():
            const.value = 1.0
        parts = {}
        for name, form in zip(("residual", "objective"), forms.shape, strict=True):
            if form is None:
                continue
            b = np.zeros_like(fem.Function(model.shape_space).x.array)
            pack, kernel = [], []
            for _ in range(ARGS.kernel_repeat):
                c0 = time.process_time()
                coefficients = fem.pack_coefficients(form)
                c1 = time.process_time()
                fem.assemble_vector(b, form, fem.pack_constants(form), coefficients)
                c2 = time.process_time()
                pack.append(c1 - c0)
                kernel.append(c2 - c1)
            parts[name] = {"pack_ms": _max(1e3 * min(pack)), "kernel_ms": _max(1e3 * min(kernel))}
        parts["total_ms"] = sum(p["pack_ms"] + p["kernel_ms"] for p in parts.values())
        out[variant] = parts
    return out


def time_case(sim: ds.Simulation, objective, model: ds.Model, kind: str) -> dict:
    """First gradient (cold and warm with --cold), then best-of-repeat forward and gradient
    wall times of one control (warm cache); for the shape, of each shape-partial path."""
    rf, q, first = first_gradient(sim, objective, make_control(model, kind))
    if ARGS.cold:  # the same on a new ReducedFunctional, its kernels now in the cache
        del rf  # and its stored factorisations: the new one's factor store has the memory
        collect_garbage()
        rf, q, warm = first_gradient(sim, objective, make_control(model, kind))
        first = {"cold": first, "warm": warm}
    variants = _variants(kind)
    sweeps = _sweeps(rf, variants)
    best = dict.fromkeys(variants)
    gradients = {}
    for _ in range(ARGS.repeat):
        COMM.barrier()
        t0, c0 = time.perf_counter(), time.process_time()
        rf.forward(q)
        f, fc = _max(time.perf_counter() - t0), _max(time.process_time() - c0)
        for variant in variants:
            COMM.barrier()
            t0, c0 = time.perf_counter(), time.process_time()
            gradients[variant] = _derivative(rf, sweeps, variant)
            g, gc = _max(time.perf_counter() - t0), _max(time.process_time() - c0)
            if best[variant] is None or gc / fc < best[variant][3] / best[variant][1]:
                stats = {k: v for k, v in rf.adjoint_stats.items() if k != "krylov_per_step"}
                best[variant] = (f, fc, g, gc, stats)
    forward, forward_cpu, gradient, gradient_cpu, stats = best[variants[0]]
    paths = None
    if len(variants) > 1:
        paths = {
            v: {
                "gradient_s": best[v][2],
                "ratio": best[v][2] / best[v][0],
                "gradient_cpu_s": best[v][3],
                "ratio_cpu": best[v][3] / best[v][1],
                "phase_seconds": best[v][4].get("phase_seconds"),
            }
            for v in variants
        }
        ref = gradients["ufl"]
        diff = COMM.allreduce(float(np.sum((gradients["auto"] - ref) ** 2)), op=MPI.SUM)
        norm = COMM.allreduce(float(np.sum(ref**2)), op=MPI.SUM)
        paths["gradient_rel_diff"] = float(np.sqrt(diff / norm))
        paths["kernels"] = shape_kernel_times(model, objective, sim.integrator.dynamic)
    rf._sweep = sweeps["auto"]
    profile = None
    if ARGS.profile:
        pr = cProfile.Profile()
        pr.enable()
        rf.derivative()
        pr.disable()
        out = io.StringIO()
        pstats.Stats(pr, stream=out).sort_stats("cumulative").print_stats(25)
        profile = out.getvalue()
    newton = rf.trajectory.newton_iterations()
    store = rf.factor_store
    if store is not None:
        stats["stored_factors"] = len(store.factors)
        stats["stored_mb"] = round(store.used_mb, 1)
        stats["factors_on_disk"] = store.out_of_core
    return {
        "forward_s": forward,
        "gradient_s": gradient,
        "ratio": gradient / forward,
        "forward_cpu_s": forward_cpu,
        "gradient_cpu_s": gradient_cpu,
        "ratio_cpu": gradient_cpu / forward_cpu,
        "first_gradient": first,
        "newton_its": newton,
        "adjoint": stats,
        "profile": profile,
        "num_parameters": rf.size,
        "shape_partials": paths,
    }


def _rounded(tree):
    if isinstance(tree, dict):
        return {k: _rounded(v) for k, v in tree.items()}
    return round(tree, 2)


def _first(first: dict) -> str:
    def one(t: dict) -> str:
        forward = f", forward {t['forward_s']:.1f} s" if "forward_s" in t else ""
        return f"{t['s']:.1f} s (cpu {t['cpu_s']:.1f} s{forward})"

    if "cold" in first:
        return f"cold {one(first['cold'])}, warm {one(first['warm'])}"
    return one(first)


def _kernels(parts: dict) -> str:
    return ", ".join(
        f"{name} pack {p['pack_ms']:.1f} + kernel {p['kernel_ms']:.1f}"
        for name, p in parts.items()
        if isinstance(p, dict)
    )


def fd_case(sim, objective, control, sweep) -> list[dict]:
    """Central finite differences along unit vectors of the largest gradient entries and a
    random direction (steps as in finite_difference_check: relative to (1 + |q|) / |dq|)."""
    rf = ReducedFunctional(sim, objective, [control])
    q = rf.initial_parameters()
    g = rf.gradient(q)
    directions = []
    for k in np.argsort(-np.abs(g))[: ARGS.fd_params]:
        d = np.zeros_like(q)
        d[k] = 1.0
        directions.append((f"e_{k}", d))
    rng = np.random.default_rng(0)
    d = rng.standard_normal(q.size)
    if isinstance(control, ShapeControl):
        d *= 1e-3 / np.abs(d).max()  # a vertex motion well inside the cells
    directions.append(("random", d))
    results = []
    for name, d in directions:
        support = d != 0
        steps = (1.0 + np.linalg.norm(q[support])) / np.linalg.norm(d) * sweep
        res = finite_difference_check(rf, q, d, steps=steps, gradient=g)
        say(f"    FD {name:10s} adjoint {res.adjoint: .8e}  error {res.relative_error:.2e}"
            f"  (h = {res.best_step:.1e})")  # fmt: skip
        results.append(
            {"direction": name, "adjoint": res.adjoint, "relative_error": res.relative_error}
        )
    rf.controls.assign(q)
    return results


def main() -> dict:
    domain = create_box(
        COMM,
        [[0, 0, 0], [4, 0.5, 0.5]],
        ARGS.cells,
        facets={1: lambda x: np.isclose(x[0], 0), 2: lambda x: np.isclose(x[0], 4)},
    )
    dofs = 3 * domain.mesh.geometry.index_map().size_global
    say(f"bench_gradient: {dofs} dofs, {COMM.size} rank(s), cells {ARGS.cells}")
    t0, c0 = time.perf_counter(), _cpu()
    scenarios = {}
    for name, dynamic in (("static", False), ("dynamic", True)):
        if ARGS.only not in (None, name):
            continue
        model = build_model(domain, dynamic)
        sim = make_simulation(model, dynamic, ARGS.rtol)
        scenarios[name] = (model, sim, build_objective(model, dynamic), dynamic)
    setup = {"s": _max(time.perf_counter() - t0), "cpu_s": _max(_cpu() - c0)}
    say(f"model set-up incl. Newton forms ({'cold' if ARGS.cold else 'cache as found'}): "
        f"{_first(setup)}")  # fmt: skip
    if ARGS.cold:  # the same set-up again, its kernels now in the cache
        t0, c0 = time.perf_counter(), _cpu()
        for _, _, _, dynamic in scenarios.values():
            make_simulation(build_model(domain, dynamic), dynamic, ARGS.rtol)
        wall, cpu = _max(time.perf_counter() - t0), _max(_cpu() - c0)
        setup = {"cold": setup, "warm": {"s": wall, "cpu_s": cpu}}
        say(f"model set-up: {_first(setup)}")

    timings, fd_errors = {}, []
    for name, (model, sim, objective, _) in scenarios.items():
        for kind in () if ARGS.skip_timing else ARGS.controls:
            r = time_case(sim, objective, model, kind)
            timings[f"{name}/{kind}"] = r
            say(
                f"{name:7s} {kind:7s} ({r['num_parameters']} parameters): forward "
                f"{r['forward_s']:7.2f} s (cpu {r['forward_cpu_s']:7.2f} s, {r['newton_its']} "
                f"Newton its), gradient {r['gradient_s']:6.3f} s (cpu {r['gradient_cpu_s']:6.3f}"
                f" s), ratio {r['ratio']:.4f} (cpu {r['ratio_cpu']:.4f})  first gradient "
                f"{_first(r['first_gradient'])}  adjoint {r['adjoint']}"
            )
            paths = r["shape_partials"]
            if paths:
                for variant in ("auto", "ufl"):
                    v, k = paths[variant], paths["kernels"][variant]
                    say(f"    shape partials {variant:4s}: gradient {v['gradient_s']:6.3f} s, "
                        f"ratio {v['ratio']:.4f} (cpu {v['ratio_cpu']:.4f}); per step: "
                        f"{k['total_ms']:.1f} ms cpu ({_kernels(k)})")  # fmt: skip
                say(f"    gradients of the two paths differ by {paths['gradient_rel_diff']:.1e}")
            if r["profile"]:
                say(r["profile"])
    if not ARGS.skip_fd:
        for name, (_, _, _, dynamic) in scenarios.items():
            if dynamic and ARGS.fd_bdf_steps == 0:
                continue
            count = ARGS.fd_dynamic_sweep if dynamic else ARGS.fd_sweep
            sweep = 10.0 ** -np.arange(3.0, 3.0 + count)
            model = build_model(domain, dynamic)
            sim = make_simulation(model, dynamic, ARGS.fd_rtol, ARGS.fd_bdf_steps)
            objective = build_objective(model, dynamic)
            for kind in ("E-field", "shape"):
                say(f"{name} {kind}: central differences (Newton rtol {ARGS.fd_rtol:g})")
                for res in fd_case(sim, objective, make_control(model, kind), sweep):
                    fd_errors.append({"case": f"{name}/{kind}", **res})

    first = {k: v["first_gradient"] for k, v in timings.items()}
    cold = None
    if ARGS.cold:  # what the empty cache cost: cold minus warm, the set-up and first gradients
        parts = [setup, *first.values()]
        cold = {  # the forward runs compile nothing: without them, without their noise
            unit: sum(p["cold"][unit] - p["warm"][unit] for p in parts)
            - sum(p["cold"][f"forward_{unit}"] - p["warm"][f"forward_{unit}"] for p in parts[1:])
            for unit in ("s", "cpu_s")
        }
        cold.update(
            {
                f"with_forward_{unit}": sum(p["cold"][unit] - p["warm"][unit] for p in parts)
                for unit in ("s", "cpu_s")
            }
        )
        cold = {k: round(v, 2) for k, v in cold.items()}
        say(f"cold cache cost (cold - warm: set-up, first gradients without their forward runs): "
            f"{cold['s']:.1f} s (cpu {cold['cpu_s']:.1f} s); with the forward runs "
            f"{cold['with_forward_s']:.1f} s (cpu {cold['with_forward_cpu_s']:.1f} s)")  # fmt: skip

    def worst(prefix, key="ratio"):
        return max((v[key] for k, v in timings.items() if k.startswith(prefix)), default=None)

    summary = {
        "benchmark": "gradient",
        "dofs": dofs,
        "ranks": COMM.size,
        "bdf2_steps": ARGS.steps,
        "ratio_static": worst("static"),
        "ratio_dynamic": worst("dynamic"),
        "ratio_static_cpu": worst("static", "ratio_cpu"),
        "ratio_dynamic_cpu": worst("dynamic", "ratio_cpu"),
        "factor_memory_mb": ARGS.factor_memory_mb,
        "load_average": round(os.getloadavg()[0], 2),
        "fd_rel_err": max((e["relative_error"] for e in fd_errors), default=None),
        "goals": {
            "ratio_static": 0.05,
            "ratio_dynamic": 0.10,
            "fd_rel_err": 1e-6,
            "cold_cache_cost_s": 30.0,
            "peak_rss_mb": 3000.0,  # the 50-step dynamic case with the default factor storage
        },
        "cases": {
            k: {
                "forward_s": round(v["forward_s"], 4),
                "gradient_s": round(v["gradient_s"], 4),
                "ratio": round(v["ratio"], 4),
                "forward_cpu_s": round(v["forward_cpu_s"], 4),
                "gradient_cpu_s": round(v["gradient_cpu_s"], 4),
                "ratio_cpu": round(v["ratio_cpu"], 4),
                "num_parameters": v["num_parameters"],
                "newton_its": v["newton_its"],
                "adjoint": v["adjoint"],
                "shape_partials": v["shape_partials"],
            }
            for k, v in timings.items()
        },
        "fd": fd_errors,
        "cache": "cold" if ARGS.cold else "as found",
        "setup": _rounded(setup),
        "first_gradient": _rounded(first),
        "cold_cache_cost": cold,
    }
    return summary


if __name__ == "__main__":
    result = main()
    COMM.barrier()
    if COLD_CACHE is not None and COMM.rank == 0:
        shutil.rmtree(COLD_CACHE, ignore_errors=True)
    from diffsolids.parallel import peak_rss_mb

    result["peak_rss_mb"] = peak_rss_mb()  # this process's
    say(json.dumps(result))
