"""Shape derivative of the barrier gradient, with a correction for ipctk 1.6.0/1.6.1 in 3D.

``BarrierPotential.shape_derivative`` returns S[i, j] = d(grad_x B)_i / dX_j at fixed
displacement (X the rest positions). For mollified edge-edge pairs (near-parallel edges, 3D)
ipctk 1.6.0 and 1.6.1 assemble, per pair with barrier value f = w kappa b(d), barrier gradient
gf = grad_x f, mollifier m(s, eps(X)) of the cross norm s(x) = |ea x eb|^2 and
gxm = (dm/deps) grad_X eps:

    installed:  f (dm'/deps geps gs^T + m' Hs) + gxm gf^T + gf gm^T + gm gf^T + m Hf,

while differentiating grad_x(m f) = f gm + m gf with respect to X (x = X + u, eps = eps(X))
gives

    exact:      f (m' Hs + m'' gs gs^T + dm'/deps gs geps^T) + gf gxm^T + gf gm^T + gm gf^T + m Hf.

The difference (added to the matrix of :func:`barrier_shape_derivative`) is
f (m'' gs gs^T + dm'/deps (gs geps^T - geps gs^T)) + gf gxm^T - gxm gf^T, evaluated for all
mollified pairs at once.

The adjoint needs only S^T lam (:func:`barrier_shape_adjoint`), formed without ipctk's
shape derivative: the exact barrier Hessian times lam, plus per collision its barrier
gradient's product with lam times its weight gradient, plus the exact terms above that hold
grad_X eps (f dm'/deps gs geps^T + gf gxm^T, transposed). The edge ids and distance types
are read once, everything else (distances of each type and their directional derivatives,
cross norms, thresholds, the barrier, the mollifier) is batched numpy, written with the
formulas of ipctk's ``edge_edge_mollifier.cpp``, ``line_line.cpp``, ``point_line.cpp`` and
``barrier.cpp``; weight gradients as in :mod:`~diffsolids.contact.derivatives.area_weights`.
"""

from collections.abc import Iterator
from dataclasses import dataclass

import ipctk
import numpy as np
import scipy.sparse as sp

from diffsolids.contact.derivatives.area_weights import (
    weight_gradient_adjoint,
    weight_gradient_rows,
)
from diffsolids.contact.detection.collision_arrays import (
    CollisionArrays,
    collision_arrays,
    edge_edge_weights,
    merged_edge_edge,
)
from diffsolids.contact.energy.lagged_arrays import barrier_derivatives
from diffsolids.contact.geometry.tangent_frames import squared_distances

__all__ = ["barrier_shape_adjoint", "barrier_shape_derivative"]

# ipctk's EdgeEdgeDistanceType: point-point (EA0_EB0 .. EA1_EB1), point-line (EA_EB0 .. EA1_EB)
# and line-line (EA_EB); (point, other point) and (point, line end, line end) vertex slots
_POINT_POINT = {0: (0, 2), 1: (0, 3), 2: (1, 2), 3: (1, 3)}
_POINT_LINE = {4: (2, 0, 1), 5: (3, 0, 1), 6: (0, 2, 3), 7: (1, 2, 3)}
_LINE_LINE = 8
# edge_edge_mollifier_threshold: eps_x = 1e-3 |ea|^2 |eb|^2 at rest
_EPS_SCALE = 1e-3


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


@dataclass
class _MollifiedPairs:
    """The mollified edge-edge collisions of a collision set, as arrays (one row per pair)."""

    index: np.ndarray  # position in collisions.ee_collisions
    edge_ids: np.ndarray  # (n, 2): ea, eb
    vertex_ids: np.ndarray  # (n, 4): ea0, ea1, eb0, eb1
    rest: np.ndarray  # (n, 4, 3)
    positions: np.ndarray  # (n, 4, 3)
    eps: np.ndarray  # mollifier threshold at rest
    s: np.ndarray  # cross squared norm at the positions

    def __iter__(self) -> Iterator[int]:
        return iter(self.index)

    def __len__(self) -> int:
        return len(self.index)


