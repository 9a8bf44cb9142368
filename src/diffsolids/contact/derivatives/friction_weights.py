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

Under MPI the normal collisions are this rank's share and the caller sums the result over the
ranks.
"""

import ipctk
import numpy as np
import scipy.sparse

from diffsolids.contact.derivatives.area_weights import weight_gradient_adjoint
from diffsolids.contact.derivatives.barrier_shape import _barrier, _squared_distances
from diffsolids.contact.detection.collision_arrays import (
    CollisionArrays,
    collision_arrays,
    cross_squared_norms,
)

__all__ = ["friction_weight_adjoint"]


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _gather(
    C: ipctk.NormalCollisions,
    mesh: ipctk.CollisionMesh,
    lagged_positions: np.ndarray,
) -> CollisionArrays:
    """The friction collisions lagged from the normal collisions ``C`` at ``lagged_positions``.

    ipctk's ``TangentialCollisions::build`` copies C's collisions in order, less the edge-edge
    pairs mollified at the lagged positions (cross norm below eps_x); the same rule is
    applied here to C's attributes, which read ~10x faster than the tangential collisions'.
    """
    arrays = collision_arrays(C, mesh)
    if not len(arrays.ee_eps):
        return arrays
    x = lagged_positions[arrays.ids[arrays.kind == 2]]
    return arrays.without_ee(cross_squared_norms(x) < arrays.ee_eps)


def _point_point(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """d^2, beta-weights of Gamma and the tangent basis of vertex-vertex pairs (2D and 3D)."""
    p0, p1 = x[:, 0], x[:, 1]
    r = p1 - p0
    gamma = np.tile([1.0, -1.0, 0.0, 0.0], (len(x), 1))
    d2 = _squared_distances(0, x)
    if x.shape[2] == 2:
        t = _unit(r)
        return d2, gamma, np.stack([-t[:, 1], t[:, 0]], axis=1)[:, :, None]
    cx = np.cross(np.array([1.0, 0.0, 0.0]), r)
    cy = np.cross(np.array([0.0, 1.0, 0.0]), r)
    c = np.where((_dot(cx, cx) > _dot(cy, cy))[:, None], cx, cy)
    basis = np.stack([_unit(c), _unit(np.cross(r, c))], axis=2)
    return d2, gamma, basis


def _point_edge(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p, e0, e1 = x[:, 0], x[:, 1], x[:, 2]
    e = e1 - e0
    ee = _dot(e, e)
    alpha = _dot(p - e0, e) / ee
    gamma = np.column_stack([np.ones(len(x)), alpha - 1.0, -alpha, np.zeros(len(x))])
    d2 = _squared_distances(1, x)
    if x.shape[2] == 2:
        return d2, gamma, _unit(e)[:, :, None]
    basis = np.stack([_unit(e), _unit(np.cross(e, p - e0))], axis=2)
    return d2, gamma, basis


def _edge_edge(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ea0, ea1, eb0, eb1 = x[:, 0], x[:, 1], x[:, 2], x[:, 3]
    ea, eb, w = ea1 - ea0, eb1 - eb0, ea0 - eb0
    a00, a01, a11 = _dot(ea, ea), -_dot(eb, ea), _dot(eb, eb)
    r0, r1 = -_dot(w, ea), _dot(w, eb)
    det = a00 * a11 - a01 * a01
    ba, bb = (a11 * r0 - a01 * r1) / det, (a00 * r1 - a01 * r0) / det
    gamma = np.column_stack([1.0 - ba, ba, bb - 1.0, -bb])
    n = np.cross(ea, eb)
    line = _dot(eb0 - ea0, n)
    basis = np.stack([_unit(ea), _unit(np.cross(n, ea))], axis=2)
    return line * line / _dot(n, n), gamma, basis


def _face_vertex(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p, t0, t1, t2 = x[:, 0], x[:, 1], x[:, 2], x[:, 3]
    e0, e1, q = t1 - t0, t2 - t0, p - t0
    a00, a01, a11 = _dot(e0, e0), _dot(e0, e1), _dot(e1, e1)
    r0, r1 = _dot(e0, q), _dot(e1, q)
    det = a00 * a11 - a01 * a01
    b0, b1 = (a11 * r0 - a01 * r1) / det, (a00 * r1 - a01 * r0) / det
    gamma = np.column_stack([np.ones(len(x)), b0 + b1 - 1.0, -b0, -b1])
    n = np.cross(e0, e1)
    basis = np.stack([_unit(e0), _unit(np.cross(n, e0))], axis=2)
    return _squared_distances(3, x), gamma, basis


_KINDS = (_point_point, _point_edge, _edge_edge, _face_vertex)
_NUM_VERTICES = (2, 3, 4, 4)


def _collision_terms(
    ids: np.ndarray,
    kind: np.ndarray,
    lagged_positions: np.ndarray,
    velocities: np.ndarray,
    lam: np.ndarray,
    barrier: ipctk.BarrierPotential,
    stiffness: float,
    eps_v: float,
) -> np.ndarray:
    """Per collision N_c f1(|tau_c|)/|tau_c| tau_c . (P_c^T Gamma_c lam) (module docstring)."""
    dim = lagged_positions.shape[1]
    lam = lam.reshape(-1, dim)
    out = np.zeros(len(ids))
    for k, (geometry, nv) in enumerate(zip(_KINDS, _NUM_VERTICES, strict=True)):
        sel = np.flatnonzero(kind == k)
        if not len(sel):
            continue
        vid = ids[sel, :nv]
        d2, gamma, basis = geometry(lagged_positions[vid])
        gamma = gamma[:, :nv]
        rel_v = np.einsum("kj,kjd->kd", gamma, velocities[vid])
        rel_l = np.einsum("kj,kjd->kd", gamma, lam[vid])
        tau = np.einsum("kdt,kd->kt", basis, rel_v)
        q = np.einsum("kdt,kd->kt", basis, rel_l)
        _, db = _barrier(barrier.barrier, d2, barrier.dhat**2)
        normal = -stiffness * db * 2.0 * np.sqrt(d2)  # barrier_force_magnitude.cpp, dmin = 0
        y = np.linalg.norm(tau, axis=1)
        f1_over_y = np.where(y >= eps_v, 1.0 / np.maximum(y, eps_v), (2.0 - y / eps_v) / eps_v)
        out[sel] = normal * f1_over_y * _dot(tau, q)
    return out


def _sides(ids: np.ndarray, body_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Body index of the two sides of each collision (first and last vertex)."""
    last = np.where(ids[:, 3] >= 0, ids[:, 3], np.where(ids[:, 2] >= 0, ids[:, 2], ids[:, 1]))
    return body_index[ids[:, 0]], body_index[last]


