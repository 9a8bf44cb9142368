"""Forward simulation: a Model advanced by an Integrator, one Newton solve per step."""

import contextlib
import logging
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from dolfinx import fem
from mpi4py import MPI

from diffsolids.errors import InvertedElementError, NewtonConvergenceError, ParameterError
from diffsolids.integrators import Integrator, TimeStep
from diffsolids.mesh.ordering import CanonicalLayout
from diffsolids.parallel import collective_comm
from diffsolids.solvers import NewtonResult, NewtonSolver, SolverOptions
from diffsolids.states import (
    Phase,
    RunDriver,
    RunRecord,
    StateHistory,
    StateRecorder,
    StepContext,
    StepRecord,
    Trajectory,
)

if TYPE_CHECKING:
    import os

    from diffsolids.io.output import TrajectoryWriter
    from diffsolids.model import Model

# Trajectory, StateHistory, StateRecorder and StepRecord live in diffsolids.states (importable
# from here too)
__all__ = ["CanonicalValues", "Simulation"]

logger = logging.getLogger("diffsolids")


@dataclass(frozen=True)
class CanonicalValues:
    """Nodal values of the displacement space in the canonical (partition-independent) order.

    The order of the controls' parameter vectors (``diffsolids.mesh.ordering``): P1
    nodes in the input vertex order, other spaces in the lexicographic order of their node
    coordinates, the components of a node after each other. The array has the global length
    (number of nodes x dimension), or the shape (number of nodes, dimension), and the same
    values on every rank, e.g. ``InitialCondition(sim, "velocity").value()`` of any run. Given
    as ``u0``, ``v0`` or a start-up state of a :class:`Simulation`, it sets the same field on
    any number of ranks (a plain array is a local array, ordered as the rank's dofs).

    Attributes:
        values: The nodal values.

    Example:
        ``ds.Simulation(model, ds.BDF(2, 0.01, 50), v0=CanonicalValues(v))``.
    """

    values: np.ndarray


#: What ``u0``, ``v0`` and the start-up states of a Simulation may be given as.
InitialValue = np.ndarray | Sequence[float] | fem.Function | Callable | CanonicalValues | None


