"""Targets of a PolyFEM / paper scene: a stored trajectory, nodes, a signed distance, loads.

Per-step :class:`~diffsolids.objectives.Series` (one value per state 0..N) to be reduced with
time weights (``time_integral(series, "uniform")``, a list of steps, ``final_value``):

* :func:`target_trajectory`: the deformed state matched node by node to a stored
  :class:`~diffsolids.simulation.Trajectory` of the same mesh at every step (PolyFEM's
  ``target`` objective with ``"matching": "exact"``, used by the puzzle and kangaroo scenes:
  ``int ||X + u^i - (X^trg + u^trg,i)||^2`` over a surface or the volume).
* :func:`center_target`: the centre of mass matched to that of a stored run (PolyFEM's
  ``center-target``, the sliding bunny of fig21).
* :func:`node_target`: the displacement or position of selected nodes of the displacement
  (PolyFEM's ``node-target``; any Lagrange node, P2 edge nodes included), an exact sum.
* :func:`sdf_target`: ``int sdf(X + u)^2`` of a user signed-distance function written in UFL
  (PolyFEM's ``sdf-target``); its gradient is UFL's.
* :func:`compliance`: the work ``f . u`` of the model's tractions and body forces per step.

PolyFEM's ``{"type": "transient_integral", "weight": w, "static_objective": {...}}`` with its
default ``integral_type`` "uniform" (w_0 = 0, w_i = dt) is ``w * time_integral(series,
"uniform")``; "final" is ``final_value``, "steps" a list of steps (PolyFEM divides by their
number). The per-step values of any of them along a trajectory are ``series_values(simulation,
series, trajectory)``; those of an objective's series at the last forward run ``step_values(rf)``.
"""

import itertools
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, override

import dolfinx.la
import numpy as np
import numpy.typing as npt
import ufl
from dolfinx import fem
from mpi4py import MPI
from ufl.core.expr import Expr

from diffsolids import forms
from diffsolids.errors import ParameterError
from diffsolids.mesh.ordering import CanonicalLayout
from diffsolids.model.terms import BodyForce, Traction
from diffsolids.objectives.functional import Integral, ObjectiveError, Series
from diffsolids.objectives.library import (
    Data,
    Tags,
    _data,
    _facet_measure,
    _volume_measure,
    center_of_mass,
    center_of_mass_trajectory,
)
from diffsolids.objectives.values import series_values
from diffsolids.parallel import collective_comm
from diffsolids.states import Trajectory

if TYPE_CHECKING:
    from diffsolids.model import Model, StepFields
    from diffsolids.simulation import Simulation

__all__ = [
    "TrajectoryTarget",
    "center_target",
    "compliance",
    "node_target",
    "sdf_target",
    "step_selector",
    "target_trajectory",
]

_MATCHES = ("positions", "displacement")


def _measure(model: "Model", f: "StepFields", facets: Tags, bodies: Tags) -> ufl.Measure:
    if facets is not None and bodies is not None:
        raise ParameterError("give facets (boundary target) or bodies (volume target), not both")
    if facets is not None:
        return _facet_measure(model, f, facets)
    return _volume_measure(model, f, bodies)


def step_selector(t: Expr | float, times: Sequence[float]) -> list:
    """UFL indicators chi_i(t), 1 when t is (nearest to) the time t_i of state i, else 0.

    The states' times split the line at their midpoints: chi_i = 1 on [m_{i-1}, m_i) (the
    first and last intervals end half a step outside t_0 and t_N), so exactly one indicator is
    1 at each time of the run. With them a form holds per-step data ``sum_i chi_i(t) d_i``: the
    step's data are picked by the model's time constant, set for every step by the forward run,
    the objective evaluation and the adjoint sweep alike.

    Args:
        t: The model's UFL time (``model.fields.t``).
        times: Increasing times t_0 < ... < t_N.
    """
    times = np.asarray(times, dtype=float)
    if times.size > 1 and not np.all(np.diff(times) > 0):
        raise ParameterError("the states' times must increase")
    half = 0.5 * np.min(np.diff(times)) if times.size > 1 else 0.5
    edges = np.concatenate([[times[0] - half], 0.5 * (times[1:] + times[:-1]), [times[-1] + half]])
    return [
        ufl.conditional(ufl.And(ufl.ge(t, float(lo)), ufl.lt(t, float(hi))), 1.0, 0.0)
        for lo, hi in itertools.pairwise(edges)
    ]


