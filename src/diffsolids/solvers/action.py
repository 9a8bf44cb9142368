"""Matrix-free action of the exact step Jacobian (a PETSc python matrix).

Assembling the action K d as a vector costs a small fraction of assembling K (the matrix
insertion dominates); Krylov solves preconditioned by an existing factorisation need only a
couple of actions.
"""

import dolfinx.fem.petsc as fem_petsc
import dolfinx.la.petsc
import ufl
from dolfinx import fem
from petsc4py import PETSc

from diffsolids.solvers.callbacks import WeakContext
from diffsolids.solvers.forms import compile_form

__all__ = ["JacobianAction"]


class JacobianAction:
    """y = K(u) x with identity Dirichlet rows and columns, K the exact step Jacobian.

    Args:
        newton: The NewtonSolver (its residual form, model and numeric terms).
    """

    def __init__(self, newton):
        model = newton.model
        V = model.V
        self.newton = newton
        self.direction = fem.Function(V)
        self.form = compile_form(
            ufl.derivative(newton.residual_ufl, model.fields.u, self.direction)
        )
        bs = V.dofmap.index_map_bs
        self.owned = V.dofmap.index_map.size_local * bs
        dofs = model.dirichlet_dofs()
        self.bc_owned = dofs[dofs < self.owned]
        self.bc_all = dofs
        n, N = self.owned, V.dofmap.index_map.size_global * bs
        # Krylov vectors have no ghosts: assemble into a ghosted vector, copy the owned part
        self._ghosted = fem_petsc.create_vector(V)
        context = WeakContext(self)  # the matrix must not keep this object alive
        self.mat = PETSc.Mat().createPython(((n, N), (n, N)), context, comm=V.mesh.comm)
        self.mat.setUp()

    def mult(self, mat, x: PETSc.Vec, y: PETSc.Vec) -> None:
        """PETSc callback: y = K x."""
        d = self.direction
        d.x.petsc_vec.array_w[:] = x.array_r
        d.x.scatter_forward()
        d.x.array[self.bc_all] = 0.0
        w = self._ghosted
        with w.localForm() as loc:
            loc.set(0.0)
        fem_petsc.assemble_vector(w, self.form)
        dolfinx.la.petsc._ghost_update(w, PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        u = self.newton.u
        for term in self.newton.numeric_terms:
            term.add_hessian_action(u, d.x.array, w)
        w.array_w[self.bc_owned] = x.array_r[self.bc_owned]
        y.array_w[:] = w.array_r
