"""Box constraints of the parameters: checks, projection, active set and step limits."""

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from diffsolids.optimize.options import OptimizationError

if TYPE_CHECKING:
    from diffsolids.controls import ControlSet

__all__ = [
    "active_set",
    "block_limits",
    "check_bounds",
    "project",
    "projected_gradient",
    "step_limit",
]


def _blocks(controls: "ControlSet") -> list[tuple[str, slice]]:
    offsets = controls.offsets
    return [
        (c.name, slice(int(a), int(b)))
        for c, a, b in zip(controls.controls, offsets[:-1], offsets[1:], strict=True)
    ]


def _where(controls: "ControlSet", index: int) -> str:
    for name, sl in _blocks(controls):
        if sl.start <= index < sl.stop:
            return f"{name}[{index - sl.start}]"
    return f"q[{index}]"


def check_bounds(
    q: np.ndarray, lower: np.ndarray, upper: np.ndarray, controls: "ControlSet"
) -> None:
    """Raise OptimizationError if the bounds are malformed or exclude ``q``.

    Args:
        q: Parameters.
        lower: Lower bounds (may be -inf).
        upper: Upper bounds (may be +inf).
        controls: The ControlSet (names the offending parameters).
    """
    if lower.shape != q.shape or upper.shape != q.shape:
        raise OptimizationError(
            f"bounds have shapes {lower.shape} and {upper.shape}, the parameters {q.shape}"
        )
    if np.any(np.isnan(lower)) or np.any(np.isnan(upper)):
        raise OptimizationError("bounds contain NaN")
    crossed = np.flatnonzero(lower > upper)
    if crossed.size:
        names = ", ".join(_where(controls, i) for i in crossed[:5])
        raise OptimizationError(
            f"lower bound above upper bound for {crossed.size} parameters: {names}"
        )
    outside = np.flatnonzero((q < lower) | (q > upper))
    if outside.size:
        shown = ", ".join(
            f"{_where(controls, i)} = {q[i]:.6g} not in [{lower[i]:.6g}, {upper[i]:.6g}]"
            for i in outside[:5]
        )
        raise OptimizationError(
            f"the bounds exclude the initial point ({outside.size} parameters): {shown}"
        )


def project(q: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Closest point of the box."""
    return np.clip(q, lower, upper)


def projected_gradient(
    q: np.ndarray, g: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> np.ndarray:
    """``P(q - g) - q``: zero exactly at a first-order (KKT) point of the box problem."""
    return project(q - g, lower, upper) - q


def active_set(q: np.ndarray, g: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Variables at a bound whose gradient pushes them outwards (they stay fixed)."""
    return ((q <= lower) & (g > 0)) | ((q >= upper) & (g < 0))


def block_limits(
    max_change: float | Sequence[float | None] | Mapping[str | int, float | None] | None,
    controls: "ControlSet",
) -> list[tuple[slice, float]]:
    """Per-control-block limits of the max-norm of a step.

    Args:
        max_change: None, one number, a sequence (one entry per control, None: no limit) or
            a mapping from control name or index to a limit.
        controls: The ControlSet.
    """
    if max_change is None:
        return []
    blocks = _blocks(controls)
    if isinstance(max_change, Mapping):
        names = [name for name, _ in blocks]
        unknown = [k for k in max_change if k not in names and k not in range(len(blocks))]
        if unknown:
            raise OptimizationError(f"max_change names unknown controls {unknown}; have {names}")
        limits = [max_change.get(name, max_change.get(k)) for k, (name, _) in enumerate(blocks)]
    elif isinstance(max_change, Sequence) and not isinstance(max_change, str):
        if len(max_change) != len(blocks):
            raise OptimizationError(
                f"max_change has {len(max_change)} entries for {len(blocks)} controls"
            )
        limits = list(max_change)
    else:
        limits = [max_change] * len(blocks)
    out = []
    for (name, sl), limit in zip(blocks, limits, strict=True):
        if limit is None:
            continue
        if not float(limit) > 0:
            raise OptimizationError(f"max_change of control {name} must be positive, not {limit}")
        out.append((sl, float(limit)))
    return out


def step_limit(d: np.ndarray, limits: list[tuple[slice, float]]) -> float:
    """Largest t with ``|t d_b|_inf <= limit_b`` for every limited block b (inf if none)."""
    t = np.inf
    for sl, limit in limits:
        m = float(np.max(np.abs(d[sl]), initial=0.0))
        if m > 0:
            t = min(t, limit / m)
    return t
