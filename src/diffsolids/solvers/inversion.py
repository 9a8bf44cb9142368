"""Step bound that keeps every element non-inverted (det F > 0 at all quadrature points)."""

import basix
import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

from diffsolids.errors import ParameterError
from diffsolids.parallel import collective_comm
from diffsolids.solvers.forms import compile_expression

__all__ = ["InversionGuard"]


class InversionGuard:
    """Largest fraction of a Newton step that keeps det F > 0 at the quadrature points.

    With F0 = I + grad u and D = grad du at a point, det(F0 + a D) = det(F0) det(I + a F0^{-1} D)
    vanishes at a = -1/mu for the real eigenvalues mu < 0 of F0^{-1} D; the bound is the smallest
    such a over all points (vectorised over cells and points).

    Since |mu| <= |F0^{-1} D|_F, points with |F0^{-1} D|_F <= 1 / limit bound no step shorter
    than ``limit``: their eigenvalues are skipped (in a converging Newton solve, nearly all).

    Args:
        V: Displacement space.
        quadrature_degree: Degree of the quadrature whose points are checked.
        limit: Only bounds below this matter to the caller (e.g. 1 / step safety for a Newton
            step of length 1); larger bounds are reported as inf.
    """

    def __init__(self, V: fem.FunctionSpace, quadrature_degree: int, limit: float = np.inf) -> None:
        if not limit > 0:
            raise ParameterError(f"InversionGuard limit {limit} must be positive")
        self.limit = float(limit)
        mesh = V.mesh
        self.d = mesh.geometry.dim
        self.x = fem.Function(V)
        self.dx = fem.Function(V)
        cell = mesh.basix_cell()
        degree = quadrature_degree if V.element.basix_element.degree > 1 else 0
        points, _ = basix.make_quadrature(cell, degree)
        eye = ufl.Identity(self.d)
        expr = ufl.as_tensor([eye + ufl.grad(self.x), ufl.grad(self.dx)])
        self.expr = compile_expression(expr, points)
        num_cells = mesh.topology.index_map(mesh.topology.dim).size_local
        self.cells = np.arange(num_cells, dtype=np.int32)
        self.comm = mesh.comm

    def _load(self, target: fem.Function, vec: PETSc.Vec) -> None:
        target.x.petsc_vec.array_w[:] = vec.array_r
        target.x.scatter_forward()

    def max_step(self, x: PETSc.Vec, dx: PETSc.Vec) -> float:
        """Largest a in (0, inf] with det(F(x + s dx)) > 0 for all s in [0, a).

        Returns 0 when ``x`` itself has inverted points and inf when the bound is at least
        ``limit``.
        """
        self._load(self.x, x)
        self._load(self.dx, dx)
        values = self.expr.eval(self.x.function_space.mesh, self.cells)
        d = self.d
        vals = values.reshape(-1, 2, d, d)
        adj, det = _adjugate(vals[:, 0])
        local = np.inf
        if np.any(det <= 0):
            local = 0.0
        elif len(det):
            D = vals[:, 1]
            # |F0^{-1} D|_F <= |adj F0|_F |D|_F / det F0 sorts out most points before the product
            frob = lambda A: np.sqrt(np.einsum("pij,pij->p", A, A))  # noqa: E731
            maybe = np.flatnonzero(frob(adj) * frob(D) > det / self.limit)
            M = adj[maybe] @ D[maybe] / det[maybe, None, None]  # F0^{-1} D
            relevant = frob(M) > 1.0 / self.limit
            if relevant.any():
                mu = np.linalg.eigvals(M[relevant])
                # near-real pairs count as real: conservative where roots nearly coincide
                real = np.abs(mu.imag) <= 1e-6 * np.maximum(np.abs(mu.real), 1e-300)
                neg = real & (mu.real < 0)
                if neg.any():
                    local = float(np.min(-1.0 / mu.real[neg]))
        bound = collective_comm(self.comm).allreduce(local, op=MPI.MIN)
        return bound if bound < self.limit else np.inf


def _adjugate(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Adjugates and determinants of a stack of 2x2 or 3x3 matrices (closed form)."""
    if F.shape[1] == 2:
        adj = np.empty_like(F)
        adj[:, 0, 0], adj[:, 1, 1] = F[:, 1, 1], F[:, 0, 0]
        adj[:, 0, 1], adj[:, 1, 0] = -F[:, 0, 1], -F[:, 1, 0]
        return adj, F[:, 0, 0] * F[:, 1, 1] - F[:, 0, 1] * F[:, 1, 0]
    r0, r1, r2 = F[:, 0], F[:, 1], F[:, 2]
    # columns of adj(F) are cross products of the rows: F adj(F) = det(F) I
    adj = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=2)
    return adj, np.einsum("pi,pi->p", r0, adj[:, :, 0])
