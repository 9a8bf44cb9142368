"""The discrete adjoint: backward sweep, its forms and its linear solves."""

from diffsolids.adjoint.forms import AdjointForms
from diffsolids.adjoint.linear import AdjointLinearSolver, AdjointSolverOptions
from diffsolids.adjoint.sensitivities import Sensitivities, Targets
from diffsolids.adjoint.sweep import BackwardSweep

__all__ = [
    "AdjointForms",
    "AdjointLinearSolver",
    "AdjointSolverOptions",
    "BackwardSweep",
    "Sensitivities",
    "Targets",
]
