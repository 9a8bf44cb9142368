"""The `Model`: a displacement space and the terms of its incremental potential.

Every coefficient the physics depends on is registered in ``Model.coefficients`` (material
fields, densities, damping, loads), so controls and the adjoint find them by name. A Simulation
compiles the model's forms and collects its step bounds when it is created, so it freezes the
model: terms, loads, contact and Dirichlet conditions are added before.
"""

import contextlib
import contextvars
import functools
import numbers
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import TypeVar

import numpy as np
import numpy.typing as npt
import ufl
from dolfinx import default_scalar_type, fem
from mpi4py import MPI
from ufl.core.expr import Expr

from diffsolids import forms
from diffsolids.errors import ParameterError, TagError
from diffsolids.mesh import Domain, check_orientation
from diffsolids.model.boundary_conditions import DirichletCondition, OnBody, RealisedDirichlet
from diffsolids.model.materials import Material
from diffsolids.model.numeric import NumericTerm
from diffsolids.model.terms import (
    BodyForce,
    Damping,
    ElasticEnergy,
    EnergyTerm,
    Inertia,
    StepFields,
    Term,
    Traction,
)
from diffsolids.parallel import collective_comm

NumericTermT = TypeVar("NumericTermT", bound=NumericTerm)

__all__ = ["Model", "undo_on_refusal"]

# the undo callbacks of the open outermost Model.parameter_update (None outside one)
_REFUSAL_UNDO: contextvars.ContextVar[list | None] = contextvars.ContextVar(
    "refusal_undo", default=None
)


def undo_on_refusal(undo: Callable[[], None]) -> None:
    """Have the open :meth:`Model.parameter_update` call ``undo`` if its point is refused.

    For state a control keeps outside the parameter fields (the shape, initial values, its own
    copy of its value): the control registers how to put it back before changing it. Outside
    a ``parameter_update`` block nothing is registered.
    """
    pending = _REFUSAL_UNDO.get()
    if pending is not None:
        pending.append(undo)


_PARAMETERS = ("density", "damping_psi", "damping_phi")


