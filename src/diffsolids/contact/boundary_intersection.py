"""Whether the rest or deformed boundary of a model intersects itself or an obstacle."""

from typing import TYPE_CHECKING

import ipctk
import numpy as np

from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.contact.term import ContactTerm

if TYPE_CHECKING:
    from diffsolids.model import Model

__all__ = ["BoundaryIntersection"]


class BoundaryIntersection:
    """Whether a model's boundary (all bodies) intersects itself, at rest or deformed (ipctk).

    Args:
        model: The Model; its current rest positions are read at every call (shape changes
            are seen).
    """

    def __init__(self, model: "Model") -> None:
        self.model = model
        self.surface = CollisionSurface(model.domain, model.V, boundary="nodes")
        # kinematic obstacles are seen through their contact terms' own check
        self.contacts = [
            t for t in model.numeric_terms if isinstance(t, ContactTerm) and t.obstacles
        ]

    def intersects(self, u: np.ndarray | None = None, step: int = 0) -> bool:
        """Whether the boundary at rest (``u`` None) or deformed, ``X + u``, intersects.

        Obstacles of the model's contact terms are placed where they are at step ``step``.
        """
        if any(c.intersects(u, step) for c in self.contacts):
            return True
        s = self.surface
        s.update_rest_positions()
        x = s.rest_positions.copy()
        if u is not None:
            x += s.gather(u)
        return bool(ipctk.has_intersections(s.mesh, np.asfortranarray(x), ipctk.LBVH()))
