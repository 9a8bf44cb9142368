"""diffsolids: differentiable simulation of deforming solids with contact on DOLFINx.

The package follows the method of Huang et al., "Differentiable solver for time-dependent
deformation problems with contact" (ACM TOG 2024): forward problems are sequences of
incremental-potential minimisations (static or BDF time stepping) and gradients come from the
discrete adjoint of exactly those computations.
"""

import contextlib

# The PyPI wheel needs its MPI loaded before the DOLFINx bindings; a conda/spack/docker DOLFINx
# has no such module.
with contextlib.suppress(ImportError):
    import dolfinx_solver  # noqa: F401

from diffsolids import errors
from diffsolids.errors import (
    ConvergenceError,
    DiffsolidsError,
    InvertedElementError,
    MeshError,
    NewtonConvergenceError,
    ParameterError,
    TagError,
)
from diffsolids.integrators import BDF, Integrator, Static, bdf_coefficients
from diffsolids.mesh import Domain
from diffsolids.model import (
    DirichletCondition,
    LinearElastic,
    Material,
    Model,
    NeoHookean,
    StVenantKirchhoff,
)
from diffsolids.simulation import Simulation, Trajectory
from diffsolids.solvers import NewtonSolver, SolverOptions

__all__ = [
    "BDF",
    "ConvergenceError",
    "DiffsolidsError",
    "DirichletCondition",
    "Domain",
    "Integrator",
    "InvertedElementError",
    "LinearElastic",
    "Material",
    "MeshError",
    "Model",
    "NeoHookean",
    "NewtonConvergenceError",
    "NewtonSolver",
    "ParameterError",
    "Simulation",
    "SolverOptions",
    "StVenantKirchhoff",
    "Static",
    "TagError",
    "Trajectory",
    "bdf_coefficients",
    "errors",
]
