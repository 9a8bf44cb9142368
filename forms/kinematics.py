"""Kinematic quantities of a displacement field."""

import ufl
from ufl.core.expr import Expr

__all__ = ["deformation_gradient", "green_strain", "small_strain"]


def deformation_gradient(u: Expr) -> Expr:
    """F = I + grad(u)."""
    return ufl.Identity(len(u)) + ufl.grad(u)


def green_strain(F: Expr) -> Expr:
    """Green-Lagrange strain E = (F^T F - I) / 2."""
    return 0.5 * (F.T * F - ufl.Identity(F.ufl_shape[0]))


def small_strain(u: Expr) -> Expr:
    """Infinitesimal strain sym(grad u)."""
    return ufl.sym(ufl.grad(u))
