"""Step bound that keeps every element non-inverted (det F > 0 at all quadrature points)."""

import basix
import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

__all__ = ["InversionGuard"]


class InversionGuard:
    """Largest fraction of a Newton step that keeps det F > 0 at the quadrature points.

    With F0 = I + grad u and D = grad du at a point, det(F0 + a D) = det(F0) det(I + a F0^{-1} D)
    vanishes at a = -1/mu for the real eigenvalues mu < 0 of F0^{-1} D; the bound is the smallest
    such a over all points (vectorised over cells and points).

    Args:
        V: Displacement space.
        quadrature_degree: Degree of the quadrature whose points are checked.
    """

    def __init__(self, V: fem.FunctionSpace, quadrature_degree: int):
        mesh = V.mesh
        self.d = mesh.geometry.dim
        self.x = fem.Function(V)
        self.dx = fem.Function(V)
        cell = mesh.basix_cell()
        degree = max(quadrature_degree, 0) if V.element.basix_element.degree > 1 else 0
        points, _ = basix.make_quadrature(cell, degree)
        eye = ufl.Identity(self.d)
        expr = ufl.as_tensor([eye + ufl.grad(self.x), ufl.grad(self.dx)])
        self.expr = fem.Expression(expr, points)
        num_cells = mesh.topology.index_map(mesh.topology.dim).size_local
        self.cells = np.arange(num_cells, dtype=np.int32)
        self.comm = mesh.comm

    def _load(self, target: fem.Function, vec: PETSc.Vec) -> None:
        target.x.petsc_vec.array_w[:] = vec.array_r
        target.x.scatter_forward()

    def max_step(self, x: PETSc.Vec, dx: PETSc.Vec) -> float:
        """Largest a in (0, inf] with det(F(x + s dx)) > 0 for all s in [0, a)."""
        self._load(self.x, x)
        self._load(self.dx, dx)
        values = self.expr.eval(self.x.function_space.mesh, self.cells)
        d = self.d
        vals = values.reshape(len(self.cells), -1, 2, d, d).reshape(-1, 2, d, d)
        F0, D = vals[:, 0], vals[:, 1]
        local = np.inf
        if len(F0):
            mu = np.linalg.eigvals(np.linalg.solve(F0, D))
            # near-real pairs count as real: conservative where roots nearly coincide
            real = np.abs(mu.imag) <= 1e-6 * np.maximum(np.abs(mu.real), 1e-300)
            neg = real & (mu.real < 0)
            if neg.any():
                local = float(np.min(-1.0 / mu.real[neg]))
            if np.any(np.linalg.det(F0) <= 0):
                local = 0.0
        return self.comm.allreduce(local, op=MPI.MIN)
