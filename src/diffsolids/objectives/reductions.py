"""Smooth minima of a step series over chosen steps (PolyFEM's ``min-dist-target``).

A series s_0..s_N reduced to a differentiable approximation of min_i s_i over steps S:

* ``"logsumexp"``: m_alpha = -1/alpha log sum_{i in S} exp(-alpha s_i). It lies in
  [min s - log|S| / alpha, min s] and tends to the minimum as alpha grows; alpha has the
  inverse unit of s (choose alpha ~ a few over the spread of s that should be told apart).
* ``"harmonic"``: m = 1 / sum_{i in S} 1 / s_i for positive s (PolyFEM's choice), in
  [min s / |S|, min s].

The chain rule passes softmax weights p_i = dm/ds_i (summing to 1 for logsumexp) to the
series, so the adjoint sees only the steps that are nearly minimal.
"""

from collections.abc import Sequence
from typing import TYPE_CHECKING, override

import numpy as np
import numpy.typing as npt

from diffsolids.errors import ParameterError
from diffsolids.objectives.functional import (
    Objective,
    ObjectiveError,
    Series,
    SeriesObjective,
    TimeGrid,
    check_finite_steps,
    series_name,
    step_weights,
)
from diffsolids.objectives.library import Tags, center_of_mass_trajectory

if TYPE_CHECKING:
    from diffsolids.model import Model

__all__ = ["SoftMin", "min_distance_target", "soft_min"]

_KINDS = ("logsumexp", "harmonic")


class SoftMin(SeriesObjective):
    """A smooth minimum of a series over steps (see the module docstring).

    Args:
        series: The Series.
        steps: The steps S (indices, negative ones count from the end); None: 1..N.
        alpha: Sharpness of "logsumexp" (> 0); unused by "harmonic".
        kind: "logsumexp" or "harmonic".
    """

    def __init__(
        self, series: Series, steps: Sequence[int] | None, alpha: float, kind: str
    ) -> None:
        if not isinstance(series, Series):
            raise ObjectiveError("soft_min expects a Series (e.g. a distance per step)")
        if kind not in _KINDS:
            raise ParameterError(f"unknown soft minimum {kind!r}; choose from {_KINDS}")
        if kind == "logsumexp" and not (np.isfinite(alpha) and alpha > 0):
            raise ParameterError(f"soft_min needs alpha > 0, got {alpha}")
        self.series, self.spec, self.alpha, self.kind = series, steps, float(alpha), kind
        self.name = f"softmin({series_name(series)})"

    def steps(self, grid: TimeGrid) -> np.ndarray:
        """The steps S of the run (sorted, each once)."""
        if self.spec is None:
            return np.arange(1, grid.num_steps + 1) if grid.num_steps else np.array([0])
        arr = np.asarray(self.spec)
        if arr.dtype.kind not in "iu" or arr.ndim != 1 or arr.size == 0:
            raise ObjectiveError("soft_min steps must be a non-empty list of step indices")
        return np.flatnonzero(step_weights(arr, grid))

    def _selected(self, table: dict, grid: TimeGrid) -> tuple[np.ndarray, np.ndarray]:
        steps = self.steps(grid)
        values = np.broadcast_to(self.series.values(table), (grid.num_steps + 1,))
        check_finite_steps(self.series, values, steps)
        s = values[steps]
        if self.kind == "harmonic" and np.any(s <= 0):
            i = int(steps[np.argmax(s <= 0)])
            raise ObjectiveError(
                f"harmonic soft minimum of {series_name(self.series)!r} needs positive values; "
                f"step {i} has {values[i]} (use kind='logsumexp')"
            )
        return steps, s

    def _value_and_weights(self, s: np.ndarray) -> tuple[float, np.ndarray]:
        if self.kind == "harmonic":
            m = 1.0 / np.sum(1.0 / s)
            return float(m), m**2 / s**2
        # shifted by the minimum: no overflow for any alpha
        low = np.min(s)
        e = np.exp(-self.alpha * (s - low))
        total = np.sum(e)
        return float(low - np.log(total) / self.alpha), e / total

    @override
    def value(self, table: dict, reg: dict, grid: TimeGrid) -> float:
        _, s = self._selected(table, grid)
        return self._value_and_weights(s)[0]

    @override
    def backward(
        self, table: dict, reg: dict, grid: TimeGrid, seed: float, out: dict, reg_out: dict
    ) -> None:
        steps, s = self._selected(table, grid)
        full = np.zeros(grid.num_steps + 1)
        full[steps] = seed * self._value_and_weights(s)[1]
        self.series.backward(table, full, out)

    @override
    def requirements(self, grid: TimeGrid) -> dict:
        steps = set(self.steps(grid).tolist())
        return {leaf: set(steps) for leaf in self.series.leaves()}


def soft_min(
    series: Series,
    steps: Sequence[int] | None = None,
    alpha: float = 1.0,
    kind: str = "logsumexp",
) -> Objective:
    """A smooth minimum of a per-step series over steps (see the module docstring).

    Args:
        series: The Series (e.g. a distance per step).
        steps: Steps to take the minimum over (default: the computed steps 1..N).
        alpha: Sharpness of the log-sum-exp minimum (> 0, in the inverse unit of the series):
            the value is within log(number of steps) / alpha below the true minimum.
        kind: "logsumexp" (any sign) or "harmonic" (1 / sum 1/s_i, positive series).

    Raises:
        ParameterError: Unknown kind or alpha <= 0.
        ObjectiveError: Non-finite values (naming the step), non-positive values for
            "harmonic", steps outside the run.
    """
    return SoftMin(series, steps, alpha, kind)


def min_distance_target(
    model: "Model",
    target: npt.ArrayLike,
    steps: Sequence[int] | None = None,
    bodies: Tags = None,
    kind: str = "harmonic",
    alpha: float = 1.0,
) -> Objective:
    """Smooth minimum over steps of the squared distance of a centre of mass from a point.

    PolyFEM's ``min-dist-target`` (harmonic kind): the body should pass through ``target`` at
    some step of S, whichever. s_i = ||c^i - x^trg||^2 with c the deformed centre of mass.

    Args:
        model: The Model.
        target: The point (a vector of the mesh dimension).
        steps: The steps S (default 1..N).
        bodies: The bodies whose centre of mass is used (default: all).
        kind: "harmonic" (PolyFEM) or "logsumexp".
        alpha: Sharpness for "logsumexp" (inverse squared length).
    """
    target = np.asarray(target, dtype=float)
    if target.shape != (model.dim,):
        raise ParameterError(f"min_distance_target: target has shape {target.shape}")
    return SoftMin(center_of_mass_trajectory(model, target, bodies), steps, alpha, kind)
