"""What an optimisation run shows and writes: log lines, history, plots, selected iterates."""

import csv
import io
import json
import logging
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from mpi4py import MPI

from diffsolids.optimize.checkpoint import atomic_write_bytes, make_directory
from diffsolids.optimize.options import OptimizationError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from diffsolids.controls import ControlSet
    from diffsolids.model import Model
    from diffsolids.simulation import Trajectory

__all__ = [
    "IterationLog",
    "IterationRecord",
    "OptimizationOutput",
    "control_summary",
    "log_iteration",
    "plot_history",
    "plot_log",
    "read_log",
]

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
        parameter_norm: ``|q_k|_2``.
        parameter_summary: The controls at the iterate in a few characters (their values, or
            the norm of a control of more than three parameters).
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
    parameter_norm: float = 0.0
    parameter_summary: str = ""
    q: list[float] | None = None

    def to_json(self) -> str:
        """One JSON line."""
        return json.dumps(asdict(self))

    @classmethod
    def from_dict(cls, d: dict) -> "IterationRecord":
        """Inverse of :meth:`to_json` (after ``json.loads``)."""
        return cls(**d)


def control_summary(controls: "ControlSet", q: np.ndarray, max_values: int = 3) -> str:
    """The controls at ``q`` in a few characters, for a log line.

    A control with at most ``max_values`` parameters shows them (``E=1.2e+05``,
    ``v0=[1.61, 0.39]``), a larger one its Euclidean norm (``|shape|=0.0213``).

    Args:
        controls: The reduced functional's ControlSet (``controls``, ``offsets``).
        q: The parameters.
        max_values: Largest control shown value by value.
    """
    q = np.asarray(q, dtype=float)
    offsets = controls.offsets
    parts = []
    for c, a, b in zip(controls.controls, offsets[:-1], offsets[1:], strict=True):
        name = c.name
        if b - a == 1:
            parts.append(f"{name}={q[a]:.4g}")
        elif b - a <= max_values:
            parts.append(f"{name}=[" + ", ".join(f"{x:.4g}" for x in q[a:b]) + "]")
        else:
            parts.append(f"|{name}|={np.linalg.norm(q[a:b]):.4g}")
    return " ".join(parts)


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


# the columns of the printed log: (title, width, value of a record)
_COLUMNS = (
    ("iter", 4, lambda r: f"{r.iteration:d}"),
    ("J", 16, lambda r: f"{r.objective:.9e}"),
    ("|grad|", 9, lambda r: f"{r.gradient_norm:.3e}"),
    ("|step|", 9, lambda r: f"{r.step_norm:.3e}" if r.iteration else "-"),
    ("t", 9, lambda r: f"{r.step_length:.3g}" if r.iteration else "-"),
    ("trials", 6, lambda r: f"{r.trials}" + (f"({r.invalid_trials}!)" if r.invalid_trials else "")),
    ("fwd(s)", 7, lambda r: f"{r.forward_seconds:.2f}"),
    ("grad(s)", 7, lambda r: f"{r.gradient_seconds:.2f}"),
)

# the scalar fields of a CSV log, in order (then one ``J:<term>`` column per objective term)
CSV_FIELDS = (
    "iteration",
    "objective",
    "gradient_norm",
    "step_norm",
    "step_length",
    "trials",
    "invalid_trials",
    "forward_seconds",
    "gradient_seconds",
    "seconds",
    "parameter_norm",
    "parameter_summary",
    "remeshed",
    "objective_before_remesh",
    "q",
)


