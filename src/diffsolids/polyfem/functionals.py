"""PolyFEM's ``functionals`` (and ``stopping_conditions``) as diffsolids objectives.

Each entry of opt.json's ``functionals`` is one of PolyFEM's forms
(``polyfem/optimization/BuildFromJson.cpp``, ``build_form``; the keys and defaults of
``json-specs/objective-spec.json``). Every form's value is its ``weight`` (default 1) times
its unweighted value, at every level of nesting, and J is the sum of the entries. Mapped:

- ``transient_integral`` of a ``static_objective`` with ``integral_type`` ``uniform`` (the
  default: weight dt at steps 1..N), ``trapezoidal``, ``final`` or ``steps`` (1/len(steps)
  at each listed step), as ``TransientForm::get_transient_quadrature_weights``;
- composites (``CompositeForms.cpp``): ``power`` (f^p, ``power`` default 2), ``divide``
  (f / g), ``plus-const`` (f + value), ``log`` (ln f) and ``soft_constraint`` with
  ``soft_bound`` [l, u]: max(l - f, 0)^p + max(f - u, 0)^p (``InequalityConstraintForm``,
  ``power`` default 2);
- static forms, per step: ``target`` (int over ``surface_selection`` facets, else over the
  ``volume_selection`` bodies, of |x - x_target|^2, the target the run of ``target_state``;
  ``matching: exact`` only), ``center-target`` (squared distance of the centre of mass of
  ``volume_selection`` from the target run's), ``position`` (int over ``volume_selection`` of
  the deformed coordinate ``dim``), ``volume`` (the rest volume of ``volume_selection``),
  ``stress_norm`` (int |P|^p of the first Piola-Kirchhoff stress, ``power`` default 2) and
  ``function-target`` (int over ``surface_selection`` of f(x) at the deformed position x, f a
  PolyFEM expression of x, y, z at t = 0 (:meth:`diffsolids.io.expressions.Expression.ufl`);
  UFL differentiates f, so ``target_function_gradient`` is not needed and not read).

Shape terms: ``boundary_smoothing`` (:class:`~diffsolids.objectives.BoundarySmoothing`
over the vertices of the ``surface_selection`` facets, whose untagged facets (id 0) are the
boundary's facets of no other id; ``scale_invariant`` default true, ``power``) and, as a
stopping condition, ``min_jacobian`` (:class:`MinJacobian`).

A static form outside a ``transient_integral`` is evaluated at the last state (a static
scene's solution). Anything else raises :class:`~diffsolids.errors.ParameterError` naming
the form and its place in opt.json.
"""

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import ufl
from mpi4py import MPI

from diffsolids.errors import ParameterError
from diffsolids.objectives import (
    BoundarySmoothing,
    center_target,
    final_value,
    stress_lp_norm,
    target_trajectory,
    time_integral,
)
from diffsolids.objectives.functional import Integral, Objective, Regulariser, Series
from diffsolids.parallel import collective_comm

if TYPE_CHECKING:
    from diffsolids.model import Model
    from diffsolids.model.terms import StepFields
    from diffsolids.simulation import Simulation, Trajectory

__all__ = ["FunctionalContext", "MinJacobian", "objective_of", "objective_sum"]

_COMMON = {"type", "weight", "print_energy", "state"}
_INTEGRAL_TYPES = ("uniform", "trapezoidal", "final", "steps")


@dataclass
class FunctionalContext:
    """What the forms are built on.

    Attributes:
        simulation: The simulation of state 0 (the optimised one).
        targets: Trajectories of the other states, by state index (target runs).
    """

    simulation: "Simulation"
    targets: Mapping[int, "Trajectory"]

    @property
    def model(self) -> "Model":
        """The model of state 0."""
        return self.simulation.model


def _keys(spec: Mapping, allowed: set, where: str) -> None:
    unknown = sorted(set(spec) - allowed - _COMMON)
    if unknown:
        raise ParameterError(f"{where} ({spec.get('type')!r}): unsupported keys {unknown}")
    if int(spec.get("state", 0)) != 0:
        raise ParameterError(
            f"{where}: state {spec['state']} (only forms of state 0, the optimised run, are "
            "supported; other states are targets)"
        )


def _selection(spec: Mapping, key: str) -> list[int] | None:
    value = spec.get(key)
    if value is None:
        return None
    return [int(v) for v in (value if isinstance(value, list) else [value])]


def _target(ctx: FunctionalContext, spec: Mapping, where: str) -> "Trajectory":
    state = int(spec.get("target_state", -1))
    if state not in ctx.targets:
        raise ParameterError(
            f"{where}: target_state {state} is not a state of opt.json's states (1..)"
        )
    return ctx.targets[state]