class TrajectoryTarget(Integral):
    """An Integral of per-state data: refuses a run with another number of states."""

    def __init__(self, integrand: Callable, name: str, num_states: int) -> None:
        super().__init__(integrand, name)
        self.num_states = num_states

    @override
    def values(self, table: dict) -> np.ndarray:
        values = table[self]
        if len(values) != self.num_states:
            raise ObjectiveError(
                f"{self.name}: the target has {self.num_states} states but the run has "
                f"{len(values)} (0..{len(values) - 1})"
            )
        return values


def _target_states(
    simulation: "Simulation", target: "Trajectory | Sequence[np.ndarray]"
) -> list[np.ndarray]:
    """The target's displacement arrays, checked against the run's steps, times and layout."""
    integ = simulation.integrator
    V = simulation.model.V
    if isinstance(target, Trajectory):
        states, times = list(target.u), target.times
    elif isinstance(target, Sequence | np.ndarray):
        states, times = list(target), None
    else:
        raise ObjectiveError(
            "target must be a Trajectory (every state of a run: Checkpointing('all') keeps "
            f"them) or a sequence of displacement arrays, got {type(target).__name__}"
        )
    n = integ.num_steps + 1
    if len(states) != n:
        raise ObjectiveError(
            f"target trajectory has {len(states)} states but the simulation has {n} "
            f"(steps 0..{integ.num_steps})"
        )
    size = len(fem.Function(V).x.array)
    for i, u in enumerate(states):
        u = np.asarray(u)
        if u.shape != (size,):
            raise ObjectiveError(
                f"target trajectory, state {i}: {u.shape} values, expected ({size},) (the local "
                "displacement array of a run on the same mesh and partition)"
            )
        if not np.all(np.isfinite(u)):
            raise ObjectiveError(f"target trajectory, state {i}: non-finite displacements")
    if times is not None and len(times) == n:
        expected = np.array([integ.time(i) for i in range(n)])
        off = np.flatnonzero(~np.isclose(times, expected, rtol=0.0, atol=1e-9 * integ.dt))
        if off.size:
            i = int(off[0])
            raise ObjectiveError(
                f"target trajectory, state {i}: time {times[i]} but the simulation's step {i} "
                f"is at t = {expected[i]} (a target run with another time step?)"
            )
    return states


def target_trajectory(
    simulation: "Simulation",
    target: "Trajectory | Sequence[np.ndarray]",
    facets: Tags = None,
    bodies: Tags = None,
    match: str = "positions",
    weight: Data = 1.0,
    rest_positions: Callable | npt.ArrayLike | None = None,
) -> Series:
    """Per-step distance of the deformed state from a stored trajectory, node matched.

    s_i = int w ||X + u^i - (X^trg + u^trg,i)||^2 over tagged facets (a surface) or bodies (a
    volume) — PolyFEM's ``target`` objective with exact matching (paper figs. 14, 20: a target
    run of the same mesh with other parameters). With ``match="displacement"`` it is
    int w ||u^i - u^trg,i||^2. Node matched: u^trg,i is interpolated with the same basis as u,
    so the integrand vanishes exactly when the nodal states agree. The states of the target are
    picked by the step's time (:func:`step_selector`); reduce with time weights, e.g.
    ``time_integral(s, "uniform")`` or a subset of steps ``time_integral(s, [10, 20, 40])``.

    Args:
        simulation: The Simulation the objective is evaluated on (its steps and times).
        target: A Trajectory of a run on the same mesh and partition (or a sequence of N + 1
            local displacement arrays).
        facets: Facet tag(s) of the surface selection (PolyFEM ``surface_selection``).
        bodies: Body tag(s) of the volume selection (default: every body, when no facets).
        match: "positions" (X + u against X^trg + u^trg) or "displacement" (u against u^trg).
        weight: Weight w (number, callable of rest positions, UFL).
        rest_positions: X^trg, the target run's rest positions (a callable of x, or a local
            nodal array of the displacement space); default: the mesh's rest positions now
            (so a later shape change is penalised too).

    Raises:
        ObjectiveError: The target has another number of states, other times, another layout
            or non-finite values (naming the state).
        ParameterError: An unknown match, facets and bodies both given.
        TagError: Unknown facet tags or bodies.
    """
    if match not in _MATCHES:
        raise ParameterError(f"unknown match {match!r}; choose from {_MATCHES}")
    model = simulation.model
    V = model.V
    states = _target_states(simulation, target)
    targets = []
    for i, u in enumerate(states):
        fn = fem.Function(V, name=f"target state {i}")
        fn.x.array[:] = u
        targets.append(fn)
    positions = match == "positions"
    X_trg = None
    if positions:
        X_trg = fem.Function(V, name="target rest positions")
        if rest_positions is None:
            X_trg.interpolate(lambda x: x[: model.dim])
        elif callable(rest_positions):
            X_trg.interpolate(rest_positions)
        else:
            arr = np.asarray(rest_positions, dtype=float)
            if arr.shape != X_trg.x.array.shape or not np.all(np.isfinite(arr)):
                raise ObjectiveError(
                    f"target rest positions: expected {X_trg.x.array.shape} finite values, got "
                    f"{arr.shape}"
                )
            X_trg.x.array[:] = arr
    w = _data(model, weight, (), "target trajectory weight")
    times = [simulation.integrator.time(i) for i in range(len(states))]

    def form(f: "StepFields") -> ufl.Form:
        chi = step_selector(f.t, times)
        u_trg = sum(
            (c * fn for c, fn in zip(chi[1:], targets[1:], strict=True)), chi[0] * targets[0]
        )
        if positions:
            x, x_trg = forms.deformed_position(f.X, f.u), X_trg + u_trg
        else:
            x, x_trg = f.u, u_trg
        return forms.weighted_squared_distance(x, x_trg, w) * _measure(model, f, facets, bodies)

    form(model.fields)  # unknown tags fail here
    return TrajectoryTarget(form, "target trajectory", len(states))