class IterationLog:
    """The optimisation log: one line per accepted iterate, printed and/or written to a file.

    ``LBFGS(rf, log=True, log_file="log.csv")`` (or :func:`~diffsolids.optimize.minimize`) makes
    one; it is called like an ``on_accept`` observer, once per accepted iterate. The printed
    table has a header line, then per iterate: the iteration, J, the projected gradient norm,
    the step ``|q_k - q_{k-1}|_2`` and its line-search factor t, the line-search trials (with
    ``(k!)`` for k invalid ones), the seconds of the forward solves and of the gradient, and
    the controls (:func:`control_summary`); after a remesh a note follows. The lines go to
    rank 0's stdout, past any progress bar.

    The file (rank 0) is CSV when its name ends in ``.csv`` (the columns ``CSV_FIELDS``,
    then ``J:<name>`` per objective term) and JSON lines when it ends in ``.jsonl`` or
    ``.json`` (one :meth:`IterationRecord.to_json` per line, the format of ``history.jsonl``).
    Every line is flushed when written; :func:`read_log` reads either format back.

    Args:
        comm: Communicator of the run (rank 0 prints and writes).
        show: Print the lines.
        path: The log file (None: no file).

    Raises:
        OptimizationError: A file name with another ending.
    """

    def __init__(
        self, comm: MPI.Comm, show: bool = True, path: str | os.PathLike | None = None
    ) -> None:
        self.comm = comm
        self.show = bool(show)
        self.path = None if path is None else Path(path)
        self.format = None if self.path is None else _log_format(self.path)
        self._terms: list[str] | None = None
        self._header = False

    def header(self) -> str:
        """The title line of the printed table."""
        return " ".join(f"{t:>{w}}" for t, w, _ in _COLUMNS) + "  controls"

    def line(self, rec: IterationRecord) -> str:
        """The printed line of one record."""
        # a space between columns: a value wider than its column shifts the line, never merges
        text = " ".join(f"{f(rec):>{w}}" for _, w, f in _COLUMNS) + "  " + rec.parameter_summary
        if rec.remeshed:
            text += f"  (remeshed; J was {rec.objective_before_remesh:.9e})"
        return text

    def start(self, history: list[IterationRecord]) -> None:
        """Begin the file with ``history`` (empty, or the records before a resumption)."""
        if self.comm.rank != 0:
            return
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.path.write_text("")
            self._terms = None
            for rec in history:
                self._write(rec)
        if self.show and history:
            self._print(self.header())
            self._header = True
            self._print(f"(resumed after iteration {history[-1].iteration})")

    def __call__(self, rec: IterationRecord, optimizer: object = None) -> None:
        """Print and write one accepted iterate (rank 0; the other ranks return)."""
        if self.comm.rank != 0:
            return
        if self.show:
            if not self._header:
                self._print(self.header())
                self._header = True
            self._print(self.line(rec))
        if self.path is not None:
            self._write(rec)

    @staticmethod
    def _print(text: str) -> None:
        from diffsolids.io.progress import write_line

        write_line(text)

    def _write(self, rec: IterationRecord) -> None:
        if self.format == "jsonl":
            text = rec.to_json() + "\n"
        else:
            buf = io.StringIO()
            writer = csv.writer(buf, lineterminator="\n")
            if self._terms is None:
                self._terms = list(rec.terms)
                if self.path.stat().st_size == 0:
                    writer.writerow([*CSV_FIELDS, *(f"J:{t}" for t in self._terms)])
            row = [_csv_value(getattr(rec, f)) for f in CSV_FIELDS]
            writer.writerow(row + [_csv_value(rec.terms.get(t)) for t in self._terms])
            text = buf.getvalue()
        with open(self.path, "a") as f:
            f.write(text)
            f.flush()


