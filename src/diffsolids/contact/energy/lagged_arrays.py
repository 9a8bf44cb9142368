"""The lagged friction collisions of a step as arrays: ids, frames, normal forces, batched.

ipctk's ``TangentialCollisions::build`` copies the normal collisions at the lagged positions
x^{i-1} in order, less the edge-edge pairs mollified there, and gives each its tangent basis,
closest point and normal force magnitude N_c = -kappa b'(d_c^2, dhat^2) 2 d_c (paper sec. 8.2).
The same quantities are computed here for all collisions at once from the normal collisions'
ids, which read ~10x faster than the tangential collisions' attributes.
"""

from dataclasses import dataclass, replace

import ipctk
import numpy as np

from diffsolids.contact.detection.collision_arrays import (
    CollisionArrays,
    collision_arrays,
    cross_squared_norms,
    read_weights,
)
from diffsolids.contact.geometry.tangent_frames import collision_frames

__all__ = [
    "FrictionArrays",
    "barrier_derivatives",
    "collision_sides",
    "friction_arrays",
    "friction_collision_arrays",
    "normal_force_magnitudes",
]


def barrier_derivatives(
    kappa_b: ipctk.Barrier, d: np.ndarray, t: float
) -> tuple[np.ndarray, np.ndarray]:
    """b(d, t) and b'(d, t) of ipctk's barrier function at squared distances d (array)."""
    if type(kappa_b) is ipctk.ClampedLogBarrier:  # barrier.cpp, vectorised
        inside = (d > 0) & (d < t)
        dd = np.where(inside, d, t)
        log = np.log(dd / t)
        b = np.where(inside, -((dd - t) ** 2) * log, 0.0)
        db = np.where(inside, (t - dd) * (2.0 * log - t / dd + 1.0), 0.0)
        return b, db
    values = [(kappa_b(float(s), t), kappa_b.first_derivative(float(s), t)) for s in d]
    return tuple(np.array(v, dtype=float).reshape(len(d)) for v in zip(*values, strict=True))


def normal_force_magnitudes(
    d2: np.ndarray, barrier: ipctk.BarrierPotential, stiffness: float
) -> np.ndarray:
    """N = -kappa b'(d^2, dhat^2) 2 d at squared distances d2 (``barrier_force_magnitude.cpp``)."""
    _, db = barrier_derivatives(barrier.barrier, d2, barrier.dhat**2)
    return -stiffness * db * 2.0 * np.sqrt(d2)


def friction_collision_arrays(
    C: ipctk.NormalCollisions,
    mesh: ipctk.CollisionMesh,
    lagged_positions: np.ndarray,
    weights: bool = False,
    arrays: CollisionArrays | None = None,
) -> CollisionArrays:
    """The friction collisions lagged from the normal collisions ``C`` at ``lagged_positions``.

    ipctk's rule: C's collisions in order, less the edge-edge pairs whose cross squared norm
    is below their mollifier threshold eps_x at the lagged positions. ``arrays``: C's
    :func:`collision_arrays` if already read (with their weights, if read).
    """
    arrays = collision_arrays(C, mesh) if arrays is None else arrays
    if weights and arrays.weight is None:
        arrays = replace(arrays, weight=read_weights(C, arrays, mesh, lagged_positions))
    if not len(arrays.ee_eps):
        return arrays
    x = lagged_positions[arrays.ids[arrays.kind == 2]]
    return arrays.without_ee(cross_squared_norms(x) < arrays.ee_eps)


@dataclass
class FrictionArrays:
    """The lagged friction collisions of a step, one row each.

    Attributes:
        ids: (n, 4) vertex ids (-1 padded).
        gamma: (n, 4) vertex weights of the relative velocity Gamma_c = sum_j gamma_cj I.
        basis: (n, dim, dim - 1) tangent bases P_c.
        coefficients: (n,) w_c mu_c N_c (mu_c N_c unweighted).
        collisions: The collisions' ids and types (:func:`friction_collision_arrays`).
    """

    ids: np.ndarray
    gamma: np.ndarray
    basis: np.ndarray
    coefficients: np.ndarray
    collisions: CollisionArrays


def friction_arrays(
    C: ipctk.NormalCollisions,
    mesh: ipctk.CollisionMesh,
    lagged_positions: np.ndarray,
    barrier: ipctk.BarrierPotential,
    stiffness: float,
    mu_table: np.ndarray,
    body_index: np.ndarray,
    weighted: bool = True,
    arrays: CollisionArrays | None = None,
) -> FrictionArrays:
    """The TangentialCollisions ipctk lags from C, as arrays.

    Args:
        C: The normal collisions at ``lagged_positions`` (this rank's share).
        mesh: The collision mesh.
        lagged_positions: (num_vertices, dim) positions x^{i-1}.
        barrier: The barrier potential (dmin = 0).
        stiffness: Its stiffness kappa.
        mu_table: (num_bodies, num_bodies) friction coefficient of each pair of bodies.
        body_index: Body index of each collision vertex.
        weighted: Whether the coefficients include the collisions' weights w_c.
        arrays: C's :func:`collision_arrays` if already read.
    """
    arrays = friction_collision_arrays(C, mesh, lagged_positions, weighted, arrays)
    d2, gamma, basis = collision_frames(arrays.ids, arrays.kind, lagged_positions)
    a, b = collision_sides(arrays.ids, body_index)
    coefficients = mu_table[a, b] * normal_force_magnitudes(d2, barrier, stiffness)
    if weighted:
        coefficients = arrays.weight * coefficients
    return FrictionArrays(arrays.ids, gamma, basis, coefficients, arrays)


def collision_sides(ids: np.ndarray, body_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Body index of the two sides of each collision (first and last vertex)."""
    last = np.where(ids[:, 3] >= 0, ids[:, 3], np.where(ids[:, 2] >= 0, ids[:, 2], ids[:, 1]))
    return body_index[ids[:, 0]], body_index[last]
