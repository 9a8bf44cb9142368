"""Time discretisations: static (load steps) and BDF of order 1 to 6 with start-up steps.

BDF_m (paper eq. 4): u^i + sum_{j=1}^{m_i} alpha_j u^{i-j} = beta dt v^i, and the same relation
between velocities and accelerations, with m_i = min(i, m) (lower-order start-up steps).

Everything a step's time discretisation means is held by one object, the :class:`TimeStep` of
step i (``integrator.step(i)``): its coefficients, the history fields it sets for the Newton
solve and for the objective (``u_prev``, the predictor ``u_tilde``, ``dt``, ``beta dt``), the
velocity v^i it assigns to the converged u^i, and the transposes (vector-Jacobian products) of
the predictor and the velocity that the backward sweep pushes adjoints through. A static step
is the same object with no predictor history (u_tilde = 0, nothing to transpose) and the
first-order difference v^i = (u^i - u^{i-1}) / dt as its rate.
"""

import math
import numbers
from abc import ABC, abstractmethod
from collections.abc import MutableMapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Protocol, override

import numpy as np

from diffsolids.errors import ParameterError

__all__ = ["BDF", "Integrator", "Static", "StepFieldTargets", "TimeStep", "bdf_coefficients"]


class _ValueHolder(Protocol):
    value: Any


class _ArrayHolder(Protocol):
    @property
    def x(self) -> Any: ...


class StepFieldTargets(Protocol):
    """What :meth:`TimeStep.set_fields` writes (met by :class:`diffsolids.model.StepFields`)."""

    dt: _ValueHolder
    beta_dt: _ValueHolder
    u_prev: _ArrayHolder
    u_tilde: _ArrayHolder


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
class TimeStep:
    """The time discretisation of one step i, shared by the forward solve and the adjoint.

    The velocity (rate) of the step (paper eq. 4):

        v^i = (u^i + sum_{j=1}^{m_i} alpha_j u^{i-j}) / (beta dt),

    and, for inertial (BDF) steps, the predictor the inertia term reads (paper eq. 4, the
    velocity relation applied to v^{i-j}):

        u_tilde^i = -sum_{j=1}^{m_i} alpha_j (u^{i-j} + beta dt v^{i-j}),

    so that (u^i - u_tilde^i) / (beta dt)^2 is the BDF acceleration. A static step has
    ``inertial=False``: no predictor history (u_tilde^i = 0, its transpose pushes nothing) and
    the first-order difference alpha = (-1,), beta = 1 as the rate of lagged terms.

    The methods take the states as sequences indexed by the absolute step (``traj.u``,
    ``traj.v`` of a Trajectory or of a checkpointing view); they read u^{i-j}, v^{i-j} for
    j = 1..``order`` only.

    Attributes:
        order: The order m_i used by the step (start-up steps use lower orders).
        alpha: alpha_1..alpha_{m_i}.
        beta: beta of the order m_i.
        dt: The step size.
        index: The step i (1-based; 0 for coefficients not attached to a step).
        time: t_i (the load parameter of a static step).
        inertial: Whether the step has inertia, i.e. a predictor (BDF) or not (static).
    """

    order: int
    alpha: tuple[float, ...]
    beta: float
    dt: float
    index: int = 0
    time: float = 0.0
    inertial: bool = False

    @property
    def beta_dt(self) -> float:
        """Beta * dt."""
        return self.beta * self.dt

    @property
    def lags(self) -> range:
        """The j = 1..m_i of the earlier states u^{i-j}, v^{i-j} the step reads."""
        return range(1, self.order + 1)

    # -- forward --------------------------------------------------------------------------
    def predictor(
        self, u: Sequence[np.ndarray], v: Sequence[np.ndarray], out: np.ndarray | None = None
    ) -> np.ndarray:
        """u_tilde^i = -sum_j alpha_j (u^{i-j} + beta dt v^{i-j}) (zeros for a static step).

        Args:
            u: Displacements by step (u[i - j] is read for j in :attr:`lags`).
            v: Velocities by step.
            out: Array to write into (default: a new one).
        """
        i = self.index
        if out is None:
            out = np.zeros_like(u[i - 1])
        else:
            out[:] = 0.0
        if self.inertial:
            for j, a in enumerate(self.alpha, start=1):
                out -= a * (u[i - j] + self.beta_dt * v[i - j])
        return out

    def velocity(self, u_i: np.ndarray, u: Sequence[np.ndarray]) -> np.ndarray:
        """v^i = (u^i + sum_j alpha_j u^{i-j}) / (beta dt) of the converged u^i.

        Args:
            u_i: The step's displacement.
            u: Displacements by step (u[i - j] is read for j in :attr:`lags`).
        """
        i = self.index
        v = u_i.copy()
        for j, a in enumerate(self.alpha, start=1):
            v += a * u[i - j]
        return v / self.beta_dt

    def extrapolation(self, u: Sequence[np.ndarray], v: Sequence[np.ndarray]) -> np.ndarray:
        """u^{i-1} + dt v^{i-1} (constant velocity) for an inertial step, u^{i-1} for a static one.

        The ``"predictor"`` initial Newton guess of the step (not the BDF predictor u_tilde,
        which is not a displacement the body reaches).
        """
        prev = u[self.index - 1]
        return prev + self.dt * v[self.index - 1] if self.inertial else prev.copy()

    def set_fields(
        self, fields: StepFieldTargets, u: Sequence[np.ndarray], v: Sequence[np.ndarray]
    ) -> None:
        """Write the step's ``dt``, ``beta_dt``, ``u_prev`` and ``u_tilde`` into the fields.

        What the step's incremental potential (Newton) and the objective integrals of the step
        read besides u^i, v^i. A static step leaves ``u_tilde`` as it is (no predictor: no form
        of a static run reads it).
        """
        fields.dt.value = self.dt
        fields.beta_dt.value = self.beta_dt
        fields.u_prev.x.array[:] = u[self.index - 1]
        if self.inertial:
            self.predictor(u, v, out=fields.u_tilde.x.array)

    # -- transposes (the backward sweep) --------------------------------------------------
    def add_velocity_transpose(
        self, vbar: np.ndarray, ubar: MutableMapping[int, np.ndarray]
    ) -> None:
        """Push the adjoint vbar^i of v^i into ubar^i and ubar^{i-j} (transpose of velocity).

        ubar^i += vbar^i / (beta dt) and ubar^{i-j} += alpha_j vbar^i / (beta dt).

        Args:
            vbar: The complete adjoint of v^i.
            ubar: Accumulated adjoints of the displacements by step (updated in place).
        """
        i = self.index
        ubar[i] += vbar / self.beta_dt
        for j, a in enumerate(self.alpha, start=1):
            ubar[i - j] += a * vbar / self.beta_dt

    def add_predictor_transpose(
        self,
        g: np.ndarray,
        ubar: MutableMapping[int, np.ndarray],
        vbar: MutableMapping[int, np.ndarray],
    ) -> None:
        """Push a partial g = dJ/du_tilde^i into ubar^{i-j}, vbar^{i-j} (transpose of predictor).

        ubar^{i-j} -= alpha_j g and vbar^{i-j} -= alpha_j beta dt g for the leading ``len(g)``
        entries (e.g. the owned dofs); nothing for a static step.

        Args:
            g: The partial with respect to u_tilde^i.
            ubar: Accumulated adjoints of the displacements by step (updated in place).
            vbar: Accumulated adjoints of the velocities by step (updated in place).
        """
        if not self.inertial:
            return
        i, n = self.index, len(g)
        for j, a in enumerate(self.alpha, start=1):
            ubar[i - j][:n] -= a * g
            vbar[i - j][:n] -= a * self.beta_dt * g


