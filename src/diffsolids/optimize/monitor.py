"""What an optimisation run shows and writes: log lines, history, plots, selected iterates."""

import json
import logging
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from mpi4py import MPI

from diffsolids.optimize.checkpoint import atomic_write_bytes
from diffsolids.optimize.options import OptimizationError

if TYPE_CHECKING:
    from diffsolids.model import Model
    from diffsolids.simulation import Trajectory

__all__ = ["IterationRecord", "OptimizationOutput", "log_iteration", "plot_history"]

logger = logging.getLogger("diffsolids")


@dataclass
class IterationRecord:
    """One accepted iterate (iteration 0 is the initial point).

    Attributes:
        iteration: Number of accepted steps so far.
        objective: J at the iterate.
        terms: Values of the objective's additive terms (sum to J).
        gradient_norm: Euclidean norm of the projected gradient ``P(q - g) - q``.
        step_norm: ``|q_k - q_{k-1}|_2`` (0 for iteration 0).
        step_length: Line-search factor of the accepted step (0 for iteration 0).
        trials: Forward solves of the line search (including invalid ones).
        invalid_trials: Trials rejected as invalid (inverted elements, intersections, failed
            forward solves, non-finite objective).
        forward_seconds: Wall time of the forward solves of this iteration.
        gradient_seconds: Wall time of the adjoint gradient of this iteration.
        seconds: Wall time since the run (or its resumption) started.
        remeshed: The mesh was rebuilt after this iterate (J, gradient are on the new mesh).
        objective_before_remesh: J on the old mesh when ``remeshed``.
        q: Parameters (only when the run records them).
    """

    iteration: int
    objective: float
    terms: dict[str, float] = field(default_factory=dict)
    gradient_norm: float = 0.0
    step_norm: float = 0.0
    step_length: float = 0.0
    trials: int = 0
    invalid_trials: int = 0
    forward_seconds: float = 0.0
    gradient_seconds: float = 0.0
    seconds: float = 0.0
    remeshed: bool = False
    objective_before_remesh: float | None = None
    q: list[float] | None = None

    def to_json(self) -> str:
        """One JSON line."""
        return json.dumps(asdict(self))

    @classmethod
    def from_dict(cls, d: dict) -> "IterationRecord":
        """Inverse of :meth:`to_json` (after ``json.loads``)."""
        return cls(**d)


def log_iteration(rec: IterationRecord) -> None:
    """One log line per iteration on the "diffsolids" logger."""
    terms = ""
    if len(rec.terms) > 1:
        terms = " (" + ", ".join(f"{k}={v:.6e}" for k, v in rec.terms.items()) + ")"
    line = (
        f"opt {rec.iteration:4d}  J={rec.objective:.10e}{terms}  |g|={rec.gradient_norm:.3e}"
        f"  step={rec.step_norm:.3e} (t={rec.step_length:.3g}, trials={rec.trials}"
        f", invalid={rec.invalid_trials})  forward {rec.forward_seconds:.2f}s"
        f"  gradient {rec.gradient_seconds:.2f}s"
    )
    if rec.remeshed:
        line += f"  remeshed (J before {rec.objective_before_remesh:.10e})"
    logger.info(line)


def plot_history(history: list[IterationRecord], directory: Path) -> None:
    """``objective.png`` (J and its terms) and ``gradient_norm.png`` per iteration."""
    from matplotlib.figure import Figure  # Agg canvas, no pyplot state

    it = [r.iteration for r in history]
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    J = np.array([r.objective for r in history])
    positive = bool(np.all(J > 0))
    ax.plot(it, J, "o-", label="J")
    labels = list(history[-1].terms) if len(history[-1].terms) > 1 else []
    for label in labels:
        vals = np.array([r.terms.get(label, np.nan) for r in history])
        positive = positive and bool(np.all(vals[np.isfinite(vals)] > 0))
        ax.plot(it, vals, ".--", label=label)
    if positive:
        ax.set_yscale("log")
    for r in history:
        if r.remeshed:
            ax.axvline(r.iteration, color="0.7", lw=0.8)
    ax.set_xlabel("iteration")
    ax.set_ylabel("objective")
    if labels:
        ax.legend(fontsize="small")
    _save(fig, directory / "objective.png")
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    gn = np.array([r.gradient_norm for r in history])
    ax.plot(it, gn, "o-")
    if np.all(gn > 0):
        ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("projected gradient norm")
    _save(fig, directory / "gradient_norm.png")


