"""Control of contact parameters: friction coefficients per pair of bodies."""

import functools
from collections.abc import Sequence
from typing import TYPE_CHECKING, override

import numpy as np

from diffsolids.adjoint.sensitivities import Sensitivities, Targets
from diffsolids.controls.base import Control, ControlError
from diffsolids.controls.maps import Identity, ParameterMap, as_map
from diffsolids.model import undo_on_refusal

if TYPE_CHECKING:
    from diffsolids.contact.term import ContactTerm
    from diffsolids.simulation import Simulation

__all__ = ["FrictionControl"]


class FrictionControl(Control):
    """Friction coefficients of (some) pairs of bodies of a ContactTerm (paper sec. 8.2).

    The friction force is linear in the coefficient of its pair; the adjoint gets dJ/dmu from
    ``ContactTerm.adjoint_friction``.

    Args:
        contact: The ContactTerm (added to the simulation's model).
        pairs: Pairs of bodies ``(a, b)`` (ids or names) to control; default all pairs.
        log: Parametrise by the logarithm (mu = exp(q)); the same as ``map=Log()``.
        map: Change of variables mu = map(q) (see :mod:`diffsolids.controls.maps`).
    """

    def __init__(
        self,
        contact: "ContactTerm",
        pairs: Sequence[tuple[int | str, int | str]] | None = None,
        log: bool = False,
        map: ParameterMap | None = None,
    ) -> None:
        self.contact = contact
        self.map = as_map(map, log)
        all_pairs = contact.friction_pairs
        if pairs is None:
            self.index = np.arange(len(all_pairs))
        else:
            self.index = np.array([contact.pair_index(a, b) for a, b in pairs], dtype=int)
        if len(self.index) == 0:
            raise ControlError("the contact term has no pair of bodies to control")
        self.name = "friction" + ("" if map is None and not log else f"[{self.map.name}]")
        try:
            self.map.inverse(contact.friction_coefficients[self.index])
        except ControlError as err:
            raise ControlError(f"friction coefficients cannot be parametrised: {err}") from None

    @override
    def check(self, simulation: "Simulation") -> None:
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
        return self.map.inverse(self.contact.friction_coefficients[self.index])

    @override
    def assign(self, q: np.ndarray) -> None:
        mu_new = self.map.forward(np.asarray(q, dtype=float))
        if np.any(mu_new < 0) or not np.all(np.isfinite(mu_new)):
            raise ControlError(f"friction coefficients {mu_new} must be finite and >= 0")
        mu = self.contact.friction_coefficients
        undo_on_refusal(
            functools.partial(setattr, self.contact, "friction_coefficients", mu.copy())
        )
        mu[self.index] = mu_new
        self.contact.friction_coefficients = mu

    @override
    def targets(self) -> Targets:
        return Targets(contact=frozenset({"friction"}))

    @override
    def pullback(self, sens: Sensitivities) -> np.ndarray:
        g = np.asarray(sens.contact.get("friction", np.zeros(len(self.contact.friction_pairs))))
        return self.map.pullback(self.value(), g[self.index])

    @override
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        low, high = (0.0, np.inf) if isinstance(self.map, Identity) else self.map.bounds()
        return np.full(self.size, low), np.full(self.size, high)
