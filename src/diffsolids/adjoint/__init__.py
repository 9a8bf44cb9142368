"""The discrete adjoint: backward sweep, its forms and its linear solves."""

from diffsolids.adjoint.checkpointing import (
    CheckpointedRun,
    CheckpointedTrajectory,
    Checkpointing,
    CheckpointingError,
)
from diffsolids.adjoint.forms import AdjointForms
from diffsolids.adjoint.linear import AdjointLinearSolver, AdjointSolverOptions
from diffsolids.adjoint.sensitivities import Sensitivities, Targets
from diffsolids.adjoint.sweep import BackwardSweep

__all__ = [
    "AdjointForms",
    "AdjointLinearSolver",
    "AdjointSolverOptions",
    "BackwardSweep",
    "CheckpointedRun",
    "CheckpointedTrajectory",
    "Checkpointing",
    "CheckpointingError",
    "Sensitivities",
    "Targets",
]
