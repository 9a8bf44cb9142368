"""Terms of an incremental potential expressed in UFL.

Every force of the model is a term with an energy (a scalar UFL form in the fields of a step).
Residual, Newton Jacobian, and all partial derivatives used by the adjoint (w.r.t. the current
and previous displacements, the shape and any parameter coefficient) come from ``ufl.derivative``
of the summed energy, so a new force is one new term and nothing else changes.

The shape partial of the adjoint (lambda . dG/dX, paper eqs. 20, 25) is UFL's coordinate
derivative for every term; the built-in terms also give it explicitly
(:meth:`Term.shape_partial`, the energy-momentum form of ``forms.shape_partials``), which
compiles to kernels several times cheaper. The adjoint uses those when every term of the step has
one; tests compare the two to 1e-12.
"""

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import override

import ufl
from dolfinx import fem
from ufl.core.expr import Expr

from diffsolids import forms

#: The built-in constitutive laws (exact types): their elastic terms give explicit shape partials.
_BUILTIN_LAWS = (
    forms.LinearElasticEnergy,
    forms.StVenantKirchhoffEnergy,
    forms.NeoHookeanEnergy,
)

__all__ = [
    "BodyForce",
    "Damping",
    "ElasticEnergy",
    "EnergyTerm",
    "Inertia",
    "StepFields",
    "Term",
    "Traction",
]


@dataclass
class StepFields:
    """The UFL coefficients of one step's incremental potential.

    Attributes:
        u: Unknown displacement u^i.
        u_prev: Previous displacement u^{i-1} (damping, lagged friction).
        u_tilde: BDF predictor (inertia).
        v: Velocity v^i (used by objectives).
        t: Time of the step.
        dt: Time-step size.
        beta_dt: beta_m dt of the BDF order used by the step.
        X: Rest (reference) coordinates.
        dx: Volume measure with body tags, quadrature exact for mass-type integrands.
        ds: Boundary measure with facet tags and the same quadrature degree.
        dx_strain: Volume measure for integrands of the strain (two degrees less: exact for
            linear elasticity, one point per cell with P1).
        coefficients: Named parameter coefficients (material fields, loads).
    """

    u: fem.Function
    u_prev: fem.Function
    u_tilde: fem.Function
    v: fem.Function
    t: fem.Constant
    dt: fem.Constant
    beta_dt: fem.Constant
    X: ufl.SpatialCoordinate
    dx: ufl.Measure
    ds: ufl.Measure
    dx_strain: ufl.Measure
    coefficients: dict = field(default_factory=dict)


class Term:
    """A contribution to the incremental potential of a step.

    Attributes:
        name: Human-readable name.
        dynamic_only: Only part of time-dependent (BDF) steps (inertia, damping).
        quadratic: The energy is quadratic in u (its Hessian does not depend on u).
        finite_strain: The energy sees det F: the solver bounds steps so no element inverts.
    """

    name: str = "term"
    dynamic_only: bool = False
    quadratic: bool = False
    finite_strain: bool = False

    def energy(self, f: StepFields) -> ufl.Form:
        """The term's incremental potential as a scalar UFL form."""
        raise NotImplementedError

    def magnitude(self, f: StepFields) -> ufl.Form:
        """A form bounding the magnitude of the energy's addends (roundoff estimate)."""
        return abs(self.energy_density(f)) * self.measure(f)

    def energy_density(self, f: StepFields) -> Expr:
        """The integrand of the energy (override together with :meth:`measure`)."""
        raise NotImplementedError

    def measure(self, f: StepFields) -> ufl.Measure:
        """The integration measure of :meth:`energy_density`."""
        return f.dx

    def shape_partial(
        self, f: StepFields, lam: fem.Function, theta: ufl.Argument
    ) -> ufl.Form | None:
        """The explicit shape derivative of the residual, or None (use UFL's).

        Args:
            f: The step fields.
            lam: The adjoint (direction of the residual dE/du[lam]).
            theta: Test function of the shape (coordinate) space.

        Returns:
            A linear form in theta equal to the coordinate derivative of
            ``ufl.derivative(self.energy(f), f.u, lam)`` along theta, or None: user-written terms
            (and any term whose integrand reads the rest coordinates directly) are
            differentiated by UFL.
        """
        return None


