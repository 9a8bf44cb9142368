"""IPC contact and friction (numpy + ipctk) as a numeric term of the incremental potential."""

from diffsolids.contact.obstacle import Obstacle
from diffsolids.contact.stiffness import BarrierContact, suggest_barrier_stiffness
from diffsolids.contact.surface import CollisionSurface
from diffsolids.contact.term import ContactRecord, ContactTerm

__all__ = [
    "BarrierContact",
    "CollisionSurface",
    "ContactRecord",
    "ContactTerm",
    "Obstacle",
    "suggest_barrier_stiffness",
]
