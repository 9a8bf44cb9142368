"""PolyFEM's scene and optimisation files read and run by diffsolids.

``python -m diffsolids.polyfem OPT_JSON`` runs an experiment as its files state it.
"""

from diffsolids.polyfem.optimization import (
    PolyFEMOptimization,
    PolyFEMProblem,
    StoppingConditions,
    read_polyfem_optimization,
)
from diffsolids.polyfem.scene import (
    BoxSideSelection,
    PolyFEMBoundaryValue,
    PolyFEMGeometry,
    PolyFEMMaterial,
    PolyFEMScene,
    PolyFEMSetup,
    read_polyfem_scene,
)

__all__ = [
    "BoxSideSelection",
    "PolyFEMBoundaryValue",
    "PolyFEMGeometry",
    "PolyFEMMaterial",
    "PolyFEMOptimization",
    "PolyFEMProblem",
    "PolyFEMScene",
    "PolyFEMSetup",
    "StoppingConditions",
    "read_polyfem_optimization",
    "read_polyfem_scene",
]
