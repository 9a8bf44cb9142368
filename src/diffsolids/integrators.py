"""Time discretisations: static (load steps) and BDF of order 1 to 6 with start-up steps.

BDF_m (paper eq. 4): u^i + sum_{j=1}^{m_i} alpha_j u^{i-j} = beta dt v^i, and the same relation
between velocities and accelerations, with m_i = min(i, m) (lower-order start-up steps).
"""

import math
import numbers
from abc import ABC, abstractmethod
from dataclasses import dataclass
from fractions import Fraction
from typing import override

from diffsolids.errors import ParameterError

__all__ = ["BDF", "Integrator", "Static", "StepCoefficients", "bdf_coefficients"]


def bdf_coefficients(order: int) -> tuple[list[float], float]:
    """(alpha_1..alpha_m, beta) of BDF_m in the form u^i + sum alpha_j u^{i-j} = beta dt v^i.

    From the derivative of the interpolating polynomial at t_i: dt u'(t_i) =
    sum_{j=0}^m c_j u^{i-j} with c_0 = sum_{k=1}^m 1/k and c_j = (-1)^j binom(m, j) / j.
    """
    if not isinstance(order, int) or not 1 <= order <= 6:
        raise ParameterError(f"BDF order {order} outside 1..6")
    c0 = sum(Fraction(1, k) for k in range(1, order + 1))
    alphas = [Fraction((-1) ** j * math.comb(order, j), j) / c0 for j in range(1, order + 1)]
    return [float(a) for a in alphas], float(1 / c0)


@dataclass(frozen=True)
class StepCoefficients:
    """Coefficients of step i: order m_i, alpha_1..alpha_{m_i}, beta and dt."""

    order: int
    alpha: tuple[float, ...]
    beta: float
    dt: float

    @property
    def beta_dt(self) -> float:
        """Beta * dt."""
        return self.beta * self.dt


class Integrator(ABC):
    """A sequence of steps, each minimising an incremental potential.

    Attributes:
        dt: Step size (time, or load parameter increment for Static).
        num_steps: Number of steps N; the trajectory holds u^0..u^N.
        dynamic: Whether steps carry inertia (and damping).
    """

    dynamic: bool = False

    def __init__(self, dt: float, num_steps: int):
        if not (isinstance(dt, numbers.Real) and math.isfinite(dt)) or dt <= 0:
            raise ParameterError(f"time step dt = {dt} must be a positive finite number")
        if not isinstance(num_steps, int) or num_steps < 1:
            raise ParameterError(f"num_steps = {num_steps} must be a positive integer")
        self.dt = float(dt)
        self.num_steps = num_steps

    def time(self, step: int) -> float:
        """Time (or load parameter) of step ``step``."""
        return step * self.dt

    @abstractmethod
    def coefficients(self, step: int) -> StepCoefficients:
        """Coefficients of step ``step`` (1-based)."""


class Static(Integrator):
    """Static equilibrium, optionally in several load steps (quasi-static).

    Step i depends on step i-1 only through lagged quantities (friction); rates used by such
    terms are first-order differences over the load step: v^i = (u^i - u^{i-1}) / dt.
    """

    dynamic = False

    def __init__(self, num_steps: int = 1, dt: float = 1.0):
        super().__init__(dt, num_steps)

    @override
    def coefficients(self, step: int) -> StepCoefficients:
        return StepCoefficients(1, (-1.0,), 1.0, self.dt)


class BDF(Integrator):
    """Backward differentiation formula of order 1..6 (step i uses order min(i, order)).

    Args:
        order: BDF order m.
        dt: Time-step size.
        num_steps: Number of steps (give this or ``t_end``).
        t_end: Final time (num_steps = round(t_end / dt)).
    """

    dynamic = True

    def __init__(
        self, order: int, dt: float, num_steps: int | None = None, t_end: float | None = None
    ):
        bdf_coefficients(order)  # validates the order
        if num_steps is None:
            if t_end is None or not math.isfinite(t_end) or t_end <= 0:
                raise ParameterError("give num_steps or a positive finite t_end")
            if dt <= 0:
                raise ParameterError(f"time step dt = {dt} must be a positive finite number")
            num_steps = max(1, round(t_end / dt))
        super().__init__(dt, num_steps)
        self.order = order

    @override
    def coefficients(self, step: int) -> StepCoefficients:
        m = min(step, self.order)
        alpha, beta = bdf_coefficients(m)
        return StepCoefficients(m, tuple(alpha), beta, self.dt)
