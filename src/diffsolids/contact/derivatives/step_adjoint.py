"""Adjoint kernels of the contact term: products of the step residual's derivatives with lam.

g is the contact part of the residual of step i at an evaluation (see
:mod:`diffsolids.contact.term`): the barrier gradient and the lagged friction force
-F(X, U^{i-1}, v). Its transposed derivatives w.r.t. the earlier states (friction's lagged
normal forces and tangent bases, the BDF velocity), the rest positions (the barrier's shape
derivative with area weights and the 3D edge-edge mollifier correction, friction's rest-position
Jacobian) and the friction coefficient of each pair of bodies are applied to an adjoint vector
lam, each rank on its share of the collision set, then summed over the ranks. Obstacles have
neither shape dofs nor state: only the body rows are kept.
"""

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import ipctk
import numpy as np
import scipy.sparse as sp
from dolfinx import fem

from diffsolids.contact.derivatives.area_weights import (
    merged_weight_collisions,
    weight_gradient_rows,
)
from diffsolids.contact.derivatives.barrier_shape import barrier_shape_adjoint
from diffsolids.contact.derivatives.friction_weights import (
    LaggedSet,
    friction_coefficient_adjoint,
    friction_weight_adjoint,
)
from diffsolids.contact.detection.collision_arrays import (
    CollisionArrays,
    collision_arrays,
    read_weights,
    weights_from_gradients,
)
from diffsolids.contact.energy.contact_potential import ContactPotential
from diffsolids.contact.energy.evaluation import Evaluation
from diffsolids.contact.energy.lagging import LaggedFriction
from diffsolids.contact.step import ContactStep

if TYPE_CHECKING:
    from diffsolids.model import Model

__all__ = ["ContactAdjoint"]


