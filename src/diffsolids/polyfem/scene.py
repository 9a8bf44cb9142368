"""PolyFEM scene JSON files read into a diffsolids Domain, Model, ContactTerm and integrator.

:func:`read_polyfem_scene` reads a PolyFEM ``run.json``-style scene (the paper's data repository
ships one per experiment) into a :class:`PolyFEMScene` that holds the numbers as written and
builds the diffsolids objects from them:

- ``geometry[]``: each entry a mesh file (relative paths against the JSON's folder, any format
  :func:`~diffsolids.mesh.read_mesh` reads) with ``transformation`` (``scale``, ``rotation`` in
  degrees, ``translation``: x' = R (s x) + t), ``volume_selection`` (its body id: the cell tag)
  and ``surface_selection`` (an id given to every boundary facet of that mesh, or a list of
  PolyFEM selections ``{"id", "box" | "axis"/"position" | "center"/"radius" |
  "normal"/"point", "relative"}`` or ``{"threshold", "id_offset"}`` (ids 1..7 by the side of
  the bounding box), tested on facet barycentres against that mesh's bounding box after its
  transformation; the first selection holding a facet gives its id, as in PolyFEM's
  ``GeometryReader.cpp``). Body order follows ``geometry[]``.
- ``materials``: one dict for all bodies or a list of dicts with ``id`` (a body id): ``type``
  ``NeoHookean`` or ``LinearElasticity``, ``E``, ``nu``, ``rho`` (default 1, as PolyFEM),
  optional damping ``phi``, ``psi``. 2D scenes are plane stress (PolyFEM's 2D convention;
  ``model(domain, plane_stress=False)`` for plane strain).
- ``time``: ``t0`` (0), ``tend``, ``dt`` or ``time_steps``, ``integrator`` ("BDF1".."BDF6",
  "ImplicitEuler", or ``{"type": "BDF", "steps": k}``; default BDF1). Without ``time`` the
  scene is static: one solve (:class:`~diffsolids.Static`), as PolyFEM's default.
- ``contact``: ``enabled``, ``dhat`` (default: PolyFEM's rule from the shortest collision-mesh
  edge and ``dhat_percentage``, see :mod:`diffsolids.polyfem.contact`), ``epsv``,
  ``friction_coefficient``;
  ``solver.contact.barrier_stiffness`` (see :mod:`diffsolids.polyfem.contact` for how PolyFEM's
  kappa maps to ours: as written, with ``area_weighting=False``).
- ``boundary_conditions``: ``rhs`` (minus the body force per unit mass: ``[0, 9.8]`` is
  gravity along -y), ``dirichlet_boundary`` and ``neumann_boundary`` entries ``{"id": surface
  id, "value": [numbers], "dimension": [bools]}``.
- ``initial_conditions``: ``velocity`` and ``solution`` (displacement) entries ``{"id": body id,
  "value": [numbers]}``; ``acceleration`` is not needed by BDF and must be zero.

Ignored as harmless (they change how PolyFEM solves or writes, not the problem): ``output``,
``solver.linear``, ``solver.nonlinear``, ``solver.max_threads``, ``solver.advanced``,
``solver.contact.CCD``, ``space.advanced`` (``quadrature_order``: diffsolids integrates
mass terms at 2 x degree and strain terms at 2 x degree - 2, exact for P1),
``geometry[].advanced.normalize_mesh = false``, ``n_refs = 0``. Any other key raises
:class:`~diffsolids.errors.ParameterError` naming it (with its path in the JSON), so a scene
is never read with part of its meaning dropped.

Obstacles (``is_obstacle: true``) become kinematic :class:`~diffsolids.contact.Obstacle` s of
the contact term (``obstacles="kinematic"``, the default): the boundary of their mesh, placed
by its ``transformation``, with no dofs in the FE system. An obstacle moves as PolyFEM moves
it (``polyfem/mesh/GeometryReader.cpp``, ``read_obstacle_geometry``): its displacement is the
``value`` of the first ``boundary_conditions.dirichlet_boundary`` entry whose ``id`` is the
obstacle's ``surface_selection`` (an integer), replaced by the first matching
``boundary_conditions.obstacle_displacements`` entry (``id``: that integer, a list holding it,
or ``"all"``); without one (or without a ``surface_selection``) it is fixed. ``value`` has one
component per axis, each a number or an expression string of x, y, z, t in PolyFEM's (TinyExpr)
grammar (``diffsolids.io.expressions``: parsed, never ``eval``-ed), evaluated at the
obstacle's placed rest vertices (z = 0 in 2D) and at the step's time, from t = 0 on (a
constant moves the obstacle before the first step). PolyFEM applies the whole value to an
obstacle (its ``dimension`` is ignored there, and so here). An optional ``interpolation``
({"type": "none" | "linear" | "linear_ramp", "to", "from"}, or one per component) multiplies
the value by 1, t or the ramp min(max(t - from, 0), to - from), as PolyFEM's
``TensorBCValue::eval``. Refused by name (file and entry): per-vertex or per-time value
arrays, file and Python values, units, ``time_reference``, other interpolations, a 2D value
with a non-zero third component. ``obstacles="clamp"`` makes them
bodies whose boundary is clamped (a warning says so; their dofs stay in the system),
``obstacles="error"`` refuses them. ``fixed_bodies="obstacles"`` also turns every body whose
whole boundary is clamped to zero (the paper's grounds and pool, which are volume meshes
with ``dirichlet_boundary`` value 0 on their ``surface_selection``) into a fixed obstacle: the
other bodies see the same contact surface (its vertices are at rest in both set-ups), the FE
system loses the clamped body's dofs, and the clamped body's own interior deformation under
gravity, which no other body sees, is not computed.
"""

import dataclasses
import json
import math
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import dolfinx
import numpy as np
from mpi4py import MPI

from diffsolids.errors import ParameterError
from diffsolids.mesh import Domain, read_mesh
from diffsolids.mesh.scene import combine_meshes
from diffsolids.mesh.selections import (
    AxisPlaneSelection,
    BoxSelection,
    PlaneSelection,
    Selection,
    SphereSelection,
)

if TYPE_CHECKING:
    from diffsolids.contact import ContactTerm, Obstacle
    from diffsolids.integrators import Integrator
    from diffsolids.model.materials import Material
    from diffsolids.model.model import Model
    from diffsolids.simulation import Simulation
    from diffsolids.solvers.newton import SolverOptions

__all__ = [
    "BoxSideSelection",
    "PolyFEMBoundaryValue",
    "PolyFEMGeometry",
    "PolyFEMMaterial",
    "PolyFEMScene",
    "PolyFEMSetup",
    "read_polyfem_scene",
]

