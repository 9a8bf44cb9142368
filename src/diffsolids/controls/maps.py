"""Parameter maps: the differentiable change of variables between q and a physical value.

A control stores its parameters q and writes the physical value p = map(q) into the model; its
gradient is pulled back through the map's vector-Jacobian product. Every map here acts entry by
entry, so the Jacobian is diagonal and the product is ``g * dp/dq``. Maps compose:
``Compose(Power(3.0), Affine(scale=E0))`` is ``p = E0 * q**3``.

A new parametrisation is one subclass of :class:`ParameterMap` with ``forward``, ``derivative``
and ``inverse``; every control that takes ``map=`` then accepts it.
"""

from abc import ABC, abstractmethod

import numpy as np

from diffsolids.controls.base import ControlError

__all__ = ["Affine", "Compose", "Identity", "Log", "ParameterMap", "Power", "Simp", "as_map"]


class ParameterMap(ABC):
    """An entrywise, invertible, differentiable map p = f(q) from parameters to values."""

    name: str = "map"

    @abstractmethod
    def forward(self, q: np.ndarray) -> np.ndarray:
        """Physical values p = f(q)."""

    @abstractmethod
    def derivative(self, q: np.ndarray) -> np.ndarray:
        """Entrywise dp/dq at q."""

    @abstractmethod
    def inverse(self, p: np.ndarray) -> np.ndarray:
        """Parameters q with f(q) = p; ControlError if p is outside the map's range."""

    def pullback(self, q: np.ndarray, grad_p: np.ndarray) -> np.ndarray:
        """dJ/dq from dJ/dp (the chain rule)."""
        return np.asarray(grad_p, dtype=float) * self.derivative(np.asarray(q, dtype=float))

    def bounds(self) -> tuple[float, float]:
        """The interval of q on which the map is defined and invertible."""
        return -np.inf, np.inf

    def __repr__(self) -> str:
        return self.name


class Identity(ParameterMap):
    """p = q."""

    name = "identity"

    def forward(self, q: np.ndarray) -> np.ndarray:  # noqa: D102
        return np.asarray(q, dtype=float).copy()

    def derivative(self, q: np.ndarray) -> np.ndarray:  # noqa: D102
        return np.ones_like(np.asarray(q, dtype=float))

    def inverse(self, p: np.ndarray) -> np.ndarray:  # noqa: D102
        return np.asarray(p, dtype=float).copy()


class Log(ParameterMap):
    """p = exp(q): q is the logarithm of a positive value (scale-free steps for E, mu, ...)."""

    name = "log"

    def forward(self, q: np.ndarray) -> np.ndarray:  # noqa: D102
        with np.errstate(over="ignore"):  # inf: refused by the model's check, naming the field
            return np.exp(np.asarray(q, dtype=float))

    def derivative(self, q: np.ndarray) -> np.ndarray:  # noqa: D102
        with np.errstate(over="ignore"):
            return np.exp(np.asarray(q, dtype=float))

    def inverse(self, p: np.ndarray) -> np.ndarray:  # noqa: D102
        p = np.asarray(p, dtype=float)
        if np.any(p <= 0):
            raise ControlError(f"log parametrisation needs positive values (smallest {p.min()})")
        return np.log(p)


class Affine(ParameterMap):
    """p = scale * q + shift (scale != 0): nondimensional parameters of order one."""

    def __init__(self, scale: float = 1.0, shift: float = 0.0) -> None:
        if scale == 0 or not np.isfinite(scale) or not np.isfinite(shift):
            raise ControlError(f"affine map needs a finite nonzero scale (got {scale}, {shift})")
        self.scale, self.shift = float(scale), float(shift)
        self.name = f"affine({self.scale:g}, {self.shift:g})"

    def forward(self, q: np.ndarray) -> np.ndarray:  # noqa: D102
        return self.scale * np.asarray(q, dtype=float) + self.shift

    def derivative(self, q: np.ndarray) -> np.ndarray:  # noqa: D102
        return np.full_like(np.asarray(q, dtype=float), self.scale)

    def inverse(self, p: np.ndarray) -> np.ndarray:  # noqa: D102
        return (np.asarray(p, dtype=float) - self.shift) / self.scale