class ContactAdjoint:
    """Transposed derivatives of the contact residual of a step applied to an adjoint vector.

    Args:
        model: The Model (its displacement and shape spaces).
        lagging: The step's lagged friction and its coefficients; its builder builds the
            collision sets with weight gradients (on its surface, partitioned over the ranks).
        potential: The barrier (kappa) and the friction potential.
        eps_v: Friction smoothing velocity.
    """

    def __init__(
        self, model: "Model", lagging: LaggedFriction, potential: ContactPotential, eps_v: float
    ) -> None:
        self.model = model
        self.dim = model.dim
        self.builder = lagging.builder
        self.surface = self.builder.surface
        self.partition = self.builder.partition
        self.area_weighting = self.builder.area_weighting
        self.lagging = lagging
        self.potential = potential
        self.friction_potential = potential.friction_potential
        self.eps_v = eps_v
        self.num_pairs = len(lagging.mu)
        # step index -> (surface state key, U^i, collisions) of the converged forward
        self._kept: dict[int, tuple] = {}
        self._merged: list[tuple] = []  # (collision set, its merged_rows), the last two
        self._arrays: list[tuple] = []  # (collision set, its collision_arrays), the last two

    def keep_collisions(self, step: ContactStep | None, ev: Evaluation) -> None:
        """Keep the collision set of the converged state of a forward step.

        The backward sweep evaluates the contact Hessian at the same u^i: the set is used again
        when the displacement, the collision mesh and the static mask are the same (see
        :meth:`kept_collisions`), so the sweep builds none of its own.
        """
        if step is None:
            return
        self._kept[step.index] = (self.surface.state_key(), ev.U.copy(), ev.collisions)

    def kept_collisions(
        self, step: ContactStep | None, U: np.ndarray
    ) -> ipctk.NormalCollisions | None:
        """The kept collision set of ``step`` if it was built at U on the current surface."""
        entry = None if step is None else self._kept.get(step.index)
        if entry is None:
            return None
        state, Uk, C = entry
        return C if self.surface.has_state(state) and np.array_equal(Uk, U) else None

    def surface_vector(self, lam: fem.Function | np.ndarray) -> np.ndarray:
        """The collision-dof vector of a local V array or Function (gathered, flat)."""
        values = lam.x.array if isinstance(lam, fem.Function) else np.asarray(lam)
        return self.surface.gather(values).ravel()

    def local(self, g: np.ndarray) -> np.ndarray:
        """A collision-dof vector as a local V array (owned entries)."""
        return self.surface.to_local(g, len(self.model.fields.u.x.array))

    def friction_jacobian(
        self,
        ev: Evaluation,
        T: ipctk.TangentialCollisions,
        wrt: ipctk.FrictionPotential.DiffWRT,
    ) -> sp.csc_matrix:
        """The friction force's Jacobian w.r.t. ``wrt`` at ev (ipctk; this rank's collisions)."""
        V = np.asfortranarray(self.lagging.velocity(ev.U))
        return sp.csc_matrix(
            self.friction_potential.force_jacobian(
                T,
                self.surface.mesh,
                np.asfortranarray(self.surface.rest_positions),
                np.asfortranarray(self.lagging.step.lagged),
                V,
                self.potential.barrier,
                wrt,
            )
        )

    def lagged_jacobian(self, ev: Evaluation) -> sp.csc_matrix:
        """dF/dU^{i-1} at ev (kept with ev: the history and shape kernels both need it)."""
        J = ev.friction_lagged_jacobian
        if J is None:
            wrt = ipctk.FrictionPotential.DiffWRT.LAGGED_DISPLACEMENTS
            J = self.friction_jacobian(ev, ev.friction, wrt)
            ev.friction_lagged_jacobian = J
        return J

    def history(self, ev: Evaluation, lam: fem.Function | np.ndarray) -> dict[int, np.ndarray]:
        """(d g / d u^{i-j})^T lam for j = 1..m_i (owned entries of local V arrays).

        g is the contact part of the step residual: friction depends on u^{i-1} through the
        lagged normal forces and tangent bases and on u^{i-1}..u^{i-m} through the velocity.
        """
        T = ev.friction
        step = self.lagging.step
        lags = range(1, len(step.alpha) + 1)
        if T is None:
            n = len(self.model.fields.u.x.array)
            return {j: np.zeros(n) for j in lags}
        lam_c = self.surface_vector(lam)
        DW = ipctk.FrictionPotential.DiffWRT
        # g_f = -F(X, U^{i-1}, v):  dg/dU^{i-j} = -dF/dv dv/dU^{i-j}  (- dF/dU_lag, j = 1),
        # -dF/dv = Hess_v D: the friction Hessian of the step's exact Hessian at ev when the
        # adjoint solve computed it (symmetric), else ipctk's velocity Jacobian
        Hf = ev.friction_hessian
        if Hf is not None:
            vbar = Hf @ lam_c
        else:
            vbar = -(self.friction_jacobian(ev, T, DW.VELOCITIES).T @ lam_c)
        Jl = self.lagged_jacobian(ev)
        # this rank's collisions: summed over the ranks in one allreduce
        vbar, jl = self.partition.sum(np.stack([vbar, Jl.T @ lam_c]))
        # through v = (U + sum_j alpha_j U^{i-j}) / (beta dt): the integrator's transpose
        i = step.index
        ubar = {i - j: np.zeros_like(vbar) for j in (0, *lags)}
        step.time_step.add_velocity_transpose(vbar, ubar)
        ubar[i - 1] -= jl
        return {j: self.local(ubar[i - j]) for j in lags}

    def shape(self, ev: Evaluation, lam: fem.Function | np.ndarray) -> np.ndarray:
        """(d g / d X)^T lam over the dofs of the P1 rest-coordinate space (owned entries).

        Includes the barrier shape derivative with area-weight terms and the 3D edge-edge
        mollifier correction, and the friction force's rest-position Jacobian.
        """
        lam_c = self.surface_vector(lam)
        mesh = self.surface.mesh
        C = self.builder.build(ev.x, shape_derivatives=True)
        x = np.asfortranarray(ev.x)
        self.potential.hessian(ev)  # exact; keeps its barrier part
        Hb_lam = ev.barrier_hessian @ lam_c
        g = barrier_shape_adjoint(
            C,
            mesh,
            x,
            self.potential.barrier,
            self.potential.stiffness,
            lam_c,
            Hb_lam,
            self.merged_rows(C),
            self.collision_arrays(C),
        )
        if self.lagging.active:
            g = g - self.friction_rest(ev, lam_c)
        g = self.partition.sum(g)  # this rank's collisions: summed over the ranks
        Sspace = self.model.shape_space
        smap = self.surface.shape_map(Sspace)
        bs = Sspace.dofmap.index_map_bs
        imap = Sspace.dofmap.index_map
        out = np.zeros((imap.size_local + imap.num_ghosts) * bs)
        d = self.dim
        gv = smap.pull_back(g.reshape(-1, d))  # edge/face nodes move with their vertices
        out.reshape(-1, bs)[smap.blocks, :d] += gv[smap.cv]
        return out

    def friction_rest(self, ev: Evaluation, lam_c: np.ndarray) -> np.ndarray:
        """(dF/dX)^T lam: the friction force's rest-position Jacobian at fixed U^{i-1}, transposed.

        This rank's collisions only (the caller sums over the ranks).

        dF/dX = dF/dU^{i-1} + sum_c (F_c / w_c) grad w_c^T (area weights w_c; the force of
        collision c is proportional to w_c). ipctk's REST_POSITIONS Jacobian adds these outer
        products to one growing sparse matrix, a cost quadratic in the number of collisions
        (1 s per step for 2k collisions); applied to lam they are scalars times weight
        gradients, batched over all collisions by
        :func:`~diffsolids.contact.derivatives.friction_weights.friction_weight_adjoint`.
        """
        out = self.lagged_jacobian(ev).T @ lam_c
        if not self.area_weighting:
            return out
        x, C = self.lagging.lagged_state(shape_derivatives=True)
        lagged = self._lagged_set(ev, C, x, self.collision_arrays(C))
        mu_table = self.lagging.mu_table(self.lagging.mu)
        return out + friction_weight_adjoint(lagged, lam_c, mu_table, self.merged_rows(C))

    def _lagged_set(
        self, ev: Evaluation, C: ipctk.NormalCollisions, x: np.ndarray, arrays: CollisionArrays
    ) -> LaggedSet:
        """The set C built at x^{i-1} = x and what the friction terms read at ev."""
        return LaggedSet(
            C,
            self.surface.mesh,
            x,
            self.lagging.velocity(ev.U),
            self.potential.barrier,
            self.potential.stiffness,
            self.eps_v,
            self.surface.body_index,
            arrays,
        )

    def merged_rows(self, C: ipctk.NormalCollisions) -> sp.csr_matrix:
        """Weight gradients of C's collisions with merged weights, read once per set.

        The set at x^i serves the barrier of step i and the lagged friction of step i + 1
        (the builder keeps it for both); the two last read sets are kept.
        """
        return self._read_once(self._merged, C, self._weight_rows)

    def collision_arrays(self, C: ipctk.NormalCollisions) -> CollisionArrays:
        """C's ids and types, read once per set (kept for the last two, as :meth:`merged_rows`)."""
        return self._read_once(self._arrays, C, lambda C: collision_arrays(C, self.surface.mesh))

    def weighted_arrays(self, C: ipctk.NormalCollisions, x: np.ndarray) -> CollisionArrays:
        """C's :meth:`collision_arrays` with its collisions' weights, read once per set.

        x: the positions C was built at.
        """
        arrays = self.collision_arrays(C)
        if arrays.weight is None:
            mesh = self.surface.mesh
            # the merged weights from their gradients when the shape kernel read them, but
            # not where the flat regions' correction changed weights alone (convergent)
            rows = self._held(self._merged, C)
            corrected = self.builder.formulation == "convergent" and bool(self.surface.flat)
            usable = rows is not None and not corrected
            merged = weights_from_gradients(C, mesh, rows) if usable else None
            arrays.weight = read_weights(C, arrays, mesh, x, merged)
        return arrays

    def _weight_rows(self, C: ipctk.NormalCollisions) -> sp.csr_matrix:
        return weight_gradient_rows(merged_weight_collisions(C, self.dim), self.surface.mesh.ndof)

    @staticmethod
    def _held(kept: list[tuple], C: ipctk.NormalCollisions) -> Any:
        """What ``kept`` holds for C (one of its last two sets), else None."""
        return next((value for collisions, value in kept if collisions is C), None)

    @classmethod
    def _read_once(cls, kept: list[tuple], C: ipctk.NormalCollisions, read: Callable) -> Any:
        """``read(C)``, or what it gave for C if C is one of the last two sets in ``kept``."""
        value = cls._held(kept, C)
        if value is not None:
            return value
        value = read(C)
        kept[:] = [(C, value), *kept[:1]]
        return value

    def friction(self, ev: Evaluation, lam: fem.Function | np.ndarray) -> np.ndarray:
        """(d g / d mu_p)^T lam for each pair p of bodies (global, the same on all ranks).

        Each rank's collisions give their part, summed over the ranks; one batched pass over
        the collisions lagged from x^{i-1} (``friction_coefficient_adjoint``), also where the
        current coefficients are 0.
        """
        # the set with weight gradients at x^{i-1} if the shape kernel built it (its ids are
        # read already), else the forward's: the same collisions
        x = self.surface.rest_positions + self.lagging.step.lagged
        C = self.builder.kept_shape_set(x)
        if C is None:
            x, C = self.lagging.lagged_state()
        lagged = self._lagged_set(ev, C, x, self.weighted_arrays(C, x))
        out = friction_coefficient_adjoint(
            lagged, self.surface_vector(lam), self.lagging.pair_table, self.num_pairs
        )
        return self.partition.sum(out)
