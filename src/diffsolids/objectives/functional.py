"""Objectives as expression trees over per-step integrals (paper sec. 9.1, eq. 23).

An objective is a scalar built from *step series*: the values s_i, i = 0..N, of a quantity at
every step. Leaves are :class:`Integral` (a UFL integral of the step's fields, evaluated at u^i,
v^i); series combine elementwise (+, -, *, /, powers, functions) and reduce to scalars with time
weights (:func:`time_integral`, :func:`final_value`). Scalars combine again (sums, products,
powers, quotients) and with discrete regularisers. The chain rule runs through the tree once per
gradient and leaves every Integral with a weight per step, so the adjoint assembles a single
combined form per step.
"""

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partialmethod
from typing import TYPE_CHECKING, override

import numpy as np
import numpy.typing as npt
import ufl

from diffsolids.errors import DiffsolidsError

if TYPE_CHECKING:
    from diffsolids.model import Model, StepFields

__all__ = [
    "Integral",
    "NumericIntegral",
    "Objective",
    "ObjectiveError",
    "Regulariser",
    "Series",
    "SeriesObjective",
    "TimeGrid",
    "check_finite_steps",
    "final_value",
    "series_name",
    "time_integral",
]


class ObjectiveError(DiffsolidsError, ValueError):
    """An objective that cannot be evaluated (unknown steps, tags, non-finite values)."""


@dataclass(frozen=True)
class TimeGrid:
    """Steps 0..N of size dt of the simulation an objective is evaluated on."""

    num_steps: int
    dt: float
    dynamic: bool


def _wrap(other: object, kind: "type[Series] | type[Objective]") -> "Series | Objective":
    if isinstance(other, kind):
        return other
    if np.isscalar(other):
        return (ConstantSeries if kind is Series else ConstantObjective)(float(other))
    return NotImplemented


class _Algebra:
    """Elementwise algebra shared by series and scalar objectives.

    A subclass names its kind (Series or Objective) and the node types of its results: a
    binary operation and an elementwise function.
    """

    _kind: type
    _binary_node: type
    _mapped_node: type
    # a short name for labels and messages (None: the type's name is used)
    name: str | None = None

    def _operation(
        self, other: "_Algebra | float", op: str, reflected: bool = False
    ) -> "Series | Objective":
        """``self op other`` (``other op self`` when ``reflected``); numbers become constants."""
        other = _wrap(other, self._kind)
        if other is NotImplemented:
            return NotImplemented
        return other._binary(self, op) if reflected else self._binary(other, op)

    __add__ = __radd__ = partialmethod(_operation, op="+")
    __sub__ = partialmethod(_operation, op="-")
    __rsub__ = partialmethod(_operation, op="-", reflected=True)
    __mul__ = __rmul__ = partialmethod(_operation, op="*")
    __truediv__ = partialmethod(_operation, op="/")
    __rtruediv__ = partialmethod(_operation, op="/", reflected=True)

    def __pow__(self, p: float) -> "Series | Objective":
        return self.apply(lambda x: x**p, lambda x: p * x ** (p - 1), f"pow{p}")

    def __neg__(self) -> "Series | Objective":
        return self * -1.0

    def _binary(self, other: "_Algebra", op: str) -> "Series | Objective":
        return self._binary_node(self, other, op)

    def apply(self, fn: Callable, dfn: Callable, name: str = "fn") -> "Series | Objective":
        """Elementwise ``fn`` with derivative ``dfn`` (e.g. ``np.sqrt`` and its derivative)."""
        return self._mapped_node(self, fn, dfn, name)


def _binary_grad(
    op: str, a: np.ndarray | float, b: np.ndarray | float
) -> tuple[np.ndarray | float, np.ndarray | float]:
    if op == "+":
        return 1.0, 1.0
    if op == "-":
        return 1.0, -1.0
    if op == "*":
        return b, a
    return 1.0 / b, -a / b**2


