"""PolyFEM's ``variable_to_simulation`` entries as diffsolids controls.

An entry maps the parameter vector x through its ``composition`` (a chain of
``polyfem/optimization/parametrization`` maps, ``BuildFromJson.cpp``,
``build_parametrization``) to what one kind of variable sets
(``polyfem/optimization/var2sims``). Mapped:

- ``initial`` (``InitialConditionVariableToSimulation``: y = [u0; v0] over all nodes):
  linear maps (``append-const``, ``append-values``, ``scale``) on the per-body vector,
  ``per-body-to-per-node`` (bodies in the order of their first element, i.e. ``geometry[]``
  order), then an ``append-const`` of zeros at 0 of the nodes' size (u0 = 0): the per-body
  values are each body's rigid initial velocity (:class:`~diffsolids.RigidVelocity`
  without rotation), driven through an :class:`~diffsolids.controls.AffineControl`.
- ``elastic`` (``ElasticVariableToSimulation``: y = [lambda; mu] per element, PolyFEM's
  Lamé parameters): ``exp`` over the whole vector and optionally ``per-body-to-per-elem``;
  the model then takes its materials as Lamé parameters
  (:meth:`~diffsolids.io.PolyFEMScene.model` with ``lame=True``) and the controls are
  ParameterControls of ``lmbda`` and ``mu``, per body or per cell (input cell order, bodies
  in ``geometry[]`` order as PolyFEM's element order).
- ``friction`` (``FrictionVariableToSimulation``: one coefficient for every pair): ``scale``.
- ``shape`` (``ShapeVariableToSimulation``) with ``composite_map_type`` ``boundary`` or
  ``boundary_excluding_surface`` (boundary vertices, less those of the ``surface_selection``
  facets) and no composition: a :class:`~diffsolids.optimize.MeshMotionControl` (the interior
  follows an elasticity extension, where PolyFEM smooths it with SLIM; shapes whose boundary
  would fold are refused, so the line search backs off). PolyFEM's x holds the vertices'
  positions; here q is their displacement from the initial shape (x - x0: the same gradient
  and L-BFGS steps), and ``parameters[0].number`` is not used (the paper's files give a
  placeholder; a warning names it).

Other variables or maps raise :class:`~diffsolids.errors.ParameterError` naming them.
"""

import warnings
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from diffsolids.controls import AffineControl, Control, Log, ParameterControl, RigidVelocity
from diffsolids.controls.contact import FrictionControl
from diffsolids.errors import ParameterError

if TYPE_CHECKING:
    from diffsolids.contact import ContactTerm
    from diffsolids.simulation import Simulation

__all__ = ["SUPPORTED_VARIABLES", "controls_of", "needs_lame"]

SUPPORTED_VARIABLES = ("initial", "elastic", "friction", "shape")
_SHAPE_MAPS = ("boundary", "boundary_excluding_surface")
_LINEAR_MAPS = ("append-const", "append-values", "scale")


def needs_lame(variables: Sequence[Mapping]) -> bool:
    """Whether a variable sets PolyFEM's Lamé parameters (the model must take them)."""
    return any(v.get("type") == "elastic" for v in variables)


def _stages(entry: Mapping, where: str) -> list[Mapping]:
    stages = entry.get("composition", [])
    if not isinstance(stages, list):
        raise ParameterError(f"{where}.composition must be a list")
    for k, stage in enumerate(stages):
        if int(stage.get("state", 0)) != 0:
            raise ParameterError(f"{where}.composition[{k}]: state {stage['state']} (only 0)")
    return stages


def _linear(stage: Mapping, A: np.ndarray, b: np.ndarray, where: str) -> tuple:
    """Y = A x + b after one linear map of PolyFEM (``Parametrizations.cpp``)."""
    kind = stage["type"]
    if kind == "scale":
        value = float(stage["value"])
        return A * value, b * value
    if kind == "append-const":
        values = np.full(int(stage["size"]), float(stage.get("value", 0.0)))
    else:
        values = np.asarray(stage["values"], dtype=float)
    start = int(stage.get("start", -1))
    start = len(b) if start < 0 else start
    if start > len(b):
        raise ParameterError(f"{where}: start {start} beyond the vector's {len(b)} entries")
    A = np.insert(A, [start] * len(values), 0.0, axis=0)
    b = np.insert(b, [start] * len(values), values)
    return A, b


def _initial(
    sim: "Simulation", bodies: list[int], entry: Mapping, size: int, where: str
) -> Control:
    model = sim.model
    A, b = np.eye(size), np.zeros(size)
    stages = _stages(entry, where)
    kinds = [s["type"] for s in stages]
    if "per-body-to-per-node" not in kinds:
        raise ParameterError(
            f"{where}: an initial condition per node is not supported; compose "
            "per-body-to-per-node (each body's rigid initial velocity)"
        )
    split = kinds.index("per-body-to-per-node")
    for k, stage in enumerate(stages[:split]):
        if stage["type"] not in _LINEAR_MAPS:
            raise ParameterError(
                f"{where}.composition[{k}]: map {stage['type']!r} before per-body-to-per-node "
                f"(supported: {_LINEAR_MAPS})"
            )
        A, b = _linear(stage, A, b, f"{where}.composition[{k}]")
    dim = model.dim
    num_nodes = model.V.dofmap.index_map.size_global
    rest = stages[split + 1 :]
    prepends_zero_u0 = (
        len(rest) == 1
        and rest[0]["type"] == "append-const"
        and int(rest[0].get("start", -1)) == 0
        and float(rest[0].get("value", 0.0)) == 0.0
        and int(rest[0]["size"]) == num_nodes * dim
    )
    if not prepends_zero_u0:
        raise ParameterError(
            f"{where}: after per-body-to-per-node only an append-const of {num_nodes * dim} "
            "zeros at start 0 (the initial displacement) is supported"
        )
    if len(b) != len(bodies) * dim:
        raise ParameterError(
            f"{where}: the per-body vector has {len(b)} entries; {len(bodies)} bodies x {dim} "
            "velocity components are expected"
        )
    velocities = [RigidVelocity(sim, body, angular=False) for body in bodies]
    sim.u0[:] = 0.0
    return AffineControl(velocities, A, b, name="initial velocity")


