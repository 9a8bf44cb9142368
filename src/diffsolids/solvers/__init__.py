"""Nonlinear (SNES) solver for the steps and the step bounds of its line search."""

from diffsolids.solvers.forms import JIT_OPTIONS, compile_form
from diffsolids.solvers.inversion import InversionGuard
from diffsolids.solvers.newton import NewtonResult, NewtonSolver, SolverOptions

__all__ = [
    "JIT_OPTIONS",
    "InversionGuard",
    "NewtonResult",
    "NewtonSolver",
    "SolverOptions",
    "compile_form",
]