def _binary_value(op: str, a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray | float:
    if op == "+":
        return a + b
    if op == "-":
        return a - b
    if op == "*":
        return a * b
    return a / b


class Series(_Algebra):
    """Values of a quantity at every step 0..N."""

    def leaves(self) -> list["Integral | NumericIntegral"]:
        """Integrals this series depends on."""
        raise NotImplementedError

    def values(self, table: dict) -> np.ndarray:
        """Values at all steps from the leaf value table (NaN where not evaluated)."""
        raise NotImplementedError

    def backward(self, table: dict, seed: np.ndarray, out: dict) -> None:
        """Accumulate d(objective)/d(leaf value at step i) into ``out[leaf]``."""
        raise NotImplementedError


class _Leaf(Series):
    """A series whose per-step values are evaluated directly (a leaf of the value table)."""

    @override
    def leaves(self) -> list["Integral | NumericIntegral"]:
        return [self]  # type: ignore[list-item]  # every leaf is one of the two

    @override
    def values(self, table: dict) -> np.ndarray:
        return table[self]

    @override
    def backward(self, table: dict, seed: np.ndarray, out: dict) -> None:
        out[self] = out.get(self, 0.0) + seed


class Integral(_Leaf):
    """A UFL integral of the step fields: ``integrand(fields) -> scalar form``.

    ``fields`` is the model's :class:`~diffsolids.model.StepFields` (u, v, X, t, dx, ds,
    coefficients) holding u^i, v^i when step i is evaluated; any UFL expression of them works.
    """

    def __init__(self, integrand: Callable, name: str = "integral") -> None:
        self.integrand, self.name = integrand, name

    def form(self, fields: "StepFields") -> ufl.Form:
        """The scalar UFL form of this integral."""
        return self.integrand(fields)


class NumericIntegral(_Leaf):
    """A per-step leaf computed by numeric code instead of a UFL form (e.g. ipctk distances).

    Subclasses give the value at the state held by the model's fields (u^i, v^i, the step's
    time) and its partial derivatives; the ReducedFunctional evaluates it where an Integral
    would be assembled, and the backward sweep adds ``c_i dJ/du`` to the adjoint's right-hand
    side of step i and ``c_i dJ/dX`` to the shape sensitivity, with c_i the chain-rule weight.
    """

    name = "numeric integral"

    def form(self, fields: "StepFields") -> ufl.Form:
        """Refused: a numeric leaf has no UFL form."""
        raise ObjectiveError(
            f"{self.name!r} is computed by numeric code, not a UFL form: it needs a "
            "ReducedFunctional that evaluates numeric objective leaves"
        )

    def evaluate(self, model: "Model") -> float:
        """The value at the state in ``model.fields`` (collective; the same on every rank)."""
        raise NotImplementedError

    def state_gradient(self, model: "Model") -> np.ndarray:
        """dJ/du as a local array of the displacement space (owned entries; ghosts zero)."""
        raise NotImplementedError

    def shape_gradient(self, model: "Model") -> np.ndarray | None:
        """dJ/dX on the owned entries of ``model.shape_space`` (None: no shape dependence)."""
        return None


class DataSeries(Series):
    """Values that are data, not integrals of the state: no leaves, no derivatives."""

    @staticmethod
    def num_states(table: dict, default: int) -> int:
        """States of the run whose leaf values ``table`` holds (``default`` without leaves)."""
        return len(next(iter(table.values()))) if table else default

    @override
    def leaves(self) -> list["Integral | NumericIntegral"]:
        return []

    @override
    def backward(self, table: dict, seed: np.ndarray, out: dict) -> None:
        pass


class ConstantSeries(DataSeries):
    """The same value at every step."""

    def __init__(self, value: float) -> None:
        self.value = value

    @override
    def values(self, table: dict) -> np.ndarray:
        return np.full(self.num_states(table, 1), self.value)


class _BinaryNode:
    """a (op) b of two series or two objectives: the operands and the integrals they read."""

    def __init__(self, a: "Series | Objective", b: "Series | Objective", op: str) -> None:
        self.a, self.b, self.op = a, b, op

    def leaves(self) -> list["Integral | NumericIntegral"]:
        """Integrals of both operands."""
        return self.a.leaves() + self.b.leaves()


class _MappedNode:
    """fn(a) of a series or an objective, with the derivative dfn."""

    def __init__(self, a: "Series | Objective", fn: Callable, dfn: Callable, name: str) -> None:
        self.a, self.fn, self.dfn, self.name = a, fn, dfn, name

    def leaves(self) -> list["Integral | NumericIntegral"]:
        """Integrals of the operand."""
        return self.a.leaves()


class BinarySeries(_BinaryNode, Series):
    """Elementwise a (op) b."""

    a: Series
    b: Series

    @override
    def values(self, table: dict) -> np.ndarray:
        return _binary_value(self.op, self.a.values(table), self.b.values(table))

    @override
    def backward(self, table: dict, seed: np.ndarray, out: dict) -> None:
        da, db = _binary_grad(self.op, self.a.values(table), self.b.values(table))
        self.a.backward(table, _masked(seed, da), out)
        self.b.backward(table, _masked(seed, db), out)


class MappedSeries(_MappedNode, Series):
    """Elementwise fn(a)."""

    a: Series

    @override
    def values(self, table: dict) -> np.ndarray:
        return self.fn(self.a.values(table))

    @override
    def backward(self, table: dict, seed: np.ndarray, out: dict) -> None:
        self.a.backward(table, _masked(seed, self.dfn(self.a.values(table))), out)


Series._kind, Series._binary_node, Series._mapped_node = Series, BinarySeries, MappedSeries


def _masked(seed: npt.ArrayLike, factor: npt.ArrayLike) -> np.ndarray:
    """Seed * factor, exactly zero where seed is zero (factor may be NaN there)."""
    seed = np.asarray(seed, dtype=float)
    factor = np.broadcast_to(np.asarray(factor, dtype=float), seed.shape)
    return np.where(seed != 0.0, seed * np.where(seed != 0.0, factor, 0.0), 0.0)


# -- scalar objectives -------------------------------------------------------------------------
class Objective(_Algebra):
    """A scalar objective J."""

    def leaves(self) -> list["Integral | NumericIntegral"]:
        """Integrals the objective depends on."""
        raise NotImplementedError

    def regularisers(self) -> list["Regulariser"]:
        """Discrete regularisers the objective depends on."""
        raise NotImplementedError

    def reduced_series(self) -> list["Series"]:
        """The series the objective reduces over the steps (time integrals, soft minima).

        In the order of the expression, a series as often as it is reduced; none by default.
        """
        return []

    def value(self, table: dict, reg: dict, grid: TimeGrid) -> float:
        """J from leaf values (``table``) and regulariser values (``reg``)."""
        raise NotImplementedError

    def backward(
        self, table: dict, reg: dict, grid: TimeGrid, seed: float, out: dict, reg_out: dict
    ) -> None:
        """Accumulate dJ/d(leaf at step i) into ``out`` and dJ/d(regulariser) into ``reg_out``."""
        raise NotImplementedError

    def requirements(self, grid: TimeGrid) -> dict:
        """Steps at which each leaf must be evaluated: ``{leaf: set of steps}``."""
        raise NotImplementedError


def _merge(*dicts: dict) -> dict:
    out: dict = {}
    for d in dicts:
        for k, v in d.items():
            out.setdefault(k, set()).update(v)
    return out


class _TrajectoryFree(Objective):
    """Base of the scalar objectives that read no step: no integrals, no steps to evaluate."""

    @override
    def leaves(self) -> list["Integral | NumericIntegral"]:
        return []

    @override
    def requirements(self, grid: TimeGrid) -> dict:
        return {}


class ConstantObjective(_TrajectoryFree):
    """A constant."""

    def __init__(self, value: float) -> None:
        self.c = value

    @override
    def regularisers(self) -> list["Regulariser"]:
        return []

    @override
    def value(self, table: dict, reg: dict, grid: TimeGrid) -> float:
        return self.c

    @override
    def backward(
        self, table: dict, reg: dict, grid: TimeGrid, seed: float, out: dict, reg_out: dict
    ) -> None:
        pass


class BinaryObjective(_BinaryNode, Objective):
    """a (op) b of scalar objectives."""

    a: Objective
    b: Objective

    @override
    def regularisers(self) -> list["Regulariser"]:
        return self.a.regularisers() + self.b.regularisers()

    @override
    def reduced_series(self) -> list["Series"]:
        return self.a.reduced_series() + self.b.reduced_series()

    @override
    def value(self, table: dict, reg: dict, grid: TimeGrid) -> float:
        return _binary_value(
            self.op, self.a.value(table, reg, grid), self.b.value(table, reg, grid)
        )

    @override
    def requirements(self, grid: TimeGrid) -> dict:
        return _merge(self.a.requirements(grid), self.b.requirements(grid))

    @override
    def backward(
        self, table: dict, reg: dict, grid: TimeGrid, seed: float, out: dict, reg_out: dict
    ) -> None:
        a, b = self.a.value(table, reg, grid), self.b.value(table, reg, grid)
        da, db = _binary_grad(self.op, a, b)
        self.a.backward(table, reg, grid, seed * da, out, reg_out)
        self.b.backward(table, reg, grid, seed * db, out, reg_out)


class MappedObjective(_MappedNode, Objective):
    """fn(a) of a scalar objective."""

    a: Objective

    @override
    def regularisers(self) -> list["Regulariser"]:
        return self.a.regularisers()

    @override
    def reduced_series(self) -> list["Series"]:
        return self.a.reduced_series()

    @override
    def value(self, table: dict, reg: dict, grid: TimeGrid) -> float:
        return float(self.fn(self.a.value(table, reg, grid)))

    @override
    def requirements(self, grid: TimeGrid) -> dict:
        return self.a.requirements(grid)

    @override
    def backward(
        self, table: dict, reg: dict, grid: TimeGrid, seed: float, out: dict, reg_out: dict
    ) -> None:
        a = self.a.value(table, reg, grid)
        self.a.backward(table, reg, grid, seed * float(self.dfn(a)), out, reg_out)


Objective._kind = Objective
Objective._binary_node, Objective._mapped_node = BinaryObjective, MappedObjective


def series_name(series: Series) -> str:
    """A short name of a series for messages (the Integral's or node's name, else its type)."""
    return str(series.name or type(series).__name__)


def check_finite_steps(series: Series, values: np.ndarray, steps: npt.ArrayLike) -> None:
    """Raise if the series is not finite at one of the steps an objective uses.

    Raises:
        ObjectiveError: Naming the series, the first offending steps and their values.
    """
    steps = np.asarray(steps, dtype=int)
    bad = steps[~np.isfinite(values[steps])]
    if bad.size:
        shown = ", ".join(f"step {i}: {values[i]}" for i in bad[:5])
        raise ObjectiveError(
            f"the series {series_name(series)!r} is not finite at {bad.size} step(s) the "
            f"objective uses ({shown}{', ...' if bad.size > 5 else ''})"
        )


def step_weights(spec: str | npt.ArrayLike, grid: TimeGrid) -> np.ndarray:
    """Weights w_0..w_N of a time reduction.

    Args:
        spec: "uniform" (w_0 = 0, w_i = dt), "sum" (w_0 = 0, w_i = 1: a plain sum over the
            computed steps), "trapezoidal", "final" (w_N = 1), a sequence of step indices
            (weight 1 each; negative indices count from the end) or an array of N + 1 weights.
        grid: The simulation's steps.
    """
    n = grid.num_steps
    w = np.zeros(n + 1)
    if isinstance(spec, str):
        if spec == "uniform":
            w[1:] = grid.dt
        elif spec == "sum":
            w[1:] = 1.0
        elif spec == "trapezoidal":
            w[:] = grid.dt
            w[0] = w[-1] = grid.dt / 2
        elif spec == "final":
            w[-1] = 1.0
        else:
            raise ObjectiveError(f"unknown time weighting {spec!r}")
        return w
    arr = np.asarray(spec)
    if arr.dtype.kind in "iu":
        if np.any(arr > n) or np.any(arr < -(n + 1)):
            raise ObjectiveError(f"objective refers to steps {arr.tolist()} but the run has 0..{n}")
        np.add.at(w, arr, 1.0)
        return w
    if arr.shape != (n + 1,):
        raise ObjectiveError(f"expected {n + 1} time weights, got shape {arr.shape}")
    return arr.astype(float)


class SeriesObjective(Objective):
    """Base of the scalar objectives reduced from one Series over the steps.

    A subclass sets ``self.series`` and implements ``value`` and ``backward``; the leaves are
    the series' and there are no regularisers.
    """

    series: Series

    @override
    def leaves(self) -> list["Integral | NumericIntegral"]:
        return self.series.leaves()

    @override
    def regularisers(self) -> list["Regulariser"]:
        return []

    @override
    def reduced_series(self) -> list["Series"]:
        return [self.series]


class TimeIntegral(SeriesObjective):
    """sum_i w_i s_i of a series (paper eq. 4 objective with weights w_i)."""

    def __init__(self, series: Series, spec: str | npt.ArrayLike) -> None:
        self.series, self.spec = series, spec

    @override
    def value(self, table: dict, reg: dict, grid: TimeGrid) -> float:
        w = step_weights(self.spec, grid)
        s = np.broadcast_to(self.series.values(table), w.shape)
        check_finite_steps(self.series, s, np.flatnonzero(w))
        return float(np.sum(np.where(w != 0.0, w * np.where(w != 0.0, s, 0.0), 0.0)))

    @override
    def backward(
        self, table: dict, reg: dict, grid: TimeGrid, seed: float, out: dict, reg_out: dict
    ) -> None:
        self.series.backward(table, seed * step_weights(self.spec, grid), out)

    @override
    def requirements(self, grid: TimeGrid) -> dict:
        steps = set(np.flatnonzero(step_weights(self.spec, grid)).tolist())
        return {leaf: set(steps) for leaf in self.series.leaves()}


def time_integral(series: Series, weights: str | Sequence = "uniform") -> Objective:
    """Reduce a series with time weights ("uniform", "sum", "trapezoidal", "final", steps, ...)."""
    if not isinstance(series, Series):
        raise ObjectiveError("time_integral expects a Series (e.g. an Integral)")
    return TimeIntegral(series, weights)


def final_value(series: Series) -> Objective:
    """The series at the last step (static problems: the solution)."""
    return TimeIntegral(series, "final")


class Regulariser(_TrajectoryFree):
    """A discrete term of the rest shape and/or parameter fields (not of the trajectory).

    Subclasses implement :meth:`evaluate` returning the value and :meth:`gradient` returning a
    dict of partial derivatives keyed like the adjoint's sensitivities ("shape" on the P1
    vector space of the mesh, or a coefficient name).
    """

    @override
    def regularisers(self) -> list["Regulariser"]:
        return [self]

    @override
    def value(self, table: dict, reg: dict, grid: TimeGrid) -> float:
        return reg[self]

    @override
    def backward(
        self, table: dict, reg: dict, grid: TimeGrid, seed: float, out: dict, reg_out: dict
    ) -> None:
        reg_out[self] = reg_out.get(self, 0.0) + seed

    def evaluate(self, model: "Model") -> float:
        """Value of the regulariser for the model's current shape and parameters."""
        raise NotImplementedError

    def gradient(self, model: "Model") -> dict[str, np.ndarray]:
        """Partial derivatives (owned entries, local layout of the target)."""
        raise NotImplementedError
