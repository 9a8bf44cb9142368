"""Compiled forms of the adjoint: partial derivatives of the step Lagrangian.

For step i the scalar Lagrangian is L_i = lambda . G_i(u^i; u^{i-1}, u_tilde, X, q) + J_i with
G_i the residual of the step's incremental potential (``ufl.derivative(Pi, u, lambda)``) and
J_i = sum_l c_l^i J_l the objective integrals weighted by their chain-rule weights c_l^i. Every
partial derivative the backward sweep needs is ``ufl.derivative`` of it; shape derivatives are
coordinate derivatives of its two parts (paper eqs. 20, 25, 28 come out of UFL).

The shape partial of the residual part has a second, explicit form: when every UFL term of the
step gives one (:meth:`~diffsolids.model.terms.Term.shape_partial`: the built-in laws, damping,
inertia and loads, in the energy-momentum form of ``forms.shape_partials``) and the mesh
geometry is of degree 1, lambda . dG/dX is their sum, a kernel several times cheaper than the
forward-mode coordinate derivative FFCx makes of UFL's. Otherwise (a user-written term, a
curved mesh) and with ``shape_partials="ufl"`` it is UFL's coordinate derivative, the reference
the tests compare the explicit form with.

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
from ufl.domain import extract_unique_domain

from diffsolids import forms
from diffsolids.adjoint.sensitivities import Targets
from diffsolids.errors import ParameterError
from diffsolids.objectives.functional import NumericIntegral
from diffsolids.solvers.forms import compile_form

if TYPE_CHECKING:
    from diffsolids.model import Model
    from diffsolids.model.terms import StepFields
    from diffsolids.objectives.functional import Integral, Objective, TimeGrid

__all__ = [
    "SHAPE_PARTIALS",
    "STATE_FIELDS",
    "AdjointForms",
    "check_objective_fields",
    "objective_shape_partial",
    "residual_shape_partial",
    "state_fields_read",
]

#: Ways of computing the residual's shape partial: "auto" (the terms' explicit forms where every
#: term has one, else UFL's coordinate derivative) and "ufl" (always the coordinate derivative).
SHAPE_PARTIALS = ("auto", "ufl")

#: The state fields of a step (attributes of StepFields) that objectives may read; the adjoint
#: differentiates J_i with respect to each. u_prev and u_tilde are the history fields: functions
#: of earlier steps (u^{i-1}; the predictor -sum_j alpha_j (u^{i-j} + beta dt v^{i-j})).
STATE_FIELDS = ("u", "v", "u_prev", "u_tilde")


#: Whether a form is empty after expanding its derivatives, by the form's signature. The
#: signature names the form up to the numbering of its coefficients, constants and arguments
#: (it is what FFCx keys its compiled kernels on), so the answer holds for every form with that
#: signature: the adjoint forms of another model, run or ReducedFunctional with the same
#: physics and objective skip UFL's derivative expansion (most of their set-up). The form's
#: signature is cached on it and is the one FFCx computes next.
_EMPTY_BY_SIGNATURE: dict[str, bool] = {}


def _nonempty(form: ufl.Form | None) -> ufl.Form | None:
    """The form, or None when it has no integrals after expanding derivatives."""
    if form is None:
        return None
    signature = form.signature()
    empty = _EMPTY_BY_SIGNATURE.get(signature)
    if empty is None:
        empty = _EMPTY_BY_SIGNATURE[signature] = expand_derivatives(form).empty()
    return None if empty else form


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


def residual_shape_partial(
    model: "Model", dynamic: bool, lam: fem.Function, theta: ufl.Argument, how: str = "auto"
) -> ufl.Form:
    """The shape partial lambda . dG/dX along theta of one step's residual (a linear form).

    Args:
        model: The Model.
        dynamic: A BDF step (inertia and damping present).
        lam: The adjoint.
        theta: Test function of ``model.shape_space``.
        how: One of :data:`SHAPE_PARTIALS`.

    Returns:
        The sum of the terms' explicit shape partials when ``how`` is "auto", the mesh geometry
        has degree 1 and every active term gives one; otherwise UFL's coordinate derivative of
        ``derivative(potential, u, lam)``.

    Raises:
        ParameterError: ``how`` is not one of :data:`SHAPE_PARTIALS`.
    """
    if how not in SHAPE_PARTIALS:
        raise ParameterError(f"shape_partials={how!r}: choose one of {SHAPE_PARTIALS}")
    f = model.fields
    mesh = model.V.mesh
    if how == "auto" and mesh.ufl_domain().ufl_coordinate_element().embedded_superdegree == 1:
        parts = [t.shape_partial(f, lam, theta) for t in model.active_terms(dynamic)]
        if parts and all(p is not None for p in parts):
            return sum(parts[1:], parts[0])
    L = ufl.derivative(model.potential(dynamic), f.u, lam)
    return ufl.derivative(L, f.X, theta)


def objective_shape_partial(
    J: ufl.Form | None, X: ufl.SpatialCoordinate, theta: ufl.Argument, how: str = "auto"
) -> ufl.Form | None:
    """dJ/dX along theta of the weighted objective integrals of a step.

    Args:
        J: The step's weighted objective form (None: no UFL objective).
        X: The SpatialCoordinate.
        theta: Test function of the shape space.
        how: One of :data:`SHAPE_PARTIALS`.

    Returns:
        With "auto" and a geometry of degree 1, the energy-momentum form of ``J``
        (``forms.form_shape_partial``) where it applies to every integral, else UFL's
        coordinate derivative; None without J.
    """
    if J is None:
        return None
    degree = extract_unique_domain(X).ufl_coordinate_element().embedded_superdegree
    if how == "auto" and degree == 1:
        explicit = forms.form_shape_partial(J, theta)
        if explicit is not None:
            return explicit
    return ufl.derivative(J, X, theta)


class AdjointForms:
    """Compiled derivative forms of the step Lagrangian for one model, objective and targets.

    Args:
        model: The Model.
        dynamic: BDF steps (inertia and damping present).
        leaves: The objective's Integral leaves.
        targets: Which parameter/shape sensitivities are needed.
        shape_partials: How the shape partials are computed: "auto" (the explicit
            energy-momentum forms where they apply, else UFL's coordinate derivative) or "ufl"
            (always the coordinate derivative, the reference).
    """

    def __init__(
        self,
        model: "Model",
        dynamic: bool,
        leaves: Sequence["Integral | NumericIntegral"],
        targets: Targets,
        shape_partials: str = "auto",
    ) -> None:
        f = model.fields
        V = model.V
        mesh = V.mesh
        w = ufl.TestFunction(V)
        self.shape_partials = shape_partials
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
            self.shape = (
                compile_form(
                    residual_shape_partial(model, dynamic, self.lam, theta, shape_partials)
                ),
                compile_form(objective_shape_partial(J, f.X, theta, shape_partials)),
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
