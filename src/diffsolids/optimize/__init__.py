"""Optimisation of reduced functionals: bound-constrained L-BFGS with a safeguarded line search.

The optimiser accepts only valid iterates (inside the bounds, no inverted element, no
intersecting rest configuration, a converged forward solve), warm-starts every forward solve
from the last accepted trajectory, writes a history, plots, selected iterates and checkpoints,
and offers a remeshing hook (see :mod:`diffsolids.optimize.optimizer`). Observers of accepted
iterates (``on_accept``: trajectories, invariants) are in :mod:`diffsolids.optimize.observers`,
checks of those invariants in :mod:`diffsolids.optimize.invariants`. For two parameters of which
one sits in a narrow, bent valley, :class:`FloorSearch` projects that one out.
"""

from diffsolids.optimize.checkpoint import Checkpoint
from diffsolids.optimize.contract import OptimizableFunctional
from diffsolids.optimize.floor_search import FloorSearch
from diffsolids.optimize.hooks import RebuildableInnerProduct, RemeshCheckpoints, RemeshHook
from diffsolids.optimize.invariants import (
    BoundaryIntersection,
    StateChecks,
    check_trajectories,
    inverted_rest_cells,
    min_volume_ratio,
)
from diffsolids.optimize.lbfgs import LBFGSMemory
from diffsolids.optimize.mesh_motion import (
    MeshMotion,
    MeshMotionControl,
    RieszMap,
    ShapeInnerProduct,
)
from diffsolids.optimize.monitor import (
    IterationLog,
    IterationRecord,
    OptimizationOutput,
    control_summary,
    plot_history,
    plot_log,
    read_log,
)
from diffsolids.optimize.observers import InvariantMonitor, TrajectoryKeeper
from diffsolids.optimize.optimizer import LBFGS, OptimizationResult, minimize
from diffsolids.optimize.options import LBFGSOptions, OptimizationError, OptimizationWarning
from diffsolids.optimize.remesh import Remesher, load_domain, remesh_domain, save_domain

__all__ = [
    "LBFGS",
    "BoundaryIntersection",
    "Checkpoint",
    "FloorSearch",
    "InvariantMonitor",
    "IterationLog",
    "IterationRecord",
    "LBFGSMemory",
    "LBFGSOptions",
    "MeshMotion",
    "MeshMotionControl",
    "OptimizableFunctional",
    "OptimizationError",
    "OptimizationOutput",
    "OptimizationResult",
    "OptimizationWarning",
    "RebuildableInnerProduct",
    "RemeshCheckpoints",
    "RemeshHook",
    "Remesher",
    "RieszMap",
    "ShapeInnerProduct",
    "StateChecks",
    "TrajectoryKeeper",
    "check_trajectories",
    "control_summary",
    "inverted_rest_cells",
    "load_domain",
    "min_volume_ratio",
    "minimize",
    "plot_history",
    "plot_log",
    "read_log",
    "remesh_domain",
    "save_domain",
]
