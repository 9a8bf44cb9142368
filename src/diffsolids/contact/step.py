"""The contact term's record of the step it is in: BDF history, lagged state, obstacles."""

from dataclasses import dataclass

import numpy as np

from diffsolids.integrators import TimeStep

__all__ = ["ContactStep"]


@dataclass
class ContactStep:
    """What ``ContactTerm.begin_step`` sets up for step i (collision-surface arrays).

    Attributes:
        index: The step i.
        forward: Whether a forward run takes the step (else a backward sweep re-enters it).
        time_step: The integrator's step (its BDF velocity and that velocity's transpose).
        history: Displacements u^{i-1}, ..., u^{i-m} of the collision vertices (obstacles
            included).
        v_offset: The velocity's part from the history: v = U / beta_dt + v_offset.
        lagged: u^{i-1}: the state friction is lagged from.
        obstacle: The obstacles' displacement at step i.
        blocked: The obstacles' move from u^{i-1} is not collision-free with the bodies held.
        start_body: The bodies' displacement the obstacles' move was checked from.
        friction_pattern: Vertex-block keys of the friction Hessian at zero sliding velocity
            (its stencils).
        reach: Vertex blocks of the pairs near at the start of the step.
    """

    index: int
    forward: bool
    time_step: TimeStep
    history: list[np.ndarray]
    v_offset: np.ndarray
    lagged: np.ndarray
    obstacle: np.ndarray
    blocked: bool = False
    start_body: np.ndarray | None = None
    friction_pattern: np.ndarray | None = None
    reach: np.ndarray | None = None

    @property
    def alpha(self) -> tuple[float, ...]:
        """BDF coefficients alpha_1..alpha_m of the step."""
        return tuple(self.time_step.alpha)

    @property
    def beta_dt(self) -> float:
        """The step's beta dt."""
        return self.time_step.beta_dt
