"""IPC contact and lagged smoothed friction as a numeric term of the incremental potential.

Step i adds to the incremental potential (scaled so that elasticity has coefficient 1, paper
sec. 8.2)

    B(x) + beta dt D(v(u)),    x = X + W u,   v(u) = W (u + sum_j alpha_j u^{i-j}) / (beta dt),

with B = kappa sum_k A_k b(d_k^2, dhat^2) the area-weighted log barrier over the collision set at x
and D the smoothed IPC friction dissipation potential whose normal forces and tangent bases are
lagged from x^{i-1} = X + W u^{i-1} once per step. The gradient of the friction part w.r.t. u is
-F(v) (the friction force) and its Hessian Hess_v D / (beta dt). Static load steps use
v = (u - u^{i-1}) / dt with coefficient dt (alpha = -1, beta = 1).

ContactTerm is a thin composition of the parts of this scheme, each in its module of
``diffsolids.contact``:

- ``collisions.CollisionBuilder``: this rank's share of the collision set at positions x.
- ``lagging.LaggedFriction``: the step's normal forces and tangent bases lagged from x^{i-1},
  the friction coefficients of the pairs of bodies, the BDF velocity.
- ``potential.ContactPotential``: kappa, and the energy, gradient and Hessian at an Evaluation.
- ``pattern.ContactPattern``: the vertex blocks and matrix pattern of the step.
- ``free_dofs.FreeDofs``: the free (not Dirichlet) collision dofs and the static vertices.
- ``adjoint.ContactAdjoint``: the transposed derivatives of the residual applied to lam.
- ``obstacle_moves.ObstacleMoves``: kinematic obstacles, their moves and the scheme of a step
  with moving obstacles.
- ``checks.ConfigurationCheck`` and ``step_bound.StepBound``: refused configurations and the
  collision-free step bound (CCD).

The term keeps the state of the step (its BDF history, lagged and obstacle displacements) and
the evaluation cache: one Evaluation per displacement, valid while the token is unchanged (a
new step, new rest positions or static vertices, and rebuilt lagged friction change it).

Distributed contact: all ranks hold the whole collision surface (gathered once per evaluation)
and build the collision set on it, but each collision is evaluated on one rank only
(``partition.CollisionPartition``: a hash of its ids picks the rank). Energies are summed over
the ranks, collision-dof vectors too (one allreduce of the surface vector, then each rank adds
the rows it owns); matrix entries are added by every rank with global indices into the rows
where they live (PETSc sends them in the assembly; the pattern, the union over the ranks,
preallocates them). The broad and narrow phase of the collision set, the CCD step bound and the
reach pattern are the same computation on every rank (see the partition module for why). On
one rank this is the serial code with the identity for every reduction.
"""

import contextlib
import logging
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import ipctk
import numpy as np
from dolfinx import fem
from petsc4py import PETSc

from diffsolids.contact.derivatives.step_adjoint import ContactAdjoint
from diffsolids.contact.detection.checks import ConfigurationCheck
from diffsolids.contact.detection.collision_set import CollisionBuilder
from diffsolids.contact.detection.step_bound import (  # noqa: F401  (test_soft_barrier imports them here)
    _CCD_REACH,
    _GAP_FLOOR_ULPS,
    StepBound,
    _edge_vertex_bounds,
)
from diffsolids.contact.diagnostics import (
    ContactRecord,
    continuation_schedule,
    failure_report,
    settling_gap,
    step_record,
)
from diffsolids.contact.energy.contact_potential import ContactPotential, projection_method
from diffsolids.contact.energy.evaluation import Evaluation
from diffsolids.contact.energy.friction_table import body_pairs, coefficients_of
from diffsolids.contact.energy.lagging import LaggedFriction
from diffsolids.contact.energy.pattern import ContactPattern
from diffsolids.contact.energy.stiffness import suggest_barrier_stiffness
from diffsolids.contact.geometry.free_dofs import FreeDofs
from diffsolids.contact.geometry.obstacle import Obstacle, checked_obstacles
from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.contact.obstacle_moves import ObstacleMoves
from diffsolids.contact.partition import CollisionPartition
from diffsolids.contact.step import ContactStep
from diffsolids.contact.timing import timed, timed_kernel, timing_summary
from diffsolids.errors import IntersectionError, ParameterError
from diffsolids.model.numeric import NumericTerm

