"""Optimisation of reduced functionals: bound-constrained L-BFGS with a safeguarded line search.

The optimiser accepts only valid iterates (inside the bounds, no inverted element, no
intersecting rest configuration, a converged forward solve), warm-starts every forward solve
from the last accepted trajectory, writes a history, plots, selected iterates and checkpoints,
and offers a remeshing hook (see :mod:`diffsolids.optimize.optimizer`).
"""

from diffsolids.optimize.checkpoint import Checkpoint
from diffsolids.optimize.lbfgs import LBFGSMemory
from diffsolids.optimize.mesh_motion import (
    MeshMotion,
    MeshMotionControl,
    RieszMap,
    ShapeInnerProduct,
)
from diffsolids.optimize.monitor import IterationRecord, OptimizationOutput, plot_history
from diffsolids.optimize.optimizer import LBFGS, OptimizationResult, minimize
from diffsolids.optimize.options import LBFGSOptions, OptimizationError, OptimizationWarning
from diffsolids.optimize.remesh import Remesher, load_domain, remesh_domain, save_domain

__all__ = [
    "LBFGS",
    "Checkpoint",
    "IterationRecord",
    "LBFGSMemory",
    "LBFGSOptions",
    "MeshMotion",
    "MeshMotionControl",
    "OptimizationError",
    "OptimizationOutput",
    "OptimizationResult",
    "OptimizationWarning",
    "Remesher",
    "RieszMap",
    "ShapeInnerProduct",
    "load_domain",
    "minimize",
    "plot_history",
    "remesh_domain",
    "save_domain",
]
