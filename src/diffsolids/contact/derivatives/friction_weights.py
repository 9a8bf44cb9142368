"""Area-weight part of the friction force's rest-position Jacobian, batched over collisions.

The lagged friction force of collision c (ipctk ``TangentialPotential::force``) is

    F_c = -w_c N_c mu_c f1(|tau_c|)/|tau_c| Gamma_c^T P_c tau_c,    tau_c = P_c^T Gamma_c v,

with area weight w_c, normal force magnitude N_c = -kappa b'(d_c^2, dhat^2) 2 d_c at the lagged
positions x^{i-1}, tangent basis P_c, relative-velocity Jacobian Gamma_c (closest point beta_c)
and the smoothed friction f1(y)/y (paper sec. 8.2). With area weighting F_c is proportional to
w_c, so d F / d X = d F / d U^{i-1} + sum_c (F_c / w_c) grad w_c^T and its transpose applied to
lam has the weight part

    sum_c s_c grad w_c,   s_c = F_c . lam / w_c
                              = -N_c mu_c f1(|tau_c|)/|tau_c| tau_c . (P_c^T Gamma_c lam).

ipctk's REST_POSITIONS Jacobian adds these outer products to one growing sparse matrix (a cost
quadratic in the number of collisions). Here the vertex ids are read once per collision
(from the normal collisions the friction collisions are lagged from) and s_c is computed for
all collisions at once, with ipctk's formulas for the distances, closest points, tangent bases
and relative velocities of each collision type (``distance/``, ``tangent/closest_point.cpp``,
``tangent/tangent_basis.cpp``, ``tangent/relative_velocity.cpp``). The weight gradients of
face-vertex and edge-edge collisions (and 2D edge-vertex ones) are sums of vertex and edge
area gradients, applied in bulk (:mod:`~diffsolids.contact.derivatives.area_weights`); those
of vertex-vertex and 3D edge-vertex collisions are read per collision.

The friction force is linear in each collision's coefficient, so the same per-collision terms
with mu_c = 1 and the weights w_c give its derivative w.r.t. the coefficient of each pair of
bodies (:func:`friction_coefficient_adjoint`).

Under MPI the normal collisions are this rank's share and the caller sums the result over the
ranks.
"""

from dataclasses import dataclass

import ipctk
import numpy as np
import scipy.sparse

from diffsolids.contact.derivatives.area_weights import weight_gradient_adjoint
from diffsolids.contact.detection.collision_arrays import CollisionArrays
from diffsolids.contact.energy.lagged_arrays import (
    FrictionArrays,
    collision_sides,
    friction_arrays,
)

__all__ = ["LaggedSet", "friction_coefficient_adjoint", "friction_weight_adjoint"]


def _collision_terms(
    lagged: FrictionArrays, velocities: np.ndarray, lam: np.ndarray, eps_v: float
) -> np.ndarray:
    """Per collision mu_c N_c f1(|tau_c|)/|tau_c| tau_c . (P_c^T Gamma_c lam) (docstring)."""
    dim = velocities.shape[1]

    def slips(w: np.ndarray) -> np.ndarray:  # P_c^T Gamma_c w
        w = np.append(w.reshape(-1, dim), np.zeros((1, dim)), axis=0)  # padding id -1 reads 0
        return np.einsum("kdt,kj,kjd->kt", lagged.basis, lagged.gamma, w[lagged.ids])

    tau, q = slips(velocities), slips(lam)
    y = np.linalg.norm(tau, axis=1)
    f1_over_y = np.where(y >= eps_v, 1.0 / np.maximum(y, eps_v), (2.0 - y / eps_v) / eps_v)
    return lagged.coefficients * f1_over_y * np.einsum("kt,kt->k", tau, q)


@dataclass
class LaggedSet:
    """The normal collisions a step's friction is lagged from, with what its terms read.

    Attributes:
        collisions: Normal collisions at ``positions`` (this rank's share; the friction
            collisions are those ipctk lags from them).
        mesh: The collision mesh.
        positions: (num_vertices, dim) positions x^{i-1} of the build.
        velocities: (num_vertices, dim) velocities v of the step.
        barrier: The barrier potential of the build (dmin = 0).
        stiffness: Its stiffness kappa.
        eps_v: Friction smoothing velocity.
        body_index: Body index of each collision vertex.
        arrays: The collisions' ``collision_arrays`` if already read (with their weights if
            read).
    """

    collisions: ipctk.NormalCollisions
    mesh: ipctk.CollisionMesh
    positions: np.ndarray
    velocities: np.ndarray
    barrier: ipctk.BarrierPotential
    stiffness: float
    eps_v: float
    body_index: np.ndarray
    arrays: CollisionArrays | None = None

    def terms(
        self, lam: np.ndarray, mu_table: np.ndarray, weighted: bool
    ) -> tuple[FrictionArrays, np.ndarray]:
        """The friction collisions with ``mu_table``'s coefficients and their terms with lam.

        The terms are mu_c N_c f1(|tau_c|)/|tau_c| tau_c . (P_c^T Gamma_c lam), times w_c
        when ``weighted``.
        """
        lagged = friction_arrays(
            self.collisions,
            self.mesh,
            self.positions,
            self.barrier,
            self.stiffness,
            mu_table,
            self.body_index,
            weighted,
            self.arrays,
        )
        return lagged, _collision_terms(lagged, self.velocities, lam, self.eps_v)


def friction_weight_adjoint(
    lagged: LaggedSet,
    lam: np.ndarray,
    mu_table: np.ndarray,
    merged_rows: scipy.sparse.csr_matrix,
) -> np.ndarray:
    """sum_c (F_c . lam / w_c) grad_X w_c over the friction collisions (module docstring).

    Args:
        lagged: The lagged set (its collisions with shape derivatives).
        lam: (num_vertices * dim,) adjoint vector.
        mu_table: (num_bodies, num_bodies) friction coefficient of each pair of bodies (the
            blend of the build; static and kinetic equal).
        merged_rows: Weight gradients of the collisions with merged weights, one row each
            (``area_weights.merged_weight_collisions``).

    Returns:
        (num_vertices * dim,) the weight part of (dF/dX)^T lam.
    """
    if len(lagged.collisions) == 0:
        return np.zeros(lagged.positions.size)
    friction, terms = lagged.terms(lam, mu_table, weighted=False)
    return weight_gradient_adjoint(lagged.mesh, friction.collisions, -terms, merged_rows)


def friction_coefficient_adjoint(
    lagged: LaggedSet, lam: np.ndarray, pair_table: np.ndarray, num_pairs: int
) -> np.ndarray:
    """(d g / d mu_p)^T lam for each pair p of bodies, g = -F the friction part of the residual.

    F_c is linear in mu_c: -dF_c/dmu_c . lam = w_c N_c f1(|tau_c|)/|tau_c| tau_c . (P_c^T
    Gamma_c lam), summed over the collisions of each pair (module docstring).

    Args:
        lagged: The lagged set.
        lam: (num_vertices * dim,) adjoint vector.
        pair_table: (num_bodies, num_bodies) index of each pair of bodies among the pairs.
        num_pairs: Number of pairs.

    Returns:
        (num_pairs,) this rank's collisions' part.
    """
    if len(lagged.collisions) == 0:
        return np.zeros(num_pairs)
    friction, terms = lagged.terms(lam, np.ones(pair_table.shape), weighted=True)
    a, b = collision_sides(friction.ids, lagged.body_index)
    return np.bincount(pair_table[a, b], weights=terms, minlength=num_pairs)