def _initial_array(V: fem.FunctionSpace, value: InitialValue, name: str) -> np.ndarray:
    f = fem.Function(V)
    if value is None:
        return f.x.array.copy()
    if isinstance(value, CanonicalValues):
        _scatter_canonical(f, value, name)
        return f.x.array.copy()
    if isinstance(value, fem.Function) or callable(value):
        f.interpolate(value)
    else:
        vec = np.asarray(value, dtype=float)
        d = V.mesh.geometry.dim
        if vec.size == d:
            f.x.array[:] = np.tile(vec, len(f.x.array) // d)
        elif vec.shape == f.x.array.shape:
            f.x.array[:] = vec
        else:
            imap = V.dofmap.index_map
            hint = (
                "; an array of the global size in the canonical node order (as the controls' "
                "parameters) is given as CanonicalValues(array)"
                if vec.size == imap.size_global * V.dofmap.index_map_bs
                else ""
            )
            raise ParameterError(
                f"{name}: expected a vector of length {d} or a local nodal array of "
                f"{f.x.array.size} entries (owned and ghost dofs), got shape {vec.shape}{hint}"
            )
    if not np.all(np.isfinite(f.x.array)):
        raise ParameterError(f"{name} has non-finite values")
    f.x.scatter_forward()
    return f.x.array.copy()


def _scatter_canonical(f: fem.Function, value: CanonicalValues, name: str) -> None:
    """Write canonical nodal values into ``f`` (the same on every rank: errors are collective)."""
    layout = CanonicalLayout(f.function_space)
    vec = np.asarray(value.values, dtype=float)
    if vec.size != layout.size or vec.ndim > 2 or (vec.ndim == 2 and vec.shape[1] != layout.bs):
        raise ParameterError(
            f"{name}: canonical values need {layout.size} entries ({layout.num_global} nodes x "
            f"{layout.bs} components), got shape {vec.shape}"
        )
    if not np.all(np.isfinite(vec)):
        raise ParameterError(f"{name} has non-finite values")
    layout.scatter(vec.ravel(), f)


class Simulation:
    """Runs a Model through the steps of an Integrator.

    Args:
        model: The scene.
        integrator: Static or BDF.
        solver_options: Newton options.
        u0: Initial displacement (default 0): a function of x, a constant vector, a Function,
            a local nodal array (the rank's owned and ghost dofs, e.g. ``sim.u0`` of another
            Simulation of the same model) or :class:`CanonicalValues` (the global array in the
            controls' canonical node order, the same on every rank and for any number of
            ranks).
        v0: Initial velocity (BDF only; default 0), given as ``u0``.
        output: Optional TrajectoryWriter (or path ending in .bp / .xdmf) for time series.
        progress: Show a progress bar (default: when stderr is a terminal).
        callback: Called as ``callback(step, simulation)`` after every step.
        startup: Optional states ``[(u^1, v^1), ..., (u^k, v^k)]`` (each as for ``u0``) taken
            as given instead of solving steps 1..k, e.g. exact values so that BDF_m runs at full
            order from step k + 1 = m (verification of temporal orders). Their records have
            ``order`` 0 and no Newton iterations.

    Raises:
        ParameterError: Malformed initial or start-up states.
        InvertedElementError: The initial displacement inverts elements.

    Note:
        Once created, the Simulation freezes its model (:meth:`Model.freeze`): terms, loads,
        contact terms and Dirichlet conditions must be added to the model before.

    Attributes:
        warm_start: Optional Trajectory (e.g. of the previous optimisation iterate) whose
            u^i is tried first as the initial Newton guess of step i (same dof layout; skipped
            where it does not fit or is not admissible). Only the guess changes: the converged
            states agree with a cold start to the Newton tolerance. Ignored while a
            :attr:`branch_reference` is set.
        branch_reference: Optional Trajectory of a run at fixed reference parameters whose
            u^i is Newton's first iterate of step i whenever it is an admissible state (no
            inverted element, every numeric term :meth:`admits
            <diffsolids.model.NumericTerm.admits>` it), without the straight-path test from
            u^{i-1} that other guesses pass. Where a step's incremental potential has several
            local minima, Newton then ends in the minimum of the reference's branch, so J is a
            smooth function of the parameters near the reference, whatever was evaluated
            before. ``ReducedFunctional(..., branch_reference=q_ref)`` sets it to the run at
            q_ref while the functional runs (:meth:`following_branch`), and only then.
        max_substeps: Intermediate solves allowed per step to reach Dirichlet values that
            cannot be applied in one admissible move (see ``_dirichlet_continuation``).
        substeps: Intermediate solves of the last run, by step (steps that needed any).
    """

    def __init__(
        self,
        model: "Model",
        integrator: Integrator,
        solver_options: SolverOptions | None = None,
        u0: InitialValue = None,
        v0: InitialValue = None,
        output: "TrajectoryWriter | str | os.PathLike | None" = None,
        progress: bool | None = None,
        callback: Callable | None = None,
        startup: Sequence[tuple[InitialValue, InitialValue]] | None = None,
    ) -> None:
        self.model = model
        self.integrator = integrator
        V = model.V
        self.u0 = _initial_array(V, u0, "initial displacement u0")
        self.v0 = _initial_array(V, v0, "initial velocity v0")
        if v0 is not None and not integrator.dynamic:
            raise ParameterError("an initial velocity needs a dynamic (BDF) integrator")
        self.startup = [
            (
                _initial_array(V, u, f"start-up state u^{i}"),
                _initial_array(V, v, f"start-up state v^{i}"),
            )
            for i, (u, v) in enumerate(startup or (), start=1)
        ]
        if self.startup and not integrator.dynamic:
            raise ParameterError("prescribed start-up states need a dynamic (BDF) integrator")
        if len(self.startup) >= integrator.num_steps:
            raise ParameterError(
                f"{len(self.startup)} prescribed start-up states leave no step of "
                f"{integrator.num_steps} to solve"
            )
        # after the input checks: bad input fails before any form is compiled
        self.solver = NewtonSolver(model, integrator.dynamic, solver_options)
        model.fields.u.x.array[:] = self.u0
        if self.solver.inverted():
            raise InvertedElementError("the initial displacement u0 inverts elements (det F <= 0)")
        self.output = output
        self.progress = progress
        self.callback = callback
        self.trajectory: Trajectory | None = None
        self.warm_start: Trajectory | None = None
        self.branch_reference: Trajectory | None = None
        self.max_substeps = 50
        self._round_off_reported = False
        self.substeps: dict[int, int] = {}
        # the solver compiled the model's forms and collected its step bounds: a term added
        # from now on would be ignored (or miss its collision-free bound), so none may be
        model.freeze()

    # -- step set-up shared with the adjoint -----------------------------------------------------
    def load_step(self, i: int, traj: StateHistory) -> TimeStep:
        """Set time, loads, Dirichlet values and history fields of step ``i``; its TimeStep.

        The step's :class:`~diffsolids.integrators.TimeStep` writes ``dt``, ``beta_dt``,
        ``u_prev`` and the predictor ``u_tilde`` from the states of ``traj``. Called by the
        forward solve, the objective evaluation and the backward sweep (a subclass may extend
        it, e.g. to set a per-step target).
        """
        step = self.integrator.step(i)
        self.model.update_time(step.time)
        step.set_fields(self.model.fields, traj.u, traj.v)
        return step

    def prepare_step(self, i: int, traj: StateHistory, phase: Phase) -> StepContext:
        """Set step ``i`` up for the forward solve, an objective evaluation or the adjoint.

        :meth:`load_step`, then (forward and backward phases) the numeric terms'
        :meth:`~diffsolids.model.NumericTerm.begin_step` hooks with the step's context. The one
        set-up the three drivers share.
        """
        context = StepContext(i, self.load_step(i, traj), traj, self.integrator, phase)
        if phase is not Phase.EVALUATION:
            for term in self.model.numeric_terms:
                term.begin_step(context)
        return context

    def begin_step(self, i: int, traj: StateHistory) -> TimeStep:
        """Deprecated: :meth:`prepare_step` with the phase named."""
        warnings.warn(
            "Simulation.begin_step(i, traj) is deprecated: use "
            "Simulation.prepare_step(i, traj, diffsolids.states.Phase.FORWARD or BACKWARD)",
            DeprecationWarning,
            stacklevel=2,
        )
        phase = Phase.FORWARD if len(traj.u) == i else Phase.BACKWARD
        return self.prepare_step(i, traj, phase).step

    def _initial_guess(self, i: int, traj: StateHistory, step: TimeStep) -> bool:
        """The step's first Newton iterate; whether it is the branch reference's state.

        The branch reference's u^i when it is admissible (:meth:`_reference_guess`), else
        :meth:`_default_guess`.
        """
        if self._reference_guess(i, traj.u[i - 1]):
            return True
        self._default_guess(i, traj, step)
        return False

    def _default_guess(self, i: int, traj: StateHistory, step: TimeStep) -> None:
        """The step's first Newton iterate without a branch reference, Dirichlet values applied.

        Candidates in turn: the warm start (if any), the guess chosen by
        :attr:`SolverOptions.initial_guess <diffsolids.solvers.SolverOptions.initial_guess>`
        (``"predictor"``: the step's :meth:`~diffsolids.integrators.TimeStep.extrapolation`,
        u^{i-1} + dt v^{i-1} in a dynamic run and u^{i-1} in a static one; ``"previous"``:
        u^{i-1}; ``"zero"``: u = 0) and u^{i-1}. A guess that inverts elements (or, with
        contact, collides on the way from u^{i-1}) falls back to the next candidate; if applying
        the new Dirichlet values to the previous state is still not admissible, they are
        reached by :meth:`_dirichlet_continuation`.
        """
        u = self.model.fields.u
        prev = traj.u[i - 1]
        choice = self.solver.options.initial_guess
        if choice == "predictor":
            candidates = [step.extrapolation(traj.u, traj.v), prev]
        elif choice == "zero":
            candidates = [np.zeros_like(prev), prev]
        elif choice == "previous":
            candidates = [prev]
        else:  # SolverOptions validates its value: an options object changed afterwards
            raise ParameterError(
                f"SolverOptions.initial_guess = {choice!r}: not 'predictor', 'previous' or 'zero'"
            )
        warm = None if self.branch_reference is not None else self.warm_start
        # only a full Trajectory warm-starts (a checkpointed one does not hold every state)
        if isinstance(warm, Trajectory) and i < len(warm.u) and warm.u[i].shape == prev.shape:
            candidates.insert(0, warm.u[i])
        for candidate in candidates:
            u.x.array[:] = candidate
            self._apply_dirichlet(u)
            if not self.solver.step_bounds or not self._guess_inverts(u.x.array):
                return
        u.x.array[:] = prev
        self._dirichlet_continuation(i)

    def _reference_guess(self, i: int, prev: np.ndarray) -> bool:
        """Start step ``i`` at the branch reference's u^i if it is admissible; whether it was.

        The decision is collective: a reference that does not fit the dof layout on some rank
        (another mesh) is not used on any.
        """
        ref = self.branch_reference
        fits = ref is not None and i < len(ref.u) and ref.u[i].shape == prev.shape
        everywhere = collective_comm(self.model.domain.comm).allreduce(bool(fits), op=MPI.LAND)
        if not everywhere:
            return False
        u = self.model.fields.u
        u.x.array[:] = ref.u[i]
        self._apply_dirichlet(u)
        if not self.solver.step_bounds:
            return True
        if self._inverts(u.x.array):
            return False
        return all(term.admits(u.x.array, i) for term in self.model.numeric_terms)

    def _dirichlet_continuation(self, i: int) -> None:
        """Reach the step's Dirichlet values from u^{i-1} through intermediate equilibria.

        The lifted (linearised) step onto the new values is taken when it is admissible (no
        inversion, collision-free). Otherwise the prescribed dofs move by ``step_safety`` times
        the admissible fraction of it, the step's problem is solved with them held there, and
        the lift is repeated from that equilibrium (e.g. an obstacle driven into contact by
        Dirichlet values pushes the surface ahead of it). Only the initial guess of the step's
        own solve changes: the step's solution, and its adjoint, are those of the full values.

        Raises:
            NewtonConvergenceError: No admissible progress, or more than ``max_substeps``.
        """
        solver, model = self.solver, self.model
        u = model.fields.u
        t = self.integrator.time(i)
        for substep in range(self.max_substeps):
            y = solver.lifted_step()
            try:
                bound = solver.step_bound(y)
                if bound * solver.options.step_safety >= 1.0:  # with a margin, as Newton
                    solver.advance(y)
                    self._apply_dirichlet(u)  # exactly the step's values
                    if substep:
                        self.substeps[i] = substep
                        logger.info("step %d: Dirichlet values reached in %d substeps", i, substep)
                    return
                fraction = solver.options.step_safety * bound
                if not fraction > 1e-8:
                    break
                solver.advance(y, fraction)
            finally:
                y.destroy()
            for d in model.dirichlet:
                d.prescribe(u.x.array)  # hold the prescribed dofs where they are now
            try:
                with solver.keeping_factors_in(None):  # only the step's own solve keeps them
                    solver.solve(i)
            finally:
                model.update_time(t)
        raise NewtonConvergenceError(
            i,
            0,
            float("nan"),
            float("nan"),
            f"the Dirichlet increment of this step cannot be reached admissibly (no inversion, "
            f"no collision) within {self.max_substeps} substeps; use smaller (load) steps",
        )

    def _apply_dirichlet(self, u: fem.Function) -> None:
        for d in self.model.dirichlet:
            for bc in d.bcs:
                bc.set(u.x.array)

    def _guess_inverts(self, arr: np.ndarray) -> bool:
        """Whether the guess inverts elements, or the path to it from u^{i-1} is not admissible.

        Step bounds of numeric terms (contact CCD) check the straight path from the previous
        state, which is intersection-free, to the guess.
        """
        if self._inverts(arr):
            return True
        numeric = [b for b in self.solver.step_bounds if b in self.model.numeric_terms]
        if not numeric:
            return False
        return self.solver.path_bound(self._guess_origin, arr, numeric) <= 1.0

    def _inverts(self, arr: np.ndarray) -> bool:
        """Whether the state ``arr`` fails a step bound that is not a numeric term's (inversion)."""
        numeric = self.model.numeric_terms
        guards = [b for b in self.solver.step_bounds if b not in numeric]
        return self.solver.path_bound(arr, arr, guards) <= 0.0

    # -- run -----------------------------------------------------------------------------
    def run(self, checkpoints: RunDriver | None = None) -> Trajectory | RunRecord:
        """Solve all steps and return the trajectory (also kept as ``self.trajectory``).

        Args:
            checkpoints: Optional driver of the steps by its own schedule that keeps only its
                checkpoints (:class:`~diffsolids.adjoint.checkpointing.CheckpointedRun`); the
                returned record is then its
                :class:`~diffsolids.adjoint.checkpointing.CheckpointedTrajectory`.
        """
        from diffsolids.io.progress import progress_bar

        integ = self.integrator
        self.begin_run()
        writer = self._open_writer()
        if checkpoints is None:
            traj = Trajectory(times=[0.0], u=[self.u0.copy()], v=[self.v0.copy()])
        else:
            traj = checkpoints.start()
        traj.rest_geometry = self.model.domain.mesh.geometry.x.copy()
        if writer:
            writer.write(0.0, traj.u[0], traj.v[0])
        with progress_bar(integ.num_steps, self.model.domain.comm, self.progress) as bar:

            def stepped(i: int, states: StateHistory) -> None:
                if writer:
                    writer.write(traj.times[i], states.u[i], states.v[i])
                bar.update(1)
                if self.callback:
                    self.callback(i, self)

            if checkpoints is None:
                for i in range(1, integ.num_steps + 1):
                    self.advance(i, traj)
                    stepped(i, traj)
            else:
                checkpoints.forward(stepped)
        if writer:
            writer.close()
        self._report_round_off()
        self.trajectory = traj
        return traj

    def _report_round_off(self) -> None:
        """Warn when steps ended at round-off above the residual the solver reports.

        A step whose Newton increment vanished at machine precision is accepted whatever its
        residual (nothing is left to gain): its state balances the forces only to that
        residual, not to ``rtol``, and J and its gradient may carry the imbalance. The first
        such run of a simulation warns, later ones log at info level.
        """
        steps = self.solver.reported_round_off_steps()
        if not steps:
            return
        step, residual, tolerance, f_char = max(steps, key=lambda s: s[1] / s[3])
        level = logging.INFO if self._round_off_reported else logging.WARNING
        self._round_off_reported = True  # a warning once per simulation, then info
        logger.log(
            level,
            "%d step(s) converged only to round-off (the Newton step vanished) with the "
            "residual above its tolerance: at step %d %.3g of the characteristic force "
            "(tolerance %.3g). Their forces balance only to that residual, not to rtol, and J "
            "and its gradient may carry the imbalance (a line scan or central differences "
            "show how much). With contact: pairs resting within a few hundred ulps of the "
            "coordinates; a stiffer barrier (e.g. ContactTerm's suggested stiffness) holds "
            "them farther apart.",
            len(steps),
            step,
            residual / f_char,
            tolerance / f_char,
        )

    @contextlib.contextmanager
    def following_branch(self, reference: Trajectory | None) -> Iterator[None]:
        """Steps follow ``reference`` (see :attr:`branch_reference`; None: no run) in the block.

        The previous branch reference is back afterwards, also when the block raises.
        """
        previous, self.branch_reference = self.branch_reference, reference
        try:
            yield
        finally:
            self.branch_reference = previous

    def begin_run(self) -> None:
        """Forget the previous run's solver state (cached Jacobians, stored factors)."""
        self.solver.reset()
        self.substeps = {}

    def advance(self, i: int, traj: StateRecorder, replay: bool = False) -> None:
        """Solve (or prescribe) step ``i`` from the states of ``traj`` and append u^i, v^i.

        Args:
            i: The step.
            traj: A Trajectory, or a checkpointing view holding the states step ``i`` reads
                (u^{i-j}, v^{i-j} for j = 1..max(m, 2)).
            replay: The step is recomputed from a checkpoint (backward sweep): numeric terms'
                ``end_step`` (records and output of a converged step) is not called again.
        """
        if i <= len(self.startup):
            self._prescribe(i, traj)
        else:
            self._step(i, traj, replay)

    def _step(self, i: int, traj: StateRecorder, replay: bool = False) -> None:
        t0 = time.perf_counter()
        c = self.prepare_step(i, traj, Phase.REPLAY if replay else Phase.FORWARD).step
        if i == len(self.startup) + 1:  # first solved step
            u = self.model.fields.u
            u.x.array[:] = traj.u[i - 1]
            for d in self.model.dirichlet:
                for bc in d.bcs:
                    bc.set(u.x.array)
            self.solver.set_reference_force()
        self._guess_origin = traj.u[i - 1]
        from_reference = self._initial_guess(i, traj, c)
        try:
            # from the reference's state one attempt, then the default guess with every retry
            result = self.solver.solve(i, retries=not from_reference)
        except NewtonConvergenceError as error:
            if not from_reference:
                logger.error("step %d (t = %g) failed", i, self.integrator.time(i))
                raise
            result = self._solve_again_without_reference(i, traj, c)
            result.iterations += error.iterations  # the step's record counts both solves
        u_i = self.model.fields.u.x.array.copy()
        v_i = c.velocity(u_i, traj.u)
        rec = StepRecord(
            i,
            c.time,
            c.order,
            result.iterations,
            result.residual,
            result.energy,
            time.perf_counter() - t0,
        )
        traj.append_state(rec.time, u_i, v_i, rec)
        if replay:
            return
        for term in self.model.numeric_terms:
            term.end_step(i, traj)
        logger.info(
            "step %4d  t=%-10.4g order=%d  newton=%2d  residual=%.3e  energy=%.6e  (%.2fs)",
            i,
            rec.time,
            rec.order,
            rec.iterations,
            rec.residual,
            rec.energy,
            rec.seconds,
        )

    def _solve_again_without_reference(
        self, i: int, traj: StateRecorder, step: TimeStep
    ) -> NewtonResult:
        """Step ``i`` from the default initial guess after the solve from the reference failed.

        The rule is deterministic in q: the reference's state first (one Newton attempt,
        without the solver's retries), the default guess with every retry only where Newton
        does not converge from it (e.g. parameters far from the reference's).

        Raises:
            NewtonConvergenceError: The second solve failed too.
        """
        logger.warning(
            "step %d: no convergence from the branch reference's state; solving again from "
            "the default initial guess",
            i,
        )
        self._default_guess(i, traj, step)
        try:
            return self.solver.solve(i)
        except NewtonConvergenceError:
            logger.error("step %d (t = %g) failed", i, self.integrator.time(i))
            raise

    def _prescribe(self, i: int, traj: StateRecorder) -> None:
        u_i, v_i = self.startup[i - 1]
        t = self.integrator.time(i)
        traj.append_state(t, u_i.copy(), v_i.copy(), StepRecord(i, t, 0, 0, np.nan, np.nan, 0.0))

    def _open_writer(self) -> "TrajectoryWriter | None":
        if self.output is None:
            return None
        if isinstance(self.output, str | bytes) or hasattr(self.output, "__fspath__"):
            from diffsolids.io.output import TrajectoryWriter

            return TrajectoryWriter(self.model, self.output)
        return self.output
