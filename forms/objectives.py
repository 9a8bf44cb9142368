"""Integrands of objective terms (paper sec. 9.2).

Pure UFL: every function takes UFL expressions (displacement, rest coordinates, stresses,
parameters) and returns a scalar UFL expression to be multiplied by a measure. Their derivatives
with respect to the state, the shape and the parameters come from ``ufl.derivative``.
"""

from collections.abc import Callable

import ufl
from ufl.core.expr import Expr

__all__ = [
    "deformed_position",
    "graph_misfit",
    "log_barrier",
    "penalty",
    "stress_norm",
    "stress_norm_power",
    "stress_penalty",
    "weighted_squared_distance",
]


def deformed_position(X: Expr, u: Expr) -> Expr:
    """Deformed position x^d = X + u of the material point at rest position X."""
    return X + u


def stress_norm(sigma: Expr) -> Expr:
    """Frobenius norm ||sigma||_F."""
    return ufl.sqrt(ufl.inner(sigma, sigma))


def stress_norm_power(sigma: Expr, p: float) -> Expr:
    """||sigma||_F^p, the integrand of the L_p norm of stress (eq. 30).

    Written as (sigma : sigma)^(p / 2) so that its derivative p ||sigma||^(p-2) sigma is finite
    at zero stress for p >= 2.
    """
    s2 = ufl.inner(sigma, sigma)
    return s2 if p == 2 else s2 ** (0.5 * p)


def penalty(z: Expr) -> Expr:
    """Quadratic penalty phi(z) = z^2 for z > 0, 0 otherwise (eqs. 35, 36; C^1 in z)."""
    return ufl.conditional(ufl.gt(z, 0), z * z, 0)


def stress_penalty(sigma: Expr, bound: Expr | float) -> Expr:
    """phi(||sigma||_F - s_t), the soft upper bound on stress (eq. 36)."""
    return penalty(stress_norm(sigma) - bound)


def weighted_squared_distance(x: Expr, target: Expr, weight: Expr | float = 1.0) -> Expr:
    """Weighted squared distance w ||x - x^trg||^2 (integrand of eq. 31)."""
    d = x - target
    return weight * ufl.dot(d, d)


def graph_misfit(x: Expr, function: Callable[..., Expr | float], axis: int = -1) -> Expr:
    """(x_axis - f(other coordinates))^2: distance of a point from the graph of f.

    In 2D with ``axis=-1``: (y - f(x))^2; in 3D: (z - f(x, y))^2. ``function`` takes the
    remaining coordinates as UFL scalars, e.g. ``lambda x: 0.7 * ufl.sin(x)``.
    """
    d = x.ufl_shape[0]
    axis = axis % d
    others = [x[k] for k in range(d) if k != axis]
    r = x[axis] - function(*others)
    return r * r


def log_barrier(z: Expr, z_hat: Expr | float) -> Expr:
    """IPC's clamped log barrier b(z) = -(z - z_hat)^2 log(z / z_hat) for z < z_hat, else 0.

    Keeps a quantity z positive: b grows without bound as z -> 0+, vanishes with its first two
    derivatives at z = z_hat (so it is C^2 in z) and is not defined for z <= 0 (the value is then
    NaN, which the objective reports with the step where it happened). ``z_hat`` > 0 is the
    activation distance (IPC's d-hat).
    """
    return ufl.conditional(ufl.lt(z, z_hat), -((z - z_hat) ** 2) * ufl.ln(z / z_hat), 0)
