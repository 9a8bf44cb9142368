"""J(q): forward simulation, objective and adjoint gradient behind one callable."""

import contextlib
import logging
import time
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

from diffsolids.adjoint import AdjointSolverOptions, BackwardSweep, Sensitivities
from diffsolids.adjoint.checkpointing import CheckpointedRun, CheckpointedTrajectory, Checkpointing
from diffsolids.adjoint.forms import check_objective_fields
from diffsolids.controls import Control, ControlSet
from diffsolids.errors import DiffsolidsError, ParameterError
from diffsolids.objectives import NumericIntegral, Objective, ObjectiveError, TimeGrid
from diffsolids.objectives.terms import objective_terms
from diffsolids.parallel import collective_comm
from diffsolids.solvers import compile_form
from diffsolids.solvers.factor_store import FactorStore
from diffsolids.states import Phase

if TYPE_CHECKING:
    from diffsolids.simulation import Simulation
    from diffsolids.states import StateHistory, Trajectory

__all__ = ["AdjointError", "ReducedFunctional"]

logger = logging.getLogger("diffsolids")


class AdjointError(DiffsolidsError, RuntimeError):
    """A gradient requested in a state where it cannot be computed."""


class ReducedFunctional:
    """The objective as a function of the control parameters, with its adjoint gradient.

    Args:
        simulation: The forward Simulation.
        objective: A scalar Objective.
        controls: One Control or a sequence (concatenated into one parameter vector).
        adjoint_options: Options of the adjoint linear solves.
        factor_memory_mb: Memory (per rank) for keeping each forward step's last Newton
            factorisation in memory as the adjoint preconditioner of that step (0 disables;
            None, the default, keeps them on disk, MUMPS out-of-core: see
            :class:`~diffsolids.solvers.factor_store.FactorStore`).
        checkpointing: Which forward states the adjoint keeps: a
            :class:`~diffsolids.adjoint.checkpointing.Checkpointing` policy (all in memory, a
            fixed number of checkpoints in memory, or disk); None (default) is
            ``Checkpointing("auto")``, which keeps every state in memory while the states fit
            the node's spare memory and checkpoints otherwise (the rule is in
            :class:`~diffsolids.adjoint.checkpointing.Checkpointing`). Checkpointed runs give the
            gradient of the all-in-memory run; their ``trajectory`` holds u^0, u^N and the
            records only, and does not warm-start later runs.
        branch_reference: Parameters q_ref whose forward run (solved once, when first needed)
            (:attr:`reference_run`) is the simulation's ``branch_reference`` while this
            functional runs: every later forward starts each step's Newton solve at the
            reference run's state when that state is admissible.
            Use it where a contact step has several local minima (J would jump between
            branches under tiny changes of q): J is then one deterministic function of q,
            smooth near q_ref, independent of the evaluation history, and the optimiser's
            warm start is not used. None (default): each step is solved from the
            simulation's own initial guess.
        factor_store: The store of the factorisations kept for the adjoint, for settings
            ``factor_memory_mb`` does not cover (e.g. ``FactorStore(directory=...)``); it is
            the solver's only while this functional runs its forward and adjoint
            (``rf.factor_store``).

    Raises:
        ObjectiveError: ``objective`` is not an Objective.
        ParameterError: An objective integral reads a history field where it is undefined
            (``u_prev`` or ``u_tilde`` at step 0, ``u_tilde`` in a static run).

    Example:
        ``rf = ReducedFunctional(sim, objective, [ParameterControl(model, "E", "bodies")])``;
        ``j, g = rf.value_and_gradient(q)``.
    """

    def __init__(
        self,
        simulation: "Simulation",
        objective: Objective,
        controls: Control | Sequence[Control],
        adjoint_options: AdjointSolverOptions | None = None,
        factor_memory_mb: float | None = None,
        checkpointing: Checkpointing | None = None,
        branch_reference: npt.ArrayLike | None = None,
        factor_store: FactorStore | None = None,
    ) -> None:
        if checkpointing is not None and not isinstance(checkpointing, Checkpointing):
            raise ParameterError(
                f"checkpointing must be a Checkpointing policy, got {type(checkpointing).__name__}"
            )
        if not isinstance(objective, Objective):
            raise ObjectiveError(
                "objective must be an Objective (e.g. time_integral(Integral(...)))"
            )
        self.simulation = simulation
        self.objective = objective
        self.controls = ControlSet(controls, simulation)
        self.adjoint_options = adjoint_options
        self.model = simulation.model
        self.comm = self.model.domain.comm
        self.leaves = list(dict.fromkeys(objective.leaves()))
        self.regularisers = list(dict.fromkeys(objective.regularisers()))
        check_objective_fields(objective, self.model.fields, self.grid)
        self._value_forms = {
            leaf: compile_form(leaf.form(self.model.fields))
            for leaf in self.leaves
            if not isinstance(leaf, NumericIntegral)
        }
        self._sweep: BackwardSweep | None = None
        self.factor_store = self._factor_store(factor_memory_mb, factor_store)
        self.checkpointing = checkpointing or Checkpointing()
        self._run: CheckpointedRun | None = None  # of the last forward, when checkpointed
        self._state = None  # (q, trajectory, table, reg values, J)
        self.timings: dict[str, float] = {}
        self.branch_reference = self._reference_parameters(branch_reference)
        self._reference_run: Trajectory | None = None  # solved on the first forward

    def _factor_store(
        self, memory_mb: float | None, store: FactorStore | None
    ) -> FactorStore | None:
        if store is None:
            stores = memory_mb != 0 and self.simulation.integrator.num_steps > 1
            return FactorStore(memory_mb) if stores else None
        if not isinstance(store, FactorStore) or memory_mb is not None:
            raise ParameterError(
                "factor_store must be a FactorStore, given without factor_memory_mb (its "
                f"budget is FactorStore(budget_mb=...)); got {type(store).__name__}"
                + ("" if memory_mb is None else f" and factor_memory_mb={memory_mb}")
            )
        return store

    def _reference_parameters(self, q_ref: npt.ArrayLike | None) -> np.ndarray | None:
        if q_ref is None:
            return None
        q_ref = np.array(q_ref, dtype=float).ravel()
        if q_ref.shape != (self.size,) or not np.all(np.isfinite(q_ref)):
            raise ParameterError(
                f"branch_reference must be {self.size} finite parameters, got {q_ref.tolist()}"
            )
        return q_ref

    def _solve_reference(self) -> None:
        """Solve the run at the branch reference's parameters (the first time it is needed)."""
        if self.branch_reference is None or self._reference_run is not None:
            return
        sim = self.simulation
        self.controls.assign(self.branch_reference)
        t0 = time.perf_counter()
        with sim.following_branch(None):
            self._reference_run = sim.run()
        logger.info("branch reference solved (%.2fs)", time.perf_counter() - t0)

    @property
    def reference_run(self) -> "Trajectory | None":
        """The run at the branch reference (None before the first forward or without one)."""
        return self._reference_run

    @contextlib.contextmanager
    def _running(self) -> Iterator[None]:
        """This functional's settings in the simulation while it runs, and only then.

        The solver keeps the factorisations in this functional's store, and the steps follow
        its branch reference's run (none without a reference): another functional, or a plain
        ``simulation.run()``, of the same simulation sees its own settings.
        """
        sim = self.simulation
        with sim.solver.keeping_factors_in(self.factor_store):
            self._solve_reference()
            with sim.following_branch(self._reference_run):
                yield

    @property
    def size(self) -> int:
        """Number of parameters."""
        return self.controls.size

    def initial_parameters(self) -> np.ndarray:
        """The controls' current parameters."""
        return self.controls.value()

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Parameter bounds of the controls."""
        return self.controls.bounds()

    @property
    def grid(self) -> TimeGrid:
        """Steps of the simulation."""
        integ = self.simulation.integrator
        return TimeGrid(integ.num_steps, integ.dt, integ.dynamic)

    # -- forward ---------------------------------------------------------------------------
    def forward(self, q: npt.ArrayLike) -> float:
        """Assign q, run the simulation and evaluate J."""
        with self._running():
            return self._forward(q)

    def _forward(self, q: npt.ArrayLike) -> float:
        q = np.array(q, dtype=float)
        self._close_run()
        self.controls.assign(q)
        t0 = time.perf_counter()
        policy = self.checkpointing.resolve(self.simulation)
        if policy.policy == "all":
            traj = self.simulation.run()
            table = self._evaluate_leaves(traj)
        else:
            self._run = CheckpointedRun(self.simulation, policy)
            traj, table = self._checkpointed_forward(self._run)
        self.timings["forward"] = time.perf_counter() - t0
        reg = {r: r.evaluate(self.model) for r in self.regularisers}
        J = float(self.objective.value(table, reg, self.grid))
        if not np.isfinite(J):
            raise ObjectiveError(f"the objective is not finite (J = {J})")
        self._state = (q, traj, table, reg, J)
        return J

    def _evaluate_leaves(self, traj: "StateHistory") -> dict:
        table, needed = self._empty_table()
        steps = sorted(set().union(*needed.values())) if needed else []
        for i in steps:
            self._evaluate_step(i, traj, table, needed)
        return table

    def _empty_table(self) -> tuple[dict, dict]:
        grid = self.grid
        needed = self.objective.requirements(grid)
        table = {leaf: np.full(grid.num_steps + 1, np.nan) for leaf in self.leaves}
        return table, needed

    def _evaluate_step(self, i: int, traj: "StateHistory", table: dict, needed: dict) -> None:
        """The objective's integrals of step i (``traj`` holds u^{i-d..i}, v^{i-d..i})."""
        if not any(i in leaf_steps for leaf_steps in needed.values()):
            return
        f = self.model.fields
        if i > 0:
            self.simulation.prepare_step(i, traj, Phase.EVALUATION)
        else:
            self.model.update_time(0.0)
        f.u.x.array[:] = traj.u[i]
        f.v.x.array[:] = traj.v[i]
        for leaf, leaf_steps in needed.items():
            if i in leaf_steps and isinstance(leaf, NumericIntegral):
                table[leaf][i] = leaf.evaluate(self.model)
            elif i in leaf_steps:
                local = fem.assemble_scalar(self._value_forms[leaf])
                table[leaf][i] = collective_comm(self.comm).allreduce(local, op=MPI.SUM)

    def _checkpointed_forward(
        self, run: CheckpointedRun
    ) -> "tuple[Trajectory | CheckpointedTrajectory, dict]":
        """Forward run of a checkpointing schedule, the integrals evaluated as states appear."""
        table, needed = self._empty_table()
        run.on_state = lambda i, view: self._evaluate_step(i, view, table, needed)
        try:
            traj = self.simulation.run(checkpoints=run)
        finally:
            run.on_state = None
        return traj, table

    def _close_run(self) -> None:
        if self._run is not None:
            self._run.close()
            self._run = None

    def __call__(self, q: npt.ArrayLike) -> float:
        """J(q) (reuses the last forward run when q is unchanged)."""
        q = np.asarray(q, dtype=float)
        if self._state is not None and np.array_equal(self._state[0], q):
            return self._state[4]
        return self.forward(q)

    # -- gradient ----------------------------------------------------------------------------
    def derivative(self) -> np.ndarray:
        """dJ/dq at the last forward run.

        Raises:
            AdjointError: No forward run yet.
        """
        with self._running():
            return self._derivative()

    def _derivative(self) -> np.ndarray:
        if self._state is None:
            raise AdjointError(
                "no forward solve yet: call rf(q) or rf.forward(q) before the gradient"
            )
        _, traj, table, reg, _ = self._state
        grid = self.grid
        leaf_weights: dict = {}
        reg_weights: dict = {}
        self.objective.backward(table, reg, grid, 1.0, leaf_weights, reg_weights)
        if self._sweep is None:
            self._sweep = BackwardSweep(
                self.simulation, self.leaves, self.controls.targets(), self.adjoint_options
            )
        t0 = time.perf_counter()
        run = traj.run if isinstance(traj, CheckpointedTrajectory) else None
        if run is None:
            sens = self._sweep.run(traj, leaf_weights)
        else:
            if run.closed or run.exhausted or run.reversed:
                # its schedule allowed one reverse, a later forward freed its checkpoints, or
                # the last reverse freed the factors: the same forward again (the same states
                # and factors: the same gradient)
                self._forward(self._state[0])
                run = self._state[1].run
            sens = self._sweep.run_checkpointed(run, leaf_weights)
        self._add_regularisers(sens, reg_weights)
        g = self.controls.pullback(sens)
        self.timings["gradient"] = time.perf_counter() - t0
        if not np.all(np.isfinite(g)):
            raise ObjectiveError("the gradient has non-finite entries")
        return g

    def _add_regularisers(self, sens: Sensitivities, reg_weights: dict) -> None:
        for reg, seed in reg_weights.items():
            for key, g in reg.gradient(self.model).items():
                if key == "shape" and sens.shape is not None:
                    sens.shape += seed * g[: len(sens.shape)]
                elif key in sens.coefficients:
                    sens.coefficients[key] += seed * g[: len(sens.coefficients[key])]

    def gradient(self, q: npt.ArrayLike) -> np.ndarray:
        """dJ/dq at q (runs the forward problem if q changed)."""
        self(q)
        return self.derivative()

    def value_and_gradient(self, q: npt.ArrayLike) -> tuple[float, np.ndarray]:
        """(J(q), dJ/dq)."""
        J = self(q)
        return J, self.derivative()

    def term_values(self) -> dict[str, float]:
        """Values of the objective's additive terms at the last forward run (they sum to J).

        Raises:
            AdjointError: No forward run yet.
        """
        if self._state is None:
            raise AdjointError("no forward solve yet: call rf(q) before term_values()")
        _, _, table, reg, _ = self._state
        return {t.label: t.value(table, reg, self.grid) for t in objective_terms(self.objective)}

    def snapshot(self) -> tuple | None:
        """An opaque record of the last forward run (parameters, trajectory, values)."""
        return self._state

    def restore(self, snapshot: tuple | None) -> None:
        """Return to a :meth:`snapshot`: assign its parameters and make it the last forward run.

        The controls (model coefficients, mesh) are reset even if a later ``assign`` failed
        half-way; the gradient then refers to the snapshot's point.
        """
        if snapshot is None:
            raise AdjointError("cannot restore an empty snapshot (no forward run was recorded)")
        self.controls.assign(snapshot[0])
        self._state = snapshot
        self.simulation.trajectory = snapshot[1]

    def tao_objective_gradient(self, tao: PETSc.TAO, x: PETSc.Vec, g: PETSc.Vec) -> float:
        """PETSc TAO objective-and-gradient callback: returns J(x) and fills ``g``.

        ``x`` and ``g`` are either sequential Vecs holding the full parameter vector on every
        rank (all ranks running the same TAO solve on ``COMM_SELF``) or one distributed Vec
        (gathered to every rank here).

        Example:
            ``tao.setObjectiveGradient(rf.tao_objective_gradient, g)``.
        """
        if x.getComm().getSize() > 1:
            scatter, full = PETSc.Scatter.toAll(x)
            scatter.scatter(x, full, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
            q = full.getArray(readonly=True).copy()
            scatter.destroy()
            full.destroy()
        else:
            q = x.getArray(readonly=True).copy()
        J, grad = self.value_and_gradient(q)
        start, end = g.getOwnershipRange()
        g.setArray(grad[start:end])
        return J

    @property
    def trajectory(self) -> "Trajectory | CheckpointedTrajectory | None":
        """Trajectory of the last forward run."""
        return None if self._state is None else self._state[1]

    def warm_start(self, trajectory: "StateHistory | None") -> None:
        """Warm-start the next forward runs: each step's Newton solve from ``trajectory``.

        None: from the simulation's own initial guess.
        """
        self.simulation.warm_start = trajectory

    def dof_layout(self) -> np.ndarray:
        """A fingerprint of this rank's dof layout: the dof count, then the cells' input indices.

        A checkpointed trajectory fits a run with the same fingerprint.
        """
        V, mesh = self.model.V, self.model.domain.mesh
        n = (V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts) * V.dofmap.index_map_bs
        return np.concatenate([[n], mesh.topology.original_cell_index]).astype(np.int64)

    @property
    def adjoint_stats(self) -> dict:
        """Statistics of the last backward sweep."""
        return {} if self._sweep is None else self._sweep.stats
