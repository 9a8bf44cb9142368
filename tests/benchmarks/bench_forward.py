"""Forward-solve benchmark: diffsolids against a bare DOLFINx ``NonlinearProblem``.

A 3D Neo-Hookean beam (box [0, 4] x [0, 0.5]^2, P1 vector, about 30k dofs) clamped at x = 0 sags
under gravity: one static solve and 20 BDF2 steps. Both solvers use the same UFL forms (so the
same compiled kernels), SNES newtonls with a backtracking line search, MUMPS LU (``--pc
gamg``: GMRES with algebraic multigrid in both), the same convergence test ``||F|| <= rtol *
max(f_ref, ||F_0||)`` and the same initial guesses. Ours also evaluates the potential in the
line search and bounds every step against element inversion; the bare solver does neither.
Time per Newton iteration is split into assembly (residual, Jacobian, potential),
factorisation (MUMPS symbolic + numeric; with gamg the preconditioner set-up), triangular
solves (with gamg the Krylov iterations), the inversion guard and the rest, from PETSc's log
events.

Large problems: ``--cells 160 20 20 --pc gamg --only static --repeat 1`` is a static solve of
213k dofs, the size of the paper's 3D beam (Fig. 7, 209 409 dofs, 192 s per forward in its
Table 4).

Run ``python tests/benchmarks/bench_forward.py`` (``make bench``); ``--cold`` compiles the forms
into an empty FFCx cache to also report the cold set-up time. After an untimed warm-up solve, each
problem runs ``--repeat`` times (default 2) per solver, alternating which solver goes first, and
the best time of each is kept; wall and CPU times are reported (CPU time is the steadier measure
on a shared machine). Works under ``mpiexec -n 2``. The
last line printed is a JSON object with the numbers.
"""

import json
import os
import sys
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

from beam_args import beam_parser


def _parse(argv):
    p = beam_parser(__doc__.splitlines()[0], steps=20)
    p.add_argument("--rtol", type=float, default=1e-9, help="residual tolerance")
    p.add_argument(
        "--repeat",
        type=int,
        default=2,
        help="timed repetitions, alternating which solver runs first (best is reported)",
    )
    p.add_argument(
        "--pc",
        default="lu",
        help="preconditioner of both solvers: lu (MUMPS, the default) or gamg (GMRES to 1e-8 "
        "with the rigid body modes as near-null space; for large meshes)",
    )
    p.add_argument(
        "--only", choices=("static", "bdf2"), default=None, help="run one of the two problems"
    )
    p.add_argument(
        "--bare-linesearch",
        default="basic",
        help="line search of the bare solver (basic = full Newton steps; bt backtracks on the "
        "residual norm, which stalls on this problem)",
    )
    return p.parse_args(argv)


ARGS = _parse(sys.argv[1:])
if ARGS.cold:  # must precede the DOLFINx import: the JIT reads its cache location once
    os.environ["XDG_CACHE_HOME"] = tempfile.mkdtemp(prefix="diffsolids-bench-cache-")

import diffsolids as ds  # noqa: E402  (first: it loads the MPI library DOLFINx's wheel needs)

# isort: split
import dolfinx.fem.petsc as fem_petsc  # noqa: E402
import numpy as np  # noqa: E402
import ufl  # noqa: E402
from dolfinx import fem  # noqa: E402
from mpi4py import MPI  # noqa: E402
from petsc4py import PETSc  # noqa: E402

from diffsolids.mesh import create_box  # noqa: E402
from diffsolids.solvers import JIT_OPTIONS  # noqa: E402
from diffsolids.solvers.inversion import InversionGuard  # noqa: E402
from diffsolids.solvers.linear_options import rigid_body_modes  # noqa: E402

COMM = MPI.COMM_WORLD
GAMG = ARGS.pc == "gamg"
EVENTS = {
    "assembly": ("SNESFunctionEval", "SNESJacobianEval"),
    "potential": ("SNESObjectiveEval",),
    "factorisation": ("PCSetUp",) if GAMG else ("MatLUFactorSym", "MatLUFactorNum"),
    "solve": ("KSPSolve",) if GAMG else ("MatSolve",),
}
if ARGS.pc not in ("lu", "gamg"):
    sys.exit(f"bench_forward: --pc {ARGS.pc!r} is not lu or gamg")