def _elastic(
    sim: "Simulation", bodies: list[int], entry: Mapping, size: int, where: str
) -> list[Control]:
    model = sim.model
    if model.parametrisation != ("lmbda", "mu"):
        raise ParameterError(f"{where}: the model must take Lamé parameters (lame=True)")
    log, per_body = False, False
    for k, stage in enumerate(_stages(entry, where)):
        kind = stage["type"]
        if (
            kind == "exp"
            and int(stage.get("from", -1)) in (-1, 0)
            and (int(stage.get("to", -1)) in (-1, size))
        ):
            log = True
        elif kind == "per-body-to-per-elem" and not per_body:
            per_body = True
        else:
            raise ParameterError(
                f"{where}.composition[{k}]: map {stage!r} is not supported for elastic "
                "variables (exp over the whole vector, per-body-to-per-elem)"
            )
    mode = "bodies" if per_body else "field"
    return [
        ParameterControl(model, name, mode, bodies=bodies, map=Log() if log else None)
        for name in ("lmbda", "mu")
    ]


def _friction(contact: "ContactTerm | None", entry: Mapping, where: str) -> Control:
    if contact is None:
        raise ParameterError(f"{where}: a friction variable in a scene without contact")
    scale = 1.0
    for k, stage in enumerate(_stages(entry, where)):
        if stage["type"] != "scale":
            raise ParameterError(
                f"{where}.composition[{k}]: map {stage['type']!r} (friction: scale only)"
            )
        scale *= float(stage["value"])
    pairs = len(contact.friction_pairs)
    return AffineControl(
        FrictionControl(contact),
        np.full((pairs, 1), scale),
        name="friction",
        lower=0.0 if scale > 0 else -np.inf,
        upper=np.inf if scale > 0 else 0.0,
    )


def _shape(sim: "Simulation", entry: Mapping, size: int, where: str) -> Control:
    from diffsolids.optimize import MeshMotionControl

    kind = entry.get("composite_map_type", "boundary")
    if kind not in _SHAPE_MAPS:
        raise ParameterError(
            f"{where}: composite_map_type {kind!r} is not supported (supported: {_SHAPE_MAPS})"
        )
    if entry.get("composition"):
        raise ParameterError(f"{where}: a shape variable with a composition is not supported")
    domain = sim.model.domain
    excluded = _selection_ids(entry.get("surface_selection", []), where)
    if kind == "boundary":
        excluded = []
    fixed = [t for t in excluded if t in domain.facet_ids]
    control = MeshMotionControl(
        sim.model, "boundary", exclude_facets=fixed, refuse_intersections=True
    )
    if control.size != size:
        warnings.warn(
            f"{where}: parameters[0].number is {size}, the shape variable has {control.size} "
            "parameters (its boundary vertices' displacements); the number is not used",
            stacklevel=3,
        )
    return control


def _selection_ids(value: object, where: str) -> list[int]:
    if isinstance(value, int):
        return [value]
    if isinstance(value, list) and all(isinstance(v, int) for v in value):
        return list(value)
    raise ParameterError(f"{where}: surface_selection must be an id or a list of ids")


def controls_of(
    sim: "Simulation",
    contact: "ContactTerm | None",
    variables: Sequence[Mapping],
    size: int,
    bodies: list[int],
) -> list[Control]:
    """The controls of opt.json's ``variable_to_simulation`` (each takes the whole x).

    Args:
        sim: The simulation of state 0.
        contact: Its contact term (None without contact).
        variables: The entries.
        size: The number of parameters (``parameters[0].number``).
        bodies: The FE bodies' ids in PolyFEM's order (``geometry[]``).

    Raises:
        ParameterError: An unsupported variable, map or layout (named).
    """
    if len(variables) != 1:
        raise ParameterError(
            f"variable_to_simulation has {len(variables)} entries; one is supported"
        )
    (entry,) = variables
    where = "variable_to_simulation[0]"
    kind = entry.get("type")
    if int(entry.get("state", 0)) != 0:
        raise ParameterError(f"{where}: state {entry['state']} (only state 0 is optimised)")
    keys = {"type", "state", "composition"}
    if kind == "shape":
        keys |= {"composite_map_type", "surface_selection"}
    unknown = sorted(set(entry) - keys)
    if unknown:
        raise ParameterError(f"{where} ({kind!r}): unsupported keys {unknown}")
    if kind == "initial":
        controls = [_initial(sim, bodies, entry, size, where)]
    elif kind == "elastic":
        controls = _elastic(sim, bodies, entry, size, where)
    elif kind == "friction":
        controls = [_friction(contact, entry, where)]
    elif kind == "shape":
        return [_shape(sim, entry, size, where)]
    else:
        raise ParameterError(
            f"{where}: variable type {kind!r} is not supported (supported: "
            f"{', '.join(SUPPORTED_VARIABLES)})"
        )
    total = sum(c.size for c in controls)
    if total != size:
        raise ParameterError(
            f"{where} ({kind!r}) drives {total} parameters, parameters[0].number is {size}"
        )
    return controls