class _DensityTerm(Term):
    @override
    def energy(self, f: StepFields) -> ufl.Form:
        return self.energy_density(f) * self.measure(f)

    def gradient_density(self, f: StepFields) -> tuple[Expr, dict] | None:
        """The density written through variables of the field gradients, for the shape partial.

        Returns:
            (psi, {field: variable}) with psi equal to :meth:`energy_density` and reading the
            gradient of each field only through its ``ufl.variable``; None if not available.
        """
        return None

    def stresses(self, f: StepFields) -> dict:
        """dpsi/dGrad w written out for some fields w (the others come from ``ufl.diff``).

        A term that gives P_u declares that its density depends on u only through Grad u: the
        residual integrand is then P_u : Grad lambda.
        """
        return {}

    @override
    def shape_partial(
        self, f: StepFields, lam: fem.Function, theta: ufl.Argument
    ) -> ufl.Form | None:
        # the built-in terms only: a subclass may change the density (UFL's derivative then)
        written = self.gradient_density(f) if type(self) in _EXPLICIT_SHAPE_TERMS else None
        if written is None:
            return None
        psi, gradients = written
        if not forms.is_transformable(psi, gradients):  # gradients of the declared fields only
            return None
        stresses = self.stresses(f)
        residual = ufl.inner(stresses[f.u], ufl.grad(lam)) if f.u in stresses else None
        return forms.residual_shape_partial(
            psi, f.u, lam, gradients, theta, self.measure(f), stresses, residual
        )


class ElasticEnergy(_DensityTerm):
    """Strain energy of the bodies using one constitutive law.

    Args:
        law: The constitutive law (a ``forms.StrainEnergy``).
        bodies: Body ids using the law, or None for the whole mesh.
        lame: Callable returning (lambda, mu) UFL expressions from the step fields.
    """

    def __init__(
        self, law: forms.StrainEnergy, bodies: Sequence[int] | None, lame: Callable
    ) -> None:
        self.law, self.bodies, self.lame = law, bodies, lame
        self.name = f"elastic[{law.name}]"
        self.quadratic = law.small_strain
        self.finite_strain = not law.small_strain

    @override
    def energy_density(self, f: StepFields) -> Expr:
        lmbda, mu = self.lame(f)
        return self.law.energy(f.u, lmbda, mu)

    @override
    def magnitude(self, f: StepFields) -> ufl.Form:
        if self.law.small_strain:
            return super().magnitude(f)
        # Near F = I the finite-strain densities cancel addends of size mu (tr F^T F + d)
        # (e.g. Neo-Hookean tr C - d - 2 ln J): their roundoff scales with those addends.
        lmbda, mu = self.lame(f)
        F = forms.deformation_gradient(f.u)
        addends = mu * (ufl.tr(F.T * F) + len(f.u)) + abs(lmbda)
        return (abs(self.energy_density(f)) + addends) * self.measure(f)

    @override
    def measure(self, f: StepFields) -> ufl.Measure:
        return f.dx_strain if self.bodies is None else f.dx_strain(tuple(self.bodies))

    @override
    def gradient_density(self, f: StepFields) -> tuple[Expr, dict] | None:
        if type(self.law) not in _BUILTIN_LAWS:  # a user-written law: UFL's coordinate derivative
            return None
        lmbda, mu = self.lame(f)
        F = ufl.variable(forms.deformation_gradient(f.u))
        return self.law.density(F, lmbda, mu), {f.u: F}


class Inertia(_DensityTerm):
    """rho / (2 (beta dt)^2) |u - u_tilde|^2 (paper eq. 4)."""

    name = "inertia"
    dynamic_only = True
    quadratic = True

    @override
    def energy_density(self, f: StepFields) -> Expr:
        return forms.inertia_energy(f.u, f.u_tilde, f.coefficients["density"], f.beta_dt)

    @override
    def gradient_density(self, f: StepFields) -> tuple[Expr, dict] | None:
        return self.energy_density(f), {}