def _mollified_pairs(
    collisions: ipctk.NormalCollisions,
    mesh: ipctk.CollisionMesh,
    rest: np.ndarray,
    x: np.ndarray,
    arrays: CollisionArrays | None = None,
) -> _MollifiedPairs:
    """Edge-edge collisions whose cross squared norm is below the mollifier threshold.

    Args:
        collisions: The collision set.
        mesh: Its collision mesh.
        rest: (num_vertices, 3) rest positions.
        x: (num_vertices, 3) positions.
        arrays: The set's :func:`collision_arrays` if already read.
    """
    c = collision_arrays(collisions, mesh) if arrays is None else arrays
    pairs = c.ee_edges
    ids = c.ids[c.kind == 2]
    xr, xp = rest[ids], x[ids]
    ea, eb = xr[:, 0] - xr[:, 1], xr[:, 2] - xr[:, 3]
    eps = _EPS_SCALE * _dot(ea, ea) * _dot(eb, eb)
    n = np.cross(xp[:, 1] - xp[:, 0], xp[:, 3] - xp[:, 2])
    s = _dot(n, n)
    keep = np.flatnonzero(s < eps)
    return _MollifiedPairs(keep, pairs[keep], ids[keep], xr[keep], xp[keep], eps[keep], s[keep])


