"""Strain-rate viscous damping (paper sec. 8.1, Brown et al. 2018).

The Green strain rate is discretised as Edot = (E(F^i) - E(F^{i-1})) / dt, which only needs
Fdot = (F^i - F^{i-1}) / dt: E^i - E^{i-1} = (Fdot^T F^i + F^{i-1,T} Fdot) dt / 2. With the
dissipation potential D(Edot) = psi Edot:Edot + phi/2 tr(Edot)^2, the term dt * D is a potential in
u^i whose gradient is the force with Piola stress F (2 psi Edot + phi tr(Edot) I).
"""

import ufl
from diffsolids.forms.kinematics import deformation_gradient, green_strain
from ufl.core.expr import Expr

__all__ = ["damping_density", "damping_potential", "damping_stresses", "green_strain_rate"]


def green_strain_rate(u: Expr, u_prev: Expr, dt: Expr | float) -> Expr:
    """Edot = (E(F(u)) - E(F(u_prev))) / dt."""
    return (green_strain(deformation_gradient(u)) - green_strain(deformation_gradient(u_prev))) / dt


def damping_density(
    F: Expr, F_prev: Expr, dt: Expr | float, psi: Expr | float, phi: Expr | float
) -> Expr:
    """The damping potential dt * (psi Edot:Edot + phi/2 tr(Edot)^2) of F^i and F^{i-1}."""
    Edot = (green_strain(F) - green_strain(F_prev)) / dt
    return dt * (psi * ufl.inner(Edot, Edot) + 0.5 * phi * ufl.tr(Edot) ** 2)


def damping_potential(
    u: Expr, u_prev: Expr, dt: Expr | float, psi: Expr | float, phi: Expr | float
) -> Expr:
    """Incremental damping potential dt * (psi Edot:Edot + phi/2 tr(Edot)^2)."""
    return damping_density(deformation_gradient(u), deformation_gradient(u_prev), dt, psi, phi)


def damping_stresses(
    F: Expr, F_prev: Expr, dt: Expr | float, psi: Expr | float, phi: Expr | float
) -> tuple[Expr, Expr]:
    """The stresses of :func:`damping_density`: its derivatives by F^i and F^{i-1}.

    With S = 2 psi Edot + phi tr(Edot) I (the viscous second Piola-Kirchhoff stress) and
    dEdot = sym(F^T dF) / dt: d/dF^i = F^i S and d/dF^{i-1} = -F^{i-1} S.
    """
    Edot = (green_strain(F) - green_strain(F_prev)) / dt
    S = 2 * psi * Edot + phi * ufl.tr(Edot) * ufl.Identity(F.ufl_shape[0])
    return F * S, -F_prev * S