def _log_format(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return "csv"
    if suffix in (".jsonl", ".json"):
        return "jsonl"
    raise OptimizationError(
        f"log_file {str(path)!r}: the name must end in .csv (CSV) or .jsonl/.json (JSON lines)"
    )


def _csv_value(value: object) -> str:
    if value is None:
        return ""
    if isinstance(value, list):  # q: all digits, blank-separated
        return " ".join(repr(float(x)) for x in value)
    if isinstance(value, float):
        return repr(value)  # all digits: read_log gives the numbers back exactly
    return str(value)


def read_log(path: str | os.PathLike) -> list[IterationRecord]:
    """The records of an optimisation log (CSV or JSON lines) or of a ``history.jsonl``.

    Raises:
        OptimizationError: A file name that is neither ``.csv`` nor ``.jsonl``/``.json``.
    """
    path = Path(path)
    if _log_format(path) == "jsonl":
        lines = path.read_text().splitlines()
        return [IterationRecord.from_dict(json.loads(s)) for s in lines if s.strip()]
    records = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            terms = {k[2:]: float(v) for k, v in row.items() if k.startswith("J:") and v != ""}
            d = {k: _from_csv(k, row[k]) for k in CSV_FIELDS if k in row}
            records.append(IterationRecord(terms=terms, **d))
    return records


def _from_csv(field_name: str, text: str) -> int | str | bool | float | list[float] | None:
    if field_name in ("iteration", "trials", "invalid_trials"):
        return int(text)
    if field_name == "parameter_summary":
        return text
    if field_name == "remeshed":
        return text == "True"
    if field_name == "q":
        return [float(x) for x in text.split()] if text else None
    return float(text) if text != "" else None


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


def plot_log(
    history: list[IterationRecord], path: str | os.PathLike, title: str | None = None
) -> Path:
    """One figure of a run: J (and its terms) and the projected gradient norm per iteration.

    Two panels over the iteration, logarithmic where the values are positive, a grey line at
    each remesh; the format follows the name (``.svg``, ``.png``, ``.pdf``). Plot a finished
    run with ``plot_log(read_log("log.csv"), "log.svg")``.

    Args:
        history: The records (``result.history`` or :func:`read_log`).
        path: The figure file.
        title: Title above the panels.

    Returns:
        The path written.
    """
    from matplotlib.figure import Figure  # Agg canvas, no pyplot state

    if not history:
        raise OptimizationError("plot_log needs at least one record")
    path = Path(path)
    it = [r.iteration for r in history]
    fig = Figure(figsize=(6.4, 4.8), layout="constrained")
    ax_j, ax_g = fig.subplots(2, 1, sharex=True)
    series = [("J", [r.objective for r in history], "o-")]
    if len(history[-1].terms) > 1:
        for label in history[-1].terms:
            values = [r.terms.get(label, np.nan) for r in history]
            series.append((label, values, ".--"))
    for ax, curves, ylabel in (
        (ax_j, series, "objective J"),
        (ax_g, [("|grad|", [r.gradient_norm for r in history], "s-")], "projected |grad J|"),
    ):
        positive = True
        for label, values, style in curves:
            values = np.asarray(values, dtype=float)
            positive = positive and bool(np.all(values[np.isfinite(values)] > 0))
            ax.plot(it, values, style, label=label, ms=4)
        if positive:
            ax.set_yscale("log")
        for r in history:
            if r.remeshed:
                ax.axvline(r.iteration, color="0.7", lw=0.8)
        ax.set_ylabel(ylabel)
        ax.grid(True, which="major", color="0.9")
        if len(curves) > 1:
            ax.legend(fontsize="small")
    ax_g.set_xlabel("iteration")
    ax_g.xaxis.get_major_locator().set_params(integer=True)
    if title:
        ax_j.set_title(title)
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    fmt = path.suffix.lstrip(".").lower() or "png"
    metadata = {"Date": None} if fmt == "svg" else None  # the same file for the same run
    fig.savefig(buf, format=fmt, dpi=100, metadata=metadata)
    atomic_write_bytes(path, buf.getvalue())
    return path


def _save(fig: "Figure", path: Path) -> None:
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
        write_parameters: bool = True,
        plot_every: int = 10,
        iterate_every: int = 0,
        iterate_format: str = "bp",
    ) -> None:
        if iterate_format not in ("bp", "xdmf"):
            raise OptimizationError(
                f"iterate_format must be 'bp' or 'xdmf', not {iterate_format!r}"
            )
        if plot_every < 0 or iterate_every < 0:
            raise OptimizationError("plot_every and iterate_every must be >= 0 (0: never)")
        self.directory = make_directory(directory, comm, "output directory")
        self.comm = comm
        self.write_parameters = write_parameters
        self.plot_every = plot_every
        self.iterate_every = iterate_every
        self.iterate_format = iterate_format

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
        from diffsolids.io.output import write_trajectory

        path = self.directory / "iterates" / f"iterate_{iteration:04d}.{self.iterate_format}"
        write_trajectory(model, trajectory, path)
        return path
