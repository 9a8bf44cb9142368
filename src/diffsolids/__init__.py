"""diffsolids: differentiable simulation of deforming solids with contact on DOLFINx.

The package follows the method of Huang et al., "Differentiable solver for time-dependent
deformation problems with contact" (ACM TOG 2024): forward problems are sequences of
incremental-potential minimisations (static or BDF time stepping) and gradients come from the
discrete adjoint of exactly those computations.
"""

import contextlib
import sys

# The PyPI wheel needs its MPI loaded before the DOLFINx bindings; a conda/spack/docker DOLFINx
# has no such module.
with contextlib.suppress(ImportError):
    import dolfinx_solver  # noqa: F401

try:
    import dolfinx  # noqa: F401
except ImportError as _error:
    if "adios2" in sys.modules and "adios2" in str(_error):
        raise ImportError(
            "DOLFINx cannot load its ADIOS2 library because the adios2 Python package was "
            "imported first and brought its own libadios2_core (same soname, other build: "
            f"{_error}). Import diffsolids (or dolfinx) before adios2; adios2 imported "
            "afterwards works."
        ) from _error
    raise

from diffsolids import errors
from diffsolids.adjoint.checkpointing import Checkpointing

# Everything a problem script needs is importable from here (the modules stay the reference).
from diffsolids.contact import ContactTerm, Obstacle, suggest_barrier_stiffness
from diffsolids.controls import (
    DirichletControl,
    FrictionControl,
    InitialCondition,
    ParameterControl,
    RigidVelocity,
    ShapeControl,
)
from diffsolids.errors import (
    ConvergenceError,
    DiffsolidsError,
    IntersectionError,
    InvertedElementError,
    MeshError,
    NewtonConvergenceError,
    ParameterError,
    PortabilityError,
    TagError,
)
from diffsolids.integrators import BDF, Integrator, Static, bdf_coefficients
from diffsolids.mesh import Domain, combine_meshes, create_domain, read_mesh, select_facets
from diffsolids.model import (
    DirichletCondition,
    LinearElastic,
    Material,
    Model,
    NeoHookean,
    NumericTerm,
    OnBody,
    StVenantKirchhoff,
)
from diffsolids.objectives import (
    Integral,
    center_of_mass,
    final_value,
    series_values,
    soft_min,
    step_values,
    stress_lp_norm,
    target_displacement,
    target_trajectory,
    time_integral,
)
from diffsolids.optimize import LBFGSOptions, minimize
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.simulation import CanonicalValues, Simulation, Trajectory
from diffsolids.solvers import NewtonSolver, SolverOptions
from diffsolids.verification import (
    DifferentiableFunctional,
    check_reproducible,
    finite_difference_check,
    line_scan,
    taylor_test,
)

__all__ = [
    "BDF",
    "CanonicalValues",
    "Checkpointing",
    "ContactTerm",
    "ConvergenceError",
    "DifferentiableFunctional",
    "DiffsolidsError",
    "DirichletCondition",
    "DirichletControl",
    "Domain",
    "FrictionControl",
    "InitialCondition",
    "Integral",
    "Integrator",
    "IntersectionError",
    "InvertedElementError",
    "LBFGSOptions",
    "LinearElastic",
    "Material",
    "MeshError",
    "Model",
    "NeoHookean",
    "NewtonConvergenceError",
    "NewtonSolver",
    "NumericTerm",
    "Obstacle",
    "OnBody",
    "ParameterControl",
    "ParameterError",
    "PortabilityError",
    "ReducedFunctional",
    "RigidVelocity",
    "ShapeControl",
    "Simulation",
    "SolverOptions",
    "StVenantKirchhoff",
    "Static",
    "TagError",
    "Trajectory",
    "bdf_coefficients",
    "center_of_mass",
    "check_reproducible",
    "combine_meshes",
    "create_domain",
    "errors",
    "final_value",
    "finite_difference_check",
    "line_scan",
    "minimize",
    "read_mesh",
    "select_facets",
    "series_values",
    "soft_min",
    "step_values",
    "stress_lp_norm",
    "suggest_barrier_stiffness",
    "target_displacement",
    "target_trajectory",
    "taylor_test",
    "time_integral",
]
