"""Checks shared by the contact tests: every Newton iterate watched for intersections."""

import ipctk
import numpy as np

import diffsolids as ds
from diffsolids.contact import ContactTerm

__all__ = ["IntersectionMonitor"]


class IntersectionMonitor:
    """Checks every Newton iterate of the solver (SNES monitor) for intersections.

    Attributes:
        checked: How many iterates were checked.
        bad: The Newton iteration numbers at which the surface intersected itself.
    """

    def __init__(self, sim: ds.Simulation, contact: ContactTerm) -> None:
        self.surface = contact.surface
        self.checked = 0
        self.bad: list[int] = []
        sim.solver.snes.setMonitor(self)

    def __call__(self, snes: object, it: int, fnorm: float) -> None:
        s = self.surface
        x = s.rest_positions + s.gather(snes.getSolution().array_r)
        self.checked += 1
        if ipctk.has_intersections(s.mesh, np.asfortranarray(x)):
            self.bad.append(it)
