"""Model definition: materials, terms of the incremental potential, boundary conditions."""

from diffsolids.model.boundary_conditions import DirichletCondition, OnBody, RealisedDirichlet
from diffsolids.model.materials import LinearElastic, Material, NeoHookean, StVenantKirchhoff
from diffsolids.model.model import Model, undo_on_refusal
from diffsolids.model.numeric import NumericTerm
from diffsolids.model.terms import (
    BodyForce,
    Damping,
    ElasticEnergy,
    EnergyTerm,
    Inertia,
    StepFields,
    Term,
    Traction,
)

__all__ = [
    "BodyForce",
    "Damping",
    "DirichletCondition",
    "ElasticEnergy",
    "EnergyTerm",
    "Inertia",
    "LinearElastic",
    "Material",
    "Model",
    "NeoHookean",
    "NumericTerm",
    "OnBody",
    "RealisedDirichlet",
    "StVenantKirchhoff",
    "StepFields",
    "Term",
    "Traction",
    "undo_on_refusal",
]
