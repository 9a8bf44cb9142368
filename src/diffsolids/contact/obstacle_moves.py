"""Moving obstacles in the steps of the contact term: their displacements and the CCD of moves.

Kinematic obstacles (:class:`~diffsolids.contact.geometry.obstacle.Obstacle`) are extra vertices of
the collision mesh with prescribed displacements O^i = O(t_i) and no dofs: x = X + W u + O^i, their
rows and columns never enter the PETSc vectors and matrices, and every adjoint product keeps the
body rows only (obstacles have neither shape dofs nor state). Their velocity in the friction
potential is the same BDF formula, (O^i + sum_j alpha_j O^{i-j}) / (beta dt), and the lagged normal
forces and tangent bases are those at x^{i-1} (obstacles at O^{i-1}): friction acts on the
relative sliding velocity.

Scheme of a step with moving obstacles (never intersected): the Newton solve of step i runs with
the obstacles at O^i (its line search scales only the body part). The move O^{i-1} -> O^i before
it is checked by CCD at the start of the step (:meth:`ObstacleMoves.check_move`, from
``ContactTerm.begin_step``): (1) with the bodies held at u^{i-1}; if that is collision-free, the
Newton start (u^{i-1}, O^i) is admissible and every later path (the guess, the Newton steps) is
checked with the obstacles at O^i; (2) otherwise (an obstacle pushing a body, e.g. an elevator,
closes the gap within the step) the start is not admissible and the move must be made together
with the body's initial guess: ``ContactTerm.max_step`` from exactly u^{i-1} then checks the
straight path on which the obstacles move from O^{i-1} to O^i while the body moves from u^{i-1}
to the guess (:meth:`ObstacleMoves.first_move`), and admits it only in full (inf or 0). If no
guess passes, a clear IntersectionError names the obstacle and the step (a smaller time step, or
an initial guess that moves with the obstacle, is needed). So a moving obstacle may carry a body
that already moves with it (the extrapolated guess u^{i-1} + dt v^{i-1} of a body riding a lift)
or slide along it (a belt), but not push a body at rest, or quasi-statically in load steps, by
more than their gap per step: that needs a continuation of the obstacle's move with
intermediate solves (as ``Simulation._dirichlet_continuation`` does for Dirichlet values).
"""

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from diffsolids.contact.diagnostics import obstacle_move_error
from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.contact.step import ContactStep
from diffsolids.contact.timing import timed
from diffsolids.errors import ParameterError

if TYPE_CHECKING:
    from diffsolids.integrators import Integrator

__all__ = ["ObstacleMoves"]

logger = logging.getLogger("diffsolids")

# collision-free fraction of the straight path x0 -> x1 with the bodies at U0 (all ranks)
Fraction = Callable[[np.ndarray, np.ndarray, np.ndarray], float]


class ObstacleMoves:
    """The obstacles' displacements at each step and the collision check of their moves.

    Args:
        surface: The collision surface (its obstacles' motions).
        dim: Geometric dimension.
        timings: The contact term's timers (``ccd_obstacles`` is added here).

    Attributes:
        clock: Time of step k (None until a step began).
        dynamic: Whether the integrator is dynamic (for the error message).
        moved_with_guess: Forward steps whose obstacle move was made with the body's guess.
    """

    def __init__(self, surface: CollisionSurface, dim: int, timings: dict[str, list]) -> None:
        self.surface = surface
        self.dim = dim
        self.timings = timings
        self.clock: Callable[[int], float] | None = None
        self.dynamic = True
        self.moved_with_guess: list[int] = []

    def follow(self, integrator: "Integrator") -> None:
        """Take the times of the steps from the run's integrator."""
        self.clock = integrator.time
        self.dynamic = integrator.dynamic

    def at(self, k: int) -> np.ndarray:
        """(num_vertices, dim): zero body rows, the obstacles' displacements at step ``k``."""
        surf = self.surface
        if not surf.has_moving_obstacles:
            return np.zeros((surf.num_vertices, self.dim))
        if self.clock is None:
            if k != 0:
                raise ParameterError(
                    f"the time of step {k} is not known yet (moving obstacles): run or begin a "
                    "step of the simulation first"
                )
            return surf.obstacle_displacement(0.0)
        return surf.obstacle_displacement(float(self.clock(k)))

    def check_move(self, step: ContactStep, O_prev: np.ndarray, fraction: Fraction) -> None:
        """CCD of the obstacles' move O^{i-1} -> O^i with the bodies held at u^{i-1} (collective).

        Free: the Newton start (u^{i-1}, O^i) is admissible. Not free: the move must be made
        with the body's initial guess (see :meth:`first_move`); the step's ``blocked`` records
        that.
        """
        lagged, O_now = step.lagged, step.obstacle
        if np.array_equal(O_prev, O_now):
            return
        X = self.surface.rest_positions
        x0 = np.asfortranarray(X + lagged)
        x1 = np.asfortranarray(x0 + (O_now - O_prev))
        with timed(self.timings, "ccd_obstacles"):
            toi = fraction(lagged, x0, x1)
        step.blocked = toi < 1.0
        step.start_body = lagged - O_prev
        if step.blocked:
            self.moved_with_guess.append(step.index)
            logger.info(
                "contact step %d: the obstacles' move alone is not collision-free (fraction "
                "%.3g): it is made with the body's initial guess",
                step.index,
                toi,
            )

    def first_move(
        self, step: ContactStep | None, Ub: np.ndarray, dU: np.ndarray, fraction: Fraction
    ) -> float | None:
        """The step bound of a blocked step's first move from u^{i-1} (None: not that move).

        The path on which the obstacles move from O^{i-1} to O^i while the bodies move from
        u^{i-1} (``Ub``) by ``dU``: inf if collision-free, else 0.

        Raises:
            IntersectionError: The move is not admissible even without body motion.
        """
        if step is None or not step.blocked or not np.array_equal(Ub, step.start_body):
            return None
        X = self.surface.rest_positions
        x0 = np.asfortranarray(X + step.lagged)
        x1 = np.asfortranarray(X + Ub + dU + step.obstacle)
        with timed(self.timings, "ccd_obstacles"):
            toi = fraction(step.lagged, x0, x1)
        if toi >= 1.0:
            return np.inf
        if not np.any(dU):
            move = step.obstacle - (step.lagged - step.start_body)
            raise obstacle_move_error(self.surface, step.index, move, self.dynamic)
        return 0.0