class Model:
    """Displacement field, material parameters, loads and boundary conditions of a scene.

    Args:
        domain: Mesh with body and facet tags.
        materials: One Material for all bodies, or ``{body: Material}`` covering every body.
        degree: Lagrange degree of the displacement (1, 2 or 3).
        plane_stress: In 2D, use plane stress instead of plane strain.
        quadrature_degree: Quadrature degree of mass-type terms (inertia, loads; default
            ``2 * degree``); terms of the strain (elasticity, damping) use two less.
        fields: Optional parameter fields replacing per-body constants, e.g.
            ``{"E": Function}`` on a DG0 or CG1 space.
        damping: Include the damping term even if all damping parameters are zero
            (e.g. to optimise them starting from zero).

    Raises:
        TagError: A material for a body the mesh does not have, or a body without material.
        ParameterError: Non-physical parameters for the chosen law and dimension.
        InvertedElementError: The rest mesh has degenerate or folded cells.

    Note:
        Terms, loads, contact terms and Dirichlet conditions (the ``add_*`` methods) are added
        before the first :class:`~diffsolids.Simulation` of the model is created: it freezes
        the model (see :meth:`freeze`), and a later ``add_*`` raises ParameterError.
    """

    def __init__(
        self,
        domain: Domain,
        materials: Material | Mapping[int | str, Material],
        degree: int = 1,
        plane_stress: bool = False,
        quadrature_degree: int | None = None,
        fields: Mapping[str, fem.Function] | None = None,
        damping: bool = False,
    ) -> None:
        if degree not in (1, 2, 3):
            raise ParameterError(f"displacement degree {degree} not supported (1, 2 or 3)")
        self.domain = domain
        mesh = domain.mesh
        self.dim = mesh.geometry.dim
        self.plane_stress = bool(plane_stress) and self.dim == 2
        self.degree = degree
        self.reference_signs = check_orientation(mesh)
        self.V = fem.functionspace(mesh, ("Lagrange", degree, (self.dim,)))
        self.materials = self._body_materials(materials)
        for mat in self.materials.values():
            mat.validate_for(self.dim, self.plane_stress)
        params = {m.parametrisation for m in self.materials.values()}
        if len(params) > 1:
            raise ParameterError("all bodies must give elastic parameters the same way")
        self.parametrisation = params.pop()
        self.coefficients: dict[str, fem.Function] = {}
        self._load_updates: list[tuple[fem.Function, Callable]] = []
        self._make_parameter_fields(fields or {})
        self.fields = self._make_fields(quadrature_degree or 2 * degree)
        self.terms: list[Term] = self._elastic_terms()
        has_damping = damping or any(
            m.damping_psi > 0 or m.damping_phi > 0 for m in self.materials.values()
        )
        if has_damping:
            self.terms.append(Damping())
        self.inertia = Inertia()
        self.dirichlet: list[RealisedDirichlet] = []
        self.numeric_terms: list[NumericTerm] = []
        self._frozen = False
        self._deferred_validation = 0

    # -- construction helpers -------------------------------------------------------------
    def _body_materials(
        self, materials: Material | Mapping[int | str, Material]
    ) -> dict[int, Material]:
        bodies = self.domain.body_ids
        if isinstance(materials, Material):
            return dict.fromkeys(bodies, materials)
        resolved = {self.domain.body_id(k): m for k, m in materials.items()}
        missing = sorted(set(bodies) - set(resolved))
        if missing:
            raise TagError(
                f"bodies {missing} have no material (materials given for {sorted(resolved)})"
            )
        return resolved

    def _make_parameter_fields(self, fields: Mapping[str, fem.Function]) -> None:
        mesh = self.domain.mesh
        Q = fem.functionspace(mesh, ("DG", 0))
        names = (*self.parametrisation, *_PARAMETERS)
        unknown = set(fields) - set(names)
        if unknown:
            raise ParameterError(f"unknown parameter fields {sorted(unknown)}; expected {names}")
        for name in names:
            if name in fields:
                self.coefficients[name] = fields[name]
                continue
            fn = fem.Function(Q, name=name)
            for body, mat in self.materials.items():
                fn.x.array[self.domain.cell_tags.find(body)] = getattr(mat, name)
            self.coefficients[name] = fn
        self.validate_parameters()

    @contextlib.contextmanager
    def parameter_update(self) -> Iterator[None]:
        """Change several parameter fields, then validate them together once.

        Controls that each set one field (lmbda, then mu) validate at the end of the block.
        Blocks nest; the outermost one is all or nothing: when its fields are non-physical, or
        an exception leaves it, every parameter field gets back its values from before the
        block (and the callbacks given to :func:`undo_on_refusal` run), so that a refused
        trial point leaves the model and its controls at the last accepted one.

        Raises:
            ParameterError: The fields at the end of the block are non-physical.
        """
        if self._deferred_validation > 0:  # nested: the outermost block validates
            with self._validation_deferred():
                yield
            return
        saved = {name: f.x.array.copy() for name, f in self.coefficients.items()}
        undo: list[Callable[[], None]] = []
        token = _REFUSAL_UNDO.set(undo)
        try:
            with self._validation_deferred():
                yield
            self.validate_parameters()
        except BaseException:
            for name, values in saved.items():
                self.coefficients[name].x.array[:] = values
            for step in reversed(undo):
                step()
            raise
        finally:
            _REFUSAL_UNDO.reset(token)

    @contextlib.contextmanager
    def _validation_deferred(self) -> Iterator[None]:
        """:meth:`parameters_changed` does not validate inside the block."""
        self._deferred_validation += 1
        try:
            yield
        finally:
            self._deferred_validation -= 1

    def parameters_changed(self) -> None:
        """Validate the parameter fields after a change, unless inside :meth:`parameter_update`.

        Raises:
            ParameterError: A non-finite or out-of-range value, naming the parameter.
        """
        if self._deferred_validation == 0:
            self.validate_parameters()

    def validate_parameters(self) -> None:
        """Check the current parameter fields (every dof) for physical ranges.

        Raises:
            ParameterError: A non-finite or out-of-range value, naming the parameter.
        """
        comm = self.domain.comm
        bounds = {
            "E": (0, None),
            "mu": (0, None),
            "density": (0, None),
            "damping_psi": (0, None),
            "damping_phi": (0, None),
        }
        upper_nu = 1.0 if self.plane_stress else 0.5
        bounds["nu"] = (-1.0, upper_nu)
        for name, (lo, hi) in bounds.items():
            if name not in self.coefficients:
                continue
            arr = self.coefficients[name].x.array
            bad_nan = collective_comm(comm).allreduce(
                int(np.count_nonzero(~np.isfinite(arr))), op=MPI.SUM
            )
            if bad_nan:
                raise ParameterError(f"parameter field {name} has {bad_nan} non-finite values")
            strict = name in ("E", "mu", "density", "nu")
            lo_bad = arr <= lo if strict else arr < lo
            hi_bad = arr >= hi if hi is not None else np.zeros_like(lo_bad)
            count = collective_comm(comm).allreduce(
                int(np.count_nonzero(lo_bad | hi_bad)), op=MPI.SUM
            )
            if count:
                rng = f"({lo}, {hi if hi is not None else 'inf'})"
                raise ParameterError(
                    f"parameter field {name} has {count} values outside the physical range {rng}"
                )

    def _make_fields(self, qdeg: int) -> StepFields:
        mesh = self.domain.mesh
        md = {"quadrature_degree": qdeg}
        md_strain = {"quadrature_degree": max(qdeg - 2, 0)}
        c = lambda v: fem.Constant(mesh, default_scalar_type(v))  # noqa: E731
        return StepFields(
            u=fem.Function(self.V, name="displacement"),
            u_prev=fem.Function(self.V, name="u_prev"),
            u_tilde=fem.Function(self.V, name="u_tilde"),
            v=fem.Function(self.V, name="velocity"),
            t=c(0.0),
            dt=c(1.0),
            beta_dt=c(1.0),
            X=ufl.SpatialCoordinate(mesh),
            dx=ufl.Measure("dx", domain=mesh, subdomain_data=self.domain.cell_tags, metadata=md),
            ds=ufl.Measure("ds", domain=mesh, subdomain_data=self.domain.facet_tags, metadata=md),
            dx_strain=ufl.Measure(
                "dx", domain=mesh, subdomain_data=self.domain.cell_tags, metadata=md_strain
            ),
            coefficients=self.coefficients,
        )

    def lame(self, f: StepFields | None = None) -> tuple[Expr | float, Expr | float]:
        """UFL expressions (lambda, mu) of the parameter fields (plane stress aware)."""
        c = self.coefficients
        if self.parametrisation == ("E", "nu"):
            return forms.lame_parameters(c["E"], c["nu"], self.plane_stress)
        lmbda, mu = c["lmbda"], c["mu"]
        if self.plane_stress:  # effective 2D lambda of plane stress
            return 2 * lmbda * mu / (lmbda + 2 * mu), mu
        return lmbda, mu

    def _elastic_terms(self) -> list[Term]:
        laws: dict[forms.StrainEnergy, list[int]] = {}
        for body, mat in self.materials.items():
            laws.setdefault(mat.law, []).append(body)
        single = len(laws) == 1
        return [
            ElasticEnergy(law, None if single else bodies, lambda f: self.lame(f))
            for law, bodies in laws.items()
        ]

    # -- freezing -----------------------------------------------------------------------------
    @property
    def frozen(self) -> bool:
        """Whether a Simulation uses the model (no more terms, loads or conditions)."""
        return self._frozen

    def freeze(self) -> None:
        """Refuse further terms, loads, contact terms and Dirichlet conditions.

        Called by :class:`~diffsolids.Simulation` once it is created: its Newton solver has
        compiled the potential and collected the step bounds (element inversion, contact CCD)
        of the terms present then, so a later term would be ignored or miss its step bound.
        """
        self._frozen = True

    def _check_not_frozen(self, method: str) -> None:
        """Raise if a Simulation already uses the model.

        Raises:
            ParameterError: The model is frozen.
        """
        if self._frozen:
            raise ParameterError(
                f"Model.{method}: the model is already used by a Simulation, which compiled its "
                "forms and collected its step bounds when it was created; add terms, loads, "
                "contact terms and Dirichlet conditions before creating the Simulation"
            )

    # -- user API -----------------------------------------------------------------------------
    def add_term(self, term: Term | Callable) -> Term:
        """Add a UFL term (a Term or a callable ``fields -> scalar form``).

        Raises:
            ParameterError: A Simulation already uses the model.
        """
        self._check_not_frozen("add_term")
        if not isinstance(term, Term):
            term = EnergyTerm(term)
        self.terms.append(term)
        return term

    def _uniform_vector_field(self, name: str, value: npt.ArrayLike | Callable) -> fem.Function:
        """A load vector as a uniform DG0 field, so UFL can differentiate with respect to it."""
        if name in self.coefficients:
            raise ParameterError(f"a coefficient named {name!r} already exists")
        initial = value(0.0) if callable(value) else value
        arr = np.broadcast_to(np.asarray(initial, dtype=float), (self.dim,)).copy()
        if not np.all(np.isfinite(arr)):
            raise ParameterError(f"{name} = {arr} is not finite")
        Q = fem.functionspace(self.domain.mesh, ("DG", 0, (self.dim,)))
        field = fem.Function(Q, name=name)
        field.x.array.reshape(-1, self.dim)[:] = arr
        self.coefficients[name] = field
        if callable(value):
            self._load_updates.append((field, value))
        return field

    def add_body_force(
        self,
        acceleration: npt.ArrayLike | Callable,
        bodies: Sequence[int | str] | None = None,
        name: str | None = None,
    ) -> Term:
        """Body force rho g (e.g. gravity), ``acceleration`` a vector or ``g(t)``.

        Raises:
            ParameterError: A non-finite value, or a Simulation already uses the model.
        """
        self._check_not_frozen("add_body_force")
        name = name or f"body_force_{len([t for t in self.terms if isinstance(t, BodyForce)])}"
        ids = None if bodies is None else [self.domain.body_id(b) for b in bodies]
        self._uniform_vector_field(name, acceleration)
        return self.add_term(BodyForce(name, ids))

    def add_gravity(self, g: float = 9.81, axis: int | None = None) -> Term:
        """Gravity of magnitude g along -axis (default: the last axis).

        Raises:
            ParameterError: g is not a finite number, axis is not an axis of the mesh, or a
                Simulation already uses the model.
        """
        self._check_not_frozen("add_gravity")
        if not isinstance(g, numbers.Real) or not np.isfinite(g):
            raise ParameterError(
                f"gravity: g must be a finite number (a magnitude along -axis), got {g!r}; "
                "use add_body_force for a vector"
            )
        axis = self.dim - 1 if axis is None else axis
        if axis not in range(self.dim):
            raise ParameterError(f"gravity: axis {axis} is not an axis of a {self.dim}D mesh")
        vec = np.zeros(self.dim)
        vec[axis] = -g
        return self.add_body_force(vec, name="gravity")

    def add_traction(
        self, facet_tag: int | str, traction: npt.ArrayLike | Callable, name: str | None = None
    ) -> Term:
        """Dead traction on tagged facets, ``traction`` a vector or ``t(t)``.

        Raises:
            ParameterError: A non-finite value, or a Simulation already uses the model.
        """
        self._check_not_frozen("add_traction")
        tag = self.domain.facet_id(facet_tag)
        name = name or f"traction_{tag}"
        self._uniform_vector_field(name, traction)
        return self.add_term(Traction(name, tag))

    def add_dirichlet(
        self,
        where: int | str | OnBody | Callable,
        value: float | Sequence[float] | Callable = 0.0,
        components: Sequence[int] | None = None,
    ) -> RealisedDirichlet:
        """Prescribe displacements on facets, a body or located nodes (see DirichletCondition).

        ``where`` is a facet tag (id or name), ``OnBody(body)`` for every node of a body, or a
        node locator ``marker(x) -> bool mask``.

        Raises:
            ParameterError: A Simulation already uses the model.
        """
        self._check_not_frozen("add_dirichlet")
        bc = RealisedDirichlet(DirichletCondition(where, value, components), self.V, self.domain)
        self.dirichlet.append(bc)
        return bc

    def add_numeric_term(self, term: NumericTermT) -> NumericTermT:
        """Add a non-UFL term (e.g. contact) answering the same questions numerically.

        Returns:
            The term, so that ``contact = model.add_numeric_term(ContactTerm(model, ...))``.

        Raises:
            ParameterError: A Simulation already uses the model, or ``term`` is not a
                :class:`~diffsolids.model.numeric.NumericTerm`.
        """
        self._check_not_frozen("add_numeric_term")
        if not isinstance(term, NumericTerm):
            raise ParameterError(
                f"add_numeric_term takes a NumericTerm (diffsolids.model.NumericTerm), "
                f"not {type(term).__name__}"
            )
        self.numeric_terms.append(term)
        return term

    # -- queries used by integrators, solvers and the adjoint ----------------------------
    @property
    def bcs(self) -> list[fem.DirichletBC]:
        """All DOLFINx Dirichlet conditions."""
        return [bc for d in self.dirichlet for bc in d.bcs]

    def dirichlet_dofs(self) -> np.ndarray:
        """Sorted unrolled local indices of all constrained dofs."""
        if not self.dirichlet:
            return np.zeros(0, dtype=np.int32)
        return np.unique(np.concatenate([d.dofs for d in self.dirichlet]))

    def active_terms(self, dynamic: bool) -> list[Term]:
        """UFL terms of a static (``dynamic=False``) or BDF step."""
        terms = [t for t in self.terms if dynamic or not t.dynamic_only]
        return [self.inertia, *terms] if dynamic else terms

    def potential(self, dynamic: bool) -> ufl.Form:
        """Incremental potential of a step (sum of the active UFL terms)."""
        return sum(t.energy(self.fields) for t in self.active_terms(dynamic))

    def magnitude(self, dynamic: bool) -> ufl.Form:
        """Sum of |energy densities| (scale of the roundoff of the potential)."""
        return sum(t.magnitude(self.fields) for t in self.active_terms(dynamic))

    def is_quadratic(self, dynamic: bool) -> bool:
        """True when the step Jacobian does not depend on u (linear problem)."""
        return not self.numeric_terms and all(t.quadratic for t in self.active_terms(dynamic))

    def update_time(self, t: float) -> None:
        """Set time-dependent loads, Dirichlet values and the time constant to time ``t``."""
        self.fields.t.value = t
        for field, fn in self._load_updates:
            arr = np.broadcast_to(np.asarray(fn(t), dtype=float), (self.dim,))
            if not np.all(np.isfinite(arr)):
                raise ParameterError(f"load value {arr} at t = {t} is not finite")
            field.x.array.reshape(-1, self.dim)[:] = arr
        for d in self.dirichlet:
            d.update(t)

    def body_measure(self, body: int | str | None = None) -> ufl.Measure:
        """Volume measure of one body (all bodies if None)."""
        dx = self.fields.dx
        return dx if body is None else dx(self.domain.body_id(body))

    @functools.cached_property
    def shape_space(self) -> fem.FunctionSpace:
        """P1 vector space of the rest coordinates (shape derivatives live here)."""
        return fem.functionspace(self.domain.mesh, ("Lagrange", 1, (self.dim,)))
