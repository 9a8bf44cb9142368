"""Values of step series along a trajectory: the numbers behind an objective, per state.

An objective's :class:`~diffsolids.objectives.Series` (a centre of mass, a stress norm, a
misfit) has one value per state; :func:`series_values` evaluates it on any trajectory, e.g. the
path of a body's centre of mass for a figure or a check::

    com = series_values(sim, center_of_mass(model, "B"), trajectory)  # (N + 1, dim)

and :func:`step_values` gives the per-state values of every series an objective reduces (time
integrals, soft minima) along the last forward run of a ReducedFunctional, by label.
"""

from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

import numpy as np
from dolfinx import fem
from mpi4py import MPI

from diffsolids.objectives.functional import NumericIntegral, Objective, ObjectiveError, Series
from diffsolids.objectives.terms import series_label
from diffsolids.parallel import collective_comm
from diffsolids.solvers.forms import compile_form
from diffsolids.states import Phase

if TYPE_CHECKING:
    from diffsolids.simulation import Simulation
    from diffsolids.states import StateHistory

__all__ = ["EvaluatedFunctional", "objective_series", "series_values", "step_values"]


class EvaluatedFunctional(Protocol):
    """A functional after its forward run (met by :class:`~diffsolids.ReducedFunctional`)."""

    @property
    def objective(self) -> Objective:
        """The objective J."""
        ...

    @property
    def simulation(self) -> "Simulation":
        """The simulation whose run J reads."""
        ...

    @property
    def trajectory(self) -> "StateHistory | None":
        """The last forward run's states (None before the first run)."""
        ...


def _state_indices(steps: Sequence[int] | None, num_states: int) -> list[int]:
    if steps is None:
        return list(range(num_states))
    out = []
    for s in steps:
        i = int(s)
        if not -num_states <= i < num_states:
            raise IndexError(f"state {i} out of range for a trajectory of {num_states} states")
        out.append(i % num_states)
    return out


def series_values(
    simulation: "Simulation",
    series: Series | Sequence[Series],
    trajectory: "StateHistory",
    steps: Sequence[int] | None = None,
) -> np.ndarray:
    """Values of one or several series at the states of a trajectory (collective).

    Every state is evaluated as the ReducedFunctional evaluates an objective: the step's data
    (time, loads, history fields) are those set by ``simulation.load_step(i, trajectory)``
    (time 0 for state 0, where the history fields ``u_prev`` and ``u_tilde`` hold u^0: no
    motion before the start) and the model's ``u`` and ``v`` hold the state. The model's ``u`` and
    ``v`` are restored afterwards; the step data stay those of the last state evaluated (every
    solve and objective evaluation sets its own).

    Args:
        simulation: The Simulation the trajectory belongs to (its model and integrator).
        series: A Series, or a sequence of them (e.g. ``center_of_mass(model, "B")``).
        trajectory: The Trajectory (states 0..N).
        steps: The states to evaluate (negative indices count from the end; default: all).

    Returns:
        Shape (number of states,) for one series, (number of states, number of series) for a
        sequence; the same on every rank.

    Raises:
        IndexError: A state outside 0..N.
    """
    single = isinstance(series, Series)
    parts = [series] if single else list(series)
    model = simulation.model
    f = model.fields
    num_states = len(trajectory.u)
    wanted = _state_indices(steps, num_states)
    leaves = list(dict.fromkeys(leaf for s in parts for leaf in s.leaves()))
    forms = {
        leaf: compile_form(leaf.form(f)) for leaf in leaves if not isinstance(leaf, NumericIntegral)
    }
    comm = collective_comm(model.domain.comm)
    table = {leaf: np.full(num_states, np.nan) for leaf in leaves}
    saved_u, saved_v = f.u.x.array.copy(), f.v.x.array.copy()
    try:
        for i in sorted(set(wanted)):
            if i > 0:
                simulation.prepare_step(i, trajectory, Phase.EVALUATION)
            else:
                model.update_time(0.0)
                # no motion before the start: the history fields of state 0 hold u^0
                f.u_prev.x.array[:] = trajectory.u[0]
                f.u_tilde.x.array[:] = trajectory.u[0]
            f.u.x.array[:] = trajectory.u[i]
            f.v.x.array[:] = trajectory.v[i]
            for leaf in leaves:
                if isinstance(leaf, NumericIntegral):
                    table[leaf][i] = leaf.evaluate(model)
                else:
                    table[leaf][i] = collective_comm(comm).allreduce(
                        fem.assemble_scalar(forms[leaf]), op=MPI.SUM
                    )
    finally:
        f.u.x.array[:] = saved_u
        f.v.x.array[:] = saved_v
    values = np.column_stack([np.broadcast_to(s.values(table), (num_states,)) for s in parts])
    values = values[wanted]
    return values[:, 0] if single else values


def objective_series(objective: Objective) -> dict[str, Series]:
    """The series an objective reduces over steps (time integrals, soft minima), by label.

    Labels are those of the objective's terms (e.g. ``"target trajectory"``); a repeated label
    gets a ``#k`` suffix. A series reduced twice is listed once.
    """
    found: list[Series] = []
    for series in objective.reduced_series():
        if all(series is not s for s in found):
            found.append(series)
    labels = [series_label(s) for s in found]
    out: dict[str, Series] = {}
    counts: dict[str, int] = {}
    for label, series in zip(labels, found, strict=True):
        if labels.count(label) > 1:
            counts[label] = counts.get(label, 0) + 1
            label = f"{label}#{counts[label]}"
        out[label] = series
    return out


def step_values(rf: EvaluatedFunctional) -> dict[str, np.ndarray]:
    """Per-state values of the series of an objective along the last forward run (collective).

    Every state 0..N is evaluated (also those the objective gives zero weight, so there is no
    NaN placeholder), as :func:`series_values` does; the numbers behind a time integral are
    ``J_term = sum_i w_i s_i``.

    Args:
        rf: A ReducedFunctional after a forward run (``rf(q)``).

    Returns:
        ``{label: array of shape (N + 1,)}``, the same on every rank.

    Raises:
        ObjectiveError: No forward run yet.
        CheckpointingError: A checkpointed run that did not keep every state (use
            ``Checkpointing("all")``).
    """
    if rf.trajectory is None:
        raise ObjectiveError("no forward run yet: call rf(q) before step_values(rf)")
    series = objective_series(rf.objective)
    if not series:
        return {}
    values = series_values(rf.simulation, list(series.values()), rf.trajectory)
    return {label: values[:, k] for k, label in enumerate(series)}