def center_target(simulation: "Simulation", target: "Trajectory", bodies: Tags = None) -> Series:
    """Per-step squared distance of the centre of mass from that of a stored run.

    ||c^i - c^trg,i||^2 with c the deformed centre of mass of ``bodies`` (PolyFEM's
    ``center-target``, the sliding bunny of fig21 with ``integral_type: final``). The target's
    centres are computed once, now, from its states on the current mesh (the numbers stay fixed
    when the shape or the density changes later).

    Args:
        simulation: The Simulation the objective is evaluated on.
        target: A Trajectory of a run on the same mesh and partition.
        bodies: The bodies whose centre of mass is matched (default: all).

    Raises:
        ObjectiveError: The target has another number of states, times or layout.
    """
    _target_states(simulation, target)
    com = series_values(simulation, center_of_mass(simulation.model, bodies), target)
    return center_of_mass_trajectory(simulation.model, com, bodies)


# -- node targets ------------------------------------------------------------------------------
_NUMBERINGS = ("input", "canonical")


def _node_spaces(model: "Model") -> tuple[fem.FunctionSpace, fem.FunctionSpace]:
    """The scalar and the vector space of the displacement's element (the nodes of u)."""
    mesh = model.domain.mesh
    element = model.V.ufl_element()
    return fem.functionspace(mesh, element.sub_elements[0]), fem.functionspace(mesh, element)


def _vertex_of_dof(Q: fem.FunctionSpace) -> np.ndarray:
    """Per local dof of Q: the geometry node of its vertex, or -1 (an edge, face or cell node)."""
    mesh = Q.mesh
    layout = Q.dofmap.dof_layout
    corners = dolfinx.cpp.mesh.cell_num_vertices(mesh.topology.cell_type)
    local = [layout.entity_dofs(0, v)[0] for v in range(corners)]
    imap = Q.dofmap.index_map
    out = np.full(imap.size_local + imap.num_ghosts, -1, dtype=np.int64)
    # the vertex nodes come first in the (affine) geometry dofmap
    out[Q.dofmap.list[:, local].ravel()] = mesh.geometry.dofmaps[0][:, :corners].ravel()
    return out


