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
from diffsolids.objectives.library import (
    StepValues,
    boundary_graph_fit,
    center_of_mass,
    center_of_mass_trajectory,
    height_objective,
    stress_bound_penalty,
    stress_lp_norm,
    target_displacement,
    target_positions,
    volume_penalty,
)
from diffsolids.objectives.regularisers import BoundarySmoothing, MaterialSmoothing
from diffsolids.objectives.values import series_values

__all__ = [
    "BoundarySmoothing",
    "Integral",
    "MaterialSmoothing",
    "Objective",
    "ObjectiveError",
    "Regulariser",
    "Series",
    "StepValues",
    "TimeGrid",
    "boundary_graph_fit",
    "center_of_mass",
    "center_of_mass_trajectory",
    "final_value",
    "height_objective",
    "series_values",
    "step_weights",
    "stress_bound_penalty",
    "stress_lp_norm",
    "target_displacement",
    "target_positions",
    "time_integral",
    "volume_penalty",
]
