"""L-BFGS with a projected, safeguarded backtracking line search (paper sec. 5, Algorithm 1).

Every trial point of the line search is checked before it counts: the step is projected onto
the parameter bounds and limited per control block, and a trial whose controls cannot be
applied (inverted elements of a shape update, intersecting rest configurations) or whose forward
solve fails (Newton failure, non-finite objective, any DiffsolidsError) is *invalid*: the model
returns to the last accepted point and the step is shortened. Only trials that are valid and
satisfy the Armijo condition are accepted.

Remeshing hook: an optional ``remesher``, a :class:`~diffsolids.optimize.hooks.RemeshHook`, with

- ``needs_remesh(rf, q) -> bool``, called after every accepted iterate, and
- ``remesh(rf, q) -> (new_rf, new_q)``, building the scene on a new mesh. The L-BFGS memory is
  reset afterwards; the iteration count and history continue.
- optionally ``save_checkpoint(directory, rf)`` (called on all ranks after a remesh when the run
  writes checkpoints) and ``load_checkpoint(directory, rf) -> new_rf`` (called on resume with
  the freshly built original functional; returns the functional on the saved mesh).

An ``inner_product`` (``g -> M^{-1} g`` for an SPD operator M) is the initial inverse Hessian
of L-BFGS; if it has a method ``rebuild(rf)``, that is called after a remesh and its result
used from then on.

Observers: ``on_accept`` callables ``observer(record, optimizer)`` are called once per accepted
iterate (the initial point included, after a remesh with the remeshed iterate), in order, on
every rank (they may use collectives), never for rejected or invalid line-search trials; they
keep trajectories, check invariants or log (:mod:`diffsolids.optimize.observers`). Stop
conditions decide whether to stop; they are evaluated after the observers.
"""

import logging
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from os import PathLike
from typing import TYPE_CHECKING, overload

import numpy as np
import numpy.typing as npt
from mpi4py import MPI

from diffsolids.errors import DiffsolidsError
from diffsolids.io.progress import progress_bar
from diffsolids.optimize.bounds import (
    active_set,
    block_limits,
    check_bounds,
    project,
    projected_gradient,
    step_limit,
)
from diffsolids.optimize.checkpoint import Checkpoint
from diffsolids.optimize.contract import OptimizableFunctional
from diffsolids.optimize.hooks import (
    RebuildableInnerProduct,
    RemeshCheckpoints,
    RemeshHook,
    condition_name,
)
from diffsolids.optimize.interrupt import InterruptRequest
from diffsolids.optimize.lbfgs import LBFGSMemory
from diffsolids.optimize.monitor import (
    IterationLog,
    IterationRecord,
    OptimizationOutput,
    control_summary,
    log_iteration,
)
from diffsolids.optimize.options import LBFGSOptions, OptimizationError, OptimizationWarning
from diffsolids.parallel import collective_comm

if TYPE_CHECKING:
    from diffsolids.adjoint.checkpointing import CheckpointedTrajectory
    from diffsolids.simulation import Trajectory

__all__ = ["LBFGS", "OptimizationResult", "minimize"]

logger = logging.getLogger("diffsolids")

_CONVERGED = ("gradient_atol", "gradient_rtol", "step", "objective")

# an on_accept observer: observer(record, optimizer), return value ignored
Observer = Callable[[IterationRecord, "LBFGS"], object]


@dataclass
class OptimizationResult:
    """Outcome of an optimisation.

    Attributes:
        q: The last accepted parameters.
        objective: J(q).
        gradient: dJ/dq at q.
        iterations: Accepted steps (including those before a resumption).
        reason: Why the run stopped: "gradient_atol", "gradient_rtol", "step", "objective",
            "max_iterations", "line_search" (no acceptable step found), "interrupted" (Ctrl-C:
            the run stopped after the trial in progress), "remesh: <error>" (the
            remesher failed; the result is the last accepted point on the mesh before) or
            "user: <name>".
        message: Readable explanation.
        history: One record per iterate, starting with the initial point.
        num_forward: Forward solves of this process (line-search trials and restarts).
        num_gradient: Adjoint gradients of this process.
        num_invalid_trials: Invalid trials of this process.
        functional: The reduced functional at the end (a new one after remeshing).
        resumed_from: Iteration the run resumed from (None for a fresh run).
    """

    q: np.ndarray
    objective: float
    gradient: np.ndarray
    iterations: int
    reason: str
    message: str
    history: list[IterationRecord] = field(default_factory=list)
    num_forward: int = 0
    num_gradient: int = 0
    num_invalid_trials: int = 0
    functional: object = None
    resumed_from: int | None = None

    @property
    def converged(self) -> bool:
        """Stopped by a convergence criterion (gradient, step, objective or a user condition)."""
        return self.reason in _CONVERGED or self.reason.startswith("user")

    def __str__(self) -> str:
        return (
            f"optimisation stopped after {self.iterations} iterations ({self.reason}): "
            f"{self.message}; J = {self.objective:.10e}"
        )


