"""Compiled forms of the adjoint: partial derivatives of the step Lagrangian.

For step i the scalar Lagrangian is L_i = lambda . G_i(u^i; u^{i-1}, u_tilde, X, q) + J_i with
G_i the residual of the step's incremental potential (``ufl.derivative(Pi, u, lambda)``) and
J_i = sum_l c_l^i J_l the objective integrals weighted by their chain-rule weights c_l^i. Every
partial derivative the backward sweep needs is ``ufl.derivative`` of it; shape derivatives are
coordinate derivatives of its two parts (paper eqs. 20, 25, 28 come out of UFL).
"""

import ufl
from dolfinx import default_scalar_type, fem
from ufl.algorithms import expand_derivatives

from diffsolids.adjoint.sensitivities import Targets
from diffsolids.solvers.forms import compile_form

__all__ = ["AdjointForms"]


def _nonempty(form):
    """The form, or None when it has no integrals after expanding derivatives."""
    if form is None:
        return None
    expanded = expand_derivatives(form)
    return None if expanded.empty() else form


class AdjointForms:
    """Compiled derivative forms of the step Lagrangian for one model, objective and targets.

    Args:
        model: The Model.
        dynamic: BDF steps (inertia and damping present).
        leaves: The objective's Integral leaves.
        targets: Which parameter/shape sensitivities are needed.
    """

    def __init__(self, model, dynamic: bool, leaves, targets: Targets):
        f = model.fields
        V = model.V
        mesh = V.mesh
        w = ufl.TestFunction(V)
        self.lam = fem.Function(V, name="adjoint")
        self.weights = {leaf: fem.Constant(mesh, default_scalar_type(0.0)) for leaf in leaves}
        L = ufl.derivative(model.potential(dynamic), f.u, self.lam)
        parts = [c * leaf.form(f) for leaf, c in self.weights.items()]
        J = _nonempty(sum(parts[1:], parts[0])) if parts else None
        self.objective_u = compile_form(_nonempty(ufl.derivative(J, f.u, w)) if J else None)
        self.objective_v = compile_form(_nonempty(ufl.derivative(J, f.v, w)) if J else None)
        self.history_tilde = compile_form(_nonempty(ufl.derivative(L, f.u_tilde, w)))
        self.history_prev = compile_form(_nonempty(ufl.derivative(L, f.u_prev, w)))
        self.jacobian_action = (
            compile_form(ufl.derivative(L, f.u, w)) if targets.dirichlet else None
        )
        # The residual part (lambda . G_i) and the objective part (J_i) of every partial are
        # separate forms, assembled and summed: FFCx 0.11 miscompiles kernels that mix a
        # one-point quadrature rule (the strain quadrature of P1) with other rules when a
        # non-constant coefficient (e.g. a CG1 material field) appears in both; the residual
        # and the objective are each free of such mixtures.
        self.coefficients = {}
        for name in sorted(targets.coefficients):
            c = model.coefficients[name]
            dc = ufl.TestFunction(c.function_space)
            self.coefficients[name] = tuple(
                compile_form(_nonempty(ufl.derivative(part, c, dc)) if part else None)
                for part in (L, J)
            )
        self.shape = None
        if targets.shape:
            theta = ufl.TestFunction(model.shape_space)
            self.shape = tuple(
                compile_form(ufl.derivative(part, f.X, theta) if part else None) for part in (L, J)
            )

    def set_weights(self, weights: dict, step: int) -> bool:
        """Load the chain-rule weights c_l^i of step ``step``; True if any is nonzero."""
        active = False
        for leaf, const in self.weights.items():
            value = float(weights[leaf][step]) if leaf in weights else 0.0
            const.value = value
            active |= value != 0.0
        return active
