"""Shared plumbing of the demos: arguments, output folder, report with checked outcomes, figures.

Every optimisation demo is a script with ``main(argv=None) -> DemoReport``. Sizes: ``--tiny``
(smoke tests: a few iterations on a coarse mesh), default (under 2 minutes on 2 cores, checks
the outcome stated in the README), ``--full`` (paper-like resolution). ``--check`` makes the
exit code non-zero when an outcome falls short (``make demos`` runs every demo that way).
"""

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
from mpi4py import MPI

from diffsolids.parallel import collective_comm

ROOT = Path(__file__).resolve().parents[1]
MESHES = ROOT / "meshes"

__all__ = [
    "MESHES",
    "DemoReport",
    "Outcome",
    "boundary_segments",
    "demo_parser",
    "finish",
    "plot_history",
    "report_from",
    "run_demo",
    "save_figure",
]


@dataclass
class Outcome:
    """A stated result of a demo and whether the run achieved it."""

    name: str
    value: float
    threshold: float
    passed: bool
    text: str = ""


@dataclass
class DemoReport:
    """What a demo printed: objective before/after, iterations, timings and checked outcomes."""

    demo: str
    size: str
    initial_objective: float
    final_objective: float
    iterations: int
    forward_seconds: float
    gradient_seconds: float
    wall_seconds: float
    stop_reason: str = ""
    outcomes: list[Outcome] = field(default_factory=list)
    extra: dict = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        """All outcomes achieved."""
        return all(o.passed for o in self.outcomes)

    def check(
        self, name: str, value: float, threshold: float, passed: bool, text: str = ""
    ) -> None:
        """Record an outcome."""
        self.outcomes.append(Outcome(name, float(value), float(threshold), bool(passed), text))

    def summary(self) -> str:
        """Human-readable lines."""
        lines = [
            f"{self.demo} ({self.size}): J {self.initial_objective:.6e} -> "
            f"{self.final_objective:.6e} in {self.iterations} iterations ({self.stop_reason}); "
            f"forward {self.forward_seconds:.2f} s, gradient {self.gradient_seconds:.2f} s "
            f"per iteration; total {self.wall_seconds:.1f} s"
        ]
        for o in self.outcomes:
            mark = "ok  " if o.passed else "FAIL"
            lines.append(
                f"  [{mark}] {o.name}: {o.value:.6g} (threshold {o.threshold:.6g}) {o.text}"
            )
        return "\n".join(lines)


def demo_parser(description: str, default_out: str) -> argparse.ArgumentParser:
    """Arguments common to all demos."""
    p = argparse.ArgumentParser(description=description)
    size = p.add_mutually_exclusive_group()
    size.add_argument("--tiny", action="store_true", help="smoke-test size (a few iterations)")
    size.add_argument("--full", action="store_true", help="paper-like resolution")
    p.add_argument("--iterations", type=int, help="optimisation iteration limit")
    p.add_argument("--out", type=Path, default=ROOT / "output" / default_out, help="output folder")
    p.add_argument("--xdmf", action="store_true", help="write XDMF instead of VTX")
    p.add_argument("--no-plot", action="store_true", help="skip the PNG figure")
    p.add_argument("--check", action="store_true", help="exit non-zero if an outcome falls short")
    p.add_argument("--verbose", action="store_true", help="log every Newton step")
    return p


def size_name(args) -> str:
    """The size of the run: tiny, default or full."""
    return "tiny" if args.tiny else ("full" if args.full else "default")


def report_from(demo: str, args, result, t0: float) -> DemoReport:
    """A DemoReport from an OptimizationResult (timings averaged per iteration)."""
    hist = result.history
    n = max(len(hist) - 1, 1)
    return DemoReport(
        demo=demo,
        size=size_name(args),
        initial_objective=float(hist[0].objective),
        final_objective=float(result.objective),
        iterations=int(result.iterations),
        forward_seconds=float(sum(h.forward_seconds for h in hist) / max(len(hist), 1)),
        gradient_seconds=float(sum(h.gradient_seconds for h in hist) / n),
        wall_seconds=time.perf_counter() - t0,
        stop_reason=result.reason,
    )


def finish(report: DemoReport, args, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Print the summary and write ``result.json`` (rank 0)."""
    if comm.rank == 0:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "result.json").write_text(json.dumps(asdict(report), indent=2))
        print(report.summary(), flush=True)
    return report


def plot_history(ax, result, label: str = "objective") -> None:
    """Objective per iteration on a log axis."""
    its = [h.iteration for h in result.history]
    vals = np.array([h.objective for h in result.history])
    ax.semilogy(its, np.abs(vals), "o-", ms=3, label=label)
    ax.set_xlabel("iteration")
    ax.set_ylabel("objective")
    ax.grid(True, which="both", alpha=0.3)


def boundary_segments(domain, displacement: np.ndarray | None = None, V=None) -> np.ndarray:
    """Boundary edges of a 2D mesh as an (n, 2, 2) array (gathered on all ranks)."""
    import dolfinx.mesh

    mesh = domain.mesh
    fdim = mesh.topology.dim - 1
    mesh.topology.create_connectivity(fdim, fdim + 1)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    nodes = dolfinx.mesh.entities_to_geometry(mesh, fdim, facets)
    x = mesh.geometry.x[:, :2].copy()
    if displacement is not None:
        from dolfinx import fem

        u = fem.Function(V)
        u.x.array[:] = displacement
        P1 = fem.functionspace(mesh, ("Lagrange", 1, (2,)))
        u1 = fem.Function(P1)
        u1.interpolate(u)
        # P1 dofs and geometry nodes share the per-cell ordering
        node_of_dof = np.empty(len(x), dtype=np.int64)
        node_of_dof[mesh.geometry.dofmaps[0].ravel()] = P1.dofmap.list.ravel()
        x += u1.x.array.reshape(-1, 2)[node_of_dof]
    return np.concatenate(collective_comm(mesh.comm).allgather(x[nodes]))


def save_figure(fig, path: Path, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
    """Save a matplotlib figure on rank 0."""
    if comm.rank == 0:
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=130, bbox_inches="tight")


def run_demo(main, argv: Sequence[str] | None = None) -> None:
    """Entry point of a demo script: exit code 1 when --check finds a failed outcome."""
    report = main(argv)
    if "--check" in (argv if argv is not None else sys.argv[1:]) and not report.passed:
        sys.exit(1)
