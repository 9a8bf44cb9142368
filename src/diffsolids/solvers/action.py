"""Matrix-free action of the exact step Jacobian (a PETSc python matrix).

Assembling the action K d as a vector costs a small fraction of assembling K (the matrix
insertion dominates); Krylov solves preconditioned by an existing factorisation need only a
couple of actions. Within one solve only the direction d changes:
:meth:`JacobianAction.fixed_state` packs the form's coefficients once and each action then
rewrites only the direction's columns (packing all of them is about a fifth of an action).
"""

from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

import dolfinx.fem.petsc as fem_petsc
import dolfinx.la.petsc
import ufl
from dolfinx import fem
from petsc4py import PETSc

from diffsolids.solvers.callbacks import WeakContext
from diffsolids.solvers.forms import compile_form
from diffsolids.solvers.packing import coefficient_layout

if TYPE_CHECKING:
    from diffsolids.solvers.newton import NewtonSolver

__all__ = ["JacobianAction"]


class JacobianAction:
    """y = K(u) x with identity Dirichlet rows and columns, K the exact step Jacobian.

    Args:
        newton: The NewtonSolver (its residual form, model and numeric terms).
    """

    def __init__(self, newton: "NewtonSolver") -> None:
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
        self._packed: dict | None = None
        self._direction_columns = self._direction_gather()

    def _direction_gather(self) -> dict | None:
        """Per cell integral: (packed columns of the direction, its dof indices per cell).

        None when the direction's values cannot be gathered by the cell dofmap alone (facet
        integrals, or an element needing DOF transformations): every action then packs all
        coefficients.
        """
        cpp = self.form._cpp_object
        if set(cpp.integral_types) != {fem.IntegralType.cell}:
            return None
        layout = coefficient_layout(self.form)
        if layout is None:
            return None
        gather = {}
        for key, parts in layout.items():
            found = [(cols, dofs) for c, cols, dofs in parts if c is self.direction._cpp_object]
            if len(found) != 1:
                return None
            gather[key] = found[0]
        return gather

    @contextmanager
    def fixed_state(self) -> Iterator[None]:
        """Within this block the state (u and every coefficient but the direction) is fixed."""
        if self._direction_columns is not None:
            self._packed = fem.pack_coefficients(self.form)
        try:
            yield
        finally:
            self._packed = None

    def _coefficients(self) -> dict | None:
        """Packed coefficients for this action (None: let the assembler pack them)."""
        if self._packed is None:
            return None
        values = self.direction.x.array
        for key, (columns, dofs) in self._direction_columns.items():
            self._packed[key][:, columns] = values[dofs]
        return self._packed

    def mult(self, mat: PETSc.Mat, x: PETSc.Vec, y: PETSc.Vec) -> None:
        """PETSc callback: y = K x."""
        d = self.direction
        d.x.petsc_vec.array_w[:] = x.array_r
        d.x.scatter_forward()
        d.x.array[self.bc_all] = 0.0
        w = self._ghosted
        with w.localForm() as loc:
            loc.set(0.0)
        fem_petsc.assemble_vector(w, self.form, coeffs=self._coefficients())
        dolfinx.la.petsc._ghost_update(w, PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        u = self.newton.u
        for term in self.newton.numeric_terms:
            term.add_hessian_action(u, d.x.array, w)
        w.array_w[self.bc_owned] = x.array_r[self.bc_owned]
        y.array_w[:] = w.array_r
