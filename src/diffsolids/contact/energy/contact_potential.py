"""The contact potential at an evaluation: energy, gradient and Hessian, kept with it.

B(x) + beta dt D(v(u)) of the current step (see :mod:`diffsolids.contact.term`) evaluated on
this rank's share of the collision set (:mod:`~diffsolids.contact.energy.evaluation`): the energy is
summed over the ranks, the gradient too (one allreduce of the surface vector; its barrier part
is kept as this rank's share and summed on demand), the Hessian stays this rank's share (its
entries are added to the matrix by every rank with global indices). Each value is computed once
per :class:`~diffsolids.contact.energy.evaluation.Evaluation` and kept on it.
"""

import ipctk
import numpy as np
import scipy.sparse as sp

from diffsolids.contact.energy.evaluation import (
    Evaluation,
    contact_energy,
    contact_gradient,
    contact_hessian,
)
from diffsolids.contact.energy.lagged_arrays import friction_arrays
from diffsolids.contact.energy.lagging import LaggedFriction
from diffsolids.contact.energy.stick_model import StickModel
from diffsolids.contact.timing import timed
from diffsolids.errors import ParameterError

__all__ = ["ContactPotential", "projection_method"]


def projection_method(name: str) -> ipctk.PSDProjectionMethod:
    """The ipctk PSD projection method called ``name`` ("clamp" or "abs").

    Raises:
        ParameterError: Another name.
    """
    methods = {"clamp": ipctk.PSDProjectionMethod.CLAMP, "abs": ipctk.PSDProjectionMethod.ABS}
    if name not in methods:
        raise ParameterError(f"hessian_projection {name!r}: expected 'clamp' or 'abs'")
    return methods[name]


