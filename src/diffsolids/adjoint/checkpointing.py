"""Time-step checkpointing of the backward sweep: memory-bounded adjoints of long horizons.

The adjoint of step i reads the states u^{i-d}..u^i and v^{i-d}..v^i, d = max(m, 2) for BDF_m
(the predictor reads m earlier states, contact's step motion the last two velocities; the
static steps read one). Keeping every state (the default of short runs) costs N + 1 states;
a checkpointing schedule of the ``checkpoint_schedules`` package (Revolve, multistage, disk)
keeps a few and recomputes the others from them. A checkpoint of step n (forward restart data)
holds u^{n-d+1..n}, v^{n-d+1..n}: everything a step reads that is not recomputed by the step
itself. The per-step state of numeric terms (contact: lagged friction, BDF velocity history,
the step's motion bounds) is rebuilt by their ``begin_step`` from these states, the Newton
solver's reference force is that of the first solved step (kept, or recomputed by it), and a
recomputed step starts from the same initial guess as the first forward (the warm start that
run used is kept); the recomputed states, and the gradient, are therefore those of the
all-in-memory run. The forward factorisations that precondition the adjoint solves are kept
only for steps recomputed right before their adjoint (``write_adj_deps`` of the schedule's
forward actions), and freed after it.

Schedules (``checkpoint_schedules`` indexing: its step n advances state n to n + 1, our step
n + 1): ``Forward(n0, n1, write_ics, write_adj_deps, storage)``, ``Reverse(n1, n0)``,
``Copy``/``Move`` of checkpoints between RAM, DISK and WORK (the states the forward and the
adjoint use), ``EndForward``, ``EndReverse``.
"""

import contextlib
import os
import shutil
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from checkpoint_schedules import (
    CheckpointAction,
    CheckpointSchedule,
    Copy,
    EndForward,
    EndReverse,
    Forward,
    Move,
    MultistageCheckpointSchedule,
    Reverse,
    Revolve,
    SingleDiskStorageSchedule,
    SingleMemoryStorageSchedule,
    StorageType,
)
from mpi4py import MPI

from diffsolids.errors import DiffsolidsError, ParameterError
from diffsolids.parallel import collective_comm
from diffsolids.solvers.factor_store import node_memory_mb

if TYPE_CHECKING:
    import h5py

    from diffsolids.simulation import Simulation, StepRecord

__all__ = [
    "CheckpointedRun",
    "CheckpointedTrajectory",
    "Checkpointing",
    "CheckpointingError",
    "state_depth",
]

_POLICIES = ("auto", "all", "memory", "disk")
_SCHEDULES = ("revolve", "multistage")


class CheckpointingError(DiffsolidsError, LookupError):
    """A state that a checkpointed run does not hold, or a schedule that cannot go on."""


