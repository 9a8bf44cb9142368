"""Lagged friction of a step: normal forces and tangent bases from x^{i-1}, once per step.

The friction potential D of step i (see :mod:`diffsolids.contact.term`) uses the normal forces
and tangent bases of the collision set at x^{i-1} = X + W u^{i-1} (obstacles at O^{i-1}), with
each collision's coefficient from the table of the pairs of bodies (see
:mod:`~diffsolids.contact.energy.friction_table`), and the BDF velocity
v = U / (beta dt) + sum_j alpha_j U^{i-j} / (beta dt) of the collision vertices.

The step's collision set at x^{i-1} and its TangentialCollisions are kept by step index: the
adjoint sweep sets up step i again from the same u^{i-1} and reuses what the forward built
(each entry is checked against everything it was built from: the collision mesh, the static
mask, the positions x^{i-1}, the coefficients and the barrier; a mismatch rebuilds).
"""

from collections.abc import Sequence

import ipctk
import numpy as np

from diffsolids.contact.detection.collision_set import CollisionBuilder
from diffsolids.contact.energy.evaluation import Evaluation
from diffsolids.contact.energy.friction_table import checked_coefficients, tangential_collisions
from diffsolids.contact.step import ContactStep
from diffsolids.contact.timing import timed

__all__ = ["LaggedFriction"]


class LaggedFriction:
    """The friction state of the current step lagged from x^{i-1}, and its velocity.

    Args:
        builder: Builds the lagged collision sets (on its collision surface).
        pair_table: (num_bodies, num_bodies) index of each pair of bodies among the pairs.
        num_pairs: Number of pairs of bodies.
        timings: The contact term's timers (``lagged_friction`` is added here).

    Attributes:
        mu: Friction coefficient of each pair of bodies (set with :meth:`set_coefficients`).
        step: The contact term's record of the current step (None before the first): its
            ``lagged`` displacement U^{i-1}, ``beta_dt`` and velocity offset ``v_offset``.
        tangential: The step's TangentialCollisions with :attr:`mu` (None until built).
    """

    def __init__(
        self,
        builder: CollisionBuilder,
        pair_table: np.ndarray,
        num_pairs: int,
        timings: dict[str, list],
    ) -> None:
        self.surface = builder.surface
        self.builder = builder
        self.pair_table = pair_table
        self.timings = timings
        self.mu = np.zeros(num_pairs)
        self.step: ContactStep | None = None
        self.tangential: ipctk.TangentialCollisions | None = None
        self._lagged: dict | None = None
        # step index -> [surface state key, x^{i-1}, collisions at x^{i-1}, tangential
        # collisions: None or (mu, barrier, T)] of the last set-up of that step
        self._kept: dict[int, list] = {}

    def set_coefficients(self, values: np.ndarray | Sequence[float]) -> None:
        """Set the coefficients of the pairs (checked); the step's friction is rebuilt lazily."""
        mu = checked_coefficients(values, len(self.mu))
        if not np.array_equal(mu, self.mu):
            self.mu = mu
            self.tangential = None  # rebuilt lazily for the current step

    def begin_step(self, step: ContactStep) -> None:
        """Forget the lagged state of the previous step; ``step`` is the new step's record."""
        self.step = step
        self.tangential = None
        self._lagged = None

    @property
    def active(self) -> bool:
        """Whether any pair has friction."""
        return bool(np.any(self.mu > 0))

    def lagged_state(
        self, shape_derivatives: bool = False
    ) -> tuple[np.ndarray, ipctk.NormalCollisions]:
        """(positions, collisions) at x^{i-1}; with weight gradients when asked."""
        key = "lagged_shape" if shape_derivatives else "lagged"
        cached = self._lagged or {}
        if key not in cached:
            x = self.surface.rest_positions + self.step.lagged
            kept = None if shape_derivatives else self._kept_entry(x)
            if kept is not None:
                cached[key] = (x, kept[2])
            else:
                cached[key] = (x, self.builder.build(x, shape_derivatives))
                if not shape_derivatives:
                    state = self.surface.state_key()
                    self._kept[self.step.index] = [state, x, cached[key][1], None]
            self._lagged = cached
        return cached[key]

    def _kept_entry(self, x: np.ndarray) -> list | None:
        """The kept entry of the current step if it was built at x on the current surface."""
        entry = self._kept.get(self.step.index)
        if entry is None:
            return None
        state, xk = entry[:2]
        return entry if self.surface.has_state(state) and np.array_equal(xk, x) else None

    def _step_tangential(self, barrier: ipctk.BarrierPotential) -> ipctk.TangentialCollisions:
        """The step's TangentialCollisions with :attr:`mu` (kept from the step's last set-up).

        The kept ones are used when built from the same collision set, coefficients and
        barrier; else they are built (and kept).
        """
        _, C = self.lagged_state()
        entry = self._kept.get(self.step.index)
        own = entry is not None and entry[2] is C  # the kept collision set is this step's
        if own and entry[3] is not None:
            mu, kept_barrier, T = entry[3]
            if kept_barrier is barrier and np.array_equal(mu, self.mu):
                return T
        T = self.tangential_collisions(self.mu_table(self.mu), barrier)
        if own:
            entry[3] = (self.mu.copy(), barrier, T)
        return T

    def tangential_collisions(
        self,
        mu_table: np.ndarray,
        barrier: ipctk.BarrierPotential,
        shape_derivatives: bool = False,
    ) -> ipctk.TangentialCollisions:
        """TangentialCollisions lagged from x^{i-1} with the coefficients of ``mu_table``."""
        x, C = self.lagged_state(shape_derivatives)
        return tangential_collisions(self.surface, x, C, barrier, mu_table)

    def mu_table(self, coefficients: np.ndarray) -> np.ndarray:
        """(num_bodies, num_bodies) coefficient of each pair of bodies."""
        return coefficients[self.pair_table]

    def current(
        self, barrier: ipctk.BarrierPotential
    ) -> tuple[ipctk.TangentialCollisions | None, bool]:
        """(the step's TangentialCollisions, whether they were built now); None if all mu = 0."""
        if not np.any(self.mu > 0):
            return None, False
        if self.tangential is None:
            with timed(self.timings, "lagged_friction"):
                self.tangential = self._step_tangential(barrier)
            return self.tangential, True
        return self.tangential, False

    def velocity(self, U: np.ndarray) -> np.ndarray:
        """Velocity of the collision vertices at displacement U (the step's BDF formula)."""
        return U / self.step.beta_dt + self.step.v_offset

    def friction_velocity(self, ev: Evaluation) -> np.ndarray | None:
        """The velocity at ev when the step has friction (None without)."""
        return None if ev.friction is None else self.velocity(ev.U)
