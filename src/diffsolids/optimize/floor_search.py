"""Minimise J over two parameters with one projected out: the other along the floor of J's valley.

For a J(a, b) whose valley is narrow in a and bent (the floor a*(b) = argmin_a J(a, b) curves),
L-BFGS crawls: every straight step along the floor leaves it and the walls cap the next one.
:class:`FloorSearch` minimises over a at fixed b (Newton with secant curvature) and moves b along
the floor F(b) = min_a J(a, b) with its slope dF/db = dJ/db - (h_ab / h_aa) dJ/da (first order in
the inner residual), each new b starting from the floor's tangent. Example: a kangaroo's log E
(well seen by its trajectory) and nu (barely seen), ``demos/paper_kangaroo.py``.
"""

import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from diffsolids.optimize.contract import OptimizableFunctional
from diffsolids.optimize.monitor import (
    IterationRecord,
    OptimizationOutput,
    control_summary,
    log_iteration,
)
from diffsolids.optimize.observers import TrajectoryKeeper
from diffsolids.optimize.optimizer import OptimizationResult
from diffsolids.optimize.options import OptimizationError

__all__ = ["FloorSearch"]


@dataclass
class _Point:
    q: np.ndarray
    value: float
    g: np.ndarray


class FloorSearch:
    """Minimise J(a, b) with a projected out: b along the floor of J's valley.

    The inner problem (J over a at fixed b) is Newton with secant curvature ``h_aa`` and Armijo
    backtracking; its steps also give the secant of d(dJ/db)/da = ``h_ab``, hence the floor's
    slope da*/db = -h_ab / h_aa. The outer problem (the floor value F(b) = min_a J) takes secant
    steps in b bounded by ``max_change`` and by the bracket where dF/db changes sign. One
    evaluation is a forward and an adjoint solve, one history record. Stops: "step" (the next b
    step below ``step_tol``), "bound" (the minimum over b on a bound of b) or "max_iterations"
    (``max_evaluations``); the result is the lowest J evaluated.

    Args:
        rf: The functional of the two parameters (a, b), in this order.
        max_change: Largest step of (a, b).
        step_tol: (a, b) tolerances: the inner Newton stops when its next step in a would be
            below the first, the search when its next secant step in b would be below the second.
        max_evaluations: Evaluation limit.
        output: History and figures (or None).

    Attributes:
        history: One record per evaluation.
        keeper: The trajectories of the first and of the best evaluation.

    Raises:
        OptimizationError: ``rf`` does not have two parameters, or a tolerance or step limit
            is not positive.
    """

    def __init__(
        self,
        rf: OptimizableFunctional,
        max_change: npt.ArrayLike,
        step_tol: npt.ArrayLike,
        max_evaluations: int,
        output: OptimizationOutput | None = None,
    ) -> None:
        if rf.size != 2:
            raise OptimizationError(f"FloorSearch needs two parameters (a, b), got {rf.size}")
        self.max_change = np.asarray(max_change, dtype=float).reshape(-1)
        self.step_tol = np.asarray(step_tol, dtype=float).reshape(-1)
        for name, v in (("max_change", self.max_change), ("step_tol", self.step_tol)):
            if v.shape != (2,) or not np.all(v > 0):
                raise OptimizationError(f"FloorSearch {name} must be two positive values, got {v}")
        self.rf, self.output = rf, output
        self.max_evaluations = int(max_evaluations)
        self.lo, self.hi = rf.bounds()
        self.history: list[IterationRecord] = []
        self.keeper = TrajectoryKeeper()
        self.best: _Point | None = None
        self.h_aa: float | None = None
        self.h_ab = 0.0
        self._h_ab_at: float | None = None  # the b at which h_ab was measured
        self._t0 = time.perf_counter()

    def _norm(self, p: _Point) -> float:
        return float(np.linalg.norm(np.clip(p.q - p.g, self.lo, self.hi) - p.q))

    def _full(self) -> bool:
        return len(self.history) >= self.max_evaluations

    def evaluate(self, q: npt.ArrayLike, previous: _Point | None) -> _Point:
        """J and its gradient at q clipped to the bounds (recorded; the best trajectory kept)."""
        q = np.clip(np.asarray(q, dtype=float), self.lo, self.hi)
        t0 = time.perf_counter()
        value = float(self.rf.forward(q))
        t1 = time.perf_counter()
        p = _Point(q, value, self.rf.derivative())
        t2 = time.perf_counter()
        rec = IterationRecord(
            iteration=len(self.history),
            objective=value,
            terms=self.rf.term_values(),
            gradient_norm=self._norm(p),
            step_norm=0.0 if previous is None else float(np.linalg.norm(q - previous.q)),
            step_length=0.0 if previous is None else 1.0,
            trials=0 if previous is None else 1,
            forward_seconds=t1 - t0,
            gradient_seconds=t2 - t1,
            seconds=t2 - self._t0,
            parameter_norm=float(np.linalg.norm(q)),
            parameter_summary=control_summary(self.rf.controls, q),
            q=q.tolist(),
        )
        self.history.append(rec)
        log_iteration(rec)
        if self.output is not None:
            self.output.record(rec, self.history)
        if self.keeper.first is None:
            self.keeper.first = self.rf.trajectory
        if self.best is None or value <= self.best.value:
            self.best = p
            self.keeper.last = self.rf.trajectory
        return p

    def _b_free(self, p: _Point) -> bool:
        return not ((p.q[1] <= self.lo[1] and p.g[1] > 0) or (p.q[1] >= self.hi[1] and p.g[1] < 0))

    def _inner_converged(self, p: _Point) -> bool:
        if not self.h_aa:
            return False
        if abs(p.g[0] / self.h_aa) <= self.step_tol[0]:
            return True
        if self._h_ab_at != p.q[1]:
            return False  # h_ab changes with b: measured again at this b first
        ratio = self.h_ab / self.h_aa
        return self._b_free(p) and abs(ratio * p.g[0]) <= 0.1 * abs(p.g[1])  # dF/db to 10%

    def _floor(self, p: _Point) -> _Point:
        """Newton in a at the b of p until a is converged or no longer matters."""
        while not self._full() and not self._inner_converged(p):
            limit = self.max_change[0]
            step = -p.g[0] / self.h_aa if self.h_aa else -np.sign(p.g[0]) * limit
            step = float(np.clip(step, -limit, limit))
            for _ in range(10):  # Armijo backtracking
                trial = self.evaluate(p.q + np.array([step, 0.0]), p)
                da = trial.q[0] - p.q[0]
                if trial.value <= p.value + 1e-4 * p.g[0] * da or self._full():
                    break
                step *= 0.5
            if da == 0.0:
                return trial
            curvature = (trial.g[0] - p.g[0]) / da
            if curvature > 0:
                self.h_aa = curvature
                self.h_ab = (trial.g[1] - p.g[1]) / da
                self._h_ab_at = p.q[1]
            p = trial
        return p

    def run(self, q0: npt.ArrayLike) -> OptimizationResult:
        """Minimise from q0 = (a, b)."""
        self._t0 = time.perf_counter()
        if self.output is not None:
            self.output.start([])
        p = self.evaluate(q0, None)
        bracket = [self.lo[1], self.hi[1]]
        previous = None  # (b, dF/db) of the last floor point
        reason = "max_iterations"
        while True:
            p = self._floor(p)
            if self._full():
                break
            ratio = self.h_ab / self.h_aa if self.h_aa else 0.0
            b, slope = p.q[1], p.g[1] - ratio * p.g[0]
            bracket[1 if slope > 0 else 0] = b
            curvature = (slope - previous[1]) / (b - previous[0]) if previous else 0.0
            limit = self.max_change[1]
            step = -slope / curvature if curvature > 0 else -np.sign(slope) * limit
            if abs(step) <= self.step_tol[1]:
                reason = "step"
                break
            new = b + float(np.clip(step, -limit, limit))
            if not bracket[0] < new < bracket[1]:
                new = 0.5 * (bracket[0] + bracket[1])
            if new == b or not self._b_free(p):
                reason = "bound"
                break
            previous = (b, slope)
            p = self.evaluate([p.q[0] - ratio * (new - b), new], p)  # on the floor's tangent
        if self.output is not None:
            self.output.finish(self.history)
        return self._result(reason)

    def _result(self, reason: str) -> OptimizationResult:
        best = self.best
        return OptimizationResult(
            q=best.q,
            objective=best.value,
            gradient=best.g,
            iterations=len(self.history) - 1,
            reason=reason,
            message=f"floor search stopped ({reason}) after {len(self.history)} evaluations",
            history=self.history,
            num_forward=len(self.history),
            num_gradient=len(self.history),
            functional=self.rf,
        )