@dataclass(frozen=True)
class Checkpointing:
    """Which forward states the adjoint keeps, and where.

    Policies:
        ``"all"``: every state u^i, v^i in memory (no recomputation; the behaviour without
        checkpointing).
        ``"memory"``: ``snaps`` checkpoints in memory; the adjoint recomputes the steps between
        them (``schedule="revolve"``: binomial Revolve, fewest recomputations for ``snaps``;
        ``"multistage"``: the multistage schedule of Stumm and Walther).
        ``"disk"``: ``snaps=None`` writes every state to disk (no recomputation, memory of a
        few states); ``snaps=k`` keeps k multistage checkpoints on disk and recomputes. Each
        rank writes its owned and ghost entries to its own HDF5 file in a temporary directory
        (under ``directory`` if given), removed when the run is closed (by the next forward) or
        dropped.
        ``"auto"`` (default): chosen at each forward run from the memory this node has
        available (``MemAvailable`` of ``/proc/meminfo``, or the container's cgroup limit):
        the states of all ranks on the node may take ``memory_fraction`` of what the factor
        store leaves (:meth:`~diffsolids.solvers.factor_store.FactorStore.spare_mb`: with the
        default store, the memory above the node's reserve of 25% of its total, less the
        store's 10% of the available memory).
        Every state in memory when N + 1 states fit, or when they take at most 1% of the
        available memory whatever the store claims (a small run is never checkpointed because
        the node is busy: its recomputation would cost more than the memory); else Revolve
        with as many checkpoints
        (of d states each, d = max(m, 2)) as fit, at least 2; else every state on disk. Where
        the memory is unknown, every state in memory up to 2000 MB per rank. Factorisations
        are never kept beyond the factor store's own budget, and in checkpointed runs only for
        the steps recomputed right before their adjoint.

    Args:
        policy: One of ``"auto"``, ``"all"``, ``"memory"``, ``"disk"``.
        snaps: Number of checkpoints (``"memory"``: required; ``"disk"``: optional).
        schedule: ``"revolve"`` or ``"multistage"`` (``"memory"`` only).
        directory: Parent directory of the disk checkpoints (default: the system temp dir).
        memory_fraction: Share of the spare memory the states may take (``"auto"``).

    Raises:
        ParameterError: Unknown policy or schedule, or a number of checkpoints < 1.

    Example:
        ``ReducedFunctional(sim, J, controls, checkpointing=Checkpointing("memory", snaps=8))``.
    """

    policy: str = "auto"
    snaps: int | None = None
    schedule: str = "revolve"
    directory: str | os.PathLike | None = None
    memory_fraction: float = 0.5

    def __post_init__(self) -> None:
        if self.policy not in _POLICIES:
            raise ParameterError(
                f"unknown checkpointing policy {self.policy!r}; choose one of {_POLICIES}"
            )
        if self.schedule not in _SCHEDULES:
            raise ParameterError(
                f"unknown checkpointing schedule {self.schedule!r}; choose one of {_SCHEDULES}"
            )
        if self.policy == "memory" and self.snaps is None:
            raise ParameterError("the 'memory' checkpointing policy needs a number of snaps")
        if self.snaps is not None and (int(self.snaps) != self.snaps or self.snaps < 1):
            raise ParameterError(f"snaps must be a positive integer, got {self.snaps}")
        if self.policy == "all" and self.snaps is not None:
            raise ParameterError("the 'all' policy keeps every state: it takes no snaps")
        if not 0.0 < self.memory_fraction <= 1.0:
            raise ParameterError(f"memory_fraction must be in (0, 1], got {self.memory_fraction}")

    def resolve(self, simulation: "Simulation") -> "Checkpointing":
        """The concrete policy (never ``"auto"``) for a run of ``simulation`` (collective)."""
        if self.policy != "auto":
            return self
        N = simulation.integrator.num_steps
        depth = state_depth(simulation)
        state_mb = 2 * 8 * len(simulation.u0) / 2**20  # u and v, owned and ghost entries
        budget = _state_budget_mb(simulation, self.memory_fraction)
        # the most demanding rank decides for all
        fitting = int(budget // max(state_mb, 1e-300))
        states = collective_comm(simulation.model.domain.comm).allreduce(fitting, op=MPI.MIN)
        if states >= N + 1:
            return Checkpointing("all")
        snaps = states // depth
        if snaps >= 2:
            return Checkpointing("memory", snaps=min(snaps, N), directory=self.directory)
        return Checkpointing("disk", directory=self.directory)

    def make_schedule(self, num_steps: int) -> CheckpointSchedule:
        """The ``checkpoint_schedules`` schedule of this (resolved) policy for N steps."""
        N = num_steps
        if self.policy == "all":
            return SingleMemoryStorageSchedule()
        if self.policy == "memory":
            snaps = min(int(self.snaps), N)
            if self.schedule == "multistage":
                return MultistageCheckpointSchedule(N, snaps, 0)
            return Revolve(N, snaps)
        if self.policy == "disk":
            if self.snaps is None:
                return SingleDiskStorageSchedule()
            return MultistageCheckpointSchedule(N, 0, min(int(self.snaps), N))
        raise ParameterError("resolve() the 'auto' policy before making a schedule")


#: The share of the available memory the states of a run may always take (see "auto").
_SMALL_RUN_SHARE = 0.01


def _state_budget_mb(simulation: "Simulation", fraction: float) -> float:
    """Memory (MB) per rank the states of a run may take: see :class:`Checkpointing`."""
    memory = node_memory_mb()
    if memory is None:
        return 2000.0
    available, total = memory
    node = simulation.model.domain.comm.Split_type(MPI.COMM_TYPE_SHARED)
    ranks = node.size
    node.Free()
    store = simulation.solver.factor_store
    spare = available if store is None else store.spare_mb(available, total, ranks)
    # a small run is never checkpointed because the store claims the spare memory
    return max(max(spare, 0.0) * fraction, _SMALL_RUN_SHARE * available) / ranks


def state_depth(simulation: "Simulation") -> int:
    """d: a step reads u^{i-j}, v^{i-j} for j = 1..d (BDF order, at least 2; static: 1)."""
    integ = simulation.integrator
    if not integ.dynamic and not simulation.model.numeric_terms:
        return integ.history_depth  # a static step reads u^{i-1}
    # contact's step motion reads the last two states
    return max(integ.history_depth, 2)


# -- storage of checkpoints --------------------------------------------------------------------
class _MemoryStorage:
    """Checkpoints in memory: the state arrays themselves (states are never modified)."""

    def __init__(self) -> None:
        self.records: dict[int, dict] = {}

    def put(self, n: int, record: dict) -> None:
        self.records[n] = record

    def get(self, n: int) -> dict:
        return self.records[n]

    def delete(self, n: int) -> None:
        self.records.pop(n, None)

    def close(self) -> None:
        self.records.clear()


class _DiskStorage:
    """Checkpoints in one HDF5 file per rank (its owned and ghost entries), a group each."""

    def __init__(self, comm: MPI.Comm, directory: str | os.PathLike | None) -> None:
        root = None
        if comm.rank == 0:
            root = tempfile.mkdtemp(prefix="diffsolids-checkpoints-", dir=directory)
        self.root = Path(collective_comm(comm).bcast(root, root=0))
        self.comm = comm
        self.rank = comm.rank
        self.path = self.root / f"rank{self.rank}.h5"
        self._file = None

    def _open(self) -> "h5py.File":
        if self._file is None:
            import h5py

            self._file = h5py.File(self.path, "a")
        return self._file

    def put(self, n: int, record: dict) -> None:
        f = self._open()
        name = str(n)
        if name in f:
            del f[name]
        group = f.create_group(name)
        group.attrs["kind"] = record["kind"]
        for j, (u, v) in record["states"].items():
            group.create_dataset(f"u/{j}", data=u)
            group.create_dataset(f"v/{j}", data=v)

    def get(self, n: int) -> dict:
        group = self._open()[str(n)]
        states = {int(j): (group["u"][j][...], group["v"][j][...]) for j in group.get("u", {})}
        return {"kind": str(group.attrs["kind"]), "states": states}

    def delete(self, n: int) -> None:
        f = self._open()
        if str(n) in f:
            del f[str(n)]

    def close(self) -> None:
        """Remove the files (collective: rank 0 removes the directory after all ranks)."""
        self.close_local()
        self.comm.Barrier()
        if self.rank == 0:
            shutil.rmtree(self.root, ignore_errors=True)

    def close_local(self) -> None:
        """Remove this rank's file (not collective; the directory stays if others remain)."""
        if self._file is not None:
            self._file.close()
            self._file = None
        with contextlib.suppress(OSError):
            self.path.unlink()
        with contextlib.suppress(OSError):
            self.root.rmdir()


# -- trajectories ----------------------------------------------------------------------------
class _States(Sequence[np.ndarray]):
    """Read-only sequence view of the u (0) or v (1) arrays of a dict of states."""

    def __init__(self, states: dict, which: int, length: Callable[[], int]) -> None:
        self._states, self._which, self._length = states, which, length

    def __len__(self) -> int:
        return self._length()

    def __getitem__(self, i: int) -> np.ndarray:
        if i < 0:
            i += len(self)
        try:
            return self._states[i][self._which]
        except KeyError:
            raise CheckpointingError(
                f"state {i} is not held by this checkpointed trajectory (it keeps "
                f"{sorted(self._states)}); use Checkpointing('all') to keep every state"
            ) from None


class _StateView:
    """Trajectory-like view of a dict of states (what ``Simulation.advance`` reads and writes).

    ``length`` is the trajectory length a step's reader sees: the number of states so far in
    the first forward and N + 1 in recomputations and in the backward sweep, as with a
    :class:`~diffsolids.states.Trajectory`. Terms take their phase from the
    :class:`~diffsolids.states.StepContext`; the length keeps terms with the deprecated
    ``begin_step(i, traj, ...)`` hook, which told the phases apart by it, working until 0.5.
    """

    def __init__(
        self,
        states: dict,
        length: Callable[[], int],
        on_append: Callable[[int, float, "StepRecord"], None] | None = None,
    ) -> None:
        self.states = states
        self.u = _States(states, 0, length)
        self.v = _States(states, 1, length)
        self._on_append = on_append
        self.next = 0

    def append_state(self, t: float, u: np.ndarray, v: np.ndarray, record: "StepRecord") -> None:
        self.states[self.next] = (u, v)
        if self._on_append is not None:
            self._on_append(self.next, t, record)
        self.next += 1


class CheckpointedTrajectory:
    """Times and step records of a checkpointed run; states only where it keeps them.

    ``u[i]``, ``v[i]`` raise :class:`CheckpointingError` for states not held (u^0, v^0 and
    u^N, v^N are always held). ``run`` is the :class:`CheckpointedRun` holding the checkpoints.
    """

    def __init__(self, num_steps: int, states: dict) -> None:
        self.run: CheckpointedRun | None = None  # the run holding the checkpoints
        self.rest_geometry: np.ndarray | None = None  # as Trajectory.rest_geometry
        self.times: list[float] = [0.0]
        self.records: list = []
        self._N = num_steps
        self._states = states
        self.u = _States(states, 0, lambda: num_steps + 1)
        self.v = _States(states, 1, lambda: num_steps + 1)

    @property
    def num_steps(self) -> int:
        """N (the trajectory has N + 1 states)."""
        return self._N

    def newton_iterations(self) -> int:
        """Total Newton iterations over all steps."""
        return sum(r.iterations for r in self.records)


# -- the run -------------------------------------------------------------------------------
class CheckpointedRun:
    """A forward run and its backward sweep driven by a checkpointing schedule.

    Args:
        simulation: The Simulation.
        policy: A resolved :class:`Checkpointing` (not ``"auto"``).

    Attributes:
        stats: Of the run so far: ``forward_steps`` solved in the first forward,
            ``recomputed_steps``, ``checkpoints`` written, ``peak_states`` held in memory at
            once (checkpoints, working states and adjoint dependencies, each array once).
    """

    def __init__(self, simulation: "Simulation", policy: Checkpointing) -> None:
        if policy.policy == "auto":
            policy = policy.resolve(simulation)
        self.sim = simulation
        self.policy = policy
        self.N = simulation.integrator.num_steps
        self.depth = state_depth(simulation)
        self.schedule = policy.make_schedule(self.N)
        comm = simulation.model.domain.comm
        self._storage = {StorageType.RAM: _MemoryStorage()}
        if self.schedule.uses_storage_type(StorageType.DISK):
            self._storage[StorageType.DISK] = _DiskStorage(comm, policy.directory)
        self._work: dict[int, tuple] = {}  # the forward's last d states
        self._adj: dict[int, tuple] = {}  # states the adjoint reads (WORK)
        self._keep: dict[int, tuple] = {}  # u^0, v^0 and u^N, v^N
        self._n = 0  # the forward's position
        self._finished_forward = False
        self.warm_start = None
        self.trajectory: CheckpointedTrajectory | None = None
        self.stats = {"forward_steps": 0, "recomputed_steps": 0, "checkpoints": 0}
        self._peak = 0
        self.closed = False
        self.reversed = False  # a reverse ran (and freed the factors it used)
        self.on_state: Callable | None = None

    # -- bookkeeping ---------------------------------------------------------------------------
    def _window(self, n: int) -> dict:
        """The states a restart at n needs: u^j, v^j for j = n - d + 1..n."""
        return {j: self._work[j] for j in range(max(n - self.depth + 1, 0), n + 1)}

    def _count(self) -> None:
        ids = {
            id(a) for s in (self._work, self._adj, self._keep) for pair in s.values() for a in pair
        }
        for rec in self._storage[StorageType.RAM].records.values():
            ids |= {id(a) for pair in rec["states"].values() for a in pair}
        self._peak = max(self._peak, len(ids) // 2)
        self.stats["peak_states"] = self._peak

    def _put(self, storage: StorageType, n: int, record: dict) -> None:
        self._storage[storage].put(n, record)
        self.stats["checkpoints"] += 1

    # -- forward ---------------------------------------------------------------------------------
    def start(self) -> CheckpointedTrajectory:
        """Begin the first forward run (called by ``Simulation.run``): state 0."""
        sim = self.sim
        self.warm_start = sim.warm_start
        state0 = (sim.u0.copy(), sim.v0.copy())
        self._work = {0: state0}
        self._keep = {0: state0}
        self.trajectory = CheckpointedTrajectory(self.N, self._keep)
        self.trajectory.run = self
        return self.trajectory

    def forward(self, stepped: Callable | None = None) -> None:
        """Run the schedule's first forward to its end (``EndForward``).

        Args:
            stepped: Called as ``stepped(i, view)`` after step i (output, progress, callback).
                :attr:`on_state`, if set, is called as ``on_state(i, view)`` for i = 0..N
                before (the objective's integrals of the states).
        """
        self._stepped, self._on_state = stepped, self.on_state
        if self._on_state is not None:
            self._on_state(0, self._first_view(0))
        for action in self.schedule:
            if isinstance(action, EndForward):
                break
            self._action(action, first=True)
        self._finished_forward = True
        self._stepped = self._on_state = None

    def _first_view(self, n: int) -> _StateView:
        return _StateView(self._work, lambda: n + 1)

    def _advance(self, n0: int, n1: int, adj: bool, first: bool) -> None:
        """Steps n0 + 1..n1 from the working states at n0 (factors kept when ``adj``)."""
        sim = self.sim
        solver = sim.solver
        warm = sim.warm_start
        sim.warm_start = self.warm_start  # the initial guesses of the first forward
        try:
            with solver.keeping_factors_in(solver.factor_store if adj else None):
                for i in range(n0 + 1, n1 + 1):
                    self._advance_one(i, adj, first)
        finally:
            sim.warm_start = warm
        self._n = n1

    def _advance_one(self, i: int, adj: bool, first: bool) -> None:
        """Step i from the working states (recorded in the trajectory on the first forward)."""
        traj = self.trajectory

        def record(j: int, t: float, rec: "StepRecord") -> None:
            traj.times.append(t)
            traj.records.append(rec)

        if first:
            view = _StateView(self._work, lambda i=i: i, record)
        else:
            view = _StateView(self._work, lambda: self.N + 1)
        view.next = i
        self.sim.advance(i, view, replay=not first)
        self.stats["forward_steps" if first else "recomputed_steps"] += 1
        if adj:
            self._adj[i] = self._work[i]
        if i == self.N:
            self._keep[i] = self._work[i]
        if first:
            if self._on_state is not None:
                self._on_state(i, _StateView(self._work, lambda i=i: i + 1))
            if self._stepped is not None:
                self._stepped(i, _StateView(self._work, lambda i=i: i + 1))
        self._count()
        for j in [j for j in self._work if j <= i - self.depth]:
            del self._work[j]

    def _action(self, action: CheckpointAction, first: bool = False) -> None:
        schedule = self.schedule
        if isinstance(action, Forward):
            n0, n1 = action.n0, min(action.n1, self.N)
            if n0 != self._n:
                raise CheckpointingError(
                    f"the schedule runs forward from {n0}, the run is at {self._n}"
                )
            if action.write_ics:
                self._put(action.storage, n0, {"kind": "ics", "states": self._window(n0)})
            adj = action.write_adj_deps
            if adj:
                self._adj.update(self._window(n0))
            self._advance(n0, n1, adj, first)
            if adj and action.storage != StorageType.WORK:
                states = {j: self._adj.pop(j) for j in range(max(n0 - self.depth + 1, 0), n1 + 1)}
                self._put(action.storage, n0, {"kind": "adj", "states": states})
            if n1 == self.N and schedule.max_n is None:
                schedule.finalize(self.N)
        elif isinstance(action, Copy | Move):
            self._load(action)
        elif isinstance(action, Reverse | EndForward | EndReverse):
            raise CheckpointingError(f"unexpected checkpointing action {action}")
        else:
            raise CheckpointingError(f"unknown checkpointing action {action}")

    def _load(self, action: Copy | Move) -> None:
        n, source, target = action.n, action.from_storage, action.to_storage
        if target == StorageType.NONE:
            self._storage[source].delete(n)
            return
        record = self._storage[source].get(n)
        if isinstance(action, Move):
            self._storage[source].delete(n)
        if target != StorageType.WORK:
            self._storage[target].put(n, record)
            return
        if record["kind"] == "ics":
            self._work = dict(record["states"])
            self._n = n
        else:
            self._adj.update(record["states"])
        self._count()

    # -- reverse -----------------------------------------------------------------------------
    def reverse(self, adjoint_step: Callable) -> None:
        """Run the schedule's reverse phase: ``adjoint_step(i, view)`` for i = N..1.

        The view holds u^{i-d..i}, v^{i-d..i} (and has length N + 1).

        Raises:
            CheckpointingError: The first forward has not run, or the schedule is exhausted
                (one reverse per forward for Revolve and multistage schedules).
        """
        if not self._finished_forward or self.closed:
            raise CheckpointingError("no checkpointed forward to reverse (not run, or closed)")
        if self.schedule.is_exhausted:
            raise CheckpointingError("this checkpointing schedule allows no further reverse")
        view = _StateView(self._adj, lambda: self.N + 1)
        for action in self.schedule:
            if isinstance(action, EndReverse):
                break
            if isinstance(action, Reverse):
                for step in action:  # schedule step n is our step n + 1
                    adjoint_step(step + 1, view)
                if action.clear_adj_deps:
                    self._adj.clear()
                self._count()
            else:
                self._action(action)
        self._adj.clear()
        self.reversed = True

    @property
    def exhausted(self) -> bool:
        """Whether the schedule can run no further reverse (a new forward is needed)."""
        return bool(self.schedule.is_exhausted)

    def initial_state(self) -> tuple[np.ndarray, np.ndarray]:
        """(u^0, v^0)."""
        return self._keep[0]

    def close(self) -> None:
        """Free the checkpoints (removes the disk files)."""
        if self.closed:
            return
        for storage in self._storage.values():
            storage.close()
        self._work.clear()
        self._adj.clear()
        self.closed = True

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            if StorageType.DISK in self._storage:
                self._storage[StorageType.DISK].close_local()