_TOP = {
    "geometry",
    "space",
    "time",
    "contact",
    "solver",
    "boundary_conditions",
    "initial_conditions",
    "materials",
    "output",
}
_GEOMETRY = {
    "mesh",
    "transformation",
    "volume_selection",
    "surface_selection",
    "n_refs",
    "advanced",
    "is_obstacle",
    "enabled",
    "type",
}
_TRANSFORM = {"translation", "rotation", "rotation_mode", "scale"}
_TIME = {"t0", "tend", "dt", "time_steps", "integrator"}
_CONTACT = {
    "enabled",
    "dhat",
    "dhat_percentage",
    "epsv",
    "friction_coefficient",
    "use_convergent_formulation",
    "use_area_weighting",
    "use_improved_max_operator",
    "use_physical_barrier",
}
_SOLVER_IGNORED = {"linear", "nonlinear", "max_threads", "advanced"}
_SOLVER_CONTACT = {"barrier_stiffness", "CCD", "friction_iterations"}
_BCS = {"rhs", "dirichlet_boundary", "neumann_boundary", "obstacle_displacements"}
_ICS = {"velocity", "solution", "acceleration"}
_MATERIAL = {"id", "type", "E", "nu", "rho", "phi", "psi"}
_LAWS = {"NeoHookean": "neo_hookean", "LinearElasticity": "linear"}


def _check_keys(section: Mapping, known: set, where: str) -> None:
    if not isinstance(section, Mapping):
        raise ParameterError(f"{where} must be a JSON object, got {section!r}")
    unknown = sorted(set(section) - known)
    if unknown:
        raise ParameterError(
            f"PolyFEM scene: unsupported key(s) {', '.join(f'{where}.{k}' for k in unknown)} "
            f"(supported here: {sorted(known)})"
        )


def _numbers(value: object, where: str, size: int | None = None) -> np.ndarray:
    if isinstance(value, str) or (
        isinstance(value, Sequence) and any(isinstance(v, str | Mapping) for v in value)
    ):
        raise ParameterError(f"{where} = {value!r}: only numbers are supported (no expressions)")
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if not np.all(np.isfinite(arr)) or (size is not None and arr.shape != (size,)):
        raise ParameterError(f"{where} = {value!r}: needs {size or 'finite'} finite numbers")
    return arr


@dataclass(frozen=True)
class PolyFEMGeometry:
    """One ``geometry[]`` entry.

    Attributes:
        mesh: The mesh file (resolved against the scene's folder).
        body_id: ``volume_selection``: the cell tag of its cells.
        surface: ``surface_selection``: an id for all its boundary facets, a list of
            ``(id, Selection)`` tested on facet barycentres, or None (untagged).
        scale: Scale factor(s).
        rotation: Rotation in degrees (an angle in 2D, Euler x, y, z in 3D) or None.
        translation: Translation or None.
        is_obstacle: PolyFEM's ``is_obstacle``.
        kinematic: Simulated as a kinematic obstacle (no dofs), see the module docstring.
        displacement: An obstacle's displacement as written: one number or expression string
            per component (None: fixed).
        interpolation: The time factors of the displacement, ``("none",)``, ``("linear",)``
            or ``("linear_ramp", from, to)``: one for all components or one per component.
        displacement_entry: Where the displacement was read (e.g.
            ``"boundary_conditions.obstacle_displacements[0]"``), for messages.
    """

    mesh: Path
    body_id: int
    surface: int | list[tuple[int, "Selection | BoxSideSelection"]] | None
    scale: float | tuple[float, ...] = 1.0
    rotation: float | tuple[float, ...] | None = None
    translation: tuple[float, ...] | None = None
    is_obstacle: bool = False
    kinematic: bool = False
    displacement: tuple[float | str, ...] | None = None
    interpolation: tuple[tuple[str | float, ...], ...] = ()
    displacement_entry: str | None = None


@dataclass(frozen=True)
class PolyFEMMaterial:
    """A material entry: ``law`` is diffsolids' name ("neo_hookean", "linear")."""

    law: str
    E: float
    nu: float
    rho: float
    phi: float = 0.0
    psi: float = 0.0

    def material(self, **overrides: float) -> "Material":
        """The diffsolids Material (``overrides``: e.g. ``E=...``, ``nu=...``)."""
        from diffsolids.model.materials import Material

        params = {
            "E": self.E,
            "nu": self.nu,
            "density": self.rho,
            "damping_phi": self.phi,
            "damping_psi": self.psi,
        }
        params.update(overrides)
        return Material(self.law, **params)

    def lame_material(self, dim: int) -> "Material":
        """The Material given by PolyFEM's Lamé parameters (``polyfem/assembler/MatParams.cpp``).

        lambda = E nu / ((1 + nu)(1 - 2 nu)) in 3D and E nu / (1 - nu^2) in 2D (plane stress:
        PolyFEM's 2D lambda is the one its energy uses, so the Model takes it as given, with
        ``plane_stress=False``), mu = E / (2 (1 + nu)).
        """
        from diffsolids.model.materials import Material

        E, nu = self.E, self.nu
        lmbda = E * nu / ((1 + nu) * (1 - 2 * nu)) if dim == 3 else E * nu / (1 - nu * nu)
        return Material(
            self.law,
            lmbda=lmbda,
            mu=E / (2 * (1 + nu)),
            density=self.rho,
            damping_phi=self.phi,
            damping_psi=self.psi,
        )


@dataclass(frozen=True)
class PolyFEMBoundaryValue:
    """A Dirichlet/Neumann entry (``id``: a surface id) or an initial value (``id``: a body id).

    Attributes:
        id: The selection id.
        value: The vector value: numbers, or (boundary conditions) expressions of x, y, z, t
            in PolyFEM's grammar where a component varies.
        components: Components it applies to (Dirichlet ``dimension``; None: all).
    """

    id: int
    value: tuple[float | str, ...]
    components: tuple[int, ...] | None = None


@dataclass
class PolyFEMSetup:
    """What :meth:`PolyFEMScene.build` makes: the pieces of a simulation of the scene.

    Attributes:
        domain: The mesh of all bodies with PolyFEM's volume and surface ids as tags.
        model: The Model (materials, loads, Dirichlet conditions, the contact term).
        integrator: ``BDF`` of the scene's time section.
        contact: The ContactTerm when the scene has contact enabled, else None.
        simulation: The Simulation of the model with the integrator, ready to ``run()``.
    """

    domain: Domain
    model: "Model"
    integrator: "Integrator"
    contact: "ContactTerm | None"
    simulation: "Simulation"


