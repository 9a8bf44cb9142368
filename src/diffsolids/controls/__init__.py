"""Controls: the optimisation parameters and the chain rule back from the adjoint."""

from diffsolids.controls.affine import AffineControl
from diffsolids.controls.base import Control, ControlError, ControlSet
from diffsolids.controls.contact import FrictionControl
from diffsolids.controls.dirichlet import DirichletControl
from diffsolids.controls.initial import InitialCondition, RigidVelocity
from diffsolids.controls.maps import (
    Affine,
    Compose,
    Identity,
    Log,
    ParameterMap,
    Power,
    Simp,
)
from diffsolids.controls.parameters import ParameterControl
from diffsolids.controls.shape import ShapeControl, boundary_vertices
from diffsolids.mesh.ordering import CanonicalLayout as CanonicalLayout  # documented in mesh

__all__ = [
    "Affine",
    "AffineControl",
    "Compose",
    "Control",
    "ControlError",
    "ControlSet",
    "DirichletControl",
    "FrictionControl",
    "Identity",
    "InitialCondition",
    "Log",
    "ParameterControl",
    "ParameterMap",
    "Power",
    "RigidVelocity",
    "ShapeControl",
    "Simp",
    "boundary_vertices",
]
