"""States of a run and the set-up of one step, shared by the forward, the objective and the adjoint.

A run's states u^i, v^i live in a :class:`Trajectory` (or a checkpointed run's view of the
states a step reads, any :class:`StateHistory`). Before a step is solved (forward), evaluated
(objective) or differentiated (backward sweep), the simulation describes it to the model's
numeric terms by one :class:`StepContext`: the step's index, its
:class:`~diffsolids.integrators.TimeStep`, the states it reads, the integrator (the clock) and
the phase, so that no term has to guess which driver called it.
"""

import enum
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from diffsolids.integrators import Integrator, TimeStep

__all__ = [
    "Phase",
    "RunDriver",
    "RunRecord",
    "StateHistory",
    "StateRecorder",
    "StepContext",
    "StepRecord",
    "Trajectory",
]


@dataclass
class StepRecord:
    """Log of one step."""

    step: int
    time: float
    order: int
    iterations: int
    residual: float
    energy: float
    seconds: float


class StateHistory(Protocol):
    """The states a step reads: u^k, v^k by absolute step k (local arrays incl. ghosts).

    A :class:`Trajectory`, or the view of a checkpointed run that holds the states the step
    reads (u^{i-j}, v^{i-j} for j = 1..d); the forward appends the step's state to a
    :class:`StateRecorder`.
    """

    @property
    def u(self) -> Sequence[np.ndarray]:
        """Displacements by step."""

    @property
    def v(self) -> Sequence[np.ndarray]:
        """Velocities by step."""


class StateRecorder(StateHistory, Protocol):
    """A :class:`StateHistory` a forward step appends its state to.

    A :class:`Trajectory`, or the view of a checkpointed run that keeps the states its
    schedule needs.
    """

    def append_state(self, t: float, u: np.ndarray, v: np.ndarray, record: StepRecord) -> None:
        """Append u^i, v^i of the step at time ``t`` and its record."""
        ...


class RunRecord(StateHistory, Protocol):
    """What a run returns: times, step records and the states it keeps.

    A :class:`Trajectory` keeps every state; a checkpointed run's record
    (:class:`diffsolids.adjoint.checkpointing.CheckpointedTrajectory`) only some.
    """

    times: list[float]
    records: list[StepRecord]
    rest_geometry: np.ndarray | None

    @property
    def num_steps(self) -> int:
        """N (the run has N + 1 states)."""
        ...

    def newton_iterations(self) -> int:
        """Total Newton iterations over all steps."""
        ...


class RunDriver(Protocol):
    """Drives the steps of a run by its own schedule (checkpointing).

    :meth:`diffsolids.simulation.Simulation.run` calls :meth:`start` for the record of state 0,
    then :meth:`forward`, which advances the simulation through all steps.
    """

    def start(self) -> RunRecord:
        """Begin the run: the record holding state 0."""
        ...

    def forward(self, stepped: Callable[[int, StateHistory], None] | None = None) -> None:
        """Advance through all steps, calling ``stepped(i, states)`` after step i."""
        ...


@dataclass
class Trajectory:
    """States u^i, v^i (local arrays incl. ghosts) for i = 0..N and per-step records.

    ``rest_geometry`` is the mesh's ``geometry.x`` (this rank's nodes) the run started from, so
    that output written after a shape change shows the trajectory on its own rest shape (None:
    the mesh's current geometry).
    """

    times: list[float] = field(default_factory=list)
    u: list[np.ndarray] = field(default_factory=list)
    v: list[np.ndarray] = field(default_factory=list)
    records: list[StepRecord] = field(default_factory=list)
    rest_geometry: np.ndarray | None = None

    @property
    def num_steps(self) -> int:
        """N (the trajectory holds N + 1 states)."""
        return len(self.u) - 1

    def newton_iterations(self) -> int:
        """Total Newton iterations over all steps."""
        return sum(r.iterations for r in self.records)

    def append_state(self, t: float, u: np.ndarray, v: np.ndarray, record: StepRecord) -> None:
        """Append the state of the next step and its record."""
        self.times.append(t)
        self.u.append(u)
        self.v.append(v)
        self.records.append(record)


class Phase(enum.Enum):
    """Which driver sets a step up."""

    #: The forward run solves the step (its state u^i is not known yet).
    FORWARD = "forward"
    #: The backward sweep solves the step again from a checkpoint; nothing is recorded or
    #: checked again.
    REPLAY = "replay"
    #: An objective is evaluated on the step's known state.
    EVALUATION = "evaluation"
    #: The backward sweep differentiates the step at its known state.
    BACKWARD = "backward"


@dataclass(frozen=True)
class StepContext:
    """One step as the forward, the objective evaluation and the backward sweep set it up.

    Attributes:
        index: The step i (1..N).
        step: The step's time discretisation (coefficients, predictor, velocity).
        history: The states the step reads (u^{i-j}, v^{i-j}).
        integrator: The run's integrator (times of all steps, static or dynamic).
        phase: Which driver sets the step up.
    """

    index: int
    step: TimeStep
    history: StateHistory
    integrator: Integrator
    phase: Phase

    @classmethod
    def of(
        cls,
        integrator: Integrator,
        index: int,
        history: StateHistory,
        phase: Phase = Phase.FORWARD,
    ) -> "StepContext":
        """The context of step ``index`` of ``integrator`` (its TimeStep made here)."""
        return cls(index, integrator.step(index), history, integrator, phase)

    @property
    def forward(self) -> bool:
        """Whether the run solves the step for the first time (not a replay)."""
        return self.phase is Phase.FORWARD

    def time(self, k: int) -> float:
        """The time of step ``k``."""
        return float(self.integrator.time(k))
