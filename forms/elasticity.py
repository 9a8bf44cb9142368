"""Strain energy densities and stresses.

Every energy takes the displacement ``u`` and Lamé parameters; parameters may be any UFL
expression (constants, DG0/CG1 fields, or expressions of Young's modulus and Poisson's ratio),
so derivatives with respect to them come from ``ufl.derivative``.
"""

import ufl
from diffsolids.forms.kinematics import deformation_gradient, green_strain, small_strain
from ufl.core.expr import Expr

__all__ = [
    "STRAIN_ENERGIES",
    "LinearElasticEnergy",
    "NeoHookeanEnergy",
    "StVenantKirchhoffEnergy",
    "StrainEnergy",
    "cauchy_stress",
    "first_piola_kirchhoff",
    "lame_parameters",
    "linear_energy",
    "neo_hookean_energy",
    "plane_strain_normal_stress",
    "st_venant_kirchhoff_energy",
    "strain_energy",
    "strain_law",
    "von_mises",
    "von_mises_tensor",
]


def lame_parameters(
    E: Expr | float, nu: Expr | float, plane_stress: bool = False
) -> tuple[Expr | float, Expr | float]:
    """Lamé parameters (lambda, mu) from Young's modulus and Poisson's ratio.

    Plane stress uses the effective 2D first parameter lambda = nu E / (1 - nu^2).
    """
    mu = E / (2 * (1 + nu))
    if plane_stress:
        return E * nu / (1 - nu * nu), mu
    return E * nu / ((1 + nu) * (1 - 2 * nu)), mu