#: The former name of :class:`TimeStep` (its coefficients).
StepCoefficients = TimeStep


class Integrator(ABC):
    """A sequence of steps, each minimising an incremental potential.

    Attributes:
        dt: Step size (time, or load parameter increment for Static).
        num_steps: Number of steps N; the trajectory holds u^0..u^N.
        dynamic: Whether steps carry inertia (and damping).
    """

    dynamic: bool = False

    def __init__(self, dt: float, num_steps: int) -> None:
        if not (isinstance(dt, numbers.Real) and math.isfinite(dt)) or dt <= 0:
            raise ParameterError(f"time step dt = {dt} must be a positive finite number")
        if not isinstance(num_steps, int) or num_steps < 1:
            raise ParameterError(
                f"num_steps = {num_steps} must be a positive integer (the arguments are "
                "Static(num_steps, dt) and BDF(order, dt, num_steps); keywords avoid the mix-up)"
            )
        self.dt = float(dt)
        self.num_steps = num_steps

    def time(self, step: int) -> float:
        """Time (or load parameter) of step ``step``."""
        return step * self.dt

    @abstractmethod
    def step(self, step: int) -> TimeStep:
        """The :class:`TimeStep` of step ``step`` (1-based)."""

    def coefficients(self, step: int) -> TimeStep:
        """The coefficients of step ``step``: its :class:`TimeStep` (same as :meth:`step`)."""
        return self.step(step)

    @property
    def history_depth(self) -> int:
        """The most earlier states u^{i-j}, v^{i-j} any step reads (max_i m_i)."""
        return max(self.step(i).order for i in range(1, self.num_steps + 1))


class Static(Integrator):
    """Static equilibrium, optionally in several load steps (quasi-static).

    Step i depends on step i-1 only through lagged quantities (friction); rates used by such
    terms are first-order differences over the load step: v^i = (u^i - u^{i-1}) / dt.
    """

    dynamic = False

    def __init__(self, num_steps: int = 1, dt: float = 1.0) -> None:
        super().__init__(dt, num_steps)

    @override
    def step(self, step: int) -> TimeStep:
        return TimeStep(1, (-1.0,), 1.0, self.dt, step, self.time(step), inertial=False)

    @property
    @override
    def history_depth(self) -> int:
        return 1


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
    ) -> None:
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
    def step(self, step: int) -> TimeStep:
        m = min(step, self.order)
        alpha, beta = bdf_coefficients(m)
        return TimeStep(m, tuple(alpha), beta, self.dt, step, self.time(step), inertial=True)

    @property
    @override
    def history_depth(self) -> int:
        return min(self.order, self.num_steps)