def _position(ctx: FunctionalContext, spec: Mapping, where: str) -> Series:
    dim = int(spec["dim"])
    if not 0 <= dim < ctx.model.dim:
        raise ParameterError(f"{where}: dim {dim} of a {ctx.model.dim}D scene")
    bodies = _selection(spec, "volume_selection")
    domain = ctx.model.domain

    def integrand(f: "StepFields") -> ufl.Form:
        ids = tuple(domain.body_id(b) for b in bodies) if bodies else ()
        return (f.X[dim] + f.u[dim]) * (f.dx(ids) if ids else f.dx)

    return Integral(integrand, f"position[{dim}]")


def _volume(ctx: FunctionalContext, spec: Mapping) -> Series:
    bodies = _selection(spec, "volume_selection")
    domain = ctx.model.domain

    def integrand(f: "StepFields") -> ufl.Form:
        ids = tuple(domain.body_id(b) for b in bodies) if bodies else ()
        return ufl.as_ufl(1.0) * (f.dx(ids) if ids else f.dx)

    return Integral(integrand, "volume")


def _function_target(ctx: FunctionalContext, spec: Mapping, where: str) -> Series:
    from diffsolids.io.expressions import parse_expression

    facets = _selection(spec, "surface_selection")
    if not facets:
        raise ParameterError(f"{where}: function-target needs a surface_selection")
    expression = parse_expression(str(spec["target_function"]))
    domain = ctx.model.domain
    expression.ufl(*ufl.SpatialCoordinate(domain.mesh))  # refuses what UFL cannot express

    def integrand(f: "StepFields") -> ufl.Form:
        x = f.X + f.u
        value = expression.ufl(x[0], x[1], x[2] if ctx.model.dim == 3 else 0.0, 0.0)
        return value * f.ds(tuple(domain.facet_id(t) for t in facets))

    return Integral(integrand, "function-target")


def _static(ctx: FunctionalContext, spec: Mapping, where: str) -> Series:
    """A static form: one value per step."""
    kind = spec.get("type")
    weight = float(spec.get("weight", 1.0))
    if kind == "target":
        _keys(spec, {"surface_selection", "volume_selection", "target_state", "matching"}, where)
        if spec.get("matching", "exact") != "exact":
            raise ParameterError(f"{where}: matching {spec['matching']!r} (only 'exact')")
        facets = _selection(spec, "surface_selection")
        bodies = None if facets else _selection(spec, "volume_selection")
        series = target_trajectory(
            ctx.simulation, _target(ctx, spec, where), facets=facets, bodies=bodies
        )
    elif kind == "center-target":
        _keys(spec, {"volume_selection", "target_state"}, where)
        series = center_target(
            ctx.simulation, _target(ctx, spec, where), bodies=_selection(spec, "volume_selection")
        )
    elif kind == "position":
        _keys(spec, {"dim", "volume_selection"}, where)
        series = _position(ctx, spec, where)
    elif kind == "volume":
        _keys(spec, {"volume_selection"}, where)
        series = _volume(ctx, spec)
    elif kind == "stress_norm":
        _keys(spec, {"power", "volume_selection"}, where)
        p = float(spec.get("power", 2))
        bodies = _selection(spec, "volume_selection")
        series = stress_lp_norm(ctx.model, p, stress="piola", bodies=bodies) ** p
    elif kind == "function-target":
        _keys(spec, {"target_function", "target_function_gradient", "surface_selection"}, where)
        series = _function_target(ctx, spec, where)
    else:
        raise ParameterError(f"{where}: unsupported static objective {kind!r}")
    return series * weight if weight != 1.0 else series


class MinJacobian(Regulariser):
    """The smallest Jacobian determinant of the rest mesh's cells (PolyFEM's ``min_jacobian``).

    det of the affine map from the reference simplex to each cell (its vertices), the minimum
    over all cells and ranks. Not differentiable: a stopping condition, not an objective.
    """

    name = "min_jacobian"

    def evaluate(self, model: "Model") -> float:
        """The minimum over the cells (collective)."""
        mesh = model.domain.mesh
        tdim = mesh.topology.dim
        num = mesh.topology.index_map(tdim).size_local
        nodes = mesh.geometry.dofmaps[0][:num, : tdim + 1]
        x = mesh.geometry.x[nodes][:, :, :tdim]
        local = np.linalg.det(x[:, 1:] - x[:, :1]).min(initial=np.inf)
        return float(collective_comm(mesh.comm).allreduce(local, op=MPI.MIN))

    def gradient(self, model: "Model") -> dict[str, np.ndarray]:
        """Refused: the minimum has no gradient."""
        raise ParameterError("min_jacobian is a stopping condition; it has no gradient")


