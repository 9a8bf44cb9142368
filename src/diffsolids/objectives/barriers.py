"""Barrier objectives: keep a quantity above a threshold on the rest or deformed configuration.

Each uses IPC's clamped log barrier b(z; z_hat) = -(z - z_hat)^2 log(z / z_hat) for
0 < z < z_hat, 0 beyond (:func:`diffsolids.forms.objectives.log_barrier`): zero while the
quantity keeps a margin z_hat, growing without bound as it approaches the threshold. Once the
threshold is crossed the value is not finite and the objective refuses it naming the step, so a
line search steps back. These are the barriers expressible as UFL integrands or step series:

* :func:`sdf_barrier`: the signed distance sdf(x) of the surface (or volume) from an analytic
  obstacle (a plane, a sphere, any UFL function), at the rest positions (a design constraint)
  or the deformed ones (PolyFEM's ``collision_barrier`` / ``deformed_collision_barrier``
  against analytic geometry).
* :func:`inversion_barrier`: det F (deformed) or the rest cells' volume ratio to the initial
  design (rest) above a threshold (no element inverts or collapses).
* :func:`series_barrier`: any per-step series above a threshold.

The IPC barrier between the bodies' own surface primitives (PolyFEM's collision barriers
proper) needs the contact module's distance kernels and is not one of these.
"""

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import ufl
from dolfinx import fem

from diffsolids import forms
from diffsolids.errors import ParameterError
from diffsolids.forms.objectives import log_barrier
from diffsolids.objectives.functional import Integral, Objective, Series, final_value
from diffsolids.objectives.library import Tags, _volume_measure
from diffsolids.objectives.targets import _measure

if TYPE_CHECKING:
    from diffsolids.model import Model, StepFields

__all__ = ["inversion_barrier", "scalar_log_barrier", "sdf_barrier", "series_barrier"]


def _check_margin(z_hat: float, what: str) -> float:
    z_hat = float(z_hat)
    if not (np.isfinite(z_hat) and z_hat > 0):
        raise ParameterError(f"{what}: the barrier's activation distance must be > 0, got {z_hat}")
    return z_hat


def scalar_log_barrier(z: np.ndarray, z_hat: float) -> np.ndarray:
    """b(z; z_hat) of numbers (NaN for z <= 0), as :func:`~diffsolids.forms.log_barrier`."""
    z = np.asarray(z, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        inside = -((z - z_hat) ** 2) * np.log(z / z_hat)
    return np.where(z < z_hat, np.where(z > 0, inside, np.nan), 0.0)


def _scalar_log_barrier_derivative(z: np.ndarray, z_hat: float) -> np.ndarray:
    z = np.asarray(z, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        inside = -2.0 * (z - z_hat) * np.log(z / z_hat) - (z - z_hat) ** 2 / z
    return np.where(z < z_hat, np.where(z > 0, inside, np.nan), 0.0)


def _barrier_objective(
    model: "Model", form: Callable, deformed: bool, deformed_name: str, rest_name: str
) -> Series | Objective:
    """A per-step Integral of ``form`` (deformed) or its value at the rest design (a scalar).

    ``form`` is built once here on the model's fields, so bad user input fails at once.
    """
    form(model.fields)
    if deformed:
        return Integral(form, deformed_name)
    return final_value(Integral(form, rest_name))


def sdf_barrier(
    model: "Model",
    sdf: Callable,
    z_hat: float,
    facets: Tags = None,
    bodies: Tags = None,
    deformed: bool = True,
) -> Series | Objective:
    """Int b(sdf(x); z_hat) over a surface or volume: keeps sdf(x) > 0.

    Args:
        model: The Model.
        sdf: Signed distance from the obstacle, positive outside (UFL vector -> UFL scalar),
            e.g. a floor at height h: ``lambda x: x[-1] - h``.
        z_hat: Distance at which the barrier starts to act.
        facets: Facet tag(s) of the surface (default: the volume of ``bodies``).
        bodies: Body tag(s) (default: all, when no facets).
        deformed: True: a Series at the deformed positions X + u^i; False: the rest positions
            X, a scalar Objective (a constraint on the design).
    """
    z_hat = _check_margin(z_hat, "sdf_barrier")

    def form(f: "StepFields") -> ufl.Form:
        x = forms.deformed_position(f.X, f.u) if deformed else f.X
        d = sdf(x)
        if not isinstance(d, ufl.core.expr.Expr) or d.ufl_shape != ():
            raise ParameterError("sdf must map a UFL position vector to a UFL scalar")
        return log_barrier(d, z_hat) * _measure(model, f, facets, bodies)

    return _barrier_objective(model, form, deformed, "deformed sdf barrier", "rest sdf barrier")


def inversion_barrier(
    model: "Model",
    threshold: float,
    z_hat: float,
    bodies: Tags = None,
    deformed: bool = True,
) -> Series | Objective:
    """Int b(J - threshold; z_hat) dx: keeps a volume ratio J above ``threshold``.

    Deformed: J = det F of the state (a Series per step), e.g. threshold 0.2 against
    squashed elements. Rest: J = |det J(X)| / |det J(X^0)|, the cell volumes of the current
    design relative to the design when the barrier was made (a scalar Objective), against
    collapsing or inverted cells in shape optimisation (PolyFEM's ``min_jacobian`` as a
    barrier).

    Args:
        model: The Model.
        threshold: The ratio J must stay above (0 <= threshold < 1 for a design that starts
            admissible).
        z_hat: The margin above the threshold where the barrier acts.
        bodies: Restrict to these bodies (default: all).
        deformed: det F per step (True) or the rest cells' volume ratio (False).
    """
    z_hat = _check_margin(z_hat, "inversion_barrier")
    if not np.isfinite(threshold):
        raise ParameterError(f"inversion_barrier: threshold {threshold} is not finite")
    mesh = model.domain.mesh
    detJ = abs(ufl.JacobianDeterminant(mesh))
    initial = None
    if not deformed:
        initial = fem.Function(fem.functionspace(mesh, ("DG", 0)), name="initial cell scale")
        initial.interpolate(
            fem.Expression(detJ, initial.function_space.element.interpolation_points)
        )

    def form(f: "StepFields") -> ufl.Form:
        J = ufl.det(forms.deformation_gradient(f.u)) if deformed else detJ / initial
        return log_barrier(J - float(threshold), z_hat) * _volume_measure(model, f, bodies)

    return _barrier_objective(model, form, deformed, "inversion barrier", "rest inversion barrier")


def series_barrier(series: Series, threshold: float, z_hat: float) -> Series:
    """b(s_i - threshold; z_hat) elementwise: keeps a per-step series above ``threshold``.

    E.g. a centre-of-mass height above a floor: ``series_barrier(-height_objective(model),
    0.1, 0.05)``; reduce it with time weights.
    """
    z_hat = _check_margin(z_hat, "series_barrier")
    c = float(threshold)
    return series.apply(
        lambda s: scalar_log_barrier(s - c, z_hat),
        lambda s: _scalar_log_barrier_derivative(s - c, z_hat),
        "barrier",
    )