class ContactPotential:
    """Barrier and lagged friction potential of the step at an evaluation (kept on it).

    Args:
        lagging: The step's lagged friction (velocity, ``beta_dt``); the collision surface,
            the partition over the ranks and dhat are its builder's.
        friction_potential: ipctk's smoothed friction potential.
        stiffness: Barrier stiffness kappa (None: not chosen yet, see :meth:`set_stiffness`).
        projection: PSD projection of the projected Hessian.
        timings: The contact term's timers.

    Attributes:
        stiffness: Barrier stiffness kappa (None until chosen).
        barrier: ipctk BarrierPotential with :attr:`stiffness` (None until chosen).
    """

    def __init__(
        self,
        lagging: LaggedFriction,
        friction_potential: ipctk.FrictionPotential,
        stiffness: float | None,
        projection: ipctk.PSDProjectionMethod,
        timings: dict[str, list],
    ) -> None:
        self.surface = lagging.builder.surface
        self.partition = lagging.builder.partition
        self.lagging = lagging
        self.friction_potential = friction_potential
        self.dhat = lagging.builder.dhat
        self.projection = projection
        self.timings = timings
        self.stiffness: float | None = None
        self.barrier: ipctk.BarrierPotential | None = None
        self._stick: StickModel | None = None
        self._stick_of: ipctk.TangentialCollisions | None = None  # the collisions it models
        self.held: np.ndarray | None = None  # collisions held at stick for one Newton step
        if stiffness is not None:
            self.set_stiffness(stiffness)

    def set_stiffness(self, stiffness: float) -> None:
        """Fix the barrier stiffness kappa."""
        self.stiffness = stiffness
        self.barrier = self._own_barrier = ipctk.BarrierPotential(self.dhat, self.stiffness)

    def set_stiffness_factor(self, factor: float) -> None:
        """Evaluate the barrier with ``factor`` x kappa (1: kappa itself; a continuation stage).

        At 1 the term's own BarrierPotential object is back (what was built with it, e.g. the
        kept lagged friction, stays valid).
        """
        if factor == 1.0:
            self.barrier = self._own_barrier
        else:
            self.barrier = ipctk.BarrierPotential(self.dhat, self.stiffness * factor)

    def energy(self, ev: Evaluation) -> float:
        """The contact energy at ev, summed over the ranks (collective once per ev)."""
        if ev.energy is None:
            self._energy_now(ev)
        return ev.energy

    def _energy_now(self, ev: Evaluation) -> None:
        with timed(self.timings, "energy"):
            e = contact_energy(
                self.barrier,
                self.friction_potential,
                self.surface.mesh,
                ev,
                self.lagging.friction_velocity(ev),
                self.lagging.step.beta_dt,
            )
            ev.energy = self.partition.total(e)

    def gradient(self, ev: Evaluation) -> np.ndarray:
        """The gradient at ev summed over the ranks (the same on all; collective once per ev)."""
        if ev.gradient is None:
            self._gradient_now(ev)
        return ev.gradient

    def _gradient_now(self, ev: Evaluation) -> None:
        """The gradient summed over the ranks (the same on all); its barrier part kept local."""
        with timed(self.timings, "gradient"):
            g, ev.barrier_gradient_share = contact_gradient(
                self.barrier,
                self.friction_potential,
                self.surface.mesh,
                ev,
                self.lagging.friction_velocity(ev),
            )
        with timed(self.timings, "reduce"):
            ev.gradient = self.partition.sum(g)

    def barrier_gradient(self, ev: Evaluation) -> np.ndarray:
        """The barrier part of the gradient at ev, summed over the ranks (collective)."""
        if ev.barrier_gradient is None:
            self.gradient(ev)
            ev.barrier_gradient = self.partition.sum(ev.barrier_gradient_share)
        return ev.barrier_gradient

    def hessian(self, ev: Evaluation, project: bool = False) -> sp.csc_matrix:
        """This rank's share of the Hessian at ev (PSD-projected with ``project``)."""
        if project:
            if ev.projected is None:
                with timed(self.timings, "hessian_projected"):
                    ev.projected = self._hessian_now(ev, self.projection)
            return ev.projected
        if ev.hessian is None:
            with timed(self.timings, "hessian"):
                ev.hessian = self._hessian_now(ev, ipctk.PSDProjectionMethod.NONE)
        return ev.hessian

    def _hessian_now(self, ev: Evaluation, method: ipctk.PSDProjectionMethod) -> sp.csc_matrix:
        V = self.lagging.friction_velocity(ev)
        beta_dt = self.lagging.step.beta_dt if V is not None else 1.0
        return contact_hessian(
            self.barrier, self.friction_potential, self.surface.mesh, ev, V, beta_dt, method
        )

    # -- Newton steps holding sliding contacts at stick (stick_model) ------------------------
    def _stick_model(self, ev: Evaluation) -> StickModel | None:
        T = ev.friction
        if T is None or not len(T):
            return None
        if self._stick is None or self._stick_of is not T:
            with timed(self.timings, "stick_model"):
                x, C = self.lagging.lagged_state()
                lagged = friction_arrays(
                    C,
                    self.surface.mesh,
                    x,
                    self.barrier,
                    self.stiffness,
                    self.lagging.mu_table(self.lagging.mu),
                    self.surface.body_index,
                )
                eps_v = self.friction_potential.eps_v
                self._stick = StickModel(lagged, self.surface.num_vertices, eps_v)
                self._stick_of = T
        return self._stick

    def hold_reversed(self, ev: Evaluation, dU: np.ndarray) -> int:
        """Hold at stick the sliding collisions whose slip the step dU reverses (this rank's).

        Args:
            ev: The evaluation at the Newton iterate.
            dU: (num_vertices * dim,) the Newton step at the collision vertices.

        Returns:
            The number of collisions held (this rank's share).
        """
        self.held = None
        model = self._stick_model(ev)
        if model is None:
            return 0
        V = self.lagging.friction_velocity(ev)
        with timed(self.timings, "stick_check"):
            held = model.reversed(V, dU.reshape(V.shape) / self.lagging.step.beta_dt)
        self.held = held if held.any() else None
        return int(np.count_nonzero(held))

    def held_gradient_change(self, ev: Evaluation) -> np.ndarray:
        """The held collisions' stick-model minus exact gradient, summed over the ranks."""
        g = np.zeros(self.surface.mesh.ndof)
        if self.held is not None:
            g = self._stick.gradient_change(self.lagging.friction_velocity(ev), self.held)
        return self.partition.sum(g)

    def held_hessian_change(self, ev: Evaluation) -> sp.csc_matrix | None:
        """The held collisions' stick-model minus exact Hessian (this rank's share), or None."""
        if self.held is None:
            return None
        V = self.lagging.friction_velocity(ev)
        return self._stick.hessian_change(V, self.held) / self.lagging.step.beta_dt