if TYPE_CHECKING:
    from diffsolids.integrators import Integrator
    from diffsolids.model import Model
    from diffsolids.states import StateHistory, StepContext

__all__ = ["ContactRecord", "ContactTerm"]

# a failed last continuation stage ends the solve when the most loaded pair would settle within
# this factor of the collision check's gap floor (the too-soft block of tests/test_soft_barrier:
# 1.1; the fig22 ball at its kappa 1e4, which converges: 9)
_ROUND_OFF_MARGIN = 2.0

logger = logging.getLogger("diffsolids")


class ContactTerm(NumericTerm):
    """Barrier contact (self-contact included) and lagged friction between the bodies of a Model.

    Bodies are the cell tags of the mesh; every pair of bodies and every body with itself can
    collide, except pairs of fully prescribed (Dirichlet) vertices, which are static obstacles.
    Add the term with ``model.add_numeric_term(term)``.

    Args:
        model: The Model.
        dhat: Barrier activation distance (length).
        stiffness: Barrier stiffness kappa, fixed for the life of the term. None: the term
            chooses it at the first step it takes part in, with
            :func:`~diffsolids.contact.suggest_barrier_stiffness` for that simulation's
            integrator at the state before the step, and keeps it (later runs, e.g. of an
            optimisation, use the same kappa, so the objective stays a smooth function of the
            parameters).
        friction: Friction coefficient of all pairs of bodies (float), or
            ``{(body_a, body_b): mu}`` by id or name (unlisted pairs: 0).
        eps_v: Velocity below which friction is smoothed to static (velocity units).
        narrow_phase: "additive" (AdditiveCCD) or "tight_inclusion" (TightInclusionCCD(1e-6, 1000)).
        area_weighting: Weight each pair by its surface area (paper sec. 8.2).
        min_gap: Initial configurations closer than ``min_gap * dhat`` are refused.
        num_threads: ipctk threads (default 1). ipctk sums its threads' shares of the
            barrier and friction derivatives in the order the threads finish, so with more
            than one the states of two runs at the same parameters differ in the last bits
            (J by ~1e-11, relative); with one they are equal to the last bit.
        obstacles: Kinematic :class:`~diffsolids.contact.geometry.obstacle.Obstacle` s
            (collision-only, no dofs, fixed or moving); each is a body of the contact term with the
            next body id after the domain's (``body_ids``), named by its ``name`` in friction
            tables.
        hessian_projection: How the projected Newton phase makes each pair's Hessian positive
            semi-definite: "clamp" (negative eigenvalues set to zero) or "abs" (replaced by their
            absolute values), ipctk's ``PSDProjectionMethod``. Adjoints always use the exact
            Hessian.
        boundary: The collision surface of P2/P3 bodies: "nodes" (each boundary facet split at
            its edge and face nodes, so the simulated boundary never intersects) or "vertices"
            (the facets between the mesh vertices only; a curved boundary may pass through
            another body between vertices). Both are the same for P1.
        formulation: "ipc" (default): one barrier term per closest primitive pair, as in the
            IPC paper and PolyFEM's default. "convergent" (needs ``area_weighting``): the
            improved max approximation of the collision set (Li et al. 2023, ipctk's
            ``IMPROVED_MAX_APPROX``, PolyFEM's ``use_convergent_formulation``), whose terms sum to
            one barrier of the distance to a flat or smooth surface whatever its triangulation, with
            the flat regions of fixed obstacles acting through the bodies' vertices only
            (:mod:`~diffsolids.contact.geometry.flat`). With "ipc" a body resting on two coplanar
            triangles is pushed off their shared edge (a barrier ridge along it), so a symmetric
            landing becomes one of two mirror states chosen by round-off; use "convergent" for
            bodies on triangulated flat grounds.

    Raises:
        ParameterError: Non-positive dhat, stiffness or eps_v, negative friction, unknown body,
            an obstacle that is not an Obstacle or whose name is taken, an unknown
            formulation, or "convergent" without area weights.
        MeshError: An obstacle of the wrong dimension.
    """

    name = "contact"
    projectable_hessian = True
    has_hessian_action = True
    grows_pattern = True
    has_stiffness_continuation = True
    revises_newton_steps = True
    parameter_names = ("friction",)

    def __init__(
        self,
        model: "Model",
        dhat: float,
        stiffness: float | None = None,
        friction: float | Mapping = 0.0,
        eps_v: float = 1e-3,
        narrow_phase: str = "additive",
        area_weighting: bool = True,
        min_gap: float = 1e-6,
        num_threads: int | None = None,
        obstacles: Sequence[Obstacle] = (),
        hessian_projection: str = "clamp",
        boundary: str = "nodes",
        formulation: str = "ipc",
    ) -> None:
        checked = (("dhat", dhat), ("stiffness", stiffness), ("eps_v", eps_v))
        for label, value in checked:
            if value is None and label == "stiffness":
                continue
            if not (np.isfinite(value) and value > 0):
                raise ParameterError(f"contact {label} = {value} must be positive and finite")
        self.model = model
        self.comm = model.domain.comm
        self.dim = model.dim
        self.dhat = float(dhat)
        self.eps_v = float(eps_v)
        self.area_weighting = bool(area_weighting)
        self.min_gap = float(min_gap)
        self.projection = projection_method(hessian_projection)
        threads = 1 if num_threads is None else num_threads
        if not (isinstance(threads, int | np.integer) and threads >= 1):
            raise ParameterError(f"contact num_threads = {num_threads!r} must be an integer >= 1")
        ipctk.set_num_threads(int(threads))
        self.obstacles = checked_obstacles(obstacles, model.domain.names)
        self.surface = CollisionSurface(model.domain, model.V, self.obstacles, boundary)
        self.surface.obstacle_displacement(0.0)  # a bad motion fails here, not in a step
        if self.obstacles:  # obstacles never collide with each other
            static = np.zeros(self.surface.num_vertices, dtype=bool)
            static[self.surface.num_body_vertices :] = True
            self.surface.set_static(static)
        self.body_ids = self.surface.body_ids
        pairs = zip(self.obstacles, self.surface.obstacle_ids, strict=True)
        self._obstacle_names = {o.name: b for o, b in pairs if o.name}
        self.timings: dict[str, list] = {}
        self.obstacle_moves = ObstacleMoves(self.surface, self.dim, self.timings)
        self.friction_potential = ipctk.FrictionPotential(self.eps_v)
        self.broad_phase = ipctk.LBVH()
        self.partition = CollisionPartition(self.comm)
        self.builder = CollisionBuilder(
            self.surface,
            self.broad_phase,
            self.partition,
            self.dhat,
            self.area_weighting,
            formulation,
        )
        if narrow_phase == "additive":
            ccd = ipctk.AdditiveCCD()
        elif narrow_phase == "tight_inclusion":
            ccd = ipctk.TightInclusionCCD(1e-6, 1000)
        else:
            raise ParameterError(
                f"narrow_phase {narrow_phase!r}: expected 'additive' or 'tight_inclusion'"
            )
        self.step_bound = StepBound(
            self.surface, ccd, self.broad_phase, self.dhat, self.comm, self.partition
        )
        self.friction_pairs: list[tuple[int, int]]
        self.friction_pairs, self._pair_index = body_pairs(self.body_ids)
        self.lagging = LaggedFriction(
            self.builder, self._pair_index, len(self.friction_pairs), self.timings
        )
        kappa = None if stiffness is None else float(stiffness)
        self.potential = ContactPotential(
            self.lagging, self.friction_potential, kappa, self.projection, self.timings
        )
        self.adjoint = ContactAdjoint(model, self.lagging, self.potential, self.eps_v)
        self.pattern = ContactPattern(self.potential)
        self.configuration = ConfigurationCheck(
            self.builder, self.obstacles, model.domain.names, self.friction_pairs, self.min_gap
        )
        self.friction_coefficients = coefficients_of(
            friction, len(self.friction_pairs), self.pair_index
        )
        self.records: list[ContactRecord] = []
        self.force_function = fem.Function(model.V, name="contact_force")
        self._token = 0
        self._eval: Evaluation | None = None
        self._step = None
        self.free_dofs = FreeDofs(self.surface, self.comm, self.dim)
        self._forward_step: int | None = None

    @property
    def stiffness(self) -> float | None:
        """Barrier stiffness kappa (None until chosen at the first step)."""
        return self.potential.stiffness

    @property
    def barrier(self) -> ipctk.BarrierPotential | None:
        """The ipctk BarrierPotential with :attr:`stiffness` (None until chosen)."""
        return self.potential.barrier

    @property
    def moved_with_guess(self) -> list[int]:
        """Forward steps whose obstacle move was made with the body's initial guess."""
        return self.obstacle_moves.moved_with_guess

    @property
    def ccd(self) -> ipctk.NarrowPhaseCCD:
        """The narrow-phase CCD of the collision-free step bound."""
        return self.step_bound.ccd

    # -- parameters ---------------------------------------------------------------------------
    def _body_id(self, body: int | str) -> int:
        """Body id of a domain body or an obstacle (by id or name)."""
        if isinstance(body, str) and body in self._obstacle_names:
            return self._obstacle_names[body]
        if not isinstance(body, str) and int(body) in self.surface.obstacle_ids:
            return int(body)
        return self.model.domain.body_id(body)

    def pair_index(self, body_a: int | str, body_b: int | str) -> int:
        """Index of the pair of bodies in :attr:`friction_pairs`."""
        ids = self.body_ids
        ia = ids.index(self._body_id(body_a))
        ib = ids.index(self._body_id(body_b))
        return int(self._pair_index[ia, ib])

    @property
    def friction_coefficients(self) -> np.ndarray:
        """Friction coefficient of each pair in :attr:`friction_pairs` (a copy; assign to set)."""
        return self.lagging.mu.copy()

    @friction_coefficients.setter
    def friction_coefficients(self, values: np.ndarray | Sequence[float]) -> None:
        self.lagging.set_coefficients(values)

    def set_friction(self, body_a: int | str, body_b: int | str, mu: float) -> None:
        """Set the friction coefficient between two bodies (the same body for self-contact)."""
        values = self.lagging.mu.copy()
        values[self.pair_index(body_a, body_b)] = mu
        self.friction_coefficients = values

    # -- per-step set-up ---------------------------------------------------------------------
    def _choose_stiffness(self, integrator: "Integrator | None", u: np.ndarray) -> None:
        """Fix kappa from the scene (collective): suggest_barrier_stiffness at ``u``."""
        state = fem.Function(self.model.V)
        state.x.array[:] = u
        self.potential.set_stiffness(suggest_barrier_stiffness(self, integrator, state))
        logger.info("contact: barrier stiffness chosen: kappa = %.4g", self.stiffness)

    def begin_step(self, context: "StepContext") -> None:
        """Lag friction from u^{i-1} and store the BDF history of step ``i`` (collective)."""
        i, traj, coeffs = context.index, context.history, context.step
        surf = self.surface
        if surf.update_rest_positions():
            self._token += 1
        self._update_static()
        self.obstacle_moves.follow(context.integrator)
        if self.stiffness is None:
            self._choose_stiffness(context.integrator, traj.u[i - 1])
        m = len(coeffs.alpha)
        obstacle = [self.obstacle_moves.at(i - j) for j in range(m + 1)]
        hist = [surf.gather(traj.u[i - j]) + obstacle[j] for j in range(1, m + 1)]
        # the velocity's part from the history: the integrator's v at U^i = 0
        by_step = {i - j: U for j, U in enumerate(hist, start=1)}
        v_offset = coeffs.velocity(np.zeros_like(hist[0]), by_step)
        forward = context.forward
        self._step = ContactStep(
            index=i,
            forward=forward,
            time_step=coeffs,
            history=hist,
            v_offset=v_offset,
            lagged=hist[0],
            obstacle=obstacle[0],
        )
        self._token += 1
        self._eval = None
        self.lagging.begin_step(self._step)
        self.builder.segment = None
        if forward and (self._forward_step is None or i != self._forward_step + 1):
            self.records = []
            self.obstacle_moves.moved_with_guess = []
            self.check_configuration(hist[0], step=i - 1)
        self._forward_step = i if forward else None
        if forward and surf.has_moving_obstacles:
            self.obstacle_moves.check_move(self._step, obstacle[1], self._collision_free_fraction)

    def _update_static(self) -> None:
        if self.free_dofs.update_static(self.model.dirichlet_dofs()):
            self._token += 1

    def _friction(self) -> ipctk.TangentialCollisions | None:
        """The step's TangentialCollisions with the current coefficients (None if all mu = 0)."""
        if self._step is None:
            raise ParameterError("ContactTerm.begin_step must be called before evaluations")
        T, built = self.lagging.current(self.barrier)
        if built:
            self._token += 1
        return T

    # -- evaluation cache --------------------------------------------------------------------
    def _timed(self, name: str) -> contextlib.AbstractContextManager:
        return timed(self.timings, name)

    def timing_summary(self) -> dict[str, dict[str, float]]:
        """Wall seconds, calls, mean wall ms and process CPU seconds per contact operation."""
        return timing_summary(self.timings)

    def _evaluate(self, u: fem.Function | np.ndarray) -> Evaluation:
        values = u.x.array if isinstance(u, fem.Function) else u
        with self._timed("gather"):
            U = self.surface.gather(values)
        if self._step is not None and self.obstacles:
            U = U + self._step.obstacle
        T = self._friction()
        ev = self._eval
        if ev is not None and ev.token == self._token and np.array_equal(ev.U, U):
            return ev
        x = self.surface.rest_positions + U
        C = self.adjoint.kept_collisions(self._step, U)  # the forward's at a converged u^i
        if C is None:
            with self._timed("build"):
                C = self.builder.build_on_segment(U, x, self._token)
        ev = Evaluation(U, x, C, self._token, friction=T)
        self._eval = ev
        return ev

    # -- numeric-term interface (forward) -----------------------------------------------------
    def energy(self, u: fem.Function) -> float:
        """Contact part of the incremental potential (identical on all ranks; collective)."""
        return self.potential.energy(self._evaluate(u))

    def add_residual(self, u: fem.Function, b: PETSc.Vec) -> None:
        """Add the gradient of the contact potential to the owned rows of ``b`` (collective).

        The gradient is summed over the ranks' shares first.
        """
        g = self.potential.gradient(self._evaluate(u))
        self.surface.add_to_owned(b.array_w, g)

    def add_jacobian(
        self, u: fem.Function, A: PETSc.Mat, bc_dofs: np.ndarray, project: bool = False
    ) -> None:
        """Add this rank's share of the contact Hessian to ``A``, skipping Dirichlet rows/columns.

        All rows of the share are added with global indices; PETSc sends those owned by other
        ranks in the assembly (collective).

        Args:
            u: Current displacement.
            A: Matrix containing :meth:`matrix_pattern` (not yet assembled).
            bc_dofs: Local indices of Dirichlet dofs.
            project: Add the PSD-projected Hessian (Newton fallback) instead of the exact one.
        """
        ev = self._evaluate(u)
        free = self.free_dofs.mask(bc_dofs)
        H = self.potential.hessian(ev, project)
        held = self.potential.held_hessian_change(ev) if project else None
        if held is not None:
            H = H + held
        keep = self.pattern.blocks(ev, self._step) if project else None
        with self._timed("insert"):
            self.surface.add_matrix(A, H, free, keep=keep)

    def add_adjoint_jacobian(self, u: fem.Function, A: PETSc.Mat, bc_dofs: np.ndarray) -> None:
        """Add the exact (unprojected) Hessian of the contact potential w.r.t. u^i."""
        self.add_jacobian(u, A, bc_dofs, project=False)

    def add_dirichlet_lifting(
        self, u: fem.Function, b: PETSc.Vec, increment: np.ndarray, bc_dofs: np.ndarray
    ) -> None:
        """b[owned free rows] += H[free, prescribed] increment (collective).

        The linearised contact response of the free dofs to moving the prescribed ones (e.g. an
        obstacle driven by Dirichlet values): the lifting term that the matrix of
        :meth:`add_jacobian`, which drops Dirichlet columns, does not carry.

        Args:
            u: Current displacement.
            b: Right-hand side of a lifted linear step (owned entries).
            increment: Local V array holding the prescribed increment on Dirichlet dofs.
            bc_dofs: Local indices of Dirichlet dofs.
        """
        ev = self._evaluate(u)
        free = self.free_dofs.mask(bc_dofs)
        d = self.surface.gather(np.asarray(increment)).ravel()
        d[free] = 0.0
        if not np.any(d):
            return
        g = self.partition.sum(self.potential.hessian(ev) @ d)
        g[~free] = 0.0
        self.surface.add_to_owned(b.array_w, g)

    def add_hessian_action(self, u: fem.Function, direction: np.ndarray, y: PETSc.Vec) -> None:
        """y[owned rows] += H d with H the exact contact Hessian (matrix-free adjoint; collective).

        Args:
            u: Current displacement.
            direction: Local V array of d (ghosts updated, zero on Dirichlet dofs).
            y: Vector to add to (its Dirichlet rows are overwritten by the caller).
        """
        ev = self._evaluate(u)
        d = self.surface.gather(np.asarray(direction)).ravel()
        with self._timed("hessian_action"):
            Hd = self.potential.hessian(ev) @ d
        with self._timed("reduce"):
            Hd = self.partition.sum(Hd)
        self.surface.add_to_owned(y.array_w, Hd)

    def matrix_pattern(self, u: fem.Function, bc_dofs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global (rows, cols) of the entries :meth:`add_jacobian` may add at ``u`` (owned rows)."""
        return self.pattern.matrix_pattern(self._evaluate(u), self._step, self.free_dofs, bc_dofs)

    def max_step(self, x: PETSc.Vec, dx: PETSc.Vec) -> float:
        """Largest a such that the surface moves collision-free along x + s dx, s in [0, a).

        The CCD runs on the step extended to ``2 dx``, so a free full step reports a value > 1.
        Obstacles stay at their step-i positions, except on the step's first move when their
        own move is not collision-free (see ``contact.obstacle_moves``): from exactly u^{i-1}, the
        path on which they move from t_{i-1} to t_i with the body is checked, and admitted only
        in full (inf, or 0).

        Raises:
            IntersectionError: That first move is not admissible even without body motion.
        """
        Ub = self.surface.gather(x.array_r)
        dU = self.surface.gather(dx.array_r)
        step = self._step
        first = self.obstacle_moves.first_move(step, Ub, dU, self._collision_free_fraction)
        if first is not None:
            return first
        if not np.any(dU):
            return np.inf
        U0 = Ub + (step.obstacle if step is not None else 0.0)
        x0 = np.asfortranarray(self.surface.rest_positions + U0)
        x1 = np.asfortranarray(x0 + _CCD_REACH * dU)
        with self._timed("ccd"):
            toi, candidates = self._collision_free_fraction(U0, x0, x1, with_candidates=True)
        self.builder.segment = (U0, dU, candidates, self._token)
        return toi * _CCD_REACH

    def _collision_free_fraction(
        self, U0: np.ndarray, x0: np.ndarray, x1: np.ndarray, with_candidates: bool = False
    ) -> float | tuple[float, ipctk.Candidates]:
        """Collision-free fraction of the straight path x0 -> x1 (the same on all ranks)."""

        def cached() -> ipctk.NormalCollisions | None:
            ev = self._eval
            if ev is not None and ev.token == self._token and np.array_equal(ev.U, U0):
                return ev.collisions
            return None

        return self.step_bound.fraction(x0, x1, cached, with_candidates)

    # -- configuration checks ----------------------------------------------------------------
    def check_configuration(self, U: np.ndarray, step: int = 0) -> float:
        """Refuse intersecting or touching configurations; returns the minimum distance.

        Collective. Re-reads the rest positions from the mesh first; ``U`` is the (num_vertices,
        dim) displacement of the collision vertices (e.g. ``surface.gather(u)``); the rows of
        obstacles are replaced by their displacement at step ``step``.

        Raises:
            IntersectionError: Naming the bodies that intersect or are closer than
                ``min_gap * dhat``.
        """
        if self.surface.update_rest_positions():  # the shape may have changed since
            self._token += 1
        if self.obstacles:
            nb = self.surface.num_body_vertices
            U = np.array(U, dtype=float)
            U[nb:] = self.obstacle_moves.at(step)[nb:]
        return self.configuration.minimum_distance(self.surface.rest_positions + U, step)

    def intersects(self, u: np.ndarray | None = None, step: int = 0) -> bool:
        """Whether the collision surface (bodies and obstacles at step ``step``) intersects.

        Collective. ``u`` is a local V array (None: the rest shape); the rest positions are
        re-read from the mesh (shape iterates are seen).
        """
        if self.surface.update_rest_positions():
            self._token += 1
        U = self.surface.gather(u) if u is not None else np.zeros_like(self.surface.rest_positions)
        if self.obstacles:
            nb = self.surface.num_body_vertices
            U[nb:] = self.obstacle_moves.at(step)[nb:]
        x = np.asfortranarray(self.surface.rest_positions + U)
        return bool(ipctk.has_intersections(self.surface.mesh, x, ipctk.LBVH()))

    def admits(self, u: np.ndarray, step: int) -> bool:
        """Whether ``u`` is a configuration :meth:`check_configuration` accepts (collective)."""
        try:
            self.check_configuration(self.surface.gather(u), step)
        except IntersectionError:
            return False
        return True

    # -- output ---------------------------------------------------------------------------------
    def end_step(self, i: int, traj: "StateHistory") -> ContactRecord:
        """Record and log contact forces and the minimum distance of the converged step ``i``."""
        ev = self._evaluate(traj.u[i])
        self.adjoint.keep_collisions(self._step, ev)
        g = self.potential.gradient(ev)
        gb = self.potential.barrier_gradient(ev)
        rec = step_record(i, self.partition, self.surface, len(self.body_ids), ev, g, gb)
        self.records.append(rec)
        f = self.force_function
        f.x.array[:] = 0.0
        self.surface.add_to_owned(f.x.array, -g)
        f.x.scatter_forward()
        return rec

    def _largest_force(self, ev: Evaluation) -> float:
        """The largest contact force on a collision vertex at ev (collective)."""
        g = self.potential.gradient(ev).reshape(-1, self.dim)
        return float(np.linalg.norm(g, axis=1).max(initial=0.0))

    def _last_evaluation(self) -> Evaluation | None:
        """The last evaluated iterate, its values recomputed if the potential changed since."""
        ev = self._eval
        if ev is not None and ev.token != self._token:
            friction = self._friction()
            ev = Evaluation(ev.U, ev.x, ev.collisions, self._token, friction=friction)
            self._eval = ev
        return ev

    def continuation_factors(self) -> tuple[float, ...]:
        """Barrier-stiffness factors from which a stalled solve walks down to kappa (collective).

        From the largest contact force at the last evaluated iterate, see
        ``diffsolids.contact.diagnostics.continuation_schedule``; empty without pairs
        within dhat or when the barrier is not too soft for that force.
        """
        ev = self._last_evaluation()
        if ev is None or self.stiffness is None or self.partition.count(ev.collisions) == 0:
            return ()
        return continuation_schedule(self.stiffness, self.dhat, self._largest_force(ev))

    def revise_newton_model(self, u: fem.Function, step: np.ndarray, bc_dofs: np.ndarray) -> bool:
        """Hold at stick the sliding friction collisions whose slip ``step`` reverses.

        See ``diffsolids.contact.energy.stick_model`` (collective).
        """
        if not self.lagging.active:
            return False
        ev = self._evaluate(u)
        dU = self.surface.gather(np.asarray(step)).ravel()
        return self.partition.total(self.potential.hold_reversed(ev, dU)) > 0

    def add_model_change(self, b: PETSc.Vec, bc_dofs: np.ndarray) -> None:
        """b[owned free rows] += the held collisions' stick-model minus exact gradient."""
        g = self.potential.held_gradient_change(self._eval)
        g[~self.free_dofs.mask(bc_dofs)] = 0.0
        self.surface.add_to_owned(b.array_w, g)

    def end_model_revision(self) -> None:
        """Release the collisions held at stick."""
        self.potential.held = None

    def _floor_held(self) -> float:
        """The smallest gap floor that held a pair in the ranks' last step bounds, else inf."""
        floor = self.step_bound.floor_held
        return self.partition.minimum(np.inf if floor is None else floor)

    def held_at_floor(self) -> bool:
        """Whether the last collision-free step bound held a pair at its gap floor (collective).

        See ``StepBound.floor_held``: the pair's barrier did not stop it above round-off.
        """
        return bool(np.isfinite(self._floor_held()))

    def below_round_off(self) -> bool:
        """Whether kappa cannot hold the pairs above the collision check's gap floor (collective).

        True when the last step bound held a pair at its gap floor and the pair carrying the
        largest force at the last iterate settles (2 kappa dhat^4 / f) within
        ``_ROUND_OFF_MARGIN`` times that floor.
        """
        floor = self._floor_held()
        ev = self._last_evaluation()
        if not np.isfinite(floor) or ev is None or self.partition.count(ev.collisions) == 0:
            return False
        force = self._largest_force(ev)
        return settling_gap(self.stiffness, self.dhat, force) < _ROUND_OFF_MARGIN * floor

    def set_stiffness_factor(self, factor: float) -> None:
        """Evaluate the barrier with ``factor`` x kappa until set back to 1 (a continuation).

        The step's lagged friction (normal forces of the previous state) keeps kappa.
        """
        self._friction()
        self.potential.set_stiffness_factor(float(factor))
        self._token += 1

    def failure_report(self) -> str | None:
        """The contact state at the last evaluated iterate (for NewtonConvergenceError)."""
        ev = self._last_evaluation()
        if ev is None:
            return failure_report(self.stiffness, self.dhat)
        count = self.partition.count(ev.collisions)  # collective, like the solve
        if count == 0:
            return failure_report(self.stiffness, self.dhat)
        d = self.partition.minimum_distance(ev.collisions, self.surface.mesh, ev.x)
        force = self._largest_force(ev)
        floor = self._floor_held()
        return failure_report(
            self.stiffness, self.dhat, count, d, force, None if np.isinf(floor) else floor
        )

    # -- adjoint kernels ---------------------------------------------------------------------
    @timed_kernel("adjoint_history")
    def adjoint_history(
        self, u: fem.Function | np.ndarray, lam: fem.Function | np.ndarray
    ) -> dict[int, np.ndarray]:
        """(d g / d u^{i-j})^T lam for j = 1..m_i (owned entries of local V arrays).

        g is the contact part of the step residual: friction depends on u^{i-1} through the
        lagged normal forces and tangent bases and on u^{i-1}..u^{i-m} through the velocity.
        """
        return self.adjoint.history(self._evaluate(u), lam)

    @timed_kernel("adjoint_shape")
    def adjoint_shape(
        self, u: fem.Function | np.ndarray, lam: fem.Function | np.ndarray
    ) -> np.ndarray:
        """(d g / d X)^T lam over the dofs of the P1 rest-coordinate space (owned entries).

        Includes the barrier shape derivative with area-weight terms and the 3D edge-edge
        mollifier correction, and the friction force's rest-position Jacobian.
        """
        return self.adjoint.shape(self._evaluate(u), lam)

    def adjoint_parameter(
        self, name: str, u: fem.Function | np.ndarray, lam: fem.Function | np.ndarray
    ) -> np.ndarray:
        """Lam . dG_i/d(friction coefficient of each pair of :attr:`friction_pairs`)."""
        if name != "friction":
            return super().adjoint_parameter(name, u, lam)
        return self.adjoint_friction(u, lam)

    @timed_kernel("adjoint_friction")
    def adjoint_friction(
        self, u: fem.Function | np.ndarray, lam: fem.Function | np.ndarray
    ) -> np.ndarray:
        """(d g / d mu_p)^T lam for each pair p of :attr:`friction_pairs` (global, all ranks).

        Each rank's collisions give their part, summed over the ranks.
        """
        return self.adjoint.friction(self._evaluate(u), lam)