def _save(fig, path: Path) -> None:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    atomic_write_bytes(path, buf.getvalue())


class OptimizationOutput:
    """History file (JSON lines), plots and trajectories of selected iterates.

    Args:
        directory: Output directory.
        comm: Communicator of the run.
        write_parameters: Include q in every history line.
        plot_every: Update ``objective.png`` and ``gradient_norm.png`` every k iterations and at
            the end of the run (0: no plots).
        iterate_every: Write the trajectory of every k-th iterate (and the last) to
            ``iterates/iterate_<k>.<format>`` (0: never).
        iterate_format: "bp" (VTX) or "xdmf".
    """

    HISTORY = "history.jsonl"

    def __init__(
        self,
        directory: str | os.PathLike,
        comm: MPI.Comm,
        write_parameters: bool = False,
        plot_every: int = 10,
        iterate_every: int = 0,
        iterate_format: str = "bp",
    ):
        if iterate_format not in ("bp", "xdmf"):
            raise OptimizationError(
                f"iterate_format must be 'bp' or 'xdmf', not {iterate_format!r}"
            )
        if plot_every < 0 or iterate_every < 0:
            raise OptimizationError("plot_every and iterate_every must be >= 0 (0: never)")
        self.directory = Path(directory)
        self.comm = comm
        self.write_parameters = write_parameters
        self.plot_every = plot_every
        self.iterate_every = iterate_every
        self.iterate_format = iterate_format
        if comm.rank == 0:
            self.directory.mkdir(parents=True, exist_ok=True)
        comm.barrier()

    @property
    def history_path(self) -> Path:
        """The JSON-lines history file."""
        return self.directory / self.HISTORY

    def start(self, history: list[IterationRecord]) -> None:
        """Begin the history file with ``history``.

        A new run starts empty; a resumed run starts with its checkpointed records, dropping
        lines written after the checkpoint.
        """
        if self.comm.rank == 0:
            data = "".join(r.to_json() + "\n" for r in history)
            atomic_write_bytes(self.history_path, data.encode())

    def record(self, rec: IterationRecord, history: list[IterationRecord]) -> None:
        """Append a history line and update the plots when due (rank 0)."""
        if self.comm.rank != 0:
            return
        with open(self.history_path, "a") as f:
            f.write(rec.to_json() + "\n")
            f.flush()
            os.fsync(f.fileno())
        if self.plot_every > 0 and rec.iteration % self.plot_every == 0:
            plot_history(history, self.directory)

    def finish(self, history: list[IterationRecord]) -> None:
        """Final plots (rank 0)."""
        if self.comm.rank == 0 and self.plot_every > 0 and history:
            plot_history(history, self.directory)

    def wants_iterate(self, iteration: int, last: bool = False) -> bool:
        """Whether the trajectory of this iterate is written."""
        return self.iterate_every > 0 and (last or iteration % self.iterate_every == 0)

    def write_iterate(self, iteration: int, model: "Model", trajectory: "Trajectory") -> Path:
        """Write the trajectory of an iterate (collective)."""
        from diffsolids.io.output import TrajectoryWriter

        path = self.directory / "iterates" / f"iterate_{iteration:04d}.{self.iterate_format}"
        writer = TrajectoryWriter(model, path)
        for t, u, v in zip(trajectory.times, trajectory.u, trajectory.v, strict=True):
            writer.write(t, u, v)
        writer.close()
        return path