@dataclass
class _Point:
    """An accepted iterate and what belongs to it."""

    q: np.ndarray
    J: float
    g: np.ndarray
    trajectory: "Trajectory | CheckpointedTrajectory | None" = None
    snapshot: tuple | None = None


class LBFGS:
    """Bound-constrained L-BFGS on a ReducedFunctional.

    Args:
        rf: The functional: a :class:`~diffsolids.ReducedFunctional`, or any
            :class:`~diffsolids.optimize.OptimizableFunctional` (the members the optimiser
            calls).
        options: Algorithm and stopping options.
        inner_product: ``g -> M^{-1} g`` for an SPD M, the initial inverse Hessian.
        remesher: Optional remeshing hook (see the module docstring).
        stop_conditions: Callables ``condition(record, optimizer) -> bool | str`` evaluated
            after every accepted iterate; a truthy result stops the run with reason
            "user: <name>" (a returned string is used as the name).
        on_accept: A callable ``observer(record, optimizer)``, or a sequence of them, called
            once per accepted iterate with its IterationRecord and the optimiser (whose
            ``point`` is the iterate: ``q``, ``J``, ``g``, ``trajectory``), on every rank, in
            order of acceptance; never for rejected trials. Not called for the iterates of an
            earlier run when resuming from a checkpoint.
        output_dir: Directory for ``history.jsonl``, plots and iterate trajectories.
        checkpoint_dir: Directory for checkpoints (written after every iterate).
        resume: Continue from the checkpoint in ``checkpoint_dir`` if there is one.
        progress: Progress bar of the iterations (None: when stderr is a terminal).
        log: Print the optimisation log on rank 0's stdout: a header, then one line per
            accepted iterate (iteration, J, projected gradient norm, step norm and
            line-search factor, trials, forward and gradient seconds, the controls); the
            same numbers as the history of the result.
        log_file: Also write the log to this file (rank 0; a ``.csv`` or ``.jsonl`` name
            chooses the format), one flushed line per accepted iterate. Independent of
            ``log``; a resumed run rewrites it from its checkpointed history.
        write_parameters: Record q in the history, the history file and a JSON-lines log
            file (default), so that a stopped run's last iterate can be recovered; False keeps
            the files small for very large controls.
        plot_every: Update PNG plots of the objective and gradient norm every k iterations and
            at the end (0: no plots).
        iterate_every: Write the trajectory of every k-th iterate (0: never).
        iterate_format: "bp" (VTX) or "xdmf".
    """

    def __init__(
        self,
        rf: OptimizableFunctional,
        options: LBFGSOptions | None = None,
        *,
        inner_product: Callable[[np.ndarray], np.ndarray] | None = None,
        remesher: RemeshHook | None = None,
        stop_conditions: Sequence[Callable] = (),
        on_accept: Observer | Sequence[Observer] | None = None,
        output_dir: str | PathLike | None = None,
        checkpoint_dir: str | PathLike | None = None,
        resume: bool = True,
        progress: bool | None = None,
        log: bool = False,
        log_file: str | PathLike | None = None,
        write_parameters: bool = True,
        plot_every: int = 10,
        iterate_every: int = 0,
        iterate_format: str = "bp",
    ) -> None:
        if not isinstance(rf, OptimizableFunctional):
            raise OptimizationError(
                f"LBFGS needs a reduced functional (diffsolids.optimize.OptimizableFunctional: "
                f"forward, derivative, bounds, controls, ...), got {type(rf).__name__}"
            )
        self.rf = rf
        self.options = options or LBFGSOptions()
        self.options.validate()
        self.inner_product = inner_product
        if remesher is not None and not isinstance(remesher, RemeshHook):
            raise OptimizationError(
                f"remesher {type(remesher).__name__} needs needs_remesh(rf, q) and remesh(rf, q) "
                "(diffsolids.optimize.hooks.RemeshHook)"
            )
        self.remesher = remesher
        self.stop_conditions = list(stop_conditions)
        observers = [] if on_accept is None else on_accept
        self.on_accept: list[Observer] = [observers] if callable(observers) else list(observers)
        self.comm: MPI.Comm = rf.comm
        self.resume = resume
        self.progress = progress
        self.output = (
            OptimizationOutput(
                output_dir, self.comm, write_parameters, plot_every, iterate_every, iterate_format
            )
            if output_dir is not None
            else None
        )
        self.write_parameters = write_parameters
        self.log = IterationLog(self.comm, log, log_file) if log or log_file else None
        self.checkpoint = Checkpoint(checkpoint_dir, self.comm) if checkpoint_dir else None
        self.memory = LBFGSMemory(
            self.options.history_size, inner_product, self.options.curvature_tol
        )
        self.history: list[IterationRecord] = []
        self.iteration = 0
        self.remesh_count = 0
        self.num_forward = 0
        self.num_gradient = 0
        self.num_invalid = 0
        self.initial_gradient_norm = 0.0
        self.point: _Point | None = None
        self.active: np.ndarray | None = None  # variables held at their bounds last iteration
        self._t_start = 0.0
        self._stop: str | None = None  # a stop reason found while accepting an iterate
        self._interrupt = InterruptRequest(self.comm)

    # -- evaluation ---------------------------------------------------------------------------
    @overload
    def _sync(self, J: float) -> float: ...
    @overload
    def _sync(self, J: float, g: np.ndarray) -> tuple[float, np.ndarray]: ...
    def _sync(self, J: float, g: np.ndarray | None = None) -> float | tuple[float, np.ndarray]:
        """Rank 0's values on all ranks: every rank takes the same decisions."""
        J = collective_comm(self.comm).bcast(J, root=0)
        if g is None:
            return J
        return J, collective_comm(self.comm).bcast(g, root=0)

    def _set_warm_start(self) -> None:
        traj = self.point.trajectory if self.point is not None else None
        self.rf.warm_start(traj if self.options.warm_start else None)

    def _trial(self, q: np.ndarray) -> tuple[bool, float, float, str]:
        """Forward solve at a trial point: (valid, J, seconds, why invalid)."""
        self._set_warm_start()
        t0 = time.perf_counter()
        why = ""
        try:
            J = float(self.rf.forward(q))
        except DiffsolidsError as e:
            J, why = np.nan, f"{type(e).__name__}: {e}"
        self.num_forward += 1
        seconds = time.perf_counter() - t0
        valid = collective_comm(self.comm).allreduce(bool(np.isfinite(J)), op=MPI.LAND)
        if not valid and not why:
            why = "failed on another rank"
        return valid, (self._sync(J) if valid else np.nan), seconds, why

    def _gradient(self) -> tuple[np.ndarray, float]:
        t0 = time.perf_counter()
        try:
            g = np.asarray(self.rf.derivative(), dtype=float)
        except DiffsolidsError as e:
            raise OptimizationError(
                f"the gradient at iteration {self.iteration} could not be computed: {e}"
            ) from e
        self.num_gradient += 1
        if not np.all(np.isfinite(g)):
            raise OptimizationError(f"non-finite gradient at iteration {self.iteration}")
        return self._sync(0.0, g)[1], time.perf_counter() - t0

    def _restore(self) -> None:
        """Model and controls back to the accepted point after an invalid trial."""
        p = self.point
        if p.snapshot is not None:
            self.rf.restore(p.snapshot)
        else:
            self.rf.controls.assign(p.q)

    def _terms(self) -> dict[str, float]:
        return dict(self.rf.term_values())

    def _snapshot(self) -> tuple | None:
        return self.rf.snapshot()

    def _bounds(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = (np.asarray(b, dtype=float) for b in self.rf.bounds())
        check_bounds(q, lo, hi, self.rf.controls)
        return lo, hi

    # -- start and resume ------------------------------------------------------------------------
    def _start(self, q0: npt.ArrayLike | None) -> None:
        rf = self.rf
        q = np.array(rf.initial_parameters() if q0 is None else q0, dtype=float)
        if q.shape != (rf.size,):
            raise OptimizationError(f"q0 has shape {q.shape}, the controls expect ({rf.size},)")
        if not np.all(np.isfinite(q)):
            raise OptimizationError("the initial parameters are not finite")
        self._bounds(q)
        self._set_warm_start()
        t0 = time.perf_counter()
        try:
            J = float(rf.forward(q))
        except DiffsolidsError as e:
            raise OptimizationError(
                f"the objective cannot be evaluated at the initial point: {e}"
            ) from e
        self.num_forward += 1
        t_forward = time.perf_counter() - t0
        if not np.isfinite(J):
            raise OptimizationError(f"non-finite objective at the initial point (J = {J})")
        J = self._sync(J)
        g, t_grad = self._gradient()
        self.point = _Point(q, J, g, rf.trajectory, self._snapshot())
        self._warn_inactive_controls(g)
        lo, hi = self._bounds(q)
        gnorm = float(np.linalg.norm(projected_gradient(q, g, lo, hi)))
        self.initial_gradient_norm = gnorm
        rec = self._record(0.0, 0.0, 0, 0, t_forward, t_grad)
        self._accepted(rec)

    def _warn_inactive_controls(self, g: np.ndarray) -> None:
        controls = self.rf.controls
        for c, a, b in zip(
            controls.controls, controls.offsets[:-1], controls.offsets[1:], strict=True
        ):
            if b > a and not np.any(g[a:b]):
                message = (
                    f"control {c.name} has no effect on the objective: its gradient is zero at "
                    "the initial point"
                )
                logger.warning(message)
                warnings.warn(message, OptimizationWarning, stacklevel=3)

    def _resume(self) -> None:
        ckpt = self.checkpoint
        meta, arrays = ckpt.load_state()
        count = int(meta["remesh_count"])
        if count > 0:
            if not isinstance(self.remesher, RemeshCheckpoints):
                raise OptimizationError(
                    f"the checkpoint in {ckpt.directory} follows {count} remeshes; resuming needs "
                    "a remesher with load_checkpoint(directory, rf) (RemeshCheckpoints)"
                )
            self.rf = self.remesher.load_checkpoint(ckpt.mesh_directory(count), self.rf)
            self._rebuild_inner_product()
        rf = self.rf
        q = np.asarray(arrays["q"], dtype=float)
        if q.shape != (rf.size,):
            raise OptimizationError(
                f"the checkpoint in {ckpt.directory} has {q.size} parameters, the controls "
                f"expect {rf.size}: a different problem (use a new checkpoint directory)"
            )
        rf.controls.assign(q)
        trajectory, problem = ckpt.load_trajectory(meta, self.rf.dof_layout())
        self.point = _Point(q, float(meta["objective"]), np.asarray(arrays["g"]), trajectory)
        if problem is not None and self.options.warm_start:
            message = f"checkpoint: no warm start after resuming ({problem})"
            logger.warning(message)
            warnings.warn(message, OptimizationWarning, stacklevel=3)
        self.memory.load({k: arrays[k] for k in ("s", "y", "gamma")})
        self.active = np.asarray(arrays["active"], dtype=bool) if arrays["active"].size else None
        self.iteration = int(meta["iteration"])
        self.remesh_count = count
        self.initial_gradient_norm = float(meta["initial_gradient_norm"])
        self.history = [IterationRecord.from_dict(d) for d in meta["history"]]
        if self.output is not None:
            self.output.start(self.history)
        if self.log is not None:
            self.log.start(self.history)
        logger.info("opt resuming from the checkpoint of iteration %d", self.iteration)

    def _save_checkpoint(self) -> None:
        if self.checkpoint is None:
            return
        p = self.point
        meta = {
            "iteration": self.iteration,
            "remesh_count": self.remesh_count,
            "objective": p.J,
            "initial_gradient_norm": self.initial_gradient_norm,
            "history": [vars(r) for r in self.history],
        }
        active = np.zeros(0, dtype=bool) if self.active is None else self.active
        arrays = {"q": p.q, "g": p.g, "active": active, **self.memory.state()}
        self.checkpoint.save(meta, arrays, p.trajectory, self.rf.dof_layout())

    def _rebuild_inner_product(self) -> None:
        if isinstance(self.inner_product, RebuildableInnerProduct):
            self.inner_product = self.inner_product.rebuild(self.rf)
            self.memory.inner_product = self.inner_product

    # -- iterations ------------------------------------------------------------------------------
    def _record(
        self,
        step_norm: float,
        step_length: float,
        trials: int,
        invalid: int,
        t_forward: float,
        t_grad: float,
    ) -> IterationRecord:
        p = self.point
        lo, hi = self._bounds(p.q)
        return IterationRecord(
            iteration=self.iteration,
            objective=p.J,
            terms=self._terms(),
            gradient_norm=float(np.linalg.norm(projected_gradient(p.q, p.g, lo, hi))),
            step_norm=float(step_norm),
            step_length=float(step_length),
            trials=trials,
            invalid_trials=invalid,
            forward_seconds=t_forward,
            gradient_seconds=t_grad,
            seconds=time.perf_counter() - self._t_start,
            parameter_norm=float(np.linalg.norm(p.q)),
            parameter_summary=control_summary(self.rf.controls, p.q),
            q=p.q.tolist() if self.write_parameters else None,
        )

    def _accepted(self, rec: IterationRecord) -> None:
        """Remesh if asked, then log, write output and checkpoint an accepted iterate."""
        if self.iteration > 0 and self.remesher is not None:
            self._maybe_remesh(rec)
        self.history.append(rec)
        log_iteration(rec)
        if self.log is not None:
            self.log(rec, self)
        if self.output is not None:
            self.output.record(rec, self.history)
            if self.output.wants_iterate(self.iteration) and self.point.trajectory is not None:
                self.output.write_iterate(self.iteration, self.rf.model, self.point.trajectory)
        self._save_checkpoint()
        for observer in self.on_accept:
            observer(rec, self)

    def _maybe_remesh(self, rec: IterationRecord) -> None:
        """Remesh if the remesher asks; a failure keeps the accepted point and ends the run."""
        p = self.point
        wanted = bool(
            collective_comm(self.comm).bcast(bool(self.remesher.needs_remesh(self.rf, p.q)), root=0)
        )
        if not wanted:
            return
        rf, inner_product = self.rf, self.inner_product
        try:
            self._remesh(rec, p)
        except DiffsolidsError as e:
            logger.warning("opt: remeshing failed (%s); the run ends at the accepted point", e)
            self.rf, self.point, self.inner_product = rf, p, inner_product
            self.memory.inner_product = inner_product
            self._restore()
            self._stop = f"remesh: {type(e).__name__}: {e}"

    def _remesh(self, rec: IterationRecord, p: _Point) -> None:
        J_before = p.J
        new_rf, q = self.remesher.remesh(self.rf, p.q)
        self.rf = new_rf
        self._rebuild_inner_product()
        self.memory.reset()
        self.active = None
        q = np.array(q, dtype=float)
        self.point = None
        self._set_warm_start()
        t0 = time.perf_counter()
        try:
            J = float(new_rf.forward(q))
        except DiffsolidsError as e:
            raise OptimizationError(f"the forward solve fails on the remeshed scene: {e}") from e
        self.num_forward += 1
        if not np.isfinite(J):
            raise OptimizationError(f"non-finite objective after remeshing (J = {J})")
        rec.forward_seconds += time.perf_counter() - t0
        J = self._sync(J)
        g, t_grad = self._gradient()
        self.point = _Point(q, J, g, new_rf.trajectory, self._snapshot())
        self.remesh_count += 1
        lo, hi = self._bounds(q)
        rec.objective, rec.objective_before_remesh, rec.remeshed = J, J_before, True
        rec.terms = self._terms()
        rec.gradient_norm = float(np.linalg.norm(projected_gradient(q, g, lo, hi)))
        rec.gradient_seconds += t_grad
        rec.q = q.tolist() if self.write_parameters else None
        rec.parameter_norm = float(np.linalg.norm(q))
        rec.parameter_summary = control_summary(new_rf.controls, q)
        if self.checkpoint is not None:
            if isinstance(self.remesher, RemeshCheckpoints):
                directory = self.checkpoint.mesh_directory(self.remesh_count)
                self.remesher.save_checkpoint(directory, new_rf)
            else:
                logger.warning(
                    "opt: the remesher has no save_checkpoint (RemeshCheckpoints); checkpoints "
                    "after this remesh cannot be resumed"
                )

    def _direction(self, g: np.ndarray, free: np.ndarray) -> np.ndarray:
        d = -self.memory.apply(g, free)
        if not float(g @ d) < 0 and len(self.memory):
            logger.info("opt: L-BFGS direction is not a descent direction; memory reset")
            self.memory.reset(keep_scaling=True)
            d = -self.memory.apply(g, free)
        return d

    def _line_search(
        self, d: np.ndarray, lo: np.ndarray, hi: np.ndarray
    ) -> tuple[np.ndarray | None, float, float, int, int, float]:
        """Backtracking along the projected path; returns (q, J, t, trials, invalid, seconds)."""
        opts = self.options
        p = self.point
        if self.memory.scaled:
            t = 1.0
        elif opts.initial_step is not None:
            t = opts.initial_step / float(np.max(np.abs(d)))
        else:
            t = 1.0 / float(np.linalg.norm(d))
        t = min(t, step_limit(d, block_limits(opts.max_change, self.rf.controls)))
        trials = invalid = 0
        seconds = 0.0
        for _ in range(opts.max_trials):
            q = project(p.q + t * d, lo, hi)
            s = q - p.q
            if not np.any(s):
                break
            trials += 1
            valid, value, dt, why = self._trial(q)
            seconds += dt
            bound = p.J + opts.armijo * min(float(p.g @ s), 0.0)  # Armijo on the projected path
            if valid and value <= bound:
                return q, value, t, trials, invalid, seconds
            if self._interrupt.pending():
                self._stop = "interrupted"
                break
            if valid:
                logger.debug(
                    "opt: trial t=%.3g rejected (J=%.10e above the Armijo bound)", t, value
                )
            else:
                invalid += 1
                self.num_invalid += 1
                logger.info("opt: invalid trial t=%.3g (%s); step halved", t, why)
                self._restore()
            t *= opts.backtracking
        self._restore()
        return None, np.nan, t, trials, invalid, seconds

    def _stop_reason(self, rec: IterationRecord, previous: IterationRecord | None) -> str | None:
        opts = self.options
        for cond in self.stop_conditions:
            verdict = collective_comm(self.comm).bcast(cond(rec, self), root=0)
            if verdict:
                name = verdict if isinstance(verdict, str) else condition_name(cond)
                return f"user: {name}"
        gn = rec.gradient_norm
        if gn <= opts.gradient_atol or gn == 0.0:
            return "gradient_atol"
        if gn <= opts.gradient_rtol * self.initial_gradient_norm:
            return "gradient_rtol"
        if previous is not None and not rec.remeshed:
            if rec.step_norm <= opts.step_tol:
                return "step"
            decrease = previous.objective - rec.objective
            scale = max(abs(previous.objective), abs(rec.objective))
            if decrease <= max(opts.objective_atol, opts.objective_rtol * scale):
                return "objective"
        if self.iteration >= opts.max_iterations:
            return "max_iterations"
        return None

    def _step(self) -> str | None:
        """One L-BFGS iteration; returns a stop reason or None."""
        p = self.point
        lo, hi = self._bounds(p.q)
        active = active_set(p.q, p.g, lo, hi)
        if self.active is not None and not np.array_equal(active, self.active):
            # pairs whose steps moved now-fixed variables misstate the reduced curvature
            logger.debug("opt: active set changed (%d at bounds); memory reset", active.sum())
            self.memory.reset(keep_scaling=True)
        self.active = active
        free = ~active
        d = self._direction(p.g, free)
        if not float(p.g @ d) < 0:
            return "gradient_atol"
        q, J, t, trials, invalid, seconds = self._line_search(d, lo, hi)
        if q is None and self._stop is not None:
            return self._stop
        if q is None and self.memory.scaled:
            logger.info("opt: line search failed; retrying along -M^-1 g with a reset memory")
            self.memory.reset()
            d = self._direction(p.g, free)
            q, J, t, more, more_invalid, more_seconds = self._line_search(d, lo, hi)
            trials, invalid, seconds = trials + more, invalid + more_invalid, seconds + more_seconds
        if q is None:
            return "line_search"
        g, t_grad = self._gradient()
        self.memory.update(q - p.q, g - p.g, abs(float(p.g @ (q - p.q))))
        self.point = _Point(q, J, g, self.rf.trajectory, self._snapshot())
        self.iteration += 1
        step_norm = float(np.linalg.norm(q - p.q))
        rec = self._record(step_norm, t, trials, invalid, seconds, t_grad)
        self._accepted(rec)
        return self._stop

    # -- driver ----------------------------------------------------------------------------------
    def run(self, q0: npt.ArrayLike | None = None) -> OptimizationResult:
        """Minimise from ``q0`` (default: the controls' current parameters), or resume.

        The functional's warm start (``LBFGSOptions.warm_start``) ends with the run, also
        when it raises: later evaluations start from their own guesses.

        Raises:
            OptimizationError: Bounds excluding the initial point, an initial point where the
                objective cannot be evaluated, a non-finite objective or gradient at an accepted
                point, an incompatible checkpoint.
        """
        try:
            return self._run(q0)
        finally:
            self.rf.warm_start(None)

    def _run(self, q0: npt.ArrayLike | None) -> OptimizationResult:
        self._t_start = time.perf_counter()
        block_limits(self.options.max_change, self.rf.controls)  # malformed limits fail early
        resumed_from = None
        if self.checkpoint is not None and self.resume and self.checkpoint.exists():
            self._resume()
            resumed_from = self.iteration
        else:
            if self.output is not None:
                self.output.start([])
            if self.log is not None:
                self.log.start([])
            self._start(q0)
        opts = self.options
        with progress_bar(opts.max_iterations, self.comm, self.progress, "optimisation") as bar:
            bar.update(self.iteration)
            previous = self.history[-2] if len(self.history) > 1 else None
            reason = self._stop_reason(self.history[-1], previous)
            with self._interrupt:
                while reason is None:
                    reason = self._step()
                    bar.update(1)
                    if reason is None:
                        reason = self._stop_reason(self.history[-1], self.history[-2])
                    if reason is None and self._interrupt.pending():
                        reason = "interrupted"
        p = self.point
        self._restore()
        if (
            self.output is not None
            and self.output.iterate_every > 0
            and not self.output.wants_iterate(self.iteration)
            and p.trajectory is not None
        ):
            self.output.write_iterate(self.iteration, self.rf.model, p.trajectory)
        if self.output is not None:
            self.output.finish(self.history)
        message = _MESSAGES.get(reason.split(":")[0], reason)
        logger.info("opt stopped after %d iterations: %s", self.iteration, message)
        if reason in ("line_search", "interrupted") or reason.startswith("remesh"):
            detail = reason.partition(": ")[2]
            text = f"{message} ({detail})" if detail else message
            warnings.warn(f"optimisation stopped: {text}", OptimizationWarning, stacklevel=2)
        return OptimizationResult(
            q=p.q.copy(),
            objective=p.J,
            gradient=p.g.copy(),
            iterations=self.iteration,
            reason=reason,
            message=message,
            history=list(self.history),
            num_forward=self.num_forward,
            num_gradient=self.num_gradient,
            num_invalid_trials=self.num_invalid,
            functional=self.rf,
            resumed_from=resumed_from,
        )


_MESSAGES = {
    "gradient_atol": "projected gradient norm below the absolute tolerance",
    "gradient_rtol": "projected gradient norm reduced below the relative tolerance",
    "step": "step below the step tolerance",
    "objective": "objective reduction below its tolerance",
    "max_iterations": "iteration limit reached",
    "line_search": "the line search found no valid step with sufficient decrease",
    "interrupted": "interrupted (Ctrl-C); the result is the last accepted point",
    "remesh": "remeshing failed; the result is the last accepted point, on the mesh before",
    "user": "a user stopping condition was met",
}


def minimize(
    rf: OptimizableFunctional,
    q0: npt.ArrayLike | None = None,
    options: LBFGSOptions | None = None,
    **kwargs,
) -> OptimizationResult:
    """Minimise a ReducedFunctional with :class:`LBFGS` (keyword arguments as there).

    Example:
        ``result = minimize(rf, options=LBFGSOptions(gradient_rtol=1e-8), output_dir="out")``.
    """
    return LBFGS(rf, options, **kwargs).run(q0)
