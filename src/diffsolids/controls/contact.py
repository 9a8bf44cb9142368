"""Control of contact parameters: friction coefficients per pair of bodies."""

from typing import override

import numpy as np

from diffsolids.adjoint.sensitivities import Sensitivities, Targets
from diffsolids.controls.base import Control, ControlError

__all__ = ["FrictionControl"]


class FrictionControl(Control):
    """Friction coefficients of (some) pairs of bodies of a ContactTerm (paper sec. 8.2).

    The friction force is linear in the coefficient of its pair; the adjoint gets dJ/dmu from
    ``ContactTerm.adjoint_friction``.

    Args:
        contact: The ContactTerm (added to the simulation's model).
        pairs: Pairs of bodies ``(a, b)`` (ids or names) to control; default all pairs.
        log: Parametrise by the logarithm (mu = exp(q)).
    """

    def __init__(self, contact, pairs=None, log: bool = False):
        self.contact = contact
        self.log = log
        all_pairs = contact.friction_pairs
        if pairs is None:
            self.index = np.arange(len(all_pairs))
        else:
            self.index = np.array([contact.pair_index(a, b) for a, b in pairs], dtype=int)
        if len(self.index) == 0:
            raise ControlError("the contact term has no pair of bodies to control")
        self.name = "friction" + ("[log]" if log else "")
        if log and np.any(contact.friction_coefficients[self.index] <= 0):
            raise ControlError("log parametrisation of friction needs positive coefficients")

    @override
    def check(self, simulation) -> None:
        if self.contact not in simulation.model.numeric_terms:
            raise ControlError("the contact term of the friction control is not in the model")

    @override
    def footprint(self) -> set[tuple]:
        return {("friction", int(p)) for p in self.index}

    @override
    @property
    def size(self) -> int:
        return len(self.index)

    @override
    def value(self) -> np.ndarray:
        mu = self.contact.friction_coefficients[self.index]
        return np.log(mu) if self.log else mu.copy()

    @override
    def assign(self, q: np.ndarray) -> None:
        mu_new = np.exp(q) if self.log else np.asarray(q, dtype=float)
        if np.any(mu_new < 0) or not np.all(np.isfinite(mu_new)):
            raise ControlError(f"friction coefficients {mu_new} must be finite and >= 0")
        mu = self.contact.friction_coefficients
        mu[self.index] = mu_new
        self.contact.friction_coefficients = mu

    @override
    def targets(self) -> Targets:
        return Targets(contact=frozenset({"friction"}))

    @override
    def pullback(self, sens: Sensitivities) -> np.ndarray:
        g = np.asarray(sens.contact.get("friction", np.zeros(len(self.contact.friction_pairs))))
        g = g[self.index]
        if self.log:
            g = g * self.contact.friction_coefficients[self.index]
        return g

    @override
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lower = np.full(self.size, -np.inf if self.log else 0.0)
        return lower, np.full(self.size, np.inf)