def _point_line(
    p: np.ndarray, e0: np.ndarray, e1: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Squared distance of points to lines (3D) and its gradients w.r.t. p, e0, e1."""
    a, b, e = e0 - p, e1 - p, e1 - e0
    c = np.cross(a, b)
    num, den = _dot(c, c), _dot(e, e)
    d = num / den
    g0 = 2.0 * np.cross(b, c)  # d|a x b|^2 / da
    g1 = 2.0 * np.cross(c, a)  # d|a x b|^2 / db
    ge0 = (g0 + 2.0 * d[:, None] * e) / den[:, None]
    ge1 = (g1 - 2.0 * d[:, None] * e) / den[:, None]
    gp = -(g0 + g1) / den[:, None]
    return d, gp, ge0, ge1


def _line_line(xp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared distance between the lines of (ea0, ea1) and (eb0, eb1) and its gradient."""
    u, v, w = xp[:, 1] - xp[:, 0], xp[:, 3] - xp[:, 2], xp[:, 2] - xp[:, 0]
    n = np.cross(u, v)
    L, D = _dot(w, n), _dot(n, n)
    d = L * L / D
    two_l = (2.0 * L / D)[:, None]
    dd = (d / D)[:, None]
    gu = two_l * np.cross(v, w) - 2.0 * dd * np.cross(v, n)
    gv = two_l * np.cross(w, u) - 2.0 * dd * np.cross(n, u)
    gw = two_l * n
    return d, np.stack([-gu - gw, gu, gw - gv, gv], axis=1)


def _edge_edge_distance(xp: np.ndarray, dtype: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared edge-edge distance of the given ipctk distance type, and its (n, 4, 3) gradient."""
    d = np.empty(len(xp))
    grad = np.zeros_like(xp)
    for t, (i, j) in _POINT_POINT.items():
        k = np.flatnonzero(dtype == t)
        r = xp[k, i] - xp[k, j]
        d[k] = _dot(r, r)
        grad[k, i], grad[k, j] = 2.0 * r, -2.0 * r
    for t, (i, j, m) in _POINT_LINE.items():
        k = np.flatnonzero(dtype == t)
        d[k], grad[k, i], grad[k, j], grad[k, m] = _point_line(xp[k, i], xp[k, j], xp[k, m])
    k = np.flatnonzero(dtype == _LINE_LINE)
    d[k], grad[k] = _line_line(xp[k])
    known = np.isin(dtype, [*_POINT_POINT, *_POINT_LINE, _LINE_LINE])
    if not known.all():
        raise ValueError(f"edge-edge distance types {np.unique(dtype[~known])} are not handled")
    return d, grad


@dataclass
class _Terms:
    """Per mollified pair: its dofs and the vectors and scalars of the correction."""

    dofs: np.ndarray  # (n, 12)
    f: np.ndarray
    gf: np.ndarray  # (n, 12)
    gs: np.ndarray
    geps: np.ndarray
    gxm: np.ndarray
    m2: np.ndarray
    dm1: np.ndarray


def _ee_terms(
    collisions: ipctk.NormalCollisions,
    mesh: ipctk.CollisionMesh,
    x: np.ndarray,
    barrier: ipctk.BarrierPotential,
    stiffness: float,
    arrays: CollisionArrays,
) -> _Terms | None:
    """The correction's ingredients for every mollified pair (None: no mollified pair).

    ``arrays``: the set's :func:`collision_arrays`.
    """
    pairs = _mollified_pairs(collisions, mesh, mesh.rest_positions, x, arrays)
    if not len(pairs):
        return None
    dtype = arrays.ee_dtype[pairs.index]
    # the pair's own weight: area weights, merged duplicates and the convergent formulation's
    # negative edge-edge terms
    w = edge_edge_weights(collisions, arrays, mesh, x)[pairs.index]
    xp, xr, eps, s = pairs.positions, pairs.rest, pairs.eps, pairs.s
    d, grad_d = _edge_edge_distance(xp, dtype)
    b, db = barrier_derivatives(barrier.barrier, d, barrier.dhat**2)
    f = w * stiffness * b
    gf = (w * stiffness * db)[:, None] * grad_d.reshape(-1, 12)
    # cross squared norm s = |u x v|^2 (u = ea1 - ea0, v = eb1 - eb0) and its gradient
    u, v = xp[:, 1] - xp[:, 0], xp[:, 3] - xp[:, 2]
    nrm = np.cross(u, v)
    su, sv = 2.0 * np.cross(v, nrm), 2.0 * np.cross(nrm, u)
    gs = np.stack([-su, su, -sv, sv], axis=1).reshape(-1, 12)
    # threshold eps = 1e-3 |ra|^2 |rb|^2 at rest and its gradient
    ra, rb = xr[:, 0] - xr[:, 1], xr[:, 2] - xr[:, 3]
    ga = 2.0 * _EPS_SCALE * _dot(rb, rb)[:, None] * ra
    gb = 2.0 * _EPS_SCALE * _dot(ra, ra)[:, None] * rb
    geps = np.stack([ga, -ga, gb, -gb], axis=1).reshape(-1, 12)
    # mollifier derivatives (edge_edge_mollifier.cpp), s < eps for every pair here
    m2 = -2.0 / (eps * eps)
    dm1 = 2.0 * (-eps + 2.0 * s) / (eps * eps * eps)
    dm_eps = 2.0 * s * (-eps + s) / (eps * eps * eps)
    gxm = dm_eps[:, None] * geps
    dofs = (pairs.vertex_ids[:, :, None] * 3 + np.arange(3)).reshape(-1, 12)
    return _Terms(dofs, f, gf, gs, geps, gxm, m2, dm1)


def _ee_correction(
    collisions: ipctk.NormalCollisions,
    mesh: ipctk.CollisionMesh,
    x: np.ndarray,
    barrier: ipctk.BarrierPotential,
    stiffness: float,
    arrays: CollisionArrays | None = None,
) -> sp.csc_matrix:
    """The sum over mollified edge-edge pairs of the difference in the module docstring."""
    n = x.size
    arrays = collision_arrays(collisions, mesh) if arrays is None else arrays
    t = _ee_terms(collisions, mesh, x, barrier, stiffness, arrays)
    if t is None:
        return sp.csc_matrix((n, n))

    def outer(a: np.ndarray, c: np.ndarray) -> np.ndarray:
        return np.einsum("ki,kj->kij", a, c)

    delta = (t.f * t.m2)[:, None, None] * outer(t.gs, t.gs)
    delta += (t.f * t.dm1)[:, None, None] * (outer(t.gs, t.geps) - outer(t.geps, t.gs))
    delta += outer(t.gf, t.gxm) - outer(t.gxm, t.gf)
    rows = np.repeat(t.dofs, 12, axis=1).ravel()
    cols = np.tile(t.dofs, (1, 12)).ravel()
    return sp.csc_matrix((delta.ravel(), (rows, cols)), shape=(n, n))


def barrier_shape_derivative(
    collisions: ipctk.NormalCollisions,
    mesh: ipctk.CollisionMesh,
    x: np.ndarray,
    barrier: ipctk.BarrierPotential,
    stiffness: float,
) -> sp.csc_matrix:
    """S[i, j] = d(grad_x B)_i / d(rest position)_j at fixed displacement (area weights included).

    Args:
        collisions: Built with ``enable_shape_derivatives = True`` at positions ``x``.
        mesh: The collision mesh (area Jacobians initialised).
        x: (num_vertices, dim) current positions.
        barrier: The barrier potential.
        stiffness: Its stiffness kappa.
    """
    S = barrier.shape_derivative(collisions, mesh, x)
    if x.shape[1] == 3 and len(collisions.ee_collisions):
        S = S + _ee_correction(collisions, mesh, x, barrier, stiffness)
    return sp.csc_matrix(S)


def _directional_barrier(
    c: CollisionArrays,
    rest: np.ndarray,
    x: np.ndarray,
    lam: np.ndarray,
    barrier: ipctk.BarrierPotential,
    stiffness: float,
) -> np.ndarray:
    """Per collision kappa grad_x(m b(d^2)) . lam, without the collision's weight.

    d^2 of each type differentiated along lam by a complex step (vv, ev, fv) or with its
    gradient (ee, every ipctk distance type, times the mollifier m(s) of the cross squared norm
    s where s is below its threshold; ``edge_edge_mollifier.cpp``).
    """
    dim = x.shape[1]
    lam = lam.reshape(-1, dim)
    out = np.zeros(len(c.ids))
    t = barrier.dhat**2
    h = 1e-20 / max(float(np.abs(lam).max()), 1e-300)
    for kind, nv in ((0, 2), (1, 3), (3, 4)):
        sel = np.flatnonzero(c.kind == kind)
        if len(sel):
            xs, ls = x[c.ids[sel, :nv]], lam[c.ids[sel, :nv]]
            dd2 = squared_distances(kind, xs + 1j * h * ls).imag / h
            _, db = barrier_derivatives(barrier.barrier, squared_distances(kind, xs), t)
            out[sel] = stiffness * db * dd2
    sel = np.flatnonzero(c.kind == 2)
    if len(sel):
        vid = c.ids[sel]
        xp, lp, xr = x[vid], lam[vid], rest[vid]
        d2, grad = _edge_edge_distance(xp, c.ee_dtype)
        b, db = barrier_derivatives(barrier.barrier, d2, t)
        u, v = xp[:, 1] - xp[:, 0], xp[:, 3] - xp[:, 2]
        n = np.cross(u, v)
        s = _dot(n, n)
        ds = 2.0 * (
            _dot(np.cross(v, n), lp[:, 1] - lp[:, 0]) + _dot(np.cross(n, u), lp[:, 3] - lp[:, 2])
        )
        ra, rb = xr[:, 0] - xr[:, 1], xr[:, 2] - xr[:, 3]
        eps = _EPS_SCALE * _dot(ra, ra) * _dot(rb, rb)
        below = s < eps
        m = np.where(below, (2.0 - s / eps) * s / eps, 1.0)
        dm = np.where(below, 2.0 * (eps - s) / (eps * eps), 0.0)
        dd2 = np.einsum("kij,kij->k", grad, lp)
        out[sel] = stiffness * (m * db * dd2 + b * dm * ds)
    return out


def _weight_term(
    collisions: ipctk.NormalCollisions,
    mesh: ipctk.CollisionMesh,
    c: CollisionArrays,
    s: np.ndarray,
    x: np.ndarray,
    merged_rows: sp.csr_matrix,
) -> np.ndarray:
    """sum_c s_c grad_X w_c (``area_weights.weight_gradient_adjoint``).

    In the convergent formulation the weights of edge-edge pairs near or below their mollifier
    threshold are read (that formulation adds negative terms to them;
    ``NormalCollisionsBuilder``).
    """
    ee = c.kind == 2
    mollified = merged_edge_edge(collisions, c, x)
    kept = np.ones(len(s), dtype=bool)
    kept[ee] = ~mollified
    out = weight_gradient_adjoint(mesh, c.without_ee(mollified), s[kept], merged_rows)
    if mollified.any():
        listed = collisions.ee_collisions
        rows = weight_gradient_rows([listed[k] for k in np.flatnonzero(mollified)], out.size)
        out += rows.T @ s[ee][mollified]
    return out


def barrier_shape_adjoint(
    collisions: ipctk.NormalCollisions,
    mesh: ipctk.CollisionMesh,
    x: np.ndarray,
    barrier: ipctk.BarrierPotential,
    stiffness: float,
    lam: np.ndarray,
    hessian_lam: np.ndarray,
    merged_rows: sp.csr_matrix,
    arrays: CollisionArrays | None = None,
) -> np.ndarray:
    """S^T lam with S of :func:`barrier_shape_derivative`, batched over the collisions.

    With x = X + u at fixed u, S = H + sum_c kappa grad_x(m_c b_c) grad_X w_c^T + (the
    mollifier threshold's rest-position terms), H the exact barrier Hessian (symmetric), so

        S^T lam = H lam + sum_c (kappa grad_x(m_c b_c) . lam) grad_X w_c
                  + sum_{mollified ee} (f dm'/deps (gs . lam) geps + (gf . lam) gxm)

    (module docstring for the mollifier terms). The products per collision are batched
    (:func:`_directional_barrier`); the weight gradients of face-vertex, edge-edge and 2D
    edge-vertex collisions are sums of area gradients applied in bulk, those of vertex-vertex
    and 3D edge-vertex collisions are read per collision.

    Args:
        collisions: Built with ``enable_shape_derivatives = True`` at positions ``x``.
        mesh: The collision mesh (area Jacobians initialised).
        x: (num_vertices, dim) current positions.
        barrier: The barrier potential.
        stiffness: Its stiffness kappa.
        lam: (num_vertices * dim,) the vector.
        hessian_lam: H lam, H the exact barrier Hessian of ``collisions`` at x.
        merged_rows: Weight gradients of the collisions'
            :func:`~diffsolids.contact.derivatives.area_weights.merged_weight_collisions`.
        arrays: The collisions' :func:`collision_arrays` if already read.
    """
    g = np.array(hessian_lam, dtype=float)
    if len(collisions) == 0:
        return g
    c = collision_arrays(collisions, mesh) if arrays is None else arrays
    rest = np.asarray(mesh.rest_positions)
    if collisions.use_area_weighting:
        s = _directional_barrier(c, rest, x, lam, barrier, stiffness)
        g += _weight_term(collisions, mesh, c, s, x, merged_rows)
    has_ee = x.shape[1] == 3 and bool(np.any(c.kind == 2))
    t = _ee_terms(collisions, mesh, x, barrier, stiffness, c) if has_ee else None
    if t is not None:
        lc = lam[t.dofs]
        col = lambda a: a[:, None]  # noqa: E731
        v = col(t.f * t.dm1 * _dot(t.gs, lc)) * t.geps + t.gxm * col(_dot(t.gf, lc))
        np.add.at(g, t.dofs.ravel(), v.ravel())
    return g