def _smoothing(ctx: FunctionalContext, spec: Mapping, where: str) -> Objective:
    _keys(spec, {"power", "surface_selection", "scale_invariant", "dimensions"}, where)
    if spec.get("dimensions"):
        raise ParameterError(f"{where}: boundary_smoothing dimensions are not supported")
    selected = _selection(spec, "surface_selection")
    facet_ids = ctx.model.domain.facet_ids
    excluded = [] if selected is None else [t for t in facet_ids if t not in selected]
    return BoundarySmoothing(
        ctx.model,
        p=float(spec.get("power", 2)),
        exclude_facets=excluded,
        scale_invariant=bool(spec.get("scale_invariant", True)),
    )


def _soft_constraint(inner: Objective, bounds: list, p: float) -> Objective:
    lo, hi = (float(b) for b in bounds)
    if lo > hi:
        raise ParameterError(f"soft_bound {bounds}: the lower bound is above the upper one")

    def fn(a: np.ndarray) -> np.ndarray:
        return np.maximum(lo - a, 0.0) ** p + np.maximum(a - hi, 0.0) ** p

    def dfn(a: np.ndarray) -> np.ndarray:
        return -p * np.maximum(lo - a, 0.0) ** (p - 1) + p * np.maximum(a - hi, 0.0) ** (p - 1)

    return inner.apply(fn, dfn, "soft_constraint")


def _transient(ctx: FunctionalContext, spec: Mapping, where: str) -> Objective:
    _keys(spec, {"static_objective", "integral_type", "steps"}, where)
    kind = spec.get("integral_type", "uniform")
    if kind not in _INTEGRAL_TYPES:
        raise ParameterError(
            f"{where}: integral_type {kind!r} is not supported; choose from {_INTEGRAL_TYPES}"
        )
    series = _static(ctx, spec["static_objective"], f"{where}.static_objective")
    if kind != "steps":
        return time_integral(series, kind)
    steps = [int(s) for s in spec.get("steps", [])]
    n = ctx.simulation.integrator.num_steps
    if not steps or min(steps) < 1 or max(steps) > n:
        raise ParameterError(f"{where}: steps {steps} must be non-empty, within 1..{n}")
    weights = np.zeros(n + 1)
    np.add.at(weights, steps, 1.0 / len(steps))
    return time_integral(series, weights)


_COMPOSITES: dict[str, set] = {
    "power": {"objective", "power"},
    "divide": {"objective"},
    "plus-const": {"objective", "value"},
    "log": {"objective"},
    "soft_constraint": {"objective", "soft_bound", "power"},
}


def _composite(ctx: FunctionalContext, spec: Mapping, where: str) -> Objective:
    kind = spec["type"]
    _keys(spec, _COMPOSITES[kind], where)
    if kind == "divide":
        parts = spec["objective"]
        if not isinstance(parts, list) or len(parts) != 2:
            raise ParameterError(f"{where}: divide needs a list of two objectives")
        a, b = (objective_of(ctx, s, f"{where}.objective[{k}]") for k, s in enumerate(parts))
        return a / b
    inner = objective_of(ctx, spec["objective"], f"{where}.objective")
    if kind == "power":
        return inner ** float(spec.get("power", 2))
    if kind == "plus-const":
        return inner + float(spec["value"])
    if kind == "log":
        return inner.apply(np.log, lambda a: 1.0 / a, "log")
    return _soft_constraint(inner, spec["soft_bound"], float(spec.get("power", 2)))


def objective_of(ctx: FunctionalContext, spec: Mapping, where: str) -> Objective:
    """One PolyFEM form as a scalar Objective (its weight included).

    Raises:
        ParameterError: An unsupported form or key (named with ``where``).
    """
    if not isinstance(spec, Mapping) or "type" not in spec:
        raise ParameterError(f"{where}: a form needs a 'type', got {spec!r}")
    kind = spec["type"]
    if kind == "transient_integral":
        obj = _transient(ctx, spec, where)
    elif kind in _COMPOSITES:
        obj = _composite(ctx, spec, where)
    elif kind == "boundary_smoothing":
        obj = _smoothing(ctx, spec, where)
    elif kind == "min_jacobian":
        _keys(spec, set(), where)
        obj = MinJacobian()
    else:
        static = _static(ctx, {**spec, "weight": 1.0}, where)
        obj = final_value(static)
    weight = float(spec.get("weight", 1.0))
    return obj * weight if weight != 1.0 else obj


def objective_sum(
    ctx: FunctionalContext, specs: list, where: str = "functionals"
) -> tuple[Objective, list[str]]:
    """The sum of opt.json's functionals and a label for each (its ``print_energy`` or type)."""
    if not isinstance(specs, list) or not specs:
        raise ParameterError(f"{where}: a non-empty list of forms is needed")
    terms = [objective_of(ctx, s, f"{where}[{k}]") for k, s in enumerate(specs)]
    labels = [str(s.get("print_energy", s.get("type"))) for s in specs]
    total = terms[0]
    for t in terms[1:]:
        total = total + t
    return total, labels