class Power(ParameterMap):
    """p = q**k for q >= 0 (k > 0)."""

    def __init__(self, exponent: float) -> None:
        if not exponent > 0:
            raise ControlError(f"power map needs a positive exponent, got {exponent}")
        self.exponent = float(exponent)
        self.name = f"power({self.exponent:g})"

    def forward(self, q: np.ndarray) -> np.ndarray:  # noqa: D102
        return np.asarray(q, dtype=float) ** self.exponent

    def derivative(self, q: np.ndarray) -> np.ndarray:  # noqa: D102
        q = np.asarray(q, dtype=float)
        return self.exponent * q ** (self.exponent - 1.0)

    def inverse(self, p: np.ndarray) -> np.ndarray:  # noqa: D102
        p = np.asarray(p, dtype=float)
        if np.any(p < 0):
            raise ControlError(f"power map needs nonnegative values (smallest {p.min()})")
        return p ** (1.0 / self.exponent)

    def bounds(self) -> tuple[float, float]:  # noqa: D102
        return 0.0, np.inf


class Simp(ParameterMap):
    """SIMP interpolation p = low + (high - low) q**k of a density q in [0, 1].

    Args:
        low: Value at q = 0 (a small positive stiffness keeps the problem solvable).
        high: Value at q = 1.
        exponent: Penalisation k (3 is the usual choice).
    """

    def __init__(self, low: float, high: float, exponent: float = 3.0) -> None:
        if not (np.isfinite(low) and np.isfinite(high) and high > low):
            raise ControlError(f"SIMP map needs low < high, got low={low}, high={high}")
        self.low, self.high = float(low), float(high)
        self._power = Power(exponent)
        self.name = f"simp({self.low:g}, {self.high:g}, {exponent:g})"

    def forward(self, q: np.ndarray) -> np.ndarray:  # noqa: D102
        return self.low + (self.high - self.low) * self._power.forward(q)

    def derivative(self, q: np.ndarray) -> np.ndarray:  # noqa: D102
        return (self.high - self.low) * self._power.derivative(q)

    def inverse(self, p: np.ndarray) -> np.ndarray:  # noqa: D102
        p = np.asarray(p, dtype=float)
        if np.any(p < self.low) or np.any(p > self.high):
            raise ControlError(
                f"SIMP map: values must lie in [{self.low:g}, {self.high:g}] "
                f"(got {p.min():g}..{p.max():g})"
            )
        return self._power.inverse((p - self.low) / (self.high - self.low))

    def bounds(self) -> tuple[float, float]:  # noqa: D102
        return 0.0, 1.0


class Compose(ParameterMap):
    """p = maps[-1](...maps[0](q)): the first map acts on q."""

    def __init__(self, *maps: ParameterMap) -> None:
        if not maps or not all(isinstance(m, ParameterMap) for m in maps):
            raise ControlError("Compose takes one or more ParameterMap objects")
        self.maps = maps
        self.name = " -> ".join(m.name for m in maps)

    def _stages(self, q: np.ndarray) -> list[np.ndarray]:
        stages = [np.asarray(q, dtype=float)]
        for m in self.maps:
            stages.append(m.forward(stages[-1]))
        return stages

    def forward(self, q: np.ndarray) -> np.ndarray:  # noqa: D102
        return self._stages(q)[-1]

    def derivative(self, q: np.ndarray) -> np.ndarray:  # noqa: D102
        stages = self._stages(q)
        out = np.ones_like(stages[0])
        for m, x in zip(self.maps, stages[:-1], strict=True):
            out = out * m.derivative(x)
        return out

    def inverse(self, p: np.ndarray) -> np.ndarray:  # noqa: D102
        for m in reversed(self.maps):
            p = m.inverse(p)
        return p

    def bounds(self) -> tuple[float, float]:  # noqa: D102
        return self.maps[0].bounds()


def as_map(map: ParameterMap | None, log: bool = False) -> ParameterMap:
    """The map of a control's ``map=``/``log=`` arguments (``log=True`` is ``Log()``)."""
    if map is not None and log:
        raise ControlError("give either map= or log=True, not both")
    if map is None:
        return Log() if log else Identity()
    if not isinstance(map, ParameterMap):
        raise ControlError(f"map must be a ParameterMap, got {type(map).__name__}")
    return map
