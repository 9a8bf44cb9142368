"""The contact potential at one surface displacement: collision set and ipctk derivatives.

An :class:`Evaluation` caches, for one displacement U of the collision surface, the collision
set at x = X + U and whatever of the potential has been asked for (value, gradient, exact or
PSD-projected Hessian, the Newton matrix pattern). The potential of step i is
B(x) + beta dt D(v) (see :mod:`diffsolids.contact.term`): the barrier of the collision set plus
the lagged friction dissipation at the velocity v; its gradient w.r.t. u is grad B - F(v) and
its Hessian Hess B + Hess_v D / (beta dt).

Under MPI the collision set of an evaluation is this rank's share
(:class:`~diffsolids.contact.partition.CollisionPartition`): the functions here return this
rank's part; the contact term keeps the energy and gradient summed over the ranks (the same on
all) and the Hessians as this rank's share, whose rows it adds into the global matrix.
"""

from dataclasses import dataclass

import ipctk
import numpy as np
import scipy.sparse as sp

__all__ = ["Evaluation", "contact_energy", "contact_gradient", "contact_hessian"]


@dataclass
class Evaluation:
    """Collision set and derivatives at one surface displacement (cached).

    ``collisions``, ``hessian``, ``projected`` and the parts kept for the adjoint are this
    rank's share; ``energy``, ``gradient`` and ``barrier_gradient`` are summed over the ranks.

    Attributes:
        friction: The step's tangential collisions (lagged from u^{i-1}), None without
            friction.
        barrier_gradient_share: This rank's barrier part of the gradient.
        barrier_gradient: The barrier part of the gradient, summed over the ranks.
        barrier_hessian: This rank's exact barrier Hessian (the barrier shape derivative's
            x-part).
        friction_hessian: This rank's exact Hess_v D (minus the friction force's velocity
            Jacobian).
        friction_lagged_jacobian: dF/dU^{i-1}, this rank's collisions (the adjoint's history
            and shape kernels both need it).
    """

    U: np.ndarray
    x: np.ndarray
    collisions: ipctk.NormalCollisions
    token: int
    energy: float | None = None
    gradient: np.ndarray | None = None
    hessian: sp.csc_matrix | None = None
    projected: sp.csc_matrix | None = None
    blocks: np.ndarray | None = None
    friction: ipctk.TangentialCollisions | None = None
    barrier_gradient_share: np.ndarray | None = None
    barrier_gradient: np.ndarray | None = None
    barrier_hessian: sp.csc_matrix | None = None
    friction_hessian: sp.csc_matrix | None = None
    friction_lagged_jacobian: sp.csc_matrix | None = None


def contact_energy(
    barrier: ipctk.BarrierPotential,
    friction: ipctk.FrictionPotential,
    mesh: ipctk.CollisionMesh,
    ev: Evaluation,
    V: np.ndarray | None,
    beta_dt: float,
) -> float:
    """B(x) + beta dt D(v) at ev (this rank's value; the friction part if ``V`` is given).

    Args:
        barrier: The barrier potential.
        friction: The friction potential.
        mesh: The collision mesh.
        ev: The evaluation (its ``friction``: the step's tangential collisions).
        V: (num_vertices, dim) velocities, or None without friction.
        beta_dt: beta dt of the step.
    """
    e = barrier(ev.collisions, mesh, np.asfortranarray(ev.x))
    T = ev.friction
    if T is not None:
        e += beta_dt * friction(T, mesh, np.asfortranarray(V))
    return e


def contact_gradient(
    barrier: ipctk.BarrierPotential,
    friction: ipctk.FrictionPotential,
    mesh: ipctk.CollisionMesh,
    ev: Evaluation,
    V: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """(gradient, its barrier part) of the contact potential in collision dofs at ev."""
    gb = barrier.gradient(ev.collisions, mesh, np.asfortranarray(ev.x))
    T = ev.friction
    if T is None:
        return gb, gb
    return gb + friction.gradient(T, mesh, np.asfortranarray(V)), gb


def contact_hessian(
    barrier: ipctk.BarrierPotential,
    friction: ipctk.FrictionPotential,
    mesh: ipctk.CollisionMesh,
    ev: Evaluation,
    V: np.ndarray | None,
    beta_dt: float,
    method: ipctk.PSDProjectionMethod,
) -> sp.csc_matrix:
    """Hessian of the contact potential at ev (exact for NONE, else PSD-projected per pair).

    The exact parts (this rank's share) are kept: the barrier's in
    ``ev.barrier_hessian`` (the barrier shape derivative's x-part), the friction's
    Hess_v D in ``ev.friction_hessian`` (minus the friction force's velocity Jacobian
    that the adjoint's push into the earlier steps needs).
    """
    H = barrier.hessian(ev.collisions, mesh, np.asfortranarray(ev.x), method)
    if method == ipctk.PSDProjectionMethod.NONE:
        ev.barrier_hessian = H
    T = ev.friction
    if T is not None:
        Hf = friction.hessian(T, mesh, np.asfortranarray(V), method)
        if method == ipctk.PSDProjectionMethod.NONE:
            ev.friction_hessian = Hf
        if Hf.nnz:  # (in 2D the Hessian is zero where the sliding speed is above eps_v)
            H = H + Hf / beta_dt
    return H if isinstance(H, sp.csc_matrix) else sp.csc_matrix(H)