def say(*args) -> None:
    if COMM.rank == 0:
        print(*args, flush=True)


class Split:
    """Seconds spent in PETSc log events (and the inversion guard) between start and stop."""

    guard_seconds = 0.0

    def __init__(self):
        self.values = {}

    @staticmethod
    def _snapshot():
        names = [n for group in EVENTS.values() for n in group]
        snap = {n: PETSc.Log.Event(n).getPerfInfo()["time"] for n in names}
        snap["guard"] = Split.guard_seconds
        return snap

    def __enter__(self):
        COMM.barrier()
        self._t0 = time.perf_counter()
        self._cpu0 = time.process_time()
        self._start = self._snapshot()
        return self

    def __exit__(self, *exc):
        self.cpu = time.process_time() - self._cpu0
        COMM.barrier()
        self.total = time.perf_counter() - self._t0
        end = self._snapshot()
        delta = {k: end[k] - self._start[k] for k in end}
        for group, names in EVENTS.items():
            self.values[group] = sum(delta[n] for n in names)
        self.values["guard"] = delta["guard"]
        self.values["other"] = self.total - sum(self.values.values())
        # The slowest rank decides: report the maximum over ranks.
        self.values = {k: COMM.allreduce(v, op=MPI.MAX) for k, v in self.values.items()}
        self.total = COMM.allreduce(self.total, op=MPI.MAX)
        self.cpu = COMM.allreduce(self.cpu, op=MPI.MAX)


def _time_guard():
    """Accumulate the time spent in InversionGuard.max_step into Split.guard_seconds."""
    original = InversionGuard.max_step

    def timed(self, x, dx):
        t0 = time.perf_counter()
        try:
            return original(self, x, dx)
        finally:
            Split.guard_seconds += time.perf_counter() - t0

    InversionGuard.max_step = timed


def build_model(domain) -> ds.Model:
    model = ds.Model(domain, ds.NeoHookean(E=1e8, nu=0.3, density=1000.0), degree=1)
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    return model


def make_integrator(dynamic: bool):
    return ds.BDF(2, ARGS.dt, ARGS.steps) if dynamic else ds.Static()


# -- ours -------------------------------------------------------------------------------------
def run_ours(domain, dynamic: bool):
    t0 = time.perf_counter()
    model = build_model(domain)
    options = ds.SolverOptions(rtol=ARGS.rtol, petsc_options={"pc_type": "gamg"} if GAMG else {})
    sim = ds.Simulation(model, make_integrator(dynamic), options)
    setup = time.perf_counter() - t0
    with Split() as split:
        traj = sim.run()
    sim.solver.snes.destroy()
    return {
        "setup_s": setup,
        "seconds": split.total,
        "cpu_s": split.cpu,
        "newton_its": traj.newton_iterations(),
        "split": split.values,
        "u_final": traj.u[-1],
    }


