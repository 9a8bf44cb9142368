"""The friction frames of collisions at lagged positions, batched over each collision type.

A friction collision c reads its relative velocity Gamma_c v with Gamma_c = sum_j gamma_cj I
over its vertices j (closest point beta_c) and its slip tau_c = P_c^T Gamma_c v in the tangent
basis P_c (paper sec. 8.2). These are ipctk's formulas (``distance/``,
``tangent/closest_point.cpp``, ``tangent/tangent_basis.cpp``, ``tangent/relative_velocity.cpp``)
for vertex-vertex, edge-vertex, edge-edge and face-vertex collisions, in 2D and 3D, applied to
all collisions of a type at once.
"""

import numpy as np

__all__ = ["NUM_VERTICES", "collision_frames", "squared_distances"]

NUM_VERTICES = (2, 3, 4, 4)  # vertices of each collision type (vv, ev, ee, fv)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def squared_distances(kind: int, xs: np.ndarray) -> np.ndarray:
    """Squared distances of collisions of one type: point-point, point-line, line-line, point-plane.

    Rational in the coordinates, so a complex step gives exact directional derivatives.

    Args:
        kind: The collision type (0 vv, 1 ev, 2 ee, 3 fv).
        xs: (n, vertices of the type, dim) positions of the collisions' vertices.
    """
    if kind == 0:
        r = xs[:, 0] - xs[:, 1]
        return _dot(r, r)
    if kind == 1:
        p, e0, e1 = xs[:, 0], xs[:, 1], xs[:, 2]
        e = e1 - e0
        if xs.shape[2] == 2:
            num = e[:, 1] * p[:, 0] - e[:, 0] * p[:, 1] + e1[:, 0] * e0[:, 1] - e1[:, 1] * e0[:, 0]
            return num * num / _dot(e, e)
        c = np.cross(e0 - p, e1 - p)
        return _dot(c, c) / _dot(e, e)
    if kind == 2:
        n = np.cross(xs[:, 1] - xs[:, 0], xs[:, 3] - xs[:, 2])
        line = _dot(xs[:, 2] - xs[:, 0], n)
        return line * line / _dot(n, n)
    p, t0, t1, t2 = xs[:, 0], xs[:, 1], xs[:, 2], xs[:, 3]
    n = np.cross(t1 - t0, t2 - t0)
    plane = _dot(p - t0, n)
    return plane * plane / _dot(n, n)


def _point_point(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r = x[:, 1] - x[:, 0]
    gamma = np.tile([1.0, -1.0, 0.0, 0.0], (len(x), 1))
    if x.shape[2] == 2:
        t = _unit(r)
        return gamma, np.stack([-t[:, 1], t[:, 0]], axis=1)[:, :, None]
    cx = np.cross(np.array([1.0, 0.0, 0.0]), r)
    cy = np.cross(np.array([0.0, 1.0, 0.0]), r)
    c = np.where((_dot(cx, cx) > _dot(cy, cy))[:, None], cx, cy)
    return gamma, np.stack([_unit(c), _unit(np.cross(r, c))], axis=2)


def _point_edge(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p, e0, e1 = x[:, 0], x[:, 1], x[:, 2]
    e = e1 - e0
    alpha = _dot(p - e0, e) / _dot(e, e)
    gamma = np.column_stack([np.ones(len(x)), alpha - 1.0, -alpha, np.zeros(len(x))])
    if x.shape[2] == 2:
        return gamma, _unit(e)[:, :, None]
    return gamma, np.stack([_unit(e), _unit(np.cross(e, p - e0))], axis=2)


def _edge_edge(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ea0, ea1, eb0, eb1 = x[:, 0], x[:, 1], x[:, 2], x[:, 3]
    ea, eb, w = ea1 - ea0, eb1 - eb0, ea0 - eb0
    a00, a01, a11 = _dot(ea, ea), -_dot(eb, ea), _dot(eb, eb)
    r0, r1 = -_dot(w, ea), _dot(w, eb)
    det = a00 * a11 - a01 * a01
    ba, bb = (a11 * r0 - a01 * r1) / det, (a00 * r1 - a01 * r0) / det
    gamma = np.column_stack([1.0 - ba, ba, bb - 1.0, -bb])
    n = np.cross(ea, eb)
    return gamma, np.stack([_unit(ea), _unit(np.cross(n, ea))], axis=2)


def _face_vertex(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p, t0, t1, t2 = x[:, 0], x[:, 1], x[:, 2], x[:, 3]
    e0, e1, q = t1 - t0, t2 - t0, p - t0
    a00, a01, a11 = _dot(e0, e0), _dot(e0, e1), _dot(e1, e1)
    r0, r1 = _dot(e0, q), _dot(e1, q)
    det = a00 * a11 - a01 * a01
    b0, b1 = (a11 * r0 - a01 * r1) / det, (a00 * r1 - a01 * r0) / det
    gamma = np.column_stack([np.ones(len(x)), b0 + b1 - 1.0, -b0, -b1])
    n = np.cross(e0, e1)
    return gamma, np.stack([_unit(e0), _unit(np.cross(n, e0))], axis=2)


_KINDS = (_point_point, _point_edge, _edge_edge, _face_vertex)


def collision_frames(
    ids: np.ndarray, kind: np.ndarray, positions: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Squared distance, Gamma's vertex weights and tangent basis of every collision.

    Args:
        ids: (n, 4) vertex ids of the collisions (ipctk's ``vertex_ids`` order, -1 padded).
        kind: (n,) type: 0 vertex-vertex, 1 edge-vertex, 2 edge-edge, 3 face-vertex.
        positions: (num_vertices, dim) vertex positions.

    Returns:
        (n,) squared distances (:func:`squared_distances`), (n, 4) gamma (zero on padded
        vertices) and (n, dim, dim - 1) tangent bases P.
    """
    n, dim = len(ids), positions.shape[1]
    d2, gamma, basis = np.zeros(n), np.zeros((n, 4)), np.zeros((n, dim, dim - 1))
    for k, (frame, nv) in enumerate(zip(_KINDS, NUM_VERTICES, strict=True)):
        sel = np.flatnonzero(kind == k)
        if len(sel):
            xs = positions[ids[sel, :nv]]
            g, basis[sel] = frame(xs)
            gamma[sel, :nv] = g[:, :nv]
            d2[sel] = squared_distances(k, xs)
    return d2, gamma, basis
