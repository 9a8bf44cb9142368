"""Explicit shape partials of residual forms: the energy-momentum (Eshelby) transform.

The adjoint needs lambda . dG/dX [V], the derivative of the residual form
R = int_Omega0 r dX, r = dpsi/du [lambda], when the rest coordinates move, X -> X + eps V, and the
fields move with the mesh (their nodal values are fixed). UFL's coordinate derivative
(``ufl.derivative(R, SpatialCoordinate, V)``) computes it and stays the reference and the path
of user-written terms; FFCx evaluates it in forward mode, carrying the reference gradient of V
through the whole residual expression. For an integrand that depends on the rest coordinates
only through the measure and the gradients of fields (coefficients that are functions on the
mesh, such as material fields, move with it and are unchanged) the derivative is explicit:

    Grad w -> Grad w - Grad w Grad V for every field w,   dX -> (1 + div V) dX,

so that dR[V] = int T : Grad V dX with the energy-momentum tensor

    T = r I - sum_w Grad w^T dr/d(Grad w)

(Eshelby's tensor when r is an energy density). For a residual of a potential density
psi(Grad u, Grad h, u, h; q) (h: history fields such as u_prev, fixed in the Newton step),
dr/d(Grad lambda) = P_u = dpsi/dGrad u and dr/d(Grad w) = dP_w/du [lambda] for w = u, h
(the symmetry of the Hessian of psi): T needs the stresses P_w and one directional derivative of
each, never the full fourth-order tangent, and Grad V enters once at the end. A tensor T is
evaluated once per quadrature point and contracted with the gradients of the shape basis.

A surface density without gradients (a dead traction per reference area, a boundary
objective) on an exterior-facet integral has the surface Jacobian rule
dA -> (1 + div_Gamma V) dA, div_Gamma V = div V - n . (Grad V n), n the unit normal of the rest
facet (exact on flat facets). An integrand that reads the rest position X itself gains
dj/dX . V (X replaced by a variable).

The transform is exact when the integrand reads no geometric quantity other than X (no
normals, cell sizes, Jacobians), every field in it has an identity pull-back (Lagrange,
discontinuous Lagrange: values move with the mesh, unlike Piola-mapped fields), it has no
gradient of a gradient, and the mesh geometry is of degree 1 with the shape perturbation V in
its space. :func:`is_transformable` checks the integrand; the terms of the model decide where
they use it, :func:`form_shape_partial` applies the generic rule to a whole scalar form (the
objective) and answers None where it is not valid.
"""

from collections.abc import Mapping

import ufl
from ufl.algorithms import expand_derivatives
from ufl.classes import (
    Argument,
    Coefficient,
    GeometricQuantity,
    Grad,
    ReferenceGrad,
    SpatialCoordinate,
)
from ufl.core.expr import Expr
from ufl.corealg.traversal import unique_pre_traversal
from ufl.domain import extract_unique_domain
from ufl.pullback import IdentityPullback

__all__ = [
    "energy_momentum_tensor",
    "form_shape_partial",
    "is_transformable",
    "residual_shape_partial",
    "surface_residual_shape_partial",
]


def is_transformable(
    expr: Expr, fields: "Mapping[Expr, Expr] | None" = None, coordinates: bool = False
) -> bool:
    """Whether an integrand depends on the rest coordinates only through field gradients.

    Args:
        expr: A scalar integrand (derivatives are expanded first).
        fields: The fields whose gradients may appear (Coefficients or Arguments); None allows
            the gradient of any Coefficient or Argument.
        coordinates: Accept the SpatialCoordinate (its partial is then added separately).

    Returns:
        False if ``expr`` reads a geometric quantity (the SpatialCoordinate unless
        ``coordinates``), a field whose element does not have the identity pull-back, a
        gradient of a gradient, or the gradient of anything but an allowed field.
    """
    allowed = None if fields is None else set(fields)
    for node in unique_pre_traversal(expand_derivatives(expr)):
        if isinstance(node, SpatialCoordinate) and coordinates:
            continue
        if isinstance(node, (GeometricQuantity, ReferenceGrad)):
            return False
        if isinstance(node, (Coefficient, Argument)) and not isinstance(
            node.ufl_element().pullback, IdentityPullback
        ):
            return False
        if isinstance(node, Grad):
            (operand,) = node.ufl_operands
            if not isinstance(operand, (Coefficient, Argument)):
                return False  # grad of grad, or of an expression
            if allowed is not None and operand not in allowed:
                return False
    return True


def energy_momentum_tensor(
    psi: Expr,
    u: Expr,
    lam: Expr,
    gradients: Mapping[Expr, Expr],
    stresses: Mapping[Expr, Expr] | None = None,
    residual: Expr | None = None,
) -> tuple[Expr, Expr]:
    """T = r I - Grad lambda^T P_u - sum_w Grad w^T dP_w/du[lambda] of a potential density.

    Args:
        psi: Scalar density psi; its dependence on the gradient of each field ``w`` goes
            through the ``ufl.variable`` ``gradients[w]`` (of Grad w, or of I + Grad w).
        u: The unknown (a Coefficient).
        lam: The adjoint (the direction of the residual, a Coefficient).
        gradients: Field -> the variable psi reads its gradient through; must contain ``u``
            when psi depends on Grad u.
        stresses: Field -> P_w = dpsi/dGrad w written out (fewer operations than
            ``ufl.diff``); the fields not given are differentiated.
        residual: r = dpsi/du[lambda] written out (default ``ufl.derivative``).

    Returns:
        The residual integrand r = dpsi/du [lambda] and the tensor T (d x d).
    """
    d = u.ufl_shape[0]
    stresses = stresses or {}
    r = ufl.derivative(psi, u, lam) if residual is None else residual
    T = r * ufl.Identity(d)
    for w, G in gradients.items():
        P = stresses[w] if w in stresses else ufl.diff(psi, G)  # dpsi/dGrad w
        if w == u:
            T = T - ufl.grad(lam).T * P  # dr/dGrad lambda = P_u
        T = T - ufl.grad(w).T * ufl.derivative(P, u, lam)  # dr/dGrad w = dP_w/du[lambda]
    return r, T


