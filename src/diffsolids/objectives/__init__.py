"""Objectives: per-step UFL integrals combined by time weights and the chain rule."""

from diffsolids.objectives.functional import (
    Integral,
    Objective,
    ObjectiveError,
    Regulariser,
    Series,
    TimeGrid,
    final_value,
    step_weights,
    time_integral,
)

__all__ = [
    "Integral",
    "Objective",
    "ObjectiveError",
    "Regulariser",
    "Series",
    "TimeGrid",
    "final_value",
    "step_weights",
    "time_integral",
]
