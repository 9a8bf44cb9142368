"""Parameters that drive several controls through an affine map p = A q + b."""

import functools
from collections.abc import Sequence
from typing import TYPE_CHECKING, override

import numpy as np
import numpy.typing as npt

from diffsolids.adjoint.sensitivities import Sensitivities, Targets
from diffsolids.controls.base import Control, ControlError, ControlSet
from diffsolids.model import undo_on_refusal

if TYPE_CHECKING:
    from diffsolids.simulation import Simulation

__all__ = ["AffineControl"]


class AffineControl(Control):
    """Parameters q whose image p = A q + b is the concatenated parameters of other controls.

    One parameter may drive several controls (one friction coefficient for every pair of
    bodies), a parameter may drive nothing (a column of zeros: its gradient is 0) and entries
    of p may be constants (a row of zeros, its value in ``offset``). PolyFEM's linear
    parametrisations (``append-const``, ``scale``, per-body maps) are such maps.

    Args:
        controls: The driven controls (a control or a sequence; disjoint footprints).
        matrix: A, of shape (sum of the controls' sizes, number of parameters).
        offset: b (default zero).
        name: The control's name in logs and messages.
        lower: Lower bounds of q (default: unbounded).
        upper: Upper bounds of q.

    Raises:
        ControlError: A matrix or offset of the wrong shape, or non-finite entries.
    """

    def __init__(
        self,
        controls: Control | Sequence[Control],
        matrix: npt.ArrayLike,
        offset: npt.ArrayLike | None = None,
        name: str = "affine",
        lower: npt.ArrayLike = -np.inf,
        upper: npt.ArrayLike = np.inf,
    ) -> None:
        self.controls = [controls] if isinstance(controls, Control) else list(controls)
        if not self.controls:
            raise ControlError(f"control {name}: at least one driven control is needed")
        self.matrix = np.atleast_2d(np.asarray(matrix, dtype=float))
        rows = sum(c.size for c in self.controls)
        self.offset = np.zeros(rows) if offset is None else np.asarray(offset, dtype=float)
        if self.matrix.shape[0] != rows or self.offset.shape != (rows,):
            raise ControlError(
                f"control {name}: matrix {self.matrix.shape} and offset {self.offset.shape} for "
                f"driven controls of {rows} parameters "
                f"({', '.join(f'{c.name}: {c.size}' for c in self.controls)})"
            )
        if not (np.all(np.isfinite(self.matrix)) and np.all(np.isfinite(self.offset))):
            raise ControlError(f"control {name}: non-finite entries in the matrix or offset")
        self.name = name
        self._offsets = np.cumsum([0] + [c.size for c in self.controls])
        self._lower = np.broadcast_to(np.asarray(lower, dtype=float), self.size).copy()
        self._upper = np.broadcast_to(np.asarray(upper, dtype=float), self.size).copy()
        self.q = np.linalg.lstsq(self.matrix, self._inner_value() - self.offset, rcond=None)[0]

    def _inner_value(self) -> np.ndarray:
        return np.concatenate([c.value() for c in self.controls])

    @override
    def check(self, simulation: "Simulation") -> None:
        ControlSet(self.controls, simulation)  # each belongs to it, footprints disjoint

    @override
    def footprint(self) -> set[tuple]:
        return set().union(*(c.footprint() for c in self.controls))

    @override
    @property
    def size(self) -> int:
        return self.matrix.shape[1]

    @override
    def value(self) -> np.ndarray:
        return self.q.copy()

    @override
    def assign(self, q: np.ndarray) -> None:
        q = np.asarray(q, dtype=float)
        p = self.matrix @ q + self.offset
        undo_on_refusal(functools.partial(setattr, self, "q", self.q))
        for c, a, b in zip(self.controls, self._offsets[:-1], self._offsets[1:], strict=True):
            c.assign(p[a:b])
        self.q = q.copy()

    @override
    def targets(self) -> Targets:
        t = Targets()
        for c in self.controls:
            t = t | c.targets()
        return t

    @override
    def pullback(self, sens: Sensitivities) -> np.ndarray:
        g = np.concatenate([c.pullback(sens) for c in self.controls])
        return self.matrix.T @ g

    @override
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self._lower.copy(), self._upper.copy()