# -- bare DOLFINx -----------------------------------------------------------------------------
LINEAR = (
    {"ksp_type": "gmres", "ksp_rtol": 1e-8, "ksp_gmres_restart": 200, "pc_type": "gamg"}
    if GAMG
    else {"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}
)


class BareSolver:
    """The same step problems with ``dolfinx.fem.petsc.NonlinearProblem`` and plain numpy."""

    def __init__(self, domain, dynamic: bool):
        self.model = build_model(domain)
        self.integ = make_integrator(dynamic)
        self.dynamic = dynamic
        f = self.model.fields
        V = self.model.V
        residual = ufl.derivative(self.model.potential(dynamic), f.u, ufl.TestFunction(V))
        jacobian = ufl.derivative(residual, f.u, ufl.TrialFunction(V))
        self.residual_form = fem.form(residual, jit_options=JIT_OPTIONS)
        self.problem = fem_petsc.NonlinearProblem(
            residual,
            f.u,
            bcs=self.model.bcs,
            J=jacobian,
            petsc_options_prefix="bare_",
            petsc_options={
                "snes_type": "newtonls",
                "snes_linesearch_type": ARGS.bare_linesearch,
                "snes_rtol": ARGS.rtol,
                "snes_atol": 0.0,  # set from the reference force before the first step
                "snes_stol": 0.0,
                "snes_max_it": 50,
                **LINEAR,
            },
            jit_options=JIT_OPTIONS,
        )
        if GAMG:
            self.problem.A.setNearNullSpace(rigid_body_modes(V))

    def reference_force(self) -> float:
        """Residual norm at the current u with zero Dirichlet rows (as our solver computes it)."""
        b = fem_petsc.create_vector(self.model.V)
        fem_petsc.assemble_vector(b, self.residual_form)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fem_petsc.set_bc(b, self.model.bcs, self.model.fields.u.x.petsc_vec, -1.0)
        norm = b.norm()
        b.destroy()
        return norm

    def run(self):
        f = self.model.fields
        u = f.u.x.array
        integ = self.integ
        us, vs = [u.copy()], [np.zeros_like(u)]
        its = 0
        snes = self.problem.solver
        for i in range(1, integ.num_steps + 1):
            c = integ.coefficients(i)
            f.dt.value = integ.dt
            f.beta_dt.value = c.beta_dt
            if self.dynamic:
                f.u_tilde.x.array[:] = -sum(
                    a * (us[i - j] + c.beta_dt * vs[i - j]) for j, a in enumerate(c.alpha, 1)
                )
            if i == 1:
                u[:] = us[0]
                snes.setTolerances(atol=ARGS.rtol * self.reference_force())
            u[:] = us[i - 1] + integ.dt * vs[i - 1] if self.dynamic else us[i - 1]
            self.problem.solve()
            reason = snes.getConvergedReason()
            if reason <= 0:
                raise RuntimeError(f"bare SNES failed in step {i}: reason {reason}")
            its += snes.getIterationNumber()
            us.append(u.copy())
            v = u.copy()
            for j, a in enumerate(c.alpha, 1):
                v += a * us[i - j]
            vs.append(v / c.beta_dt if self.dynamic else (u - us[i - 1]) / c.dt)
        return its, us[-1]


def run_bare(domain, dynamic: bool):
    t0 = time.perf_counter()
    bare = BareSolver(domain, dynamic)
    setup = time.perf_counter() - t0
    with Split() as split:
        its, u_final = bare.run()
    return {
        "setup_s": setup,
        "seconds": split.total,
        "cpu_s": split.cpu,
        "newton_its": its,
        "split": split.values,
        "u_final": u_final,
    }


def _best(runs):
    return min(runs, key=lambda r: r["seconds"])


def _per_it(run):
    its = max(run["newton_its"], 1)
    return {k: v / its for k, v in run["split"].items()}


def _fmt_split(per_it):
    return "  ".join(f"{k} {1e3 * v:7.1f}" for k, v in per_it.items())


def main() -> dict:
    PETSc.Log.begin()
    _time_guard()
    domain = create_box(
        COMM, [[0, 0, 0], [4, 0.5, 0.5]], ARGS.cells, facets={1: lambda x: np.isclose(x[0], 0)}
    )
    V = fem.functionspace(domain.mesh, ("Lagrange", 1, (3,)))
    dofs = V.dofmap.index_map.size_global * 3
    say(f"bench_forward: {dofs} dofs, {COMM.size} rank(s), cells {ARGS.cells}")

    # Compile every form once (cold if the cache is empty), untimed beyond its set-up.
    t0 = time.perf_counter()
    problems = [(n, d) for n, d in (("static", False), ("bdf2", True)) if ARGS.only in (None, n)]
    for _, dynamic in problems:
        ds.Simulation(build_model(domain), make_integrator(dynamic))
        BareSolver(domain, dynamic)
    compile_s = COMM.allreduce(time.perf_counter() - t0, op=MPI.MAX)
    cache = "cold" if ARGS.cold else "as found"
    say(f"form set-up (compile, cache {cache}): {compile_s:.2f} s")
    # Warm-up (untimed): first MUMPS factorisations and allocations of the process.
    run_ours(domain, False)
    run_bare(domain, False)

    load_before = os.getloadavg()[0]
    results = {}
    for name, dynamic in problems:
        ours, bare = [], []
        for r in range(ARGS.repeat):  # interleaved, so that load changes hit both alike
            if r % 2 == 0:
                ours.append(run_ours(domain, dynamic))
                bare.append(run_bare(domain, dynamic))
            else:
                bare.append(run_bare(domain, dynamic))
                ours.append(run_ours(domain, dynamic))
        o, b = _best(ours), _best(bare)
        diff = np.abs(o["u_final"] - b["u_final"]).max()
        scale = np.abs(b["u_final"]).max()
        diff = COMM.allreduce(diff, op=MPI.MAX) / COMM.allreduce(scale, op=MPI.MAX)
        results[name] = (o, b, diff)
        for label, r in (("ours", o), ("bare", b)):
            say(
                f"{name:6s} {label}: {r['seconds']:7.2f} s (cpu {r['cpu_s']:7.2f} s)  "
                f"{r['newton_its']:3d} Newton its  per it [ms]: {_fmt_split(_per_it(r))}  "
                f"(set-up warm {r['setup_s']:.2f} s)"
            )
        say(
            f"{name:6s} ours/bare: wall {o['seconds'] / b['seconds']:.3f}, "
            f"cpu {o['cpu_s'] / b['cpu_s']:.3f}; max |u_ours - u_bare| / max |u| {diff:.1e}"
        )

    def total(idx, key):
        return sum(results[n][idx][key] for n in results)

    def total_split(idx):
        keys = next(iter(results.values()))[idx]["split"]
        return {k: round(sum(results[n][idx]["split"][k] for n in results), 4) for k in keys}

    forward, bare_s = total(0, "seconds"), total(1, "seconds")
    cpu, bare_cpu = total(0, "cpu_s"), total(1, "cpu_s")
    its, bare_its = total(0, "newton_its"), total(1, "newton_its")
    summary = {
        "benchmark": "forward",
        "dofs": dofs,
        "ranks": COMM.size,
        "pc": ARGS.pc,
        "newton_its": its,
        "bare_newton_its": bare_its,
        "forward_s": round(forward, 4),
        "bare_s": round(bare_s, 4),
        "overhead_vs_bare": round(forward / bare_s, 4),
        "forward_cpu_s": round(cpu, 4),
        "bare_cpu_s": round(bare_cpu, 4),
        "overhead_cpu_vs_bare": round(cpu / bare_cpu, 4),
        "per_iteration_ms": round(1e3 * forward / its, 2),
        "bare_per_iteration_ms": round(1e3 * bare_s / bare_its, 2),
        "split_s": total_split(0),
        "bare_split_s": total_split(1),
    }
    for name in results:
        o, b, diff = results[name]
        summary[name] = {
            "forward_s": round(o["seconds"], 4),
            "bare_s": round(b["seconds"], 4),
            "newton_its": o["newton_its"],
            "bare_newton_its": b["newton_its"],
            "max_rel_difference": float(diff),
        }
    if "bdf2" in summary:
        summary["bdf2"]["steps"] = ARGS.steps
    summary |= {
        "compile_s": round(compile_s, 2),
        "cache": cache,
        "repeat": ARGS.repeat,
        "load_average": [round(load_before, 2), round(os.getloadavg()[0], 2)],
    }
    say(
        f"total: ours {forward:.2f} s ({its} its), bare {bare_s:.2f} s ({bare_its} its), "
        f"overhead {forward / bare_s:.3f} wall, {cpu / bare_cpu:.3f} cpu (target <= 1.10); "
        f"load average {load_before:.1f} -> {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )
    from diffsolids.parallel import peak_rss_mb

    summary["peak_rss_mb"] = peak_rss_mb()  # this process's
    say(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
