"""Controls: the optimisation parameters and the chain rule back from the adjoint."""

from diffsolids.controls.base import Control, ControlError, ControlSet
from diffsolids.controls.contact import FrictionControl
from diffsolids.controls.dirichlet import DirichletControl
from diffsolids.controls.initial import InitialCondition, RigidVelocity
from diffsolids.controls.ordering import CanonicalLayout
from diffsolids.controls.parameters import ParameterControl
from diffsolids.controls.shape import ShapeControl, boundary_vertices

__all__ = [
    "CanonicalLayout",
    "Control",
    "ControlError",
    "ControlSet",
    "DirichletControl",
    "FrictionControl",
    "InitialCondition",
    "ParameterControl",
    "RigidVelocity",
    "ShapeControl",
    "boundary_vertices",
]