def friction_weight_adjoint(
    C: ipctk.NormalCollisions,
    mesh: ipctk.CollisionMesh,
    lagged_positions: np.ndarray,
    velocities: np.ndarray,
    lam: np.ndarray,
    barrier: ipctk.BarrierPotential,
    stiffness: float,
    eps_v: float,
    mu_table: np.ndarray,
    body_index: np.ndarray,
    merged_rows: scipy.sparse.csr_matrix,
) -> np.ndarray:
    """sum_c (F_c . lam / w_c) grad_X w_c over the friction collisions (module docstring).

    Args:
        C: Normal collisions at ``lagged_positions``, with shape derivatives (the friction
            collisions are those ipctk lags from them).
        mesh: The collision mesh.
        lagged_positions: (num_vertices, dim) positions x^{i-1} of the lagged build.
        velocities: (num_vertices, dim) velocities v.
        lam: (num_vertices * dim,) adjoint vector.
        barrier: The barrier potential of the build (dmin = 0).
        stiffness: Its stiffness kappa.
        eps_v: Friction smoothing velocity.
        mu_table: (num_bodies, num_bodies) friction coefficient of each pair of bodies (the
            blend of the build; static and kinetic equal).
        body_index: Body index of each collision vertex.
        merged_rows: Weight gradients of C's collisions with merged weights, one row each
            (``area_weights.merged_weight_collisions``).

    Returns:
        (num_vertices * dim,) the weight part of (dF/dX)^T lam.
    """
    if len(C) == 0:
        return np.zeros(lagged_positions.size)
    gathered = _gather(C, mesh, lagged_positions)
    ids, kind = gathered.ids, gathered.kind
    terms = _collision_terms(
        ids, kind, lagged_positions, velocities, lam, barrier, stiffness, eps_v
    )
    a, b = _sides(ids, body_index)
    s = -mu_table[a, b] * terms
    return weight_gradient_adjoint(mesh, gathered, s, merged_rows)
