"""Newton steps that hold a sliding friction contact at stick instead of crossing it.

Per friction collision c the lagged friction potential is w mu N f0(|tau|) with the tangential
velocity tau = P^T Gamma v (paper sec. 8.2, ipctk ``TangentialPotential``; weight w, friction
coefficient mu, lagged normal force N, tangent basis P, relative-velocity Jacobian Gamma). Its
curvature along the slip is f1'(|tau|), which is zero where the contact slides (|tau| >= eps_v):
a Newton step from a sliding state sees no friction curvature, reverses the slip across the
stick zone (|tau| < eps_v, a few micrometres of motion per step) and the line search backs off
to a small fraction of it, iteration after iteration (a disk rolling down a slope: 38 Newton
iterations for a step that takes 9 without friction).

When a Newton step would reverse the slip of sliding collisions, those collisions are modelled
for that one step by the smoothed potential's quadratic about zero slip,
w mu N |tau|^2 / eps_v (the same curvature 2 / eps_v as f0 at zero): the step is solved again
with their friction gradient and Hessian replaced by this model's. The iterate then lands in
the stick zone, where the exact Hessian is accurate. The energy line search, the convergence
test and the exact Hessian of the last iterations are unchanged: the step converges to a
stationary point of the same potential (a semismooth Newton step on the active set of stuck
contacts, after the active-set treatment of friction in nonsmooth contact mechanics).
"""

import numpy as np
import scipy.sparse as sp

from diffsolids.contact.energy.lagged_arrays import FrictionArrays

__all__ = ["StickModel"]


class StickModel:
    """The lagged linear maps of a step's friction collisions (this rank's share).

    Args:
        friction: The step's friction collisions as arrays
            (:func:`~diffsolids.contact.energy.lagged_arrays.friction_arrays`).
        num_vertices: Vertices of the collision mesh.
        eps_v: The friction's smoothing velocity.
    """

    def __init__(self, friction: FrictionArrays, num_vertices: int, eps_v: float) -> None:
        self.eps_v = eps_v
        n, dim = friction.basis.shape[:2]
        self.size = num_vertices * dim
        # per collision: its dofs (-1 padded) and P^T Gamma over them; w mu N
        ids = friction.ids
        dofs = ids[:, :, None] * dim + np.arange(dim)
        self.dofs = np.where(ids[:, :, None] >= 0, dofs, -1).reshape(n, 4 * dim)
        maps = np.einsum("kai,kj->kija", friction.basis, friction.gamma)
        self.maps = maps.reshape(n, dim - 1, 4 * dim)
        self.coefficients = friction.coefficients

    def tangential_velocities(self, velocities: np.ndarray) -> np.ndarray:
        """(n, dim - 1) tau of every collision at vertex velocities (num_vertices, dim)."""
        v = np.append(velocities.ravel(), 0.0)  # the padding index -1 reads 0
        return np.einsum("kij,kj->ki", self.maps, v[self.dofs])

    def reversed(self, velocities: np.ndarray, change: np.ndarray) -> np.ndarray:
        """Sliding collisions (|tau| >= eps_v) whose slip velocities + change reverses."""
        tau0 = self.tangential_velocities(velocities)
        tau1 = self.tangential_velocities(velocities + change)
        sliding = np.linalg.norm(tau0, axis=1) >= self.eps_v
        return sliding & (np.einsum("ki,ki->k", tau0, tau1) < 0.0)

    def _parts(self, velocities: np.ndarray) -> tuple[np.ndarray, ...]:
        """tau, tau / |tau|, f1(|tau|) / |tau| and f1'(|tau|) of every collision."""
        eps = self.eps_v
        tau = self.tangential_velocities(velocities)
        y = np.linalg.norm(tau, axis=1)
        inside = y < eps
        f1_over_y = np.where(inside, (2.0 - y / eps) / eps, 1.0 / np.maximum(y, eps))
        df1 = np.where(inside, (2.0 - 2.0 * y / eps) / eps, 0.0)
        return tau, tau / np.maximum(y, np.finfo(float).tiny)[:, None], f1_over_y, df1

    def gradient_change(self, velocities: np.ndarray, held: np.ndarray) -> np.ndarray:
        """Stick model's minus the exact friction gradient (in v) of the ``held`` collisions."""
        tau, _, f1_over_y, _ = self._parts(velocities)
        force = (2.0 / self.eps_v - f1_over_y)[:, None] * tau
        g = np.einsum("kia,ki->ka", self.maps, force * (self.coefficients * held)[:, None])
        out = np.zeros(self.size + 1)
        np.add.at(out, self.dofs.ravel(), g.ravel())
        return out[:-1]

    def hessian_change(self, velocities: np.ndarray, held: np.ndarray) -> sp.csc_matrix:
        """Stick model's minus the exact friction Hessian (in v) of the ``held`` collisions.

        In tangent coordinates: (2 / eps_v - f1/y) I + (f1/y - f1') t t^T, positive
        semidefinite (f1'(y) <= f1(y)/y <= 2 / eps_v).
        """
        tau, t, f1_over_y, df1 = self._parts(velocities)
        eye = np.eye(tau.shape[1])
        K = (2.0 / self.eps_v - f1_over_y)[:, None, None] * eye
        K += (f1_over_y - df1)[:, None, None] * (t[:, :, None] * t[:, None, :])
        K *= (self.coefficients * held)[:, None, None]
        B = np.einsum("kia,kij,kjb->kab", self.maps, K, self.maps)
        used = (self.dofs >= 0) & held[:, None]
        mask = used[:, :, None] & used[:, None, :]
        rows = np.broadcast_to(self.dofs[:, :, None], B.shape)[mask]
        cols = np.broadcast_to(self.dofs[:, None, :], B.shape)[mask]
        return sp.csc_matrix((B[mask], (rows, cols)), shape=(self.size, self.size))
