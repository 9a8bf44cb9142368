"""The additive terms of an objective tree, with readable labels (for logs and histories)."""

from dataclasses import dataclass

import numpy as np

from diffsolids.objectives.functional import (
    BinaryObjective,
    BinarySeries,
    ConstantObjective,
    ConstantSeries,
    Integral,
    MappedObjective,
    MappedSeries,
    Objective,
    Regulariser,
    Series,
    TimeGrid,
    TimeIntegral,
)

__all__ = ["ObjectiveTerm", "objective_terms", "series_label", "term_label"]


@dataclass(frozen=True)
class ObjectiveTerm:
    """One addend ``sign * node`` of an objective that is a sum.

    Attributes:
        label: Readable name (Integral names, regulariser names, weights).
        node: The sub-objective.
        sign: +1 or -1 (a subtracted term).
    """

    label: str
    node: Objective
    sign: float

    def value(self, table: dict, reg: dict, grid: TimeGrid) -> float:
        """Signed value of the term (the terms' values sum to J)."""
        return self.sign * float(self.node.value(table, reg, grid))


def series_label(s: Series) -> str:
    """A short readable label of a series."""
    if isinstance(s, Integral):
        return s.name
    if isinstance(s, ConstantSeries):
        return f"{s.value:g}"
    if isinstance(s, BinarySeries):
        return f"({series_label(s.a)}{s.op}{series_label(s.b)})"
    if isinstance(s, MappedSeries):
        return f"{s.name}({series_label(s.a)})"
    return str(s.name or type(s).__name__)


def term_label(node: Objective) -> str:
    """A short readable label of a (sub-)objective."""
    if isinstance(node, TimeIntegral):
        inner = series_label(node.series)
        return inner if isinstance(node.spec, str) and node.spec == "final" else f"sum_t {inner}"
    if isinstance(node, ConstantObjective):
        return f"{node.c:g}"
    if isinstance(node, Regulariser):
        return str(node.name or type(node).__name__)
    if isinstance(node, MappedObjective):
        return f"{node.name}({term_label(node.a)})"
    if isinstance(node, BinaryObjective):
        if node.op == "*" and isinstance(node.a, ConstantObjective):
            return f"{node.a.c:g}*{term_label(node.b)}"
        if node.op == "*" and isinstance(node.b, ConstantObjective):
            return f"{node.b.c:g}*{term_label(node.a)}"
        return f"({term_label(node.a)}{node.op}{term_label(node.b)})"
    return str(node.name or type(node).__name__)


def _flatten(node: Objective, sign: float, out: list) -> None:
    if isinstance(node, BinaryObjective) and node.op in "+-":
        _flatten(node.a, sign, out)
        _flatten(node.b, sign if node.op == "+" else -sign, out)
    else:
        out.append((node, sign))


def objective_terms(objective: Objective) -> list[ObjectiveTerm]:
    """The addends of an objective ``J = t_1 + t_2 - t_3 ...`` (one term if J is no sum).

    Labels are unique (repeated labels get a ``#k`` suffix); the terms' signed values sum to J.
    """
    flat: list = []
    _flatten(objective, 1.0, flat)
    labels = [term_label(node) for node, _ in flat]
    counts: dict[str, int] = {}
    terms = []
    for (node, sign), label in zip(flat, labels, strict=True):
        if labels.count(label) > 1:
            counts[label] = counts.get(label, 0) + 1
            label = f"{label}#{counts[label]}"
        terms.append(ObjectiveTerm(label, node, float(np.sign(sign))))
    return terms