def _selected_nodes(
    Q: fem.FunctionSpace, nodes: Callable | npt.ArrayLike, numbering: str
) -> tuple[np.ndarray, np.ndarray | None]:
    """The owned local dofs of Q selected, and for indices each one's position in the list."""
    mesh = Q.mesh
    collective = collective_comm(mesh.comm)
    owned = Q.dofmap.index_map.size_local
    if callable(nodes):
        dofs = fem.locate_dofs_geometrical(Q, nodes)
        dofs = dofs[dofs < owned]
        if collective.allreduce(len(dofs), op=MPI.SUM) == 0:
            raise ParameterError(
                "node target: the locator selects no mesh vertex (nor any other node of the "
                "displacement)"
            )
        return dofs, None
    wanted = np.asarray(nodes, dtype=np.int64).ravel()
    if wanted.size == 0 or len(np.unique(wanted)) != wanted.size:
        raise ParameterError("node target: give distinct node indices (at least one)")
    if numbering == "input":
        vertex = _vertex_of_dof(Q)[:owned]
        ids = np.where(
            vertex >= 0, mesh.geometry.input_global_indices[np.maximum(vertex, 0)], -1
        ).astype(np.int64)
        total = mesh.geometry.index_map().size_global
        what = (
            f"mesh vertex has the input index {{}} (vertex indices count 0..{total - 1} in "
            "the mesh file; numbering='canonical' selects any node)"
        )
    else:
        ids = CanonicalLayout(Q).positions.astype(np.int64)
        total = Q.dofmap.index_map.size_global
        what = (
            f"node has the canonical index {{}} (the displacement's {total} nodes count "
            f"0..{total - 1}: P1 in input vertex order, else by node coordinates)"
        )
    hit = np.isin(ids, wanted) & (ids >= 0)
    dofs = np.flatnonzero(hit).astype(np.int32)
    found = np.concatenate(collective.allgather(ids[dofs]))
    missing = np.setdiff1d(wanted, found)
    if missing.size:
        raise ParameterError("node target: no " + what.format(missing[:5].tolist()))
    order = np.argsort(wanted)[np.searchsorted(np.sort(wanted), ids[dofs])]
    return dofs, order


def node_target(
    model: "Model",
    nodes: Callable | npt.ArrayLike,
    target: npt.ArrayLike | Callable,
    match: str = "positions",
    weight: float = 1.0,
    numbering: str = "input",
) -> Series:
    """Per-step squared distance of selected nodes of the displacement from their targets.

    s_i = w sum_n ||x_n^i - x_n^trg||^2 over the selected nodes n of the displacement space
    (any Lagrange degree: for P2 the vertices and the edge nodes), with x_n = X_n + u_n
    (``match="positions"``, PolyFEM's ``node-target``) or x_n = u_n (``"displacement"``). The
    sum is exact: the integral int w chi |d|^2 / (c |det J|) dx with the quadrature rule whose
    points are the element's own nodes (unit weights), where chi selects the nodes and c
    counts the cells around each node (so neither depends on the shape and the shape
    derivative is that of the sum).

    Args:
        model: The Model.
        nodes: A locator ``x -> bool mask`` of rest node coordinates (shape (3, n); every node
            of the displacement space it holds for is selected, vertices and, for P2 and up,
            edge, face and cell nodes), or node indices (see ``numbering``).
        target: A vector (the same target for every node), a callable of rest positions (shape
            (dim, n) -> (dim, n), interpolated into the displacement space), or for indices an
            array (number of indices, dim) in their order.
        match: "positions" or "displacement".
        weight: The factor w > 0.
        numbering: What indices count: "input" (default: mesh-file vertex indices; vertices
            only) or "canonical" (the canonical node order of the displacement space, that of
            :class:`~diffsolids.simulation.CanonicalValues` and the controls: P1 nodes in the
            input vertex order, higher degrees in the lexicographic order of the node
            coordinates; any node). For P1 the two are the same.

    Raises:
        ParameterError: No node selected, unknown indices, a malformed target, an unknown
            match or numbering.
    """
    if match not in _MATCHES:
        raise ParameterError(f"unknown match {match!r}; choose from {_MATCHES}")
    if numbering not in _NUMBERINGS:
        raise ParameterError(f"unknown numbering {numbering!r}; choose from {_NUMBERINGS}")
    if not (np.isfinite(weight) and weight > 0):
        raise ParameterError(f"node target weight must be positive, got {weight}")
    mesh = model.domain.mesh
    dim = model.dim
    Q, QV = _node_spaces(model)
    dofs, order = _selected_nodes(Q, nodes, numbering)
    points = np.asarray(Q.element.basix_element.points, dtype=float)
    node_dx = ufl.Measure(
        "dx",
        domain=mesh,
        metadata={
            "quadrature_rule": "custom",
            "quadrature_points": points,
            "quadrature_weights": np.ones(len(points)),
        },
    )
    detJ = abs(ufl.JacobianDeterminant(mesh))
    # c_n: the number of cells around node n (each basis function is 1 at its own node)
    count = fem.Function(Q)
    vec = fem.assemble_vector(fem.form(ufl.TestFunction(Q) / detJ * node_dx))
    vec.scatter_reverse(dolfinx.la.InsertMode.add)
    count.x.array[:] = vec.array
    count.x.scatter_forward()
    chi = fem.Function(Q, name="node target weights")
    chi.x.array[dofs] = weight / count.x.array[dofs]
    T = fem.Function(QV, name="node targets")  # the same node numbering as Q
    values = T.x.array.reshape(-1, dim)
    if callable(target):
        T.interpolate(target)
    else:
        arr = np.asarray(target, dtype=float)
        if arr.shape == (dim,):
            values[:] = arr
        elif order is not None and arr.shape == (len(np.asarray(nodes).ravel()), dim):
            values[dofs] = arr[order]
        else:
            raise ParameterError(
                f"node target has shape {arr.shape}; expected ({dim},), a callable, or "
                f"(number of indices, {dim}) with node indices"
            )
    if not np.all(np.isfinite(values[dofs])):
        raise ParameterError("node target has non-finite values")
    # the owners' values on the ghosts (a locator may see a ghost node differently)
    chi.x.scatter_forward()
    T.x.scatter_forward()
    positions = match == "positions"

    def form(f: "StepFields") -> ufl.Form:
        x = forms.deformed_position(f.X, f.u) if positions else f.u
        return forms.weighted_squared_distance(x, T, chi) / detJ * node_dx

    return Integral(form, "node target")


