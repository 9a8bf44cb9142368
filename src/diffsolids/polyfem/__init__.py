"""PolyFEM's optimisation files run by diffsolids (``python -m diffsolids.polyfem OPT_JSON``)."""

from diffsolids.polyfem.optimization import (
    PolyFEMOptimization,
    PolyFEMProblem,
    StoppingConditions,
    read_polyfem_optimization,
)

__all__ = [
    "PolyFEMOptimization",
    "PolyFEMProblem",
    "StoppingConditions",
    "read_polyfem_optimization",
]