class StrainEnergy:
    """A hyperelastic constitutive law: a strain energy density psi(F; lambda, mu).

    A new law is one subclass that writes :meth:`density` as a function of the deformation
    gradient F; the first Piola-Kirchhoff stress (``ufl.diff``), the Cauchy stress P F^T / J and
    the plane-strain out-of-plane stress follow from it. Subclasses may write a stress out
    where that compiles to fewer operations (the built-in finite-strain laws do).

    Attributes:
        name: Key of the law in :data:`STRAIN_ENERGIES` (and in reports).
        small_strain: The energy is a quadratic function of grad u (linear elasticity): its
            Hessian does not depend on u and it has no det F (elements cannot invert).
    """

    name: str = "strain energy"
    small_strain: bool = False

    def density(self, F: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:
        """psi(F; lambda, mu)."""
        raise NotImplementedError(f"{type(self).__name__}.density")

    def energy(self, u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:
        """Strain energy density at the displacement ``u``."""
        return self.density(deformation_gradient(u), lmbda, mu)

    def first_piola_kirchhoff(self, u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:
        """P = dpsi/dF (for a small-strain law: the Cauchy stress C:eps)."""
        F = ufl.variable(deformation_gradient(u))
        return ufl.diff(self.density(F, lmbda, mu), F)

    def cauchy_stress(self, u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:
        """Sigma = P F^T / J (the small-strain stress for a small-strain law)."""
        P = self.first_piola_kirchhoff(u, lmbda, mu)
        if self.small_strain:
            return P
        F = deformation_gradient(u)
        return P * F.T / ufl.det(F)

    def plane_strain_normal_stress(self, u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:
        """Out-of-plane Cauchy stress sigma_zz of a plane-strain (F_zz = 1) state.

        The law's 3D density at F = [[F_2d, 0], [0, 1]]: sigma_zz = P_zz / J.
        """
        F2 = deformation_gradient(u)
        F = ufl.variable(
            ufl.as_matrix([[F2[0, 0], F2[0, 1], 0], [F2[1, 0], F2[1, 1], 0], [0, 0, 1]])
        )
        P = ufl.diff(self.density(F, lmbda, mu), F)
        return P[2, 2] if self.small_strain else P[2, 2] / ufl.det(F2)

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class LinearElasticEnergy(StrainEnergy):
    """Small-strain energy mu eps:eps + lambda/2 tr(eps)^2, eps = sym(F - I)."""

    name = "linear"
    small_strain = True

    def density(self, F: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:  # noqa: D102
        eps = ufl.sym(F - ufl.Identity(F.ufl_shape[0]))
        return mu * ufl.inner(eps, eps) + 0.5 * lmbda * ufl.tr(eps) ** 2

    def energy(self, u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:  # noqa: D102 - the same density of grad u, written directly
        eps = small_strain(u)
        return mu * ufl.inner(eps, eps) + 0.5 * lmbda * ufl.tr(eps) ** 2

    def plane_strain_normal_stress(self, u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:  # noqa: D102
        return lmbda * ufl.tr(small_strain(u))


class StVenantKirchhoffEnergy(StrainEnergy):
    """St. Venant-Kirchhoff energy mu E:E + lambda/2 tr(E)^2 of the Green strain."""

    name = "st_venant_kirchhoff"

    def density(self, F: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:  # noqa: D102
        E = green_strain(F)
        return mu * ufl.inner(E, E) + 0.5 * lmbda * ufl.tr(E) ** 2

    def cauchy_stress(self, u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:
        """F S F^T / J with S = lambda tr(E) I + 2 mu E (no inverse of F: fewer operations)."""
        F = deformation_gradient(u)
        E = green_strain(F)
        Id = ufl.Identity(F.ufl_shape[0])
        return F * (lmbda * ufl.tr(E) * Id + 2 * mu * E) * F.T / ufl.det(F)

    def plane_strain_normal_stress(self, u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:  # noqa: D102
        F = deformation_gradient(u)
        return lmbda * ufl.tr(green_strain(F)) / ufl.det(F)


class NeoHookeanEnergy(StrainEnergy):
    """Compressible Neo-Hookean energy mu/2 (tr F^T F - d - 2 ln J) + lambda/2 (ln J)^2."""

    name = "neo_hookean"

    def density(self, F: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:  # noqa: D102
        d = F.ufl_shape[0]
        lnJ = ufl.ln(ufl.det(F))
        return 0.5 * mu * (ufl.tr(F.T * F) - d - 2 * lnJ) + 0.5 * lmbda * lnJ**2

    def cauchy_stress(self, u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:
        """(mu (B - I) + lambda ln(J) I) / J with B = F F^T (no inverse of F)."""
        F = deformation_gradient(u)
        J = ufl.det(F)
        Id = ufl.Identity(F.ufl_shape[0])
        return (mu * (F * F.T - Id) + lmbda * ufl.ln(J) * Id) / J

    def plane_strain_normal_stress(self, u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:  # noqa: D102
        J = ufl.det(deformation_gradient(u))
        return lmbda * ufl.ln(J) / J


#: The built-in laws by name (``Material("neo_hookean", ...)`` resolves through it).
STRAIN_ENERGIES: dict[str, StrainEnergy] = {
    law.name: law for law in (LinearElasticEnergy(), StVenantKirchhoffEnergy(), NeoHookeanEnergy())
}


def strain_law(law: "str | StrainEnergy") -> StrainEnergy:
    """The law object of a name in :data:`STRAIN_ENERGIES`, or the law itself.

    Raises:
        KeyError: An unknown name.
    """
    if isinstance(law, StrainEnergy):
        return law
    if law not in STRAIN_ENERGIES:
        raise KeyError(f"unknown constitutive law {law!r}; choose from {sorted(STRAIN_ENERGIES)}")
    return STRAIN_ENERGIES[law]


def linear_energy(u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:
    """Small-strain energy mu eps:eps + lambda/2 tr(eps)^2."""
    return STRAIN_ENERGIES["linear"].energy(u, lmbda, mu)


def st_venant_kirchhoff_energy(u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:
    """St. Venant-Kirchhoff energy mu E:E + lambda/2 tr(E)^2 of the Green strain."""
    return STRAIN_ENERGIES["st_venant_kirchhoff"].energy(u, lmbda, mu)


def neo_hookean_energy(u: Expr, lmbda: Expr | float, mu: Expr | float) -> Expr:
    """Neo-Hookean energy mu/2 (tr F^T F - d - 2 ln J) + lambda/2 (ln J)^2."""
    return STRAIN_ENERGIES["neo_hookean"].energy(u, lmbda, mu)


def strain_energy(
    law: "str | StrainEnergy", u: Expr, lmbda: Expr | float, mu: Expr | float
) -> Expr:
    """Strain energy density of a law (object or name)."""
    return strain_law(law).energy(u, lmbda, mu)


def first_piola_kirchhoff(
    law: "str | StrainEnergy", u: Expr, lmbda: Expr | float, mu: Expr | float
) -> Expr:
    """First Piola-Kirchhoff stress dpsi/dF of a law (for "linear": the Cauchy stress C:eps)."""
    return strain_law(law).first_piola_kirchhoff(u, lmbda, mu)


def cauchy_stress(
    law: "str | StrainEnergy", u: Expr, lmbda: Expr | float, mu: Expr | float
) -> Expr:
    """Cauchy stress sigma = P F^T / J of a law (the small-strain stress for "linear")."""
    return strain_law(law).cauchy_stress(u, lmbda, mu)


def plane_strain_normal_stress(
    law: "str | StrainEnergy", u: Expr, lmbda: Expr | float, mu: Expr | float
) -> Expr:
    """Out-of-plane Cauchy stress sigma_zz of a plane-strain (F_zz = 1) state of a law."""
    return strain_law(law).plane_strain_normal_stress(u, lmbda, mu)


def von_mises_tensor(sigma: Expr, sigma_zz: Expr | float = 0.0) -> Expr:
    """sqrt(3/2) dev(sigma), a 3x3 tensor whose Frobenius norm is the von Mises stress.

    A 2x2 (plane) ``sigma`` is completed by the out-of-plane normal stress ``sigma_zz`` as in
    :func:`von_mises`. Stress objectives (L_p norms, soft bounds) of the von Mises stress take
    the norm of this tensor.
    """
    if sigma.ufl_shape[0] == 2:
        sigma = ufl.as_matrix(
            [[sigma[0, 0], sigma[0, 1], 0], [sigma[1, 0], sigma[1, 1], 0], [0, 0, sigma_zz]]
        )
    return float(1.5**0.5) * ufl.dev(sigma)


def von_mises(sigma: Expr, sigma_zz: Expr | float = 0.0) -> Expr:
    """Von Mises equivalent stress sqrt(3/2 s:s), s the deviator of the 3x3 Cauchy stress.

    A 2x2 (plane) ``sigma`` is completed by the out-of-plane normal stress ``sigma_zz``: 0 for
    plane stress, :func:`plane_strain_normal_stress` for plane strain.
    """
    if sigma.ufl_shape[0] == 3:
        s = ufl.dev(sigma)
        return ufl.sqrt(1.5 * ufl.inner(s, s))
    trace = ufl.tr(sigma) + sigma_zz
    return ufl.sqrt(1.5 * (ufl.inner(sigma, sigma) + sigma_zz**2 - trace**2 / 3))