# -- signed distance -------------------------------------------------------------------------
def sdf_target(
    model: "Model", sdf: Callable, facets: Tags = None, bodies: Tags = None, deformed: bool = True
) -> Series:
    """Per-step int sdf(x)^2 of a signed-distance function of the deformed position x = X + u.

    PolyFEM's ``sdf-target``: the surface (or volume) is driven onto the zero level set of sdf.
    ``sdf`` maps a UFL position vector to a UFL scalar, e.g. a circle of radius r about c:
    ``lambda x: ufl.sqrt(ufl.dot(x - c, x - c)) - r``; its gradient comes from UFL.

    Args:
        model: The Model.
        sdf: The signed distance (UFL vector -> UFL scalar).
        facets: Facet tag(s) of the surface (default: the volume of ``bodies``).
        bodies: Body tag(s) of the volume (default: every body, when no facets).
        deformed: Evaluate at X + u (default); False: at the rest position X (shape design).
    """

    def form(f: "StepFields") -> ufl.Form:
        x = forms.deformed_position(f.X, f.u) if deformed else f.X
        d = sdf(x)
        if not isinstance(d, ufl.core.expr.Expr) or d.ufl_shape != ():
            raise ParameterError("sdf must map a UFL position vector to a UFL scalar")
        return d * d * _measure(model, f, facets, bodies)

    form(model.fields)
    return Integral(form, "sdf target")


# -- loads -----------------------------------------------------------------------------------
def compliance(model: "Model", loads: Sequence[str] | None = None) -> Series:
    """Per-step compliance, the work of the dead loads on the displacement.

    s_i = sum over body forces int rho g . u^i dx + sum over tractions int t . u^i ds (for a
    static linear problem, the strain energy stored times two: minimising it stiffens the
    structure; PolyFEM's ``compliance``). Time-dependent loads enter with their value at the
    step.

    Args:
        model: The Model (its add_body_force / add_gravity / add_traction loads).
        loads: Names of the loads (e.g. "gravity", "traction_2"; default: every load).

    Raises:
        ParameterError: The model has no such load (or no load at all).
    """
    terms = [t for t in model.terms if isinstance(t, BodyForce | Traction)]
    available = [t.name for t in terms]
    if loads is not None:
        unknown = [name for name in loads if name not in available]
        if unknown:
            raise ParameterError(f"compliance: no load named {unknown}; loads are {available}")
        terms = [t for t in terms if t.name in loads]
    if not terms:
        raise ParameterError("compliance: the model has no body force or traction")

    def form(f: "StepFields") -> ufl.Form:
        parts = [-t.energy_density(f) * t.measure(f) for t in terms]
        return sum(parts[1:], parts[0])

    return Integral(form, "compliance")
