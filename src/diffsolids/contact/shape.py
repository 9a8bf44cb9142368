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

The difference (added here) is f (m'' gs gs^T + dm'/deps (gs geps^T - geps gs^T))
+ gf gxm^T - gxm gf^T. It is evaluated per mollified pair (a short loop over those pairs only,
in the adjoint, never in the Newton loop).
"""

import ipctk
import numpy as np
import scipy.sparse as sp

__all__ = ["barrier_shape_derivative"]


def _mollified_pairs(collisions: ipctk.NormalCollisions, mesh, rest: np.ndarray, x: np.ndarray):
    E, F = mesh.edges, mesh.faces
    for c in collisions.ee_collisions:
        ids = np.asarray(c.vertex_ids(E, F))
        xr = rest[ids].ravel()
        xp = x[ids].ravel()
        eps = c.mollifier_threshold(xr)
        s = ipctk.edge_edge_cross_squarednorm(*xp.reshape(4, 3))
        if s < eps:
            yield c, ids, xr, xp, eps, s


def _ee_correction(
    collisions: ipctk.NormalCollisions,
    mesh: ipctk.CollisionMesh,
    x: np.ndarray,
    barrier: ipctk.BarrierPotential,
    stiffness: float,
) -> sp.csc_matrix:
    rest = mesh.rest_positions
    n = x.size
    rows, cols, vals = [], [], []
    kappa_b = barrier.barrier
    dhat2 = barrier.dhat**2
    for c, ids, xr, xp, eps, s in _mollified_pairs(collisions, mesh, rest, x):
        d = c.compute_distance(xp)
        w = c.weight
        f = w * stiffness * kappa_b(d, dhat2)
        gf = w * stiffness * kappa_b.first_derivative(d, dhat2) * c.compute_distance_gradient(xp)
        gs = ipctk.edge_edge_cross_squarednorm_gradient(*xp.reshape(4, 3))
        geps = ipctk.edge_edge_mollifier_threshold_gradient(*xr.reshape(4, 3))
        m2 = ipctk.edge_edge_mollifier_hessian(s, eps)
        dm1 = ipctk.edge_edge_mollifier_gradient_derivative_wrt_eps_x(s, eps)
        gxm = c.mollifier_gradient_wrt_x(xr, xp)
        delta = f * (m2 * np.outer(gs, gs) + dm1 * (np.outer(gs, geps) - np.outer(geps, gs)))
        delta += np.outer(gf, gxm) - np.outer(gxm, gf)
        dofs = (ids[:, None] * 3 + np.arange(3)).ravel()
        rows.append(np.repeat(dofs, 12))
        cols.append(np.tile(dofs, 12))
        vals.append(delta.ravel())
    if not rows:
        return sp.csc_matrix((n, n))
    return sp.csc_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )


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
