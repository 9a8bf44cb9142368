"""Compiled forms of the adjoint: partial derivatives of the step Lagrangian.

For step i the scalar Lagrangian is L_i = lambda . G_i(u^i; u^{i-1}, u_tilde, X, q) + J_i with
G_i the residual of the step's incremental potential (``ufl.derivative(Pi, u, lambda)``) and
J_i = sum_l c_l^i J_l the objective integrals weighted by their chain-rule weights c_l^i. Every
partial derivative the backward sweep needs is ``ufl.derivative`` of it; shape derivatives are
coordinate derivatives of its two parts (paper eqs. 20, 25, 28 come out of UFL).

An objective integral may read every state field of :class:`~diffsolids.model.StepFields`:
u^i, v^i, the previous displacement u^{i-1} (``u_prev``) and the BDF predictor u_tilde^i
(``u_tilde``, a combination of earlier displacements and velocities). J_i is differentiated
with respect to each of them and the backward sweep pushes the partials of the history fields
into the earlier steps the way it pushes those of the residual. :func:`check_objective_fields`
refuses the objectives whose history fields are undefined (at step 0, or u_tilde of a static
run).
"""

from collections.abc import Sequence
from typing import TYPE_CHECKING

import ufl
from dolfinx import default_scalar_type, fem
from ufl.algorithms import expand_derivatives, extract_coefficients

from diffsolids.adjoint.sensitivities import Targets
from diffsolids.errors import ParameterError
from diffsolids.objectives.functional import NumericIntegral
from diffsolids.solvers.forms import compile_form

if TYPE_CHECKING:
    from diffsolids.model import Model
    from diffsolids.model.terms import StepFields
    from diffsolids.objectives.functional import Integral, Objective, TimeGrid

__all__ = ["STATE_FIELDS", "AdjointForms", "check_objective_fields", "state_fields_read"]

#: The state fields of a step (attributes of StepFields) that objectives may read; the adjoint
#: differentiates J_i with respect to each. u_prev and u_tilde are the history fields: functions
#: of earlier steps (u^{i-1}; the predictor -sum_j alpha_j (u^{i-j} + beta dt v^{i-j})).
STATE_FIELDS = ("u", "v", "u_prev", "u_tilde")


def _nonempty(form: ufl.Form | None) -> ufl.Form | None:
    """The form, or None when it has no integrals after expanding derivatives."""
    if form is None:
        return None
    expanded = expand_derivatives(form)
    return None if expanded.empty() else form


def state_fields_read(form: ufl.Form, fields: "StepFields") -> list[str]:
    """Names of the state fields (:data:`STATE_FIELDS`) a form depends on.

    Args:
        form: A UFL form.
        fields: The model's StepFields.

    Returns:
        The names, in the order of :data:`STATE_FIELDS`.
    """
    coefficients = set(extract_coefficients(form))
    return [name for name in STATE_FIELDS if getattr(fields, name) in coefficients]


def check_objective_fields(objective: "Objective", fields: "StepFields", grid: "TimeGrid") -> None:
    """Refuse objective integrals that read a history field where it is not defined.

    ``u_prev`` and ``u_tilde`` of step i are set from steps before i, so step 0 has neither;
    a static run has no predictor (``u_tilde``) at any step. An integral reading them there
    would be evaluated, and differentiated, from whatever the fields last held.

    Args:
        objective: The scalar Objective.
        fields: The model's StepFields.
        grid: The simulation's TimeGrid.

    Raises:
        ParameterError: A leaf reads ``u_tilde`` in a static run, or a history field at step 0.
    """
    steps = None
    for leaf in dict.fromkeys(objective.leaves()):
        if isinstance(leaf, NumericIntegral):  # reads u^i only
            continue
        read = state_fields_read(leaf.form(fields), fields)
        if "u_tilde" in read and not grid.dynamic:
            raise ParameterError(
                f"objective integral {leaf.name!r} reads the field u_tilde, the BDF predictor, "
                "which a static simulation does not have; use u_prev (the previous step's "
                "displacement) or v instead"
            )
        history = [name for name in read if name in ("u_prev", "u_tilde")]
        if not history:
            continue
        if steps is None:  # only objectives reading history fields have their steps checked
            steps = objective.requirements(grid)
        if 0 in steps.get(leaf, ()):
            raise ParameterError(
                f"objective integral {leaf.name!r} reads the field {history[0]} at step 0, "
                "which has no previous step: give step 0 zero weight (e.g. "
                "time_integral(..., 'uniform') or the steps 1..N)"
            )


class AdjointForms:
    """Compiled derivative forms of the step Lagrangian for one model, objective and targets.

    Args:
        model: The Model.
        dynamic: BDF steps (inertia and damping present).
        leaves: The objective's Integral leaves.
        targets: Which parameter/shape sensitivities are needed.
    """

    def __init__(
        self,
        model: "Model",
        dynamic: bool,
        leaves: Sequence["Integral | NumericIntegral"],
        targets: Targets,
    ) -> None:
        f = model.fields
        V = model.V
        mesh = V.mesh
        w = ufl.TestFunction(V)
        self.lam = fem.Function(V, name="adjoint")
        # numeric leaves (NumericIntegral) give their partials themselves; the others are UFL
        self.numeric = {leaf: 0.0 for leaf in leaves if isinstance(leaf, NumericIntegral)}
        leaves = [leaf for leaf in leaves if leaf not in self.numeric]
        self.weights = {leaf: fem.Constant(mesh, default_scalar_type(0.0)) for leaf in leaves}
        L = ufl.derivative(model.potential(dynamic), f.u, self.lam)
        parts = [c * leaf.form(f) for leaf, c in self.weights.items()]
        J = _nonempty(sum(parts[1:], parts[0])) if parts else None
        self.objective_u = compile_form(_nonempty(ufl.derivative(J, f.u, w)) if J else None)
        self.objective_v = compile_form(_nonempty(ufl.derivative(J, f.v, w)) if J else None)
        # the history fields the objective reads, pushed into earlier steps like the residual's
        # (a static step sets no predictor: u_tilde is constant there)
        self.objective_prev = compile_form(_nonempty(ufl.derivative(J, f.u_prev, w)) if J else None)
        self.objective_tilde = compile_form(
            _nonempty(ufl.derivative(J, f.u_tilde, w)) if J and dynamic else None
        )
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
        for leaf in self.numeric:
            self.numeric[leaf] = float(weights[leaf][step]) if leaf in weights else 0.0
        return active
