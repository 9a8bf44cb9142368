"""Inertia part of a BDF incremental potential (paper eq. 4).

With BDF of order m, u^i + sum_j alpha_j u^{i-j} = beta dt v^i and
M (v^i + sum_j alpha_j v^{i-j}) = beta dt h(u^i). Eliminating v^i gives
M (u^i - u_tilde) / (beta dt)^2 = h(u^i) with the predictor
u_tilde = -sum_j alpha_j u^{i-j} - beta dt sum_j alpha_j v^{i-j}; its potential is below.
"""

import ufl
from ufl.core.expr import Expr

__all__ = ["inertia_energy"]


def inertia_energy(u: Expr, u_tilde: Expr, density: Expr | float, beta_dt: Expr | float) -> Expr:
    """Rho / (2 (beta dt)^2) |u - u_tilde|^2."""
    return 0.5 * density / beta_dt**2 * ufl.dot(u - u_tilde, u - u_tilde)
