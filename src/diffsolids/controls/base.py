"""Controls: map one flat parameter vector q to what the physics reads, and gradients back."""

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from diffsolids.adjoint.sensitivities import Sensitivities, Targets
from diffsolids.errors import DiffsolidsError

if TYPE_CHECKING:
    from diffsolids.simulation import Simulation

__all__ = ["Control", "ControlError", "ControlSet"]


class ControlError(DiffsolidsError, ValueError):
    """A control that does not fit the simulation, or a parameter vector of the wrong size."""


class Control(ABC):
    """A block of the parameter vector.

    Subclasses define ``size``, read and write the parameters, name the sensitivities they need,
    and pull those back to dJ/dq (the chain rule of their parametrisation).
    """

    name: str = "control"

    @property
    @abstractmethod
    def size(self) -> int:
        """Number of parameters."""

    @abstractmethod
    def value(self) -> np.ndarray:
        """Current parameters (identical on all ranks)."""

    @abstractmethod
    def assign(self, q: np.ndarray) -> None:
        """Apply parameters to the model/simulation."""

    @abstractmethod
    def targets(self) -> Targets:
        """Sensitivities needed by :meth:`pullback`."""

    @abstractmethod
    def pullback(self, sens: Sensitivities) -> np.ndarray:
        """dJ/dq from the sensitivities (identical on all ranks)."""

    def check(self, simulation: "Simulation") -> None:  # noqa: B027 (optional hook)
        """Raise ControlError if the control does not belong to ``simulation``."""

    def footprint(self) -> set[tuple]:
        """What the control writes: ``{(quantity, part)}``, ``part`` None for all of it.

        Two controls of one parameter vector must not write the same part of a quantity (the
        later assignment would silently override the earlier one).
        """
        return {(self.name, None)}

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of the parameters (default unbounded)."""
        return np.full(self.size, -np.inf), np.full(self.size, np.inf)

    def transfer(self, old: "Control", block: np.ndarray) -> np.ndarray:
        """Parameters of this control equal to ``old``'s ``block`` on the mesh before a remesh.

        ``self`` is the same kind of control built on the new mesh (collective). The default
        copies parameters that do not depend on the mesh (same size); controls of mesh fields
        interpolate, shape controls restart at their new reference (zeros).

        Raises:
            ControlError: ``old`` is another kind of control, or its size depends on the mesh
                and the control does not say how to transfer it.
        """
        if type(old) is not type(self):
            raise ControlError(f"cannot transfer control {old.name} to {self.name}")
        block = np.asarray(block, dtype=float)
        if block.size != self.size:
            raise ControlError(
                f"cannot transfer control {self.name} ({block.size} -> {self.size} parameters) "
                "to the new mesh"
            )
        return block.copy()


def _check_disjoint(controls: Sequence[Control]) -> None:
    seen: dict[tuple, Control] = {}
    for c in controls:
        for quantity, part in c.footprint():
            for (q, p), other in seen.items():
                if q == quantity and (part is None or p is None or p == part):
                    raise ControlError(
                        f"controls {other.name} and {c.name} both set {quantity}"
                        + ("" if part is None or p is None else f" ({part})")
                    )
        seen.update(dict.fromkeys(c.footprint(), c))


class ControlSet:
    """Several controls concatenated into one flat parameter vector."""

    def __init__(self, controls: Sequence[Control], simulation: "Simulation") -> None:
        if isinstance(controls, Control):
            controls = [controls]
        if not controls:
            raise ControlError("at least one control is needed")
        self.controls = list(controls)
        self.model = simulation.model
        for c in self.controls:
            c.check(simulation)
        _check_disjoint(self.controls)
        self.offsets = np.cumsum([0] + [c.size for c in self.controls])

    @property
    def size(self) -> int:
        """Total number of parameters."""
        return int(self.offsets[-1])

    def value(self) -> np.ndarray:
        """Current concatenated parameters."""
        return np.concatenate([c.value() for c in self.controls])

    def split(self, q: npt.ArrayLike) -> list[np.ndarray]:
        """Blocks of q per control (validates the length and finiteness)."""
        q = np.asarray(q, dtype=float)
        if q.ndim != 1 or q.size != self.size:
            raise ControlError(
                f"parameter vector has length {q.size if q.ndim == 1 else q.shape}, "
                f"the controls expect {self.size} "
                f"({', '.join(f'{c.name}: {c.size}' for c in self.controls)})"
            )
        if not np.all(np.isfinite(q)):
            raise ControlError("parameter vector has non-finite entries")
        return [q[a:b] for a, b in zip(self.offsets[:-1], self.offsets[1:], strict=True)]

    def assign(self, q: npt.ArrayLike) -> None:
        """Apply the concatenated parameters; the parameter fields are validated once, at the end.

        Raises:
            ControlError: q of the wrong length or with non-finite entries.
            ParameterError: Non-physical parameter fields after the assignment.
        """
        blocks = self.split(q)
        with self.model.parameter_update():
            for c, block in zip(self.controls, blocks, strict=True):
                c.assign(block)

    def targets(self) -> Targets:
        """Union of the controls' targets."""
        t = Targets()
        for c in self.controls:
            t = t | c.targets()
        return t

    def pullback(self, sens: Sensitivities) -> np.ndarray:
        """Concatenated gradient."""
        return np.concatenate([c.pullback(sens) for c in self.controls])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Concatenated bounds."""
        lo, hi = zip(*(c.bounds() for c in self.controls), strict=True)
        return np.concatenate(lo), np.concatenate(hi)
