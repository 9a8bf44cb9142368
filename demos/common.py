"""Shared plumbing of the demos: arguments, output folder, report with checked outcomes, figures.

Every optimisation demo is a script with ``main(argv=None) -> DemoReport``. Sizes: ``--tiny``
(smoke tests: a few iterations on a coarse mesh), default (under 2 minutes on 2 cores, checks
the outcome stated in the README), ``--full`` (paper-like resolution). ``--check`` makes the
exit code non-zero when an outcome falls short (``make demos`` runs every demo that way).

What every user needs (centres of mass, trajectory keeping, invariant checks, state output,
figure geometry) is in the package (``diffsolids.objectives``, ``diffsolids.optimize``,
``diffsolids.io``); this module holds the demos' own conventions.
"""

import argparse
import json
import logging
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
from mpi4py import MPI

from diffsolids.io import configure_logging
from diffsolids.optimize import LBFGSOptions, OptimizationResult, TrajectoryKeeper, minimize
from diffsolids.parallel import collective_comm

ROOT = Path(__file__).resolve().parents[1]
MESHES = ROOT / "meshes"

__all__ = [
    "MESHES",
    "DemoReport",
    "DemoRun",
    "Outcome",
    "by_size",
    "check_decrease",
    "cpu_seconds",
    "demo_parser",
    "finish",
    "parse_sized",
    "plot_history",
    "report_from",
    "run_demo",
    "save_figure",
    "size_name",
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
    p.set_defaults(demo=default_out)
    return p


def by_size(**settings: Sequence) -> dict[str, dict]:
    """Settings per size from one (tiny, default, full) triple per setting (see parse_sized)."""
    return {
        size: {key: values[k] for key, values in settings.items()}
        for k, size in enumerate(("tiny", "default", "full"))
    }


def size_name(args: argparse.Namespace) -> str:
    """The size of the run: tiny, default or full."""
    return "tiny" if args.tiny else ("full" if args.full else "default")


def parse_sized(
    parser: argparse.ArgumentParser, argv: Sequence[str] | None, sizes: dict[str, dict]
) -> argparse.Namespace:
    """Parse the arguments; every setting of the run's size not given on the command line is set.

    Args:
        parser: The demo's parser (:func:`demo_parser` and its own options).
        argv: Command line (None: ``sys.argv``).
        sizes: Settings per size name ("tiny", "default", "full"), e.g. ``{"h": 0.1,
            "iterations": 60}``; an option left at None (or without a command-line option)
            takes the size's value.
    """
    args = parser.parse_args(argv)
    for key, value in sizes[size_name(args)].items():
        if getattr(args, key, None) is None:
            setattr(args, key, value)
    return args


def cpu_seconds(comm: MPI.Comm, start: float = 0.0) -> float:
    """Process CPU time since ``start`` summed over the ranks (the machine is shared)."""
    return collective_comm(comm).allreduce(time.process_time() - start, op=MPI.SUM)


class DemoRun:
    """One run of a demo: its arguments, communicator and start times.

    ``DemoRun(DemoRun.parser(__doc__.splitlines()[0], "throw"), argv, comm, SIZES)`` parses the
    command line (every setting of the run's size not given on it is set, see
    :func:`parse_sized`), configures logging (``--verbose``) and starts the clocks.

    Args:
        parser: The demo's parser (:meth:`parser` with the demo's own options).
        argv: Command line (None: ``sys.argv``).
        comm: Communicator of the run.
        sizes: Settings per size name.

    Attributes:
        args: The parsed arguments; ``args.demo`` is the demo's name.
        comm: The communicator.
        t0: Wall-clock start.
        cpu0: CPU-time start (this process).
    """

    parser = staticmethod(demo_parser)

    def __init__(
        self,
        parser: argparse.ArgumentParser,
        argv: Sequence[str] | None,
        comm: MPI.Comm,
        sizes: dict[str, dict],
    ):
        self.args = parse_sized(parser, argv, sizes)
        self.comm = comm
        configure_logging(logging.INFO if self.args.verbose else logging.WARNING, comm)
        self.t0, self.cpu0 = time.perf_counter(), time.process_time()

    @property
    def times(self) -> tuple[float, float]:
        """(wall-clock start, CPU start)."""
        return self.t0, self.cpu0

    def cpu_seconds(self) -> float:
        """CPU time of the run so far, summed over the ranks."""
        return cpu_seconds(self.comm, self.cpu0)

    def optimise(
        self, rf, q0, options: LBFGSOptions, **kwargs
    ) -> tuple[OptimizationResult, TrajectoryKeeper]:
        """``minimize`` writing into ``args.out`` and keeping the first and last trajectories.

        Args:
            rf: The ReducedFunctional.
            q0: Initial parameters.
            options: L-BFGS options.
            **kwargs: Further arguments of ``minimize`` (``plot_every`` defaults to 0;
                observers in ``on_accept`` run after the keeper).

        Returns:
            (result, keeper): ``keeper.first`` and ``keeper.last`` are the trajectories of the
            initial and the final iterate.
        """
        keeper = TrajectoryKeeper()
        kwargs["on_accept"] = [keeper, *kwargs.get("on_accept", ())]
        kwargs.setdefault("plot_every", 0)
        result = minimize(rf, q0, options, output_dir=self.args.out, **kwargs)
        return result, keeper

    def report(self, result: OptimizationResult) -> "DemoReport":
        """The DemoReport of an OptimizationResult (see :func:`report_from`)."""
        return report_from(self.args.demo, self.args, result, self.t0)

    def finish(self, report: "DemoReport") -> "DemoReport":
        """Print the summary and write ``result.json`` (see :func:`finish`)."""
        return finish(report, self.args, self.comm)


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


def check_decrease(report: DemoReport) -> None:
    """Record the outcome every run checks first: the objective decreased."""
    report.check(
        "objective decreased",
        report.final_objective,
        report.initial_objective,
        report.final_objective < report.initial_objective,
    )


def finish(report: DemoReport, args, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Print the summary and write ``result.json`` (rank 0)."""
    if comm.rank == 0:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "result.json").write_text(json.dumps(asdict(report), indent=2))
        print(report.summary(), flush=True)
    return report


def plot_history(ax, result, label: str = "objective", title: str | None = None, **kw) -> None:
    """Objective per iteration on a log axis (``title`` with the text options ``kw``)."""
    its = [h.iteration for h in result.history]
    vals = np.array([h.objective for h in result.history])
    ax.semilogy(its, np.abs(vals), "o-", ms=3, label=label)
    ax.set_xlabel("iteration")
    ax.set_ylabel("objective")
    ax.grid(True, which="both", alpha=0.3)
    if title is not None:
        ax.set_title(title, **kw)


def save_figure(fig, path: Path, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
    """Lay out a matplotlib figure (``tight_layout``), save it on rank 0 and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    if comm.rank == 0:
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=130, bbox_inches="tight")
    plt.close(fig)


def run_demo(main, argv: Sequence[str] | None = None) -> None:
    """Entry point of a demo script: exit code 1 when --check finds a failed outcome."""
    report = main(argv)
    if "--check" in (argv if argv is not None else sys.argv[1:]) and not report.passed:
        sys.exit(1)