@dataclass
class PolyFEMScene:
    """A PolyFEM scene as read from its JSON (numbers as written, SI units).

    Attributes:
        path: The JSON file.
        geometry: The ``geometry[]`` entries in order.
        materials: Material per body id.
        degree: ``space.discr_order``.
        t0: Start time.
        dt: Time step.
        num_steps: Number of steps (``time_steps``, or round((tend - t0) / dt)).
        bdf_order: BDF order of ``time.integrator`` (0: a static scene, no ``time`` section).
        rhs: ``boundary_conditions.rhs`` (minus the body force per unit mass), or None.
        dirichlet: Dirichlet entries (ids: surface ids).
        neumann: Neumann entries (tractions; ids: surface ids).
        initial_velocity: Initial velocity entries (ids: body ids).
        initial_displacement: Initial displacement entries (ids: body ids).
        contact_enabled: ``contact.enabled``.
        raw: The JSON as a dict (for :func:`~diffsolids.polyfem.contact.polyfem_contact_options`).
    """

    path: Path
    geometry: list[PolyFEMGeometry]
    materials: dict[int, PolyFEMMaterial]
    degree: int
    t0: float
    dt: float
    num_steps: int
    bdf_order: int
    rhs: tuple[float, ...] | None
    dirichlet: list[PolyFEMBoundaryValue] = field(default_factory=list)
    neumann: list[PolyFEMBoundaryValue] = field(default_factory=list)
    initial_velocity: list[PolyFEMBoundaryValue] = field(default_factory=list)
    initial_displacement: list[PolyFEMBoundaryValue] = field(default_factory=list)
    contact_enabled: bool = False
    raw: dict = field(default_factory=dict)

    # -- derived numbers ----------------------------------------------------------------
    @property
    def body_ids(self) -> list[int]:
        """Body ids of the FE bodies in ``geometry[]`` order (repeated ids appear once)."""
        return list(dict.fromkeys(g.body_id for g in self.bodies))

    @property
    def bodies(self) -> list[PolyFEMGeometry]:
        """The ``geometry[]`` entries simulated as FE bodies (not kinematic obstacles)."""
        return [g for g in self.geometry if not g.kinematic]

    @property
    def obstacle_geometry(self) -> list[PolyFEMGeometry]:
        """The ``geometry[]`` entries simulated as kinematic obstacles."""
        return [g for g in self.geometry if g.kinematic]

    @property
    def tend(self) -> float:
        """Final time."""
        return self.t0 + self.num_steps * self.dt

    @property
    def contact(self) -> dict:
        """``contact`` and ``solver.contact`` sections as written."""
        return {
            **self.raw.get("contact", {}),
            **self.raw.get("solver", {}).get("contact", {}),
        }

    @property
    def barrier_stiffness(self) -> float | str:
        """``solver.contact.barrier_stiffness`` ("adaptive" if absent)."""
        return self.raw.get("solver", {}).get("contact", {}).get("barrier_stiffness", "adaptive")

    # -- builders ---------------------------------------------------------------------
    def domain(self, comm: MPI.Comm = MPI.COMM_WORLD) -> Domain:
        """The scene's meshes, placed and combined into one Domain (collective).

        Cells are tagged by ``volume_selection``, boundary facets by ``surface_selection``.
        Kinematic obstacles are not part of it (see :meth:`obstacles`).
        """
        geometry = self.bodies
        meshes = [
            read_mesh(
                g.mesh,
                MPI.COMM_SELF,
                scale=g.scale,
                rotation=g.rotation,
                translation=g.translation,
            )
            for g in geometry
        ]
        dims = {m.dim for m in meshes}
        if len(dims) != 1:
            raise ParameterError(f"{self.path}: meshes of dimensions {sorted(dims)} in one scene")
        boxes = [m.bounding_box() for m in meshes]
        # combine with the geometry index + 1 as a provisional tag: the facet selections belong
        # to an entry, and two entries may share a body id
        domain = combine_meshes(comm, meshes, bodies=list(range(1, len(meshes) + 1)))
        mesh = domain.mesh
        tdim = mesh.topology.dim
        fdim = tdim - 1
        entry = np.zeros(_num_cells(mesh), dtype=np.int32)
        entry[domain.cell_tags.indices] = domain.cell_tags.values - 1
        body_of_entry = np.array([g.body_id for g in geometry], dtype=np.int32)
        cell_tags = dolfinx.mesh.meshtags(
            mesh,
            tdim,
            np.arange(len(entry), dtype=np.int32),
            body_of_entry[entry],
        )
        mesh.topology.create_connectivity(fdim, tdim)
        boundary = dolfinx.mesh.exterior_facet_indices(mesh.topology)
        f2c = mesh.topology.connectivity(fdim, tdim)
        facet_entry = entry[f2c.array[f2c.offsets[boundary]]]
        centres = dolfinx.mesh.compute_midpoints(mesh, fdim, boundary)[:, : domain.dim]
        values = np.zeros(len(boundary), dtype=np.int32)
        for k, g in enumerate(geometry):
            mine = facet_entry == k
            if isinstance(g.surface, int):
                values[mine] = g.surface
            elif g.surface is not None:
                # PolyFEM's order: the first selection holding a facet names it
                for tag, selection in reversed(g.surface):
                    idx = np.flatnonzero(mine)
                    if isinstance(selection, BoxSideSelection):
                        values[idx] = selection.ids(centres[mine], boxes[k])
                    else:
                        values[idx[selection.inside(centres[mine], boxes[k])]] = tag
        keep = values > 0
        order = np.argsort(boundary[keep], kind="stable")
        facet_tags = dolfinx.mesh.meshtags(
            mesh, fdim, boundary[keep][order].astype(np.int32), values[keep][order]
        )
        return Domain(mesh, cell_tags, facet_tags, {})

    def model(
        self,
        domain: Domain,
        materials: Mapping[int, "Material"] | None = None,
        lame: bool = False,
        **kwargs: Any,
    ) -> "Model":
        """The Model: materials per body, plane stress in 2D, loads and Dirichlet conditions.

        Args:
            domain: From :meth:`domain`.
            materials: Optional Materials replacing the scene's, by body id.
            lame: Give the materials as PolyFEM's Lamé parameters (coefficients ``lmbda``
                and ``mu``, as PolyFEM's ``elastic`` optimisation variables set them; see
                :meth:`PolyFEMMaterial.lame_material`) instead of E and nu.
            **kwargs: Further arguments of :class:`~diffsolids.Model` (``plane_stress``
                defaults to True in 2D, PolyFEM's convention; with ``lame`` to False, as
                PolyFEM's 2D lambda is already the plane-stress one).
        """
        from diffsolids.model.model import Model

        mats = {
            b: m.lame_material(domain.dim) if lame else m.material()
            for b, m in self.materials.items()
            if b in self.body_ids
        }
        mats.update(materials or {})
        kwargs.setdefault("plane_stress", domain.dim == 2 and not lame)
        model = Model(domain, mats, degree=self.degree, **kwargs)
        self._check_dim(domain.dim)
        if self.rhs is not None and any(self.rhs):
            model.add_body_force(-np.asarray(self.rhs), name="gravity")
        for n in self.neumann:
            value = _boundary_value(n, domain.dim, f"{self.path}: neumann_boundary", False)
            model.add_traction(n.id, value.at_time if callable(value) else value)
        clamped = {g.surface for g in self.obstacle_geometry}  # obstacles: no dofs
        for d in self.dirichlet:
            if d.id in clamped:
                continue
            comps = None if d.components is None else list(d.components)
            value = _boundary_value(d, domain.dim, f"{self.path}: dirichlet_boundary", True)
            model.add_dirichlet(d.id, value, comps)
            if comps is None and not any(d.value):
                clamped.add(d.id)
        for g in self.bodies:
            if g.is_obstacle and isinstance(g.surface, int) and g.surface not in clamped:
                model.add_dirichlet(g.surface, 0.0)
                clamped.add(g.surface)
        return model

    def _check_dim(self, dim: int) -> None:
        for what, entries in (
            ("dirichlet_boundary", self.dirichlet),
            ("neumann_boundary", self.neumann),
            ("initial_conditions.velocity", self.initial_velocity),
            ("initial_conditions.solution", self.initial_displacement),
        ):
            for e in entries:
                if len(e.value) != dim:
                    raise ParameterError(
                        f"{self.path}: {what} id {e.id} value {list(e.value)} for a {dim}D scene"
                    )
        if self.rhs is not None and len(self.rhs) != dim:
            raise ParameterError(f"{self.path}: rhs {list(self.rhs)} for a {dim}D scene")

    @property
    def static(self) -> bool:
        """Whether the scene has no ``time`` section (one static solve, as PolyFEM)."""
        return self.bdf_order == 0

    def integrator(self) -> "Integrator":
        """The BDF integrator of ``time``, or ``Static()`` for a static scene."""
        from diffsolids.integrators import BDF, Static

        if self.static:
            return Static()
        return BDF(self.bdf_order, self.dt, self.num_steps)

    def obstacles(self, dim: int) -> list["Obstacle"]:
        """The kinematic obstacles: each obstacle entry's mesh boundary, placed, and its motion.

        An obstacle with a displacement (module docstring) gets a ``motion`` that evaluates
        it at its rest vertices, vectorised: a translation when no component depends on x,
        y, z, else one displacement per vertex.

        Args:
            dim: The scene's geometric dimension (its bodies' domain).

        Returns:
            A list of :class:`~diffsolids.contact.Obstacle`, named ``"obstacle<volume id>"``.

        Raises:
            ParameterError: A displacement with the wrong number of components for ``dim``
                (naming the file and the entry).
        """
        from diffsolids.contact import Obstacle

        out = []
        for g in self.obstacle_geometry:
            obstacle = Obstacle.from_file(
                g.mesh,
                dim=dim,
                scale=g.scale,
                rotation=g.rotation,
                translation=g.translation,
                name=f"obstacle{g.body_id}",
            )
            if g.displacement is not None:
                motion = _ObstacleMotion(self.path, g, dim, obstacle.rest_positions)
                if motion.moves:
                    prims = {"edges": obstacle.edges} if dim == 2 else {"faces": obstacle.faces}
                    obstacle = Obstacle(
                        obstacle.rest_positions, motion=motion, name=obstacle.name, **prims
                    )
                    motion.rest_positions = obstacle.rest_positions  # the same array (broadcast)
            out.append(obstacle)
        return out

    def contact_term(
        self,
        model: "Model",
        integrator: "Integrator | None" = None,
        stiffness: float | str | None = None,
        **kwargs: Any,
    ) -> "ContactTerm | None":
        """The ContactTerm with the scene's contact parameters, added to the model.

        Args:
            model: From :meth:`model`.
            integrator: Needed when the barrier stiffness is "adaptive" (or ``stiffness`` is
                "suggest"): :func:`~diffsolids.contact.suggest_barrier_stiffness` then sets it.
            stiffness: Replace the scene's barrier stiffness (a number, or "suggest").
            **kwargs: Further ContactTerm arguments (e.g. ``narrow_phase``). The scene's
                kinematic obstacles are passed as ``obstacles`` unless given here.

        Returns:
            The ContactTerm, or None when the scene has no contact.
        """
        from diffsolids.contact import ContactTerm, suggest_barrier_stiffness
        from diffsolids.polyfem.contact import polyfem_contact_options

        if not self.contact_enabled:
            return None
        if "obstacles" in kwargs:
            obstacles = list(kwargs["obstacles"] or [])
        else:
            obstacles = self.obstacles(model.dim) if self.obstacle_geometry else []
        options = polyfem_contact_options(self.raw, model.domain, obstacles)
        if stiffness is not None:
            options["stiffness"] = None if stiffness == "suggest" else float(stiffness)
        if obstacles:
            options["obstacles"] = obstacles
        options.update(kwargs)
        if options["stiffness"] is None:
            probe = ContactTerm(model, **{**options, "stiffness": 1.0})
            options["stiffness"] = suggest_barrier_stiffness(probe, integrator)
        contact = ContactTerm(model, **options)
        model.add_numeric_term(contact)
        return contact

    def nodal_values(self, model: "Model", entries: Sequence[PolyFEMBoundaryValue]) -> np.ndarray:
        """A local nodal array (V's layout) holding each body's value (Dirichlet nodes: 0)."""
        dim = model.dim
        out = np.zeros(
            (model.V.dofmap.index_map.size_local + model.V.dofmap.index_map.num_ghosts, dim)
        )
        for e in entries:
            nodes = np.unique(model.V.dofmap.list[model.domain.cells_of(e.id)])
            out[nodes] = e.value
        prescribed = np.unique(model.dirichlet_dofs() // dim)
        out[prescribed] = 0.0
        return out.ravel()

    def simulation(
        self,
        model: "Model",
        integrator: "Integrator",
        solver_options: "SolverOptions | None" = None,
        **kwargs: Any,
    ) -> "Simulation":
        """The Simulation with the scene's initial displacement and velocity."""
        from diffsolids.simulation import Simulation

        kwargs.setdefault("progress", False)
        return Simulation(model, integrator, solver_options, **self._initial_state(model), **kwargs)

    def _initial_state(self, model: "Model") -> dict[str, np.ndarray]:
        """``u0`` and, for a dynamic scene, ``v0`` of the Simulation."""
        state = {"u0": self.nodal_values(model, self.initial_displacement)}
        if not self.static:
            state["v0"] = self.nodal_values(model, self.initial_velocity)
        elif any(any(e.value) for e in self.initial_velocity):
            raise ParameterError(f"{self.path}: an initial velocity in a static scene")
        return state

    def build(
        self,
        comm: MPI.Comm = MPI.COMM_WORLD,
        solver_options: "SolverOptions | None" = None,
        stiffness: float | str | None = None,
        simulation_class: "type[Simulation] | None" = None,
        **simulation_kwargs,
    ) -> PolyFEMSetup:
        """Domain, model, integrator, contact term and simulation of the scene in one call.

        Args:
            comm: Communicator of the mesh.
            solver_options: Newton options of the Simulation.
            stiffness: Replace the scene's barrier stiffness (see :meth:`contact_term`).
            simulation_class: A Simulation subclass to use (default Simulation).
            **simulation_kwargs: Further Simulation arguments.
        """
        domain = self.domain(comm)
        model = self.model(domain)
        integrator = self.integrator()
        contact = self.contact_term(model, integrator, stiffness)
        if simulation_class is None:
            sim = self.simulation(model, integrator, solver_options, **simulation_kwargs)
        else:
            simulation_kwargs.setdefault("progress", False)
            sim = simulation_class(
                model, integrator, solver_options, **self._initial_state(model), **simulation_kwargs
            )
        return PolyFEMSetup(domain, model, integrator, contact, sim)

    def same_geometry(self, other: "PolyFEMScene") -> bool:
        """Whether another scene (e.g. a target) places the same meshes the same way."""
        return self.geometry == other.geometry


def _num_cells(mesh: dolfinx.mesh.Mesh) -> int:
    imap = mesh.topology.index_map(mesh.topology.dim)
    return imap.size_local + imap.num_ghosts


def read_polyfem_scene(
    path: str | os.PathLike, obstacles: str = "kinematic", fixed_bodies: str = "bodies"
) -> PolyFEMScene:
    """Read a PolyFEM scene JSON file.

    Args:
        path: The JSON file; mesh paths in it are relative to its folder.
        obstacles: What to do with ``is_obstacle`` geometry: "kinematic" (default: kinematic
            obstacles of the contact term, no dofs), "clamp" (a body whose boundary is
            clamped; a warning says so) or "error".
        fixed_bodies: "bodies" (default: as written) or "obstacles": bodies whose whole
            boundary is clamped to zero become fixed kinematic obstacles too (module docstring).

    Raises:
        ParameterError: A missing file, invalid JSON, an unsupported key (named with its path),
            or a malformed value.
    """
    path = Path(path)
    if not path.is_file():
        raise ParameterError(f"PolyFEM scene {path} does not exist")
    try:
        raw = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ParameterError(f"PolyFEM scene {path} is not valid JSON: {error}") from None
    if obstacles not in ("kinematic", "error", "clamp"):
        raise ParameterError(f"obstacles={obstacles!r}: 'kinematic', 'clamp' or 'error'")
    if fixed_bodies not in ("bodies", "obstacles"):
        raise ParameterError(f"fixed_bodies={fixed_bodies!r}: 'bodies' or 'obstacles'")
    _check_keys(raw, _TOP, "scene")
    geometry = _geometry(raw.get("geometry"), path.parent, obstacles)
    space = raw.get("space", {})
    _check_keys(space, {"discr_order", "advanced"}, "space")
    degree = int(space.get("discr_order", 1))
    t0, dt, num_steps, order = _time(raw.get("time"))
    solver = raw.get("solver", {})
    _check_keys(solver, _SOLVER_IGNORED | {"contact"}, "solver")
    _check_keys(solver.get("contact", {}), _SOLVER_CONTACT, "solver.contact")
    if int(solver.get("contact", {}).get("friction_iterations", 1)) != 1:
        raise ParameterError(
            "solver.contact.friction_iterations other than 1 is not supported (diffsolids lags "
            "the friction normal forces and tangent bases once per step, as PolyFEM's default)"
        )
    contact = raw.get("contact", {})
    _check_keys(contact, _CONTACT, "contact")
    bcs = raw.get("boundary_conditions", {})
    _check_keys(bcs, _BCS, "boundary_conditions")
    ics = raw.get("initial_conditions", {})
    _check_keys(ics, _ICS, "initial_conditions")
    for entry in _values(ics.get("acceleration", []), "initial_conditions.acceleration"):
        if any(entry.value):
            raise ParameterError(
                "initial_conditions.acceleration: a non-zero initial acceleration is not "
                "supported (BDF does not use one)"
            )
    dirichlet, geometry = _obstacle_displacements(
        geometry, bcs, path, obstacles == "kinematic", path.parent
    )
    rhs = bcs.get("rhs")
    scene = PolyFEMScene(
        path=path,
        geometry=geometry,
        materials=_materials(raw.get("materials"), _material_ids(geometry, obstacles)),
        degree=degree,
        t0=t0,
        dt=dt,
        num_steps=num_steps,
        bdf_order=order,
        rhs=None if rhs is None else tuple(_numbers(rhs, "boundary_conditions.rhs").tolist()),
        dirichlet=_values(dirichlet, "dirichlet_boundary", True, expressions=True),
        neumann=_values(bcs.get("neumann_boundary", []), "neumann_boundary", expressions=True),
        initial_velocity=_values(ics.get("velocity", []), "initial_conditions.velocity"),
        initial_displacement=_values(ics.get("solution", []), "initial_conditions.solution"),
        contact_enabled=bool(contact.get("enabled", False)),
        raw=raw,
    )
    scene.geometry = _kinematic_geometry(scene, obstacles, fixed_bodies == "obstacles")
    bodies = set(scene.body_ids)
    for what, entries in (
        ("initial_conditions.velocity", scene.initial_velocity),
        ("initial_conditions.solution", scene.initial_displacement),
    ):
        for e in entries:
            if e.id not in bodies:
                raise ParameterError(f"{path}: {what} id {e.id} is not a body id {sorted(bodies)}")
    return scene


def _material_ids(geometry: list[PolyFEMGeometry], obstacles: str) -> list[int]:
    """Body ids that need a material (kinematic obstacles need none)."""
    return [g.body_id for g in geometry if not (g.is_obstacle and obstacles == "kinematic")]


def _kinematic_geometry(
    scene: PolyFEMScene, obstacles: str, fixed_as_obstacles: bool
) -> list[PolyFEMGeometry]:
    """The geometry with ``kinematic`` set on the entries simulated as obstacles."""
    zero = {d.id for d in scene.dirichlet if d.components is None and not any(d.value)}
    ids = [g.body_id for g in scene.geometry]
    surfaces = [g.surface for g in scene.geometry if isinstance(g.surface, int)]
    out = []
    for k, g in enumerate(scene.geometry):
        alone = ids.count(g.body_id) == 1 and (g.surface is None or surfaces.count(g.surface) == 1)
        fixed = isinstance(g.surface, int) and g.surface in zero and alone
        kinematic = (g.is_obstacle and obstacles == "kinematic") or (fixed_as_obstacles and fixed)
        if kinematic:
            _check_obstacle_entry(scene, k, g, alone)
        out.append(dataclasses.replace(g, kinematic=kinematic))
    if all(g.kinematic for g in out):
        raise ParameterError(f"{scene.path}: every geometry entry is an obstacle (no body)")
    return out


def _check_obstacle_entry(scene: PolyFEMScene, k: int, g: PolyFEMGeometry, alone: bool) -> None:
    where = f"{scene.path}: geometry[{k}] ({g.mesh.name}, an obstacle)"
    if not alone or not (g.surface is None or isinstance(g.surface, int)):
        raise ParameterError(
            f"{where} shares its volume or surface id with another entry or has a surface "
            "selection by region: read the scene with obstacles='clamp'"
        )
    for what, entries in (
        ("dirichlet_boundary", [d for d in scene.dirichlet if d.id == g.surface]),
        ("neumann_boundary", [n for n in scene.neumann if n.id == g.surface]),
        ("initial_conditions.velocity", [v for v in scene.initial_velocity if v.id == g.body_id]),
        (
            "initial_conditions.solution",
            [u for u in scene.initial_displacement if u.id == g.body_id],
        ),
    ):
        if any(any(e.value) for e in entries):
            raise ParameterError(
                f"{where} has a non-zero {what} entry: a kinematic obstacle moves by its "
                "displacement only (a dirichlet_boundary or obstacle_displacements entry on "
                "its surface_selection, numbers or expressions of x, y, z, t), or read the "
                "scene with obstacles='clamp'"
            )


def _matches(entry: Mapping, surface: int) -> bool:
    """PolyFEM's id rule for obstacle displacements: the id, a list holding it, or "all"."""
    ids = entry.get("id")
    if isinstance(ids, list):
        return surface in ids
    return ids == "all" or (isinstance(ids, int) and not isinstance(ids, bool) and ids == surface)


def _obstacle_displacements(
    geometry: list[PolyFEMGeometry],
    bcs: Mapping,
    path: Path,
    kinematic: bool,
    folder: Path,
) -> tuple[list, list[PolyFEMGeometry]]:
    """Split off the obstacles' displacements (module docstring, PolyFEM's lookup rule).

    Returns the ``dirichlet_boundary`` entries left for the bodies and the geometry with each
    kinematic obstacle's displacement set.
    """
    dirichlet = bcs.get("dirichlet_boundary", [])
    moves = bcs.get("obstacle_displacements", [])
    for what, entries in (("dirichlet_boundary", dirichlet), ("obstacle_displacements", moves)):
        if not isinstance(entries, list):
            raise ParameterError(
                f"{path}: boundary_conditions.{what} must be a list of {{'id', 'value'}} entries"
            )
    surfaces = {
        g.surface
        for g in geometry
        if kinematic and g.is_obstacle and isinstance(g.surface, int) and g.surface > 0
    }
    for k, e in enumerate(moves):
        where = f"{path}: boundary_conditions.obstacle_displacements[{k}]"
        if not isinstance(e, Mapping):
            raise ParameterError(f"{where} = {e!r}: an object with 'id' and 'value'")
        if not kinematic:
            raise ParameterError(
                f"{where}: obstacle displacements need kinematic obstacles (read the scene "
                "with obstacles='kinematic')"
            )
        if not any(_matches(e, s) for s in surfaces):
            raise ParameterError(
                f"{where}: id {e.get('id')!r} is not the surface_selection of an obstacle "
                f"(obstacle surfaces: {sorted(surfaces)})"
            )
    body_entries, out = [], []
    for e in dirichlet:
        id_ = e.get("id") if isinstance(e, Mapping) else None
        if not (isinstance(id_, int) and id_ in surfaces):
            body_entries.append(e)
    for g in geometry:
        if not (isinstance(g.surface, int) and g.surface in surfaces and g.is_obstacle):
            out.append(g)
            continue
        found = None
        for what, entries in (("dirichlet_boundary", dirichlet), ("obstacle_displacements", moves)):
            for k, e in enumerate(entries):
                if isinstance(e, Mapping) and _matches(e, g.surface):
                    found = (f"boundary_conditions.{what}[{k}]", e, what == "dirichlet_boundary")
                    break
        if found is None:
            out.append(g)
            continue
        where, entry, is_dirichlet = found
        value, interpolation = _displacement_entry(entry, f"{path}: {where}", is_dirichlet, folder)
        out.append(
            dataclasses.replace(
                g, displacement=value, interpolation=interpolation, displacement_entry=where
            )
        )
    return body_entries, out


_INTERPOLATIONS = {"none": set(), "linear": set(), "linear_ramp": {"to", "from"}}


def _displacement_entry(
    entry: Mapping, where: str, is_dirichlet: bool, folder: Path
) -> tuple[tuple[float | str, ...], tuple[tuple[str | float, ...], ...]]:
    """An obstacle's ``value`` components (numbers, checked expression strings) and factors."""
    from diffsolids.io.expressions import parse_expression

    known = {"id", "value", "interpolation"} | ({"dimension"} if is_dirichlet else set())
    if isinstance(entry, Mapping) and "time_reference" in entry:
        raise ParameterError(
            f"{where}.time_reference: per-time obstacle displacements are not supported"
        )
    unknown = sorted(set(entry) - known)
    if unknown:
        raise ParameterError(f"{where}: unsupported key(s) {unknown} (supported: {sorted(known)})")
    value = entry.get("value")
    if not isinstance(value, list) or not value:
        raise ParameterError(f"{where}.value = {value!r}: a list with one value per axis")
    components: list[float | str] = []
    for d, c in enumerate(value):
        w = f"{where}.value[{d}]"
        if isinstance(c, bool) or not isinstance(c, int | float | str):
            kind = "a per-vertex or per-time array" if isinstance(c, list) else "an object"
            raise ParameterError(
                f"{w} = {c!r}: {kind} is not supported (units, files and Python functions "
                "neither): give a number or an expression of x, y, z, t"
            )
        if isinstance(c, str):
            candidate = Path(c) if Path(c).is_absolute() else folder / c
            if c.strip() and candidate.is_file():
                raise ParameterError(f"{w} = {c!r}: values read from a file are not supported")
            try:
                parse_expression(c)
            except ParameterError as error:
                raise ParameterError(f"{w}: {error}") from None
            components.append(c)
        else:
            if not math.isfinite(c):
                raise ParameterError(f"{w} = {c!r} is not finite")
            components.append(float(c))
    raw = entry.get("interpolation", [])
    raw = [raw] if isinstance(raw, Mapping) else raw
    if not isinstance(raw, list):
        raise ParameterError(f"{where}.interpolation = {raw!r}: an object or a list of objects")
    factors = []
    for k, item in enumerate(raw):
        w = f"{where}.interpolation" + (f"[{k}]" if len(raw) > 1 else "")
        kind = item.get("type") if isinstance(item, Mapping) else None
        if kind not in _INTERPOLATIONS:
            raise ParameterError(
                f"{w} = {item!r}: supported interpolation types {sorted(_INTERPOLATIONS)}"
            )
        extra = sorted(set(item) - {"type"} - _INTERPOLATIONS[kind])
        if extra:
            raise ParameterError(f"{w}: unsupported key(s) {extra} for type {kind!r}")
        if kind == "linear_ramp":
            if "to" not in item:
                raise ParameterError(f"{w}: a linear_ramp needs 'to'")
            factors.append((kind, float(item.get("from", 0.0)), float(item["to"])))
        else:
            factors.append((kind,))
    return tuple(components), tuple(factors)


def _is_zero(component: float | str) -> bool:
    """A component that is the number 0 or a constant expression equal to 0."""
    from diffsolids.io.expressions import parse_expression

    if not isinstance(component, str):
        return component == 0.0
    expr = parse_expression(component)
    return not expr.variables and float(expr()) == 0.0


class _ObstacleMotion:
    """``motion(t)`` of a scene's obstacle: its displacement expressions at its rest vertices.

    Component d at vertex X is value_d(X, t) * factor_d(t) (PolyFEM's ``TensorBCValue::eval``
    with the obstacle's placed rest vertex, z = 0 in 2D). Returns a (dim,) translation when no
    component depends on the position, else (n, dim) displacements.
    """

    def __init__(
        self, path: Path, g: PolyFEMGeometry, dim: int, rest_positions: np.ndarray
    ) -> None:
        from diffsolids.io.expressions import parse_expression

        where = f"{path}: {g.displacement_entry} (obstacle geometry {g.mesh.name})"
        value = list(g.displacement)
        if len(value) == 3 and dim == 2 and _is_zero(value[2]):
            value = value[:2]  # PolyFEM reads dim components (its default is [0, 0, 0])
        if len(value) != dim:
            raise ParameterError(
                f"{where}: value has {len(g.displacement)} components for a {dim}D scene"
            )
        self.where = where
        self.rest_positions = rest_positions
        self.components = [parse_expression(c) if isinstance(c, str) else float(c) for c in value]
        factors = list(g.interpolation)
        if 1 < len(factors) < dim:
            raise ParameterError(
                f"{where}: {len(factors)} interpolations for a {dim}D scene (give one, or one "
                "per component)"
            )
        self.factors = factors * dim if len(factors) == 1 else factors[:dim]
        self.moves = not all(_is_zero(c) for c in value)
        self.uniform = not any(
            not isinstance(c, float) and c.depends_on_position for c in self.components
        )

    @staticmethod
    def _factor(spec: tuple, t: float) -> float:
        if spec[0] == "linear":
            return t
        if spec[0] == "linear_ramp":
            lo, hi = spec[1], spec[2]
            return hi - lo if t >= hi else (0.0 if t <= lo else t - lo)
        return 1.0

    def __call__(self, t: float) -> np.ndarray:
        X = self.rest_positions
        n, dim = X.shape
        if self.uniform:
            point = {"x": 0.0, "y": 0.0, "z": 0.0}
        else:
            point = {"x": X[:, 0], "y": X[:, 1], "z": X[:, 2] if dim == 3 else np.zeros(n)}
        out = []
        for d, c in enumerate(self.components):
            v = np.asarray(c(t=t, **point) if not isinstance(c, float) else c, dtype=float)
            if self.factors:
                v = v * self._factor(self.factors[d], t)
            out.append(np.broadcast_to(v, () if self.uniform else (n,)))
        U = np.stack(out, axis=-1).astype(float)
        if not np.all(np.isfinite(U)):
            raise ParameterError(f"{self.where}: the displacement at t = {t:g} is not finite")
        return U


def _geometry(entries: object, folder: Path, obstacles: str) -> list[PolyFEMGeometry]:
    if not isinstance(entries, list) or not entries:
        raise ParameterError("PolyFEM scene: 'geometry' must be a non-empty list")
    out = []
    for k, g in enumerate(entries):
        where = f"geometry[{k}]"
        _check_keys(g, _GEOMETRY, where)
        if g.get("type", "mesh") != "mesh":
            raise ParameterError(f"{where}.type = {g['type']!r}: only 'mesh' is supported")
        if not g.get("enabled", True):
            continue
        if int(g.get("n_refs", 0)) != 0:
            raise ParameterError(f"{where}.n_refs = {g['n_refs']}: refinement is not supported")
        advanced = g.get("advanced", {})
        _check_keys(advanced, {"normalize_mesh"}, f"{where}.advanced")
        if advanced.get("normalize_mesh", False):
            raise ParameterError(f"{where}.advanced.normalize_mesh = true is not supported")
        if "mesh" not in g:
            raise ParameterError(f"{where} has no 'mesh'")
        mesh = Path(g["mesh"])
        mesh = mesh if mesh.is_absolute() else folder / mesh
        t = g.get("transformation", {})
        _check_keys(t, _TRANSFORM, f"{where}.transformation")
        if t.get("rotation_mode", "xyz") != "xyz":
            raise ParameterError(
                f"{where}.transformation.rotation_mode = {t['rotation_mode']!r}: only 'xyz'"
            )
        scale = _numbers(t.get("scale", 1.0), f"{where}.transformation.scale")
        rotation = t.get("rotation")
        rotation = None if rotation is None else _numbers(rotation, f"{where}.rotation")
        translation = t.get("translation")
        translation = None if translation is None else _numbers(translation, f"{where}.translation")
        volume = g.get("volume_selection", 0)  # PolyFEM: 0 without a selection or stored ids
        if not isinstance(volume, int) or isinstance(volume, bool):
            raise ParameterError(
                f"{where}.volume_selection must be an integer body id, got {volume!r} (selections "
                "of cells by region or file are not supported)"
            )
        obstacle = bool(g.get("is_obstacle", False))
        if obstacle and obstacles == "error":
            raise ParameterError(
                f"{where}.is_obstacle: refused (obstacles='error'); read the scene with "
                "obstacles='kinematic' (kinematic obstacles) or 'clamp' (a clamped body)"
            )
        if obstacle and obstacles == "clamp":
            warnings.warn(
                f"{where} ({mesh.name}) is an obstacle: simulated as a body with a clamped "
                "boundary (its dofs stay in the system)",
                stacklevel=3,
            )
        out.append(
            PolyFEMGeometry(
                mesh=mesh,
                body_id=volume,
                surface=_surface(g.get("surface_selection"), where),
                scale=float(scale[0]) if scale.size == 1 else tuple(scale.tolist()),
                rotation=None
                if rotation is None
                else (float(rotation[0]) if rotation.size == 1 else tuple(rotation.tolist())),
                translation=None if translation is None else tuple(translation.tolist()),
                is_obstacle=obstacle,
            )
        )
    return out


def _surface(
    value: object, where: str
) -> int | list[tuple[int, "Selection | BoxSideSelection"]] | None:
    """``surface_selection`` as PolyFEM's ``Selection::build_selections`` reads it.

    An integer, one selection object or a list of them (polyfem/utils/Selection.cpp); the
    first selection that contains a facet's barycentre gives its id
    (polyfem/mesh/GeometryReader.cpp, ``compute_boundary_ids``).
    """
    if value is None or (isinstance(value, int) and not isinstance(value, bool)):
        return value
    if isinstance(value, Mapping):
        value = [value]
    if not isinstance(value, list):
        raise ParameterError(
            f"{where}.surface_selection = {value!r}: an id, a selection object or a list of them"
        )
    out = []
    for k, s in enumerate(value):
        w = f"{where}.surface_selection[{k}]"
        if isinstance(s, Mapping) and "threshold" in s:
            extra = sorted(set(s) - {"threshold", "id_offset"})
            if extra:
                raise ParameterError(f"{w}: unsupported key(s) {extra} of a side selection")
            out.append((0, BoxSideSelection(float(s["threshold"]), int(s.get("id_offset", 0)))))
            continue
        if not isinstance(s, Mapping) or not isinstance(s.get("id"), int):
            raise ParameterError(f"{w} = {s!r}: a selection with an integer 'id'")
        rel = bool(s.get("relative", False))
        keys = set(s) - {"id", "relative"}
        if keys == {"box"}:
            lo, hi = s["box"]
            sel = BoxSelection(tuple(lo), tuple(hi), rel)
        elif keys == {"axis", "position"}:
            sel = AxisPlaneSelection(s["axis"], float(s["position"]), rel)
        elif keys == {"center", "radius"}:
            sel = SphereSelection(tuple(s["center"]), float(s["radius"]), rel)
        elif keys == {"normal", "point"}:
            sel = PlaneSelection(tuple(s["normal"]), tuple(s["point"]), rel)
        else:
            raise ParameterError(f"{w}: unsupported selection keys {sorted(keys)}")
        out.append((int(s["id"]), sel))
    return out


@dataclass(frozen=True)
class BoxSideSelection:
    """PolyFEM's ``{"threshold": eps, "id_offset": o}``: ids by the side of the bounding box.

    A facet whose barycentre is within eps of the box's x min gets 1 + o, else y min 2 + o,
    x max 3 + o, y max 4 + o, z min 5 + o, z max 6 + o, any other 7 + o (in that order);
    a negative eps means 1e-2 in 3D, 1e-7 in 2D (polyfem/utils/Selection.cpp,
    ``BoxSideSelection``).
    """

    threshold: float
    id_offset: int = 0

    def ids(self, points: np.ndarray, box: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """The id of each point (num_points x dim) against the mesh's bounding box."""
        dim = points.shape[1]
        eps = self.threshold if self.threshold >= 0 else (1e-2 if dim == 3 else 1e-7)
        lo, hi = (np.asarray(b, dtype=float)[:dim] for b in box)
        ids = np.full(len(points), 7, dtype=np.int32)
        sides = [(0, lo), (1, lo), (0, hi), (1, hi)] + ([(2, lo), (2, hi)] if dim == 3 else [])
        for side, (axis, corner) in reversed(list(enumerate(sides, start=1))):
            ids[np.abs(points[:, axis] - corner[axis]) < eps] = side  # the first side wins
        return ids + self.id_offset


def _time(time: Mapping[str, Any] | None) -> tuple[float, float, int, int]:
    """(t0, dt, num_steps, BDF order); a scene without ``time`` is static (order 0)."""
    if time is None:
        return 0.0, 1.0, 1, 0
    _check_keys(time, _TIME, "time")
    t0 = float(time.get("t0", 0.0))
    if t0 != 0.0:
        raise ParameterError(f"time.t0 = {t0}: only scenes starting at t = 0 are supported")
    if "tend" not in time:
        raise ParameterError("time.tend is missing")
    tend = float(time["tend"])
    if "time_steps" in time:
        num_steps = int(time["time_steps"])
        dt = (tend - t0) / num_steps
    elif "dt" in time:
        dt = float(time["dt"])
        if not (math.isfinite(dt) and dt > 0):
            raise ParameterError(f"time.dt = {dt} must be positive")
        num_steps = max(1, round((tend - t0) / dt))
    else:
        raise ParameterError("time needs 'dt' or 'time_steps'")
    integrator = time.get("integrator", "BDF1")
    if isinstance(integrator, Mapping):
        _check_keys(integrator, {"type", "steps"}, "time.integrator")
        if integrator.get("type") != "BDF":
            raise ParameterError(f"time.integrator.type = {integrator.get('type')!r}: only BDF")
        order = int(integrator.get("steps", 1))
    elif integrator == "ImplicitEuler":
        order = 1
    elif isinstance(integrator, str) and integrator.startswith("BDF") and integrator[3:].isdigit():
        order = int(integrator[3:])
    else:
        raise ParameterError(
            f"time.integrator = {integrator!r}: BDF1..BDF6 or ImplicitEuler only "
            "(Newmark / ImplicitNewmark are not supported)"
        )
    if not 1 <= order <= 6:
        raise ParameterError(f"time.integrator: BDF order {order} outside 1..6")
    return t0, dt, num_steps, order


def _values(
    entries: object, where: str, dirichlet: bool = False, expressions: bool = False
) -> list[PolyFEMBoundaryValue]:
    if not isinstance(entries, list):
        raise ParameterError(f"{where} must be a list of {{'id', 'value'}} entries")
    out = []
    for k, e in enumerate(entries):
        w = f"{where}[{k}]"
        _check_keys(e, {"id", "value", "dimension"} if dirichlet else {"id", "value"}, w)
        if not isinstance(e.get("id"), int):
            raise ParameterError(f"{w}.id = {e.get('id')!r}: an integer id (selections by id only)")
        if expressions:
            value = _components(e.get("value"), f"{w}.value")
        else:
            value = _numbers(e.get("value"), f"{w}.value").tolist()
        comps = None
        if "dimension" in e:
            mask = [bool(b) for b in e["dimension"]]
            comps = tuple(i for i, b in enumerate(mask) if b)
            if len(comps) == len(mask):
                comps = None
        out.append(PolyFEMBoundaryValue(int(e["id"]), tuple(value), comps))
    return out


def _components(value: object, where: str) -> list[float | str]:
    """A boundary value's components: numbers, or checked PolyFEM expressions of x, y, z, t.

    A constant expression such as ``"0.7*sin(-3)"`` becomes its number.
    """
    from diffsolids.io.expressions import parse_expression

    if not isinstance(value, list) or not value:
        raise ParameterError(f"{where} = {value!r}: a list with one value per axis")
    out: list[float | str] = []
    for d, c in enumerate(value):
        if isinstance(c, str):
            try:
                expr = parse_expression(c)
            except ParameterError as error:
                raise ParameterError(f"{where}[{d}]: {error}") from None
            if expr.variables:
                out.append(c)
                continue
            c = float(expr())
        if isinstance(c, bool) or not isinstance(c, int | float) or not math.isfinite(c):
            raise ParameterError(
                f"{where}[{d}] = {c!r}: a finite number or an expression of x, y, z, t "
                "(per-vertex arrays, files and units are not supported)"
            )
        out.append(float(c))
    return out


class _BoundaryExpression:
    """A Dirichlet value ``(x, t) -> (dim, n)`` from numbers and expressions of x, y, z, t."""

    def __init__(self, components: Sequence[float | str], dim: int) -> None:
        from diffsolids.io.expressions import parse_expression

        self.dim = dim
        self.parts = [parse_expression(c) if isinstance(c, str) else float(c) for c in components]

    def __call__(self, x: np.ndarray, t: float) -> np.ndarray:
        n = x.shape[1]
        point = {"x": x[0], "y": x[1], "z": x[2] if x.shape[0] > 2 else np.zeros(n)}
        return np.stack(
            [
                np.broadcast_to(c if isinstance(c, float) else c(t=t, **point), (n,))
                for c in self.parts
            ]
        )

    def at_time(self, t: float) -> np.ndarray:
        """The value of a position-independent entry at time t (a traction)."""
        return np.array([c if isinstance(c, float) else float(c(t=t)) for c in self.parts])

    @property
    def depends_on_position(self) -> bool:
        """Whether a component uses x, y or z."""
        return any(not isinstance(c, float) and c.depends_on_position for c in self.parts)


def _boundary_value(
    entry: PolyFEMBoundaryValue, dim: int, where: str, position: bool
) -> np.ndarray | _BoundaryExpression:
    """An entry's value for the model: numbers, or an expression callable."""
    if all(isinstance(c, float) for c in entry.value):
        return np.asarray(entry.value, dtype=float)
    value = _BoundaryExpression(entry.value, dim)
    if value.depends_on_position and not position:
        raise ParameterError(
            f"{where} id {entry.id}: value {list(entry.value)} depends on x, y or z; tractions "
            "that vary over the surface are not supported (functions of t are)"
        )
    return value


def _materials(value: object, body_ids: list[int]) -> dict[int, PolyFEMMaterial]:
    if isinstance(value, Mapping):
        entries, default = [value], True
    elif isinstance(value, list) and value:
        entries, default = value, False
    else:
        raise ParameterError("PolyFEM scene: 'materials' must be an object or a non-empty list")
    out = {}
    for k, m in enumerate(entries):
        w = "materials" if default else f"materials[{k}]"
        _check_keys(m, _MATERIAL, w)
        law = m.get("type")
        if law not in _LAWS:
            raise ParameterError(f"{w}.type = {law!r}: supported {sorted(_LAWS)}")
        for key in ("E", "nu"):
            if key not in m:
                raise ParameterError(f"{w}.{key} is missing")
        mat = PolyFEMMaterial(
            _LAWS[law],
            float(m["E"]),
            float(m["nu"]),
            float(m.get("rho", 1.0)),  # PolyFEM's default (json-specs/material-parameters.json)
            float(m.get("phi", 0.0)),
            float(m.get("psi", 0.0)),
        )
        if default:
            if "id" in m:
                raise ParameterError("materials: a single material has no 'id'")
            return dict.fromkeys(dict.fromkeys(body_ids), mat)
        ids = m.get("id")
        ids = ids if isinstance(ids, list) else [ids]
        for i in ids:
            if not isinstance(i, int):
                raise ParameterError(f"{w}.id = {m.get('id')!r}: integer body id(s)")
            out[i] = mat
    missing = sorted(set(body_ids) - set(out))
    if missing:
        raise ParameterError(f"materials: bodies {missing} have no material")
    return {b: out[b] for b in dict.fromkeys(body_ids)}