class Damping(_DensityTerm):
    """Strain-rate viscous damping dt * D((E^i - E^{i-1}) / dt) (paper sec. 8.1)."""

    name = "damping"
    dynamic_only = True

    @override
    def energy_density(self, f: StepFields) -> Expr:
        c = f.coefficients
        return forms.damping_potential(f.u, f.u_prev, f.dt, c["damping_psi"], c["damping_phi"])

    @override
    def measure(self, f: StepFields) -> ufl.Measure:
        return f.dx_strain

    @override
    def gradient_density(self, f: StepFields) -> tuple[Expr, dict] | None:
        c = f.coefficients
        F = ufl.variable(forms.deformation_gradient(f.u))
        F_prev = ufl.variable(forms.deformation_gradient(f.u_prev))
        psi = forms.damping_density(F, F_prev, f.dt, c["damping_psi"], c["damping_phi"])
        return psi, {f.u: F, f.u_prev: F_prev}

    @override
    def stresses(self, f: StepFields) -> dict:
        # the density depends on u only through Grad u: r = P_u : Grad lambda (written out, a
        # third fewer kernel operations than ufl.diff gives)
        c = f.coefficients
        F = forms.deformation_gradient(f.u)
        F_prev = forms.deformation_gradient(f.u_prev)
        P, P_prev = forms.damping_stresses(F, F_prev, f.dt, c["damping_psi"], c["damping_phi"])
        return {f.u: P, f.u_prev: P_prev}


class BodyForce(_DensityTerm):
    """Body force rho g on some or all bodies; ``g`` is the named Constant coefficient."""

    def __init__(self, coefficient: str, bodies: Sequence[int] | None = None) -> None:
        self.coefficient, self.bodies = coefficient, bodies
        self.name = coefficient
        self.quadratic = True

    @override
    def energy_density(self, f: StepFields) -> Expr:
        c = f.coefficients
        return forms.body_force_potential(f.u, c["density"], c[self.coefficient])

    @override
    def measure(self, f: StepFields) -> ufl.Measure:
        return f.dx if self.bodies is None else f.dx(tuple(self.bodies))

    @override
    def gradient_density(self, f: StepFields) -> tuple[Expr, dict] | None:
        return self.energy_density(f), {}


class Traction(_DensityTerm):
    """Dead traction on tagged facets; ``t`` is the named Constant coefficient."""

    def __init__(self, coefficient: str, facet_tag: int) -> None:
        self.coefficient, self.facet_tag = coefficient, facet_tag
        self.name = coefficient
        self.quadratic = True

    @override
    def energy_density(self, f: StepFields) -> Expr:
        return forms.traction_potential(f.u, f.coefficients[self.coefficient])

    @override
    def measure(self, f: StepFields) -> ufl.Measure:
        return f.ds(self.facet_tag)

    @override
    def shape_partial(
        self, f: StepFields, lam: fem.Function, theta: ufl.Argument
    ) -> ufl.Form | None:
        psi = self.energy_density(f)
        if type(self) is not Traction or not forms.is_transformable(psi, ()):
            return None
        return forms.surface_residual_shape_partial(psi, f.u, lam, theta, self.measure(f))


#: The terms whose explicit shape partials are used (exact types, not subclasses).
_EXPLICIT_SHAPE_TERMS = (ElasticEnergy, Inertia, Damping, BodyForce)


class EnergyTerm(Term):
    """A user-written term: ``energy(fields) -> scalar UFL form``.

    Args:
        energy: Callable building the form from :class:`StepFields`.
        name: Name in logs.
        quadratic: Declare the energy quadratic in u (enables Jacobian reuse).
        dynamic_only: Only include the term in BDF steps.
    """

    def __init__(
        self,
        energy: Callable[[StepFields], ufl.Form],
        name: str = "user",
        quadratic: bool = False,
        dynamic_only: bool = False,
    ) -> None:
        self._energy, self.name = energy, name
        self.quadratic, self.dynamic_only = quadratic, dynamic_only

    @override
    def energy(self, f: StepFields) -> ufl.Form:
        return self._energy(f)

    @override
    def magnitude(self, f: StepFields) -> ufl.Form:
        form = self._energy(f)
        return sum(
            abs(i.integrand())
            * ufl.Measure(
                i.integral_type(),
                domain=i.ufl_domain(),
                subdomain_id=i.subdomain_id(),
                subdomain_data=i.subdomain_data(),
                metadata=i.metadata(),
            )
            for i in form.integrals()
        )