def residual_shape_partial(
    psi: Expr,
    u: Expr,
    lam: Expr,
    gradients: Mapping[Expr, Expr],
    theta: Expr,
    measure: ufl.Measure,
    stresses: Mapping[Expr, Expr] | None = None,
    residual: Expr | None = None,
) -> ufl.Form:
    """The shape derivative int T : Grad theta dX of int dpsi/du[lambda] dX along theta.

    Equal to ``ufl.derivative(ufl.derivative(psi * measure, u, lam), X, theta)`` (X the
    SpatialCoordinate) for a cell-integral density that :func:`is_transformable` accepts.

    Args:
        psi: Potential density (see :func:`energy_momentum_tensor`).
        u: The unknown.
        lam: The adjoint.
        gradients: Field -> variable of its gradient in psi.
        theta: Shape direction (an Argument of the coordinate element's vector space).
        measure: A cell measure (``dx``, with its subdomains and quadrature metadata).
        stresses: Optional stresses written out (see :func:`energy_momentum_tensor`).
        residual: Optional residual integrand written out.

    Returns:
        The linear form in theta.
    """
    _, T = energy_momentum_tensor(psi, u, lam, gradients, stresses, residual)
    return ufl.inner(T, ufl.grad(theta)) * measure


def surface_residual_shape_partial(
    psi: Expr, u: Expr, lam: Expr, theta: Expr, measure: ufl.Measure
) -> ufl.Form:
    """Shape derivative of int_Gamma0 dpsi/du[lambda] dA for a density without gradients.

    dA -> (1 + div theta - n . (Grad theta n)) dA on flat facets with rest normal n.

    Args:
        psi: Surface potential density (reads no gradient and no geometric quantity).
        u: The unknown.
        lam: The adjoint.
        theta: Shape direction.
        measure: An exterior-facet measure.

    Returns:
        The linear form in theta.
    """
    n = ufl.FacetNormal(extract_unique_domain(u))
    r = ufl.derivative(psi, u, lam)
    G = ufl.grad(theta)
    return r * (ufl.tr(G) - ufl.dot(n, G * n)) * measure


def _measure(integral: ufl.classes.Integral) -> ufl.Measure:
    """The measure of an integral (type, domain, subdomain and quadrature metadata)."""
    return ufl.Measure(
        integral.integral_type(),
        domain=integral.ufl_domain(),
        subdomain_id=integral.subdomain_id(),
        subdomain_data=integral.subdomain_data(),
        metadata=integral.metadata(),
    )


def _integrand_shape_partial(j: Expr, theta: Expr, surface: bool) -> Expr | None:
    """The integrand of the shape derivative of int j along theta, or None where not valid."""
    if not is_transformable(j, coordinates=True):
        return None
    j = expand_derivatives(j)
    # in a fixed order: every rank (and every run) builds the same form
    fields = sorted(
        {n.ufl_operands[0] for n in unique_pre_traversal(j) if isinstance(n, Grad)}, key=repr
    )
    if surface and fields:  # a gradient on a facet: its tangential/normal split is UFL's
        return None
    domain = extract_unique_domain(theta)
    X = ufl.SpatialCoordinate(domain)
    reads_x = any(isinstance(n, SpatialCoordinate) for n in unique_pre_traversal(j))
    variables = {ufl.grad(w): ufl.variable(ufl.grad(w)) for w in fields}
    if reads_x:
        variables[X] = ufl.variable(X)
    jv = ufl.replace(j, variables) if variables else j
    Gt = ufl.grad(theta)
    d = theta.ufl_shape[0]
    if surface:
        n = ufl.FacetNormal(domain)
        partial = j * (ufl.tr(Gt) - ufl.dot(n, Gt * n))
    else:
        T = j * ufl.Identity(d)
        for w in fields:  # Grad w -> Grad w - Grad w Grad theta
            T = T - ufl.grad(w).T * ufl.diff(jv, variables[ufl.grad(w)])
        partial = ufl.inner(T, Gt)
    if reads_x:  # the integrand's own dependence on X
        partial = partial + ufl.dot(ufl.diff(jv, variables[X]), theta)
    return partial


def form_shape_partial(form: ufl.Form, theta: Expr) -> ufl.Form | None:
    """The shape derivative of a scalar form along theta by the energy-momentum rule.

    Equal to ``ufl.derivative(form, SpatialCoordinate, theta)`` where valid: cell integrals
    whose integrands :func:`is_transformable` accepts (the SpatialCoordinate allowed) and
    exterior-facet integrals of integrands without gradients. The partials dj/d(Grad w) are
    ``ufl.diff`` with respect to variables replacing the gradients.

    Args:
        form: A scalar (0-form) UFL form.
        theta: Shape direction (an Argument of the coordinate element's vector space).

    Returns:
        The linear form in theta, or None if any integral is of another kind (interior facets,
        points) or reads what the rule does not cover: use UFL's coordinate derivative then.
    """
    parts = []
    for integral in form.integrals():
        kind = integral.integral_type()
        if kind not in ("cell", "exterior_facet"):
            return None
        partial = _integrand_shape_partial(
            integral.integrand(), theta, surface=kind == "exterior_facet"
        )
        if partial is None:
            return None
        parts.append(partial * _measure(integral))
    return sum(parts[1:], parts[0]) if parts else None
