"""IPC contact and friction (numpy + ipctk) as a numeric term of the incremental potential.

The entry is :class:`ContactTerm` (with :class:`Obstacle` and
:func:`suggest_barrier_stiffness`); its parts live in sub-packages by concern:
``geometry`` (the collision surface, obstacles and their flat regions), ``detection``
(collision sets, step bounds, configuration checks), ``energy`` (the barrier and friction
potentials) and ``derivatives`` (the adjoint's products).
"""

from diffsolids.contact.energy.stiffness import BarrierContact, suggest_barrier_stiffness
from diffsolids.contact.geometry.obstacle import Obstacle
from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.contact.term import ContactRecord, ContactTerm
from diffsolids.deprecation import alias_modules

__all__ = [
    "BarrierContact",
    "CollisionSurface",
    "ContactRecord",
    "ContactTerm",
    "Obstacle",
    "suggest_barrier_stiffness",
]

# module paths before the sub-packages (0.4): they import the moved modules and warn until 0.6
alias_modules(
    {
        "diffsolids.contact.adjoint": "diffsolids.contact.derivatives.step_adjoint",
        "diffsolids.contact.friction_adjoint": "diffsolids.contact.derivatives.friction_weights",
        "diffsolids.contact.shape": "diffsolids.contact.derivatives.barrier_shape",
        "diffsolids.contact.surface": "diffsolids.contact.geometry.surface",
        "diffsolids.contact.obstacle": "diffsolids.contact.geometry.obstacle",
        "diffsolids.contact.flat": "diffsolids.contact.geometry.flat",
        "diffsolids.contact.distances": "diffsolids.contact.geometry.distances",
        "diffsolids.contact.subdivision": "diffsolids.contact.geometry.subdivision",
        "diffsolids.contact.free_dofs": "diffsolids.contact.geometry.free_dofs",
        "diffsolids.contact.collisions": "diffsolids.contact.detection.collision_set",
        "diffsolids.contact.step_bound": "diffsolids.contact.detection.step_bound",
        "diffsolids.contact.checks": "diffsolids.contact.detection.checks",
        "diffsolids.contact.reach": "diffsolids.contact.detection.reach",
        "diffsolids.contact.potential": "diffsolids.contact.energy.contact_potential",
        "diffsolids.contact.evaluation": "diffsolids.contact.energy.evaluation",
        "diffsolids.contact.lagging": "diffsolids.contact.energy.lagging",
        "diffsolids.contact.friction_table": "diffsolids.contact.energy.friction_table",
        "diffsolids.contact.stiffness": "diffsolids.contact.energy.stiffness",
        "diffsolids.contact.pattern": "diffsolids.contact.energy.pattern",
        "diffsolids.contact.polyfem": "diffsolids.polyfem.contact",
    },
    removed_in="0.6",
)
