"""Potentials of external loads (conservative, dead loads)."""

import ufl
from ufl.core.expr import Expr

__all__ = ["body_force_potential", "traction_potential"]


def body_force_potential(u: Expr, density: Expr | float, acceleration: Expr) -> Expr:
    """-rho g . u for a body-force acceleration g (e.g. gravity)."""
    return -density * ufl.dot(acceleration, u)


def traction_potential(u: Expr, traction: Expr) -> Expr:
    """-t . u for a dead traction t (force per reference area)."""
    return -ufl.dot(traction, u)
