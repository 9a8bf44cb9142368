"""The stages of a stiffness continuation, and their refinement where a stage fails."""

from collections.abc import Sequence

import numpy as np

__all__ = ["ContinuationPath"]

# a failed stage is split while its stiffness ratio to the last converged stage is above
# _MIN_SPLIT_RATIO, at most _MAX_SPLITS times per solve
_MIN_SPLIT_RATIO = 2.0
_MAX_SPLITS = 3


class ContinuationPath:
    """Stiffness factors of several terms at stage positions from 0 to ``stages``.

    Position k (an integer below ``stages``) holds each term's k-th factor (1 beyond the
    end of its schedule); position ``stages`` is the terms' own stiffness (every factor 1).
    Between integer positions the factors are interpolated geometrically, so the stage
    halfway between two positions has the geometric mean of their factors.
    """

    def __init__(self, schedules: Sequence[Sequence[float]]) -> None:
        """Set up the path of the terms' schedules.

        Args:
            schedules: Per term, its factors (each > 1, decreasing); may be empty.
        """
        self.stages = max((len(s) for s in schedules), default=0)
        grid = range(self.stages + 1)
        self._factors = np.array(
            [[s[k] if k < len(s) else 1.0 for k in grid] for s in schedules], dtype=float
        ).reshape(len(schedules), self.stages + 1)
        self.positions: list[float] = [float(k) for k in grid]
        self.splits = 0

    def factors(self, position: float) -> list[float]:
        """Each term's stiffness factor at ``position`` (its schedule's own at an integer)."""
        if float(position).is_integer():
            return [float(f) for f in self._factors[:, int(position)]]
        grid = np.arange(self.stages + 1, dtype=float)
        return [float(np.exp(np.interp(position, grid, np.log(row)))) for row in self._factors]

    def largest_factors(self) -> tuple[float, ...]:
        """The largest factor of the terms at each position but the last (for reports)."""
        return tuple(max(self.factors(p), default=1.0) for p in self.positions[:-1])

    def can_split(self, index: int, converged_at: float | None) -> bool:
        """Whether a failure of the stage at ``index`` would be split (see :meth:`split`)."""
        if converged_at is None or self.splits >= _MAX_SPLITS:
            return False
        position = self.positions[index]
        ratio = max(
            (
                a / b
                for a, b in zip(self.factors(converged_at), self.factors(position), strict=True)
            ),
            default=1.0,
        )
        return ratio > _MIN_SPLIT_RATIO

    def split(self, index: int, converged_at: float | None) -> bool:
        """Insert a stage before ``positions[index]``, halfway from ``converged_at``.

        Args:
            index: The failed stage's index in ``positions``.
            converged_at: The position of the last stage that converged (before ``index``;
                None: none did, nothing to split from).

        Returns:
            Whether a stage was inserted (not when the two stages' factors are within
            ``_MIN_SPLIT_RATIO`` of each other or the solve has used its splits).
        """
        if not self.can_split(index, converged_at):
            return False
        position = self.positions[index]
        self.positions.insert(index, 0.5 * (converged_at + position))
        self.splits += 1
        return True
