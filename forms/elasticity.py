"""Strain energy densities and stresses.

Every energy takes the displacement ``u`` and Lamé parameters; parameters may be any UFL
expression (constants, DG0/CG1 fields, or expressions of Young's modulus and Poisson's ratio),
so derivatives with respect to them come from ``ufl.derivative``.
"""

from collections.abc import Callable

import ufl
from diffsolids.forms.kinematics import deformation_gradient, green_strain, small_strain

__all__ = [
    "STRAIN_ENERGIES",
    "cauchy_stress",
    "first_piola_kirchhoff",
    "lame_parameters",
    "linear_energy",
    "neo_hookean_energy",
    "plane_strain_normal_stress",
    "st_venant_kirchhoff_energy",
    "strain_energy",
    "von_mises",
    "von_mises_tensor",
]


def lame_parameters(E, nu, plane_stress: bool = False):
    """Lamé parameters (lambda, mu) from Young's modulus and Poisson's ratio.

    Plane stress uses the effective 2D first parameter lambda = nu E / (1 - nu^2).
    """
    mu = E / (2 * (1 + nu))
    if plane_stress:
        return E * nu / (1 - nu * nu), mu
    return E * nu / ((1 + nu) * (1 - 2 * nu)), mu


def linear_energy(u, lmbda, mu):
    """Small-strain energy mu eps:eps + lambda/2 tr(eps)^2."""
    eps = small_strain(u)
    return mu * ufl.inner(eps, eps) + 0.5 * lmbda * ufl.tr(eps) ** 2


def st_venant_kirchhoff_energy(u, lmbda, mu):
    """St. Venant-Kirchhoff energy mu E:E + lambda/2 tr(E)^2 of the Green strain."""
    E = green_strain(deformation_gradient(u))
    return mu * ufl.inner(E, E) + 0.5 * lmbda * ufl.tr(E) ** 2


def neo_hookean_energy(u, lmbda, mu):
    """Neo-Hookean energy mu/2 (tr F^T F - d - 2 ln J) + lambda/2 (ln J)^2."""
    F = deformation_gradient(u)
    d = F.ufl_shape[0]
    lnJ = ufl.ln(ufl.det(F))
    return 0.5 * mu * (ufl.tr(F.T * F) - d - 2 * lnJ) + 0.5 * lmbda * lnJ**2


STRAIN_ENERGIES: dict[str, Callable] = {
    "linear": linear_energy,
    "st_venant_kirchhoff": st_venant_kirchhoff_energy,
    "neo_hookean": neo_hookean_energy,
}


def strain_energy(name: str, u, lmbda, mu):
    """Strain energy density of the constitutive law ``name`` (a key of STRAIN_ENERGIES)."""
    return STRAIN_ENERGIES[name](u, lmbda, mu)


def first_piola_kirchhoff(name: str, u, lmbda, mu):
    """First Piola-Kirchhoff stress dpsi/dF (for "linear": the Cauchy stress C:eps)."""
    F = ufl.variable(deformation_gradient(u))
    # Express every energy as a function of F so that ufl.diff applies uniformly.
    grad_u = F - ufl.Identity(F.ufl_shape[0])
    eps = ufl.sym(grad_u)
    if name == "linear":
        psi = mu * ufl.inner(eps, eps) + 0.5 * lmbda * ufl.tr(eps) ** 2
    elif name == "st_venant_kirchhoff":
        E = green_strain(F)
        psi = mu * ufl.inner(E, E) + 0.5 * lmbda * ufl.tr(E) ** 2
    else:
        lnJ = ufl.ln(ufl.det(F))
        d = F.ufl_shape[0]
        psi = 0.5 * mu * (ufl.tr(F.T * F) - d - 2 * lnJ) + 0.5 * lmbda * lnJ**2
    return ufl.diff(psi, F)


def cauchy_stress(name: str, u, lmbda, mu):
    """Cauchy stress sigma = P F^T / J (the small-strain stress for "linear").

    Written out for the finite-strain laws (Neo-Hookean: (mu (B - I) + lambda ln(J) I) / J with
    B = F F^T; St. Venant-Kirchhoff: F S F^T / J with S = lambda tr(E) I + 2 mu E), which equals
    P F^T / J without the inverse of F that dpsi/dF carries: the stress objectives and their
    derivatives compile to about half the operations.
    """
    if name == "linear":
        return first_piola_kirchhoff(name, u, lmbda, mu)
    F = deformation_gradient(u)
    J = ufl.det(F)
    Id = ufl.Identity(F.ufl_shape[0])
    if name == "st_venant_kirchhoff":
        E = green_strain(F)
        return F * (lmbda * ufl.tr(E) * Id + 2 * mu * E) * F.T / J
    return (mu * (F * F.T - Id) + lmbda * ufl.ln(J) * Id) / J  # Neo-Hookean


def plane_strain_normal_stress(name: str, u, lmbda, mu):
    """Out-of-plane Cauchy stress sigma_zz of a plane-strain (F_zz = 1) state.

    linear: lambda tr(eps); St. Venant-Kirchhoff: lambda tr(E) / J; Neo-Hookean:
    lambda ln(J) / J (P_zz = mu (F_zz - 1 / F_zz) + lambda ln(J) / F_zz with F_zz = 1).
    """
    if name == "linear":
        return lmbda * ufl.tr(small_strain(u))
    F = deformation_gradient(u)
    J = ufl.det(F)
    if name == "st_venant_kirchhoff":
        return lmbda * ufl.tr(green_strain(F)) / J
    return lmbda * ufl.ln(J) / J


def von_mises_tensor(sigma, sigma_zz=0.0):
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


def von_mises(sigma, sigma_zz=0.0):
    """Von Mises equivalent stress sqrt(3/2 s:s), s the deviator of the 3x3 Cauchy stress.

    A 2x2 (plane) ``sigma`` is completed by the out-of-plane normal stress ``sigma_zz``: 0 for
    plane stress, :func:`plane_strain_normal_stress` for plane strain.
    """
    if sigma.ufl_shape[0] == 3:
        s = ufl.dev(sigma)
        return ufl.sqrt(1.5 * ufl.inner(s, s))
    trace = ufl.tr(sigma) + sigma_zz
    return ufl.sqrt(1.5 * (ufl.inner(sigma, sigma) + sigma_zz**2 - trace**2 / 3))
