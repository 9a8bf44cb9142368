"""Objectives: per-step UFL integrals combined by time weights and the chain rule."""

from diffsolids.objectives.barriers import (
    inversion_barrier,
    scalar_log_barrier,
    sdf_barrier,
    series_barrier,
)
from diffsolids.objectives.collision import DeformedCollisionBarrier, RestCollisionBarrier
from diffsolids.objectives.functional import (
    Integral,
    NumericIntegral,
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
from diffsolids.objectives.reductions import SoftMin, min_distance_target, soft_min
from diffsolids.objectives.regularisers import BoundarySmoothing, MaterialSmoothing
from diffsolids.objectives.targets import (
    TrajectoryTarget,
    center_target,
    compliance,
    node_target,
    sdf_target,
    step_selector,
    target_trajectory,
)
from diffsolids.objectives.values import objective_series, series_values, step_values

__all__ = [
    "BoundarySmoothing",
    "DeformedCollisionBarrier",
    "Integral",
    "MaterialSmoothing",
    "NumericIntegral",
    "Objective",
    "ObjectiveError",
    "Regulariser",
    "RestCollisionBarrier",
    "Series",
    "SoftMin",
    "StepValues",
    "TimeGrid",
    "TrajectoryTarget",
    "boundary_graph_fit",
    "center_of_mass",
    "center_of_mass_trajectory",
    "center_target",
    "compliance",
    "final_value",
    "height_objective",
    "inversion_barrier",
    "min_distance_target",
    "node_target",
    "objective_series",
    "scalar_log_barrier",
    "sdf_barrier",
    "sdf_target",
    "series_barrier",
    "series_values",
    "soft_min",
    "step_selector",
    "step_values",
    "step_weights",
    "stress_bound_penalty",
    "stress_lp_norm",
    "target_displacement",
    "target_positions",
    "target_trajectory",
    "time_integral",
    "volume_penalty",
]
