"""Options, errors and warnings of the optimiser."""

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from diffsolids.errors import DiffsolidsError

__all__ = ["LBFGSOptions", "OptimizationError", "OptimizationWarning"]


class OptimizationError(DiffsolidsError, RuntimeError):
    """An optimisation that cannot start or continue (bad bounds, non-finite values, ...)."""


class OptimizationWarning(UserWarning):
    """Something suspicious but not fatal, e.g. a control with no effect on the objective."""


@dataclass
class LBFGSOptions:
    """Options of :class:`~diffsolids.optimize.LBFGS`.

    Stopping (the first criterion met ends the run; ``0`` disables a tolerance):

    Attributes:
        history_size: Number of (s, y) pairs kept by L-BFGS.
        max_iterations: Iteration limit (accepted steps).
        gradient_atol: Stop when the projected gradient norm ``|P(q - g) - q|_2`` is below.
        gradient_rtol: Stop when the projected gradient norm is below this fraction of its
            value at the initial point.
        step_tol: Stop when an accepted step ``|q_{k+1} - q_k|_2`` is below.
        objective_rtol: Stop when ``J_k - J_{k+1} <= objective_rtol * max(|J_k|, |J_{k+1}|)``.
        objective_atol: Stop when ``J_k - J_{k+1} <= objective_atol``.
        armijo: Sufficient-decrease constant c1 of the Armijo condition
            ``J(q_t) <= J(q) + c1 g.(q_t - q)`` (``q_t`` the projected trial point).
        backtracking: Step reduction factor after a rejected or invalid trial.
        max_trials: Trials per line search before it fails.
        initial_step: Largest parameter change (max-norm) of a step taken without curvature
            information (first iteration, after a reset or remesh). ``None``: a step of unit
            Euclidean length, as L-BFGS-B does.
        max_change: Largest change of a parameter per iteration (max-norm per control block):
            one number for all controls, a sequence with one entry per control (``None`` for no
            limit) or a mapping from control name (or index) to a limit.
        warm_start: Start every forward solve from the trajectory of the last accepted iterate.
            Off by default: with it, J at a trial point depends on the iterate it was reached
            from (by the Newton tolerance, and by a branch where a step has several minima).
        curvature_tol: A pair (s, y) enters the L-BFGS memory only if
            ``s.y > curvature_tol * max(|s| |y|, |g.s|)``.
    """

    history_size: int = 6
    max_iterations: int = 100
    gradient_atol: float = 0.0
    gradient_rtol: float = 1e-6
    step_tol: float = 0.0
    objective_rtol: float = 0.0
    objective_atol: float = 0.0
    armijo: float = 1e-4
    backtracking: float = 0.5
    max_trials: int = 20
    initial_step: float | None = None
    max_change: float | Sequence | Mapping | None = None
    warm_start: bool = False
    curvature_tol: float = 1e-10

    def validate(self) -> None:
        """Raise OptimizationError naming the first invalid option."""
        checks = [
            (self.history_size >= 0, "history_size must be >= 0"),
            (self.max_iterations >= 0, "max_iterations must be >= 0"),
            (0.0 < self.armijo < 1.0, "armijo must lie in (0, 1)"),
            (0.0 < self.backtracking < 1.0, "backtracking must lie in (0, 1)"),
            (self.max_trials >= 1, "max_trials must be >= 1"),
            (
                self.initial_step is None or self.initial_step > 0,
                "initial_step must be positive (or None)",
            ),
        ]
        for name in (
            "gradient_atol",
            "gradient_rtol",
            "step_tol",
            "objective_rtol",
            "objective_atol",
            "curvature_tol",
        ):
            checks.append((getattr(self, name) >= 0, f"{name} must be >= 0"))
        for ok, message in checks:
            if not ok:
                raise OptimizationError(f"invalid optimiser option: {message}")
