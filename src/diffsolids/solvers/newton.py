"""Newton solver for one step's incremental potential.

PETSc SNES (newtonls) with the potential as SNES objective, a line-search pre-check that bounds
the step (no inverted element; the contact term adds its collision-free bound to the same hook)
and a residual tolerance scaled by a characteristic force of the simulation.
"""

import contextlib
import logging
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from numbers import Real
from typing import TYPE_CHECKING

import dolfinx.fem.petsc as fem_petsc
import dolfinx.la.petsc
import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

from diffsolids.errors import NewtonConvergenceError
from diffsolids.parallel import collective_comm
from diffsolids.solvers.callbacks import weak_callback
from diffsolids.solvers.continuation import ContinuationPath
from diffsolids.solvers.factor_store import FactorStore, detach_ksp
from diffsolids.solvers.forms import compile_form
from diffsolids.solvers.inversion import InversionGuard
from diffsolids.solvers.linear_options import (
    reason_name,
    rigid_body_modes,
    solver_prefix,
    step_petsc_options,
)
from diffsolids.solvers.sparsity import GrowingPattern

if TYPE_CHECKING:
    from diffsolids.model.model import Model

logger = logging.getLogger("diffsolids")

__all__ = ["INITIAL_GUESSES", "NewtonResult", "NewtonSolver", "SolverOptions"]

#: The choices of :attr:`SolverOptions.initial_guess`.
INITIAL_GUESSES = ("predictor", "previous", "zero")

# Exact Newton steps in a row that are no descent direction (an indefinite Hessian below
# exact_hessian_below f_char, where the solve should be converging) after which the first
# attempt gives up: the iterate is near a saddle of the potential, which the projected steps
# that replace the exact ones leave at a linear rate (the fig21 sliding bunny's step 5 at
# mu = 0.1: 70 iterations); the step is solved again with exact steps from the start.
SADDLE_STREAK = 8
# The intermediate stages of a stiffness continuation end once the residual is below
# _STAGE_RTOL f_char: each is only the way to the next, whose stiffness differs by a factor
# of ~100 (the fig22 ball at its kappa 1e4: 1e-2 -> 19% fewer iterations than converging
# them fully, 1e-1 -> 25%, 0.3 fails: the last stage starts with pairs pressed unevenly).
_STAGE_RTOL = 1e-2
# steps accepted at round-off with a residual above this fraction of f_char are reported
# (well-converged steps that round-off ends stop below 1e-8)
ROUND_OFF_REPORTED = 1e-7
# In a continuation an uncut Newton step is extended by doublings, at most _EXPAND_DOUBLINGS
# times, while the potential keeps falling along it (see NewtonSolver._expand).
_EXPAND_DOUBLINGS = 10
_DEFAULT_PETSC = {"snes_type": "newtonls", "snes_linesearch_type": "bt"}


@dataclass
class SolverOptions:
    """Options of the per-step Newton solve.

    Attributes:
        rtol: Converged when ||residual|| <= max(atol, rtol * f_char), f_char the larger of the
            simulation's reference force (residual of the initial state) and the step's initial
            residual.
        atol: Absolute residual tolerance (same units as the residual, a force): a step is
            also converged once ||residual|| <= atol, whatever ``rtol * f_char`` is. 0 (default):
            only the relative test.
        max_iterations: Newton iteration limit per step.
        petsc_options: PETSc options under the solver prefix (override the defaults: newtonls,
            bt line search, preonly + MUMPS LU; with another ``pc_type``, e.g. ``"gamg"``, the
            steps are GMRES solves to ``ksp_rtol`` 1e-8 on a scalar matrix, see
            :mod:`~diffsolids.solvers.linear_options`).
        prefix: PETSc options prefix; command-line options with this prefix also apply.
        prevent_inversion: Bound every step so that no element inverts.
        step_safety: Fraction of the largest safe step actually taken when a bound is active.
        march_after: From the ``march_after``-th Newton step in a row that a step bound cuts,
            extend the cut step along the same direction: the bounds are evaluated again from
            the point reached and the step advances by ``step_safety`` times the new bound, for
            as long as the energy decreases (0: never). A contact pair approaching along the
            step then gets to where its barrier stops it within one Newton iteration instead
            of losing a constant factor of its gap per iteration.
        march_below: ... and only extend cuts to less than this fraction of the Newton step.
            The defaults (4, 0.03) leave the first cuts of an approach alone: a barrier of the
            suggested stiffness stops an approaching pair within about three cuts of about 1/5
            each; more and smaller cuts in a row mean a soft barrier. In the stiffer stages of a
            stiffness continuation (``continuation_after``) every cut step is extended (unless
            ``march_after`` is 0); its last stage, the term's own stiffness, follows the rule
            above.
        march_substeps: At most this many extensions per Newton step.
        exact_hessian_below: Numeric terms that offer a PSD-projected Newton matrix (contact)
            give it to Newton while ||residual|| > ``exact_hessian_below * f_char`` and their
            exact Hessian below (quadratic convergence at the end, and the factors the adjoint
            reuses are mostly those of the exact Jacobian). With contact the step potential is not
            convex: Newton on the exact (indefinite) Hessian, projected only when its step is
            not a descent direction, can end at a different stationary point after a tiny
            change of the parameters, so J jumps; projected steps descend into a minimum, as in
            IPC and PolyFEM. In the exact phase an iteration whose line search cuts the exact
            Newton step below half (its quadratic model does not hold) is followed by one
            projected step, then exact again. A step whose solve fails this way is solved again
            from its initial guess with the exact Hessian from the start (as with ``inf``); its
            iterations count both attempts. Where a step has several local minima no choice of
            Hessian decides deterministically which one Newton reaches: a branch reference
            does (``ReducedFunctional(..., branch_reference=q_ref)``, see the concepts page).
            ``inf``: the exact Hessian from the start; ``0``: always projected (with the same
            retry).
        initial_guess: Where a dynamic step's Newton iteration starts (read by the Simulation;
            the step's Dirichlet values are applied to it, and a guess that inverts elements
            or collides falls back to ``"previous"``). One of ``INITIAL_GUESSES``:

            - ``"predictor"`` (default): the constant-velocity extrapolation
              u^{i-1} + dt v^{i-1} in dynamic simulations, u^{i-1} in static ones;
            - ``"previous"``: the previous state u^{i-1};
            - ``"zero"``: the reference configuration (u = 0).

            A warm start the Simulation is given (a Trajectory of an earlier run) comes first
            whatever this option says.
        continuation_after: A solve whose last ``continuation_after`` Newton steps were all
            cut by a step bound, in which a step bound held a contact pair at its round-off
            gap floor (the barrier did not stop it above), or that fails, asks the numeric
            terms for a stiffness continuation (contact: a barrier too soft for its load,
            whose pairs rest so far inside dhat that the collision check cuts every step)
            and, if one is offered, solves the step again from its initial guess through
            stiffer barriers down to the term's own (``NewtonSolver._continued_attempt``).
            0: only after a failed solve.
            The stages before the last end once the residual is below 1e-2 f_char, and
            within the continuation a Newton step that no bound cuts is extended by
            doublings while the potential falls along it.
            A stage after a converged one that does not converge within
            ``continuation_after`` iterations is split: the step goes back to the converged
            stage's state and through a stage at the geometric mean of the two stiffnesses
            first (``diffsolids.solvers.continuation``).
        revise_steps: Let numeric terms revise their model for a Newton step they would take
            badly (``NumericTerm.revise_newton_model``) and solve the step again: contact holds
            at stick the sliding friction contacts whose slip the step would reverse
            (``diffsolids.contact.energy.stick_model``). The converged state is a stationary
            point of the same potential either way; False: plain Newton steps.
    """

    rtol: float = 1e-9
    max_iterations: int = 100
    petsc_options: dict = field(default_factory=dict)
    prefix: str = "diffsolids_"
    prevent_inversion: bool = True
    step_safety: float = 0.9
    march_after: int = 4
    march_below: float = 0.03
    march_substeps: int = 25
    exact_hessian_below: float = 1e-3
    atol: float = 0.0
    initial_guess: str = "predictor"
    continuation_after: int = 30
    revise_steps: bool = True

    def __post_init__(self) -> None:
        if self.initial_guess not in INITIAL_GUESSES:
            raise ValueError(
                f"SolverOptions(initial_guess={self.initial_guess!r}): not one of "
                f"{', '.join(repr(g) for g in INITIAL_GUESSES)}"
            )
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, Real) and value >= 0.0):
                raise ValueError(
                    f"SolverOptions({name}={value!r}): must be a number >= 0 (a residual tolerance)"
                )
        if not self.rtol > 0.0 and not self.atol > 0.0:
            raise ValueError("SolverOptions: rtol and atol are both 0; no step could converge")


@dataclass
class NewtonResult:
    """Outcome of one converged step."""

    iterations: int
    residual: float
    energy: float
    characteristic_force: float


class NewtonSolver:
    """Minimises the incremental potential of a step with SNES.

    Args:
        model: The Model (its ``fields.u`` is the unknown and the initial guess).
        dynamic: Include inertia and damping terms (BDF steps).
        options: Solver options.
    """

    def __init__(self, model: "Model", dynamic: bool, options: SolverOptions | None = None) -> None:
        self.model = model
        self.options = options or SolverOptions()
        f = model.fields
        V = model.V
        self.u = f.u
        self.comm = V.mesh.comm
        potential = model.potential(dynamic)
        residual = ufl.derivative(potential, f.u, ufl.TestFunction(V))
        jacobian = ufl.derivative(residual, f.u, ufl.TrialFunction(V))
        self.residual_ufl = residual
        self.energy_form = compile_form(potential)
        self.residual_form = compile_form(residual)
        self.jacobian_form = compile_form(jacobian)
        self.magnitude_form = compile_form(model.magnitude(dynamic))
        self.numeric_terms = model.numeric_terms
        self.quadratic = model.is_quadratic(dynamic)
        self._linear_defaults, self.pc_type = step_petsc_options(
            self.options.petsc_options, self.options.prefix
        )
        self._near_null_space = rigid_body_modes(V) if self.pc_type == "gamg" else None
        self.A = self.create_matrix()
        self.b = fem_petsc.create_vector(V)
        self.x = fem_petsc.create_vector(V)
        self._work = fem_petsc.create_vector(V)
        self.step_bounds: list = []
        finite_strain = any(t.finite_strain for t in model.terms)
        if self.options.prevent_inversion and finite_strain:
            # Only finite-strain energies see det F (small-strain elasticity has no inversion).
            # Steps bounded at or beyond 1 / step_safety are taken in full: no need to know more.
            guard = InversionGuard(
                V, f.dx_strain.metadata()["quadrature_degree"], limit=1.0 / self.options.step_safety
            )
            self.step_bounds.append(guard)
        # the numeric terms' step bounds (contact: collision-free CCD fraction)
        self.step_bounds.extend(self.numeric_terms)
        self.patterns = GrowingPattern(self)
        self.projected_steps = 0
        self.revised_steps = 0  # Newton steps solved again with a revised model
        self._step_function = fem.Function(V)  # a Newton step as a ghosted V function
        self.retried_steps = 0  # steps solved again with the exact Hessian from the start
        self.saddle_stops = 0  # of which the first attempt stopped near a saddle
        self._exact_from_start = False
        self._keep_f_char = False
        self._first_attempt = 0
        self.continued_steps = 0  # steps solved by a stiffness continuation
        self.split_stages = 0  # continuation stages split (gone to halfway first)
        self.floor_continuations = 0  # continuations started by a pair held at a gap floor
        # (step, residual, tolerance, f_char) of the steps accepted at round-off above tolerance
        self.round_off_steps: list[tuple[int, float, float, float]] = []
        self._continuation: tuple[float, ...] = ()
        self._stage_splittable = False  # a stalled stage would be split (in a continuation)
        self._stage_rtol = 0.0  # an intermediate continuation stage's looser tolerance
        self._eager_march = False
        self._held_at_floor = self._floor_asked = False  # a pair at a step bound's gap floor
        self._stall_cause: str | None = None  # why the last attempt stopped early
        self._restarted_after = 0
        self.reference_force = 0.0
        self._energy_cache: tuple[PETSc.Vec, float] | None = None
        self._line_search: dict | None = None
        self._factor_store: FactorStore | None = None
        self._jacobian_key = None
        self._length_scale = 1e-8 * model.domain.characteristic_length()
        self._make_snes()

    # -- PETSc setup ---------------------------------------------------------------------
    def _make_snes(self) -> None:
        snes = PETSc.SNES().create(self.comm)
        self.prefix = solver_prefix(
            self,
            self.options.prefix,
            {**_DEFAULT_PETSC, **self._linear_defaults},
            self.options.petsc_options,
        )
        snes.setOptionsPrefix(self.prefix)
        # weak callbacks: the SNES must not keep this solver (and its factorisations) alive
        snes.setFunction(weak_callback(self._residual), self.b)
        snes.setJacobian(weak_callback(self._jacobian), self.A)
        snes.setObjective(weak_callback(self._objective))
        snes.setLineSearchPreCheck(weak_callback(self._precheck))
        snes.setConvergenceTest(weak_callback(self._converged))
        # stol = 0: a step shortened to nothing by a step bound must not count as convergence
        snes.setTolerances(stol=0.0, max_it=self.options.max_iterations)
        snes.setFromOptions()
        self.snes = snes

    # -- evaluation helpers ----------------------------------------------------------------
    def _assign(self, x: PETSc.Vec) -> None:
        dolfinx.la.petsc._ghost_update(x, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
        fem_petsc.assign(x, self.u)

    def energy(self) -> float:
        """Incremental potential at the current ``u`` (all ranks)."""
        e = collective_comm(self.comm).allreduce(fem.assemble_scalar(self.energy_form), op=MPI.SUM)
        return e + sum(t.energy(self.u) for t in self.numeric_terms)

    def assemble_residual(self, b: PETSc.Vec) -> None:
        """Residual at the current ``u``; Dirichlet rows hold u - g (zero on admissible u)."""
        with b.localForm() as loc:
            loc.set(0.0)
        fem_petsc.assemble_vector(b, self.residual_form)
        dolfinx.la.petsc._ghost_update(b, PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        for term in self.numeric_terms:
            term.add_residual(self.u, b)
        fem_petsc.set_bc(b, self.model.bcs, self.u.x.petsc_vec, -1.0)
        dolfinx.la.petsc._ghost_update(b, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)

    def create_matrix(self) -> PETSc.Mat:
        """A new matrix with the sparsity of the step Jacobian.

        Block (BAIJ) for the LU factorisation: blocks of the vector dofs of a node make
        assembly about 3x faster than scalar AIJ (fewer index lookups per inserted entry).
        Scalar (AIJ) for every other preconditioner (multigrid and MUMPS' Cholesky need it),
        with the rigid body modes as near-null space for ``gamg``.
        """
        A = fem_petsc.create_matrix(
            self.jacobian_form, kind="baij" if self.pc_type == "lu" else "aij"
        )
        if self._near_null_space is not None:
            A.setNearNullSpace(self._near_null_space)
        return A

    def assemble_jacobian(self, A: PETSc.Mat, exact: bool = False) -> None:
        """Jacobian at the current ``u`` with identity Dirichlet rows and columns.

        Args:
            A: Matrix to assemble into.
            exact: Numeric terms add their exact Hessians (adjoint) rather than the Newton
                matrix they prefer (e.g. a PSD-projected contact Hessian).
        """
        A.zeroEntries()
        fem_petsc.assemble_matrix(A, self.jacobian_form, self.model.bcs, diag=1.0)
        bc_dofs = self.model.dirichlet_dofs()
        for term in self.numeric_terms:
            if exact:
                term.add_adjoint_jacobian(self.u, A, bc_dofs)
            else:
                term.add_jacobian(self.u, A, bc_dofs)
        A.assemble()

    def residual_norm(self) -> float:
        """Norm of the residual at the current ``u``."""
        self.assemble_residual(self._work)
        return self._work.norm()

    # -- SNES callbacks ----------------------------------------------------------------------
    def _residual(self, snes: PETSc.SNES, x: PETSc.Vec, b: PETSc.Vec) -> None:
        self._assign(x)
        self.assemble_residual(b)

    def _jacobian(self, snes: PETSc.SNES, x: PETSc.Vec, A: PETSc.Mat, P: PETSc.Mat) -> None:
        if self.quadratic and self._jacobian_key == self.quadratic_key():
            return  # the Hessian of a quadratic potential does not change: keep the factors
        self._assign(x)
        below = np.inf if self._exact_from_start else self.options.exact_hessian_below
        project = self._project_next or not self._fnorm <= below * self._f_char
        self._project_next = False
        if self._projectable() and project:
            self.assemble_projected_jacobian(A)
            self._exact_factors = False
            self.projected_steps += 1
        else:
            self.assemble_jacobian(A)
            self._exact_factors = True
        self._jacobian_key = self.quadratic_key()

    def quadratic_key(self) -> tuple[float, float]:
        """(beta dt, dt) now: all that a quadratic potential's Jacobian depends on."""
        f = self.model.fields
        return (float(f.beta_dt.value), float(f.dt.value))

    def holds_factors_of(self, key: tuple[float, float]) -> bool:
        """Whether the KSP holds factors of the quadratic Jacobian at ``key``."""
        return self._jacobian_key is not None and self._jacobian_key == key

    def _energy_at(self, x: PETSc.Vec) -> float:
        """Assign ``x`` to ``u`` and return the potential there.

        The line search's trial point becomes the next iterate, whose potential SNES asks for
        again; it is remembered (one assembly less per iteration and per step).
        """
        self._assign(x)
        cached = self._energy_cache
        if cached is not None and cached[0].equal(x):
            return cached[1]
        e = self.energy()
        if cached is None:
            cached = (x.duplicate(), e)
        x.copy(cached[0])
        self._energy_cache = (cached[0], e)
        return e

    def _forget_energy(self) -> None:
        """Drop the remembered potential (the potential itself has changed)."""
        if self._energy_cache is not None:
            self._energy_cache[0].destroy()
            self._energy_cache = None

    def _objective(self, snes: PETSc.SNES, x: PETSc.Vec) -> float:
        e = self._energy_at(x)
        ls = self._line_search
        if not np.isfinite(e):
            return np.finfo(float).max / 1e10
        if ls is None:
            return e
        if ls["f0"] is None:
            ls["f0"] = e
            return e
        if abs(e - ls["f0"]) <= 1e-10 * (self._magnitude + abs(ls["f0"])):
            # The energy change is below its roundoff: estimate it from the gradients instead,
            # E(x) - E(x0) ~ (F(x0) + F(x)) . (x - x0) / 2 (exact for quadratic energies).
            # The residual norm is no substitute: along a PSD-projected (contact) Newton
            # direction it need not decrease, and stiff barrier pairs then stall Newton.
            self.assemble_residual(self._work)
            self._work.axpy(1.0, ls["F0"])
            step = x.copy()
            step.axpy(-1.0, ls["x0"])
            change = 0.5 * self._work.dot(step)
            step.destroy()
            return ls["f0"] + change
        return e

    def _precheck(self, x: PETSc.Vec, y: PETSc.Vec, *args: object) -> None:
        scale = max(x.norm(PETSc.NormType.INFINITY), self._length_scale)
        if y.norm(PETSc.NormType.INFINITY) <= 1e-13 * scale:
            # The Newton increment is at machine precision: nothing left to gain. A zero step
            # ends the line search; solve() accepts the iterate as converged to round-off.
            self._roundoff_converged = True
            y.set(0.0)
            return
        F = self.snes.getFunction()[0]
        slope = y.dot(F)  # the trial point is x - lambda y: descent needs y . F > 0
        if self._exact_factors and self._hybrid() and not self._continuation:
            self._indefinite_streak = 0 if slope > 0 else self._indefinite_streak + 1
        if not slope > 0 and self._projectable():
            # paper sec. 5: PSD-project the contact Hessian only when the exact one fails
            self._assign(x)
            self._solve_projected(F, y)
            slope = y.dot(F)
            self.projected_steps += 1
        if self.options.revise_steps and self._revising_terms:
            slope = self._revised_step(x, y, F, slope)
        if not slope > 0:
            # Not a descent direction (indefinite Hessian): fall back to the gradient direction.
            y.scale(0.0)
            y.axpy(1.0, F)
            slope = y.dot(F)
            self.fallbacks += 1
        bound, binding = np.inf, None
        if self.step_bounds:
            y.scale(-1.0)
            bounds = [b.max_step(x, y) for b in self.step_bounds]
            y.scale(-1.0)
            k = int(np.argmin(bounds))
            bound, binding = bounds[k], self.step_bounds[k]
        if bound * self.options.step_safety < 1.0:
            scale = self.options.step_safety * bound
            self._cuts_by_inversion += isinstance(binding, InversionGuard)
            self._cut_streak += 1
            o = self.options
            # in the stiffer stages of a continuation (a soft barrier: pairs rest far inside
            # dhat) every cut step is extended; otherwise only long streaks of small cuts
            streak = o.march_after <= self._cut_streak and scale < o.march_below
            if o.march_after > 0 and (self._eager_march or streak):
                scale = self._march(x, y, scale)
            y.scale(scale)
            slope *= scale
            self.bounded_steps += 1
            if self.options.continuation_after > 0 and not (
                self._continuation or self._floor_asked or self._held_at_floor
            ):
                self._held_at_floor = any([t.held_at_floor() for t in self._continuable_terms()])
            self._last_cut = scale
        else:
            self._cut_streak = 0
            if self._continuation:
                y.scale(self._expand(x, y))
        self._planned_step = y.norm()  # the line search takes a fraction of it
        self._direction_exact = self._exact_factors
        self._drop_line_search()
        self._line_search = {"f0": None, "x0": x.copy(), "F0": F.copy()}

    def _revised_step(self, x: PETSc.Vec, y: PETSc.Vec, F: PETSc.Vec, slope: float) -> float:
        """The Newton step y again where numeric terms revise their model for it (collective).

        Returns the slope y . F of the step (the revised one when a term revised its model).
        """
        self._assign(x)
        step = self._step_function.x
        step.petsc_vec.array_w[:] = y.array_r
        step.petsc_vec.scale(-1.0)  # the step is x - y
        step.scatter_forward()
        bc_dofs = self.model.dirichlet_dofs()
        terms = self._revising_terms
        revising = [t.revise_newton_model(self.u, step.array, bc_dofs) for t in terms]
        if not any(revising):
            return slope
        revised = [t for t, r in zip(terms, revising, strict=True) if r]
        rhs = F.copy()
        try:
            for term in revised:
                term.add_model_change(rhs, bc_dofs)
            self._solve_projected(rhs, y)
        finally:
            rhs.destroy()
            for term in revised:
                term.end_model_revision()
        self.revised_steps += 1
        return y.dot(F)

    def _solve_projected(self, rhs: PETSc.Vec, y: PETSc.Vec) -> None:
        """Solve A y = rhs with A the projected Newton matrix at the current u (collective)."""
        self.assemble_projected_jacobian(self.A)
        self._jacobian_key = None
        self.snes.getKSP().solve(rhs, y)
        self._exact_factors = False

    def _drop_line_search(self) -> None:
        """Free the PETSc copies of the previous line search's start point."""
        if self._line_search is not None:
            self._line_search["x0"].destroy()
            self._line_search["F0"].destroy()
        self._line_search = None

    def _march(self, x: PETSc.Vec, y: PETSc.Vec, t: float) -> float:
        """How far along the Newton step, x - s y with s in [t, 1], a cut step is extended.

        ``t`` is the cut (``step_safety`` times the step bound). A step bound tells how far the
        straight path is admissible, not where the energy along it is smallest: a contact pair
        approaching along the step is stopped at a fixed fraction of its gap, so with a soft
        barrier (equilibrium gap far inside dhat) Newton loses one iteration per factor ~5 of gap
        (11 iterations from dhat to a 1e-8 dhat gap, per pair that comes into contact). Here the
        bounds are evaluated again from the point reached along the same direction and the step
        is extended by ``step_safety`` times the new bound while (1) the energy decreases, (2)
        its slope along the direction is still negative (the barriers have not stopped the
        motion yet) and (3) the residual norm does not more than double in one extension: a pair
        that blocks the direction at a tiny gap is then being pressed far below its equilibrium
        gap, which the energy hardly shows but the residual does. Every point of the path is
        admissible (each extension is checked from its start), the energy decreases along it,
        and the line search then starts from the point reached.
        """
        safety = self.options.step_safety

        def next_fraction(t: float, bound: Callable[[], float]) -> float | None:
            if not t < 1.0:
                return None
            b = bound()
            t_next = 1.0 if b * safety >= 1.0 - t else t + safety * b
            # a bound shrunk to round-off of t: nothing to gain
            return t_next if t_next > t * (1.0 + 1e-12) else None

        t, substeps = self._extend(x, y, t, self.options.march_substeps, next_fraction)
        self.marched_substeps += substeps
        return t

    def _expand(self, x: PETSc.Vec, y: PETSc.Vec) -> float:
        """How far beyond the full Newton step, x - s y with s >= 1, it is extended.

        A stage of a stiffness continuation starts with its pairs far from the gaps at which
        its barrier holds them: a pair much closer than that is pushed by a log-like barrier
        whose Newton step only doubles its gap (the first stage from the step's initial
        guess: its residual halves per iteration, 20 iterations on the fig21 bunny). The step
        is doubled while the step bounds admit the doubled step and :meth:`_extend`'s
        conditions hold.
        """
        safety = self.options.step_safety

        def next_fraction(t: float, bound: Callable[[], float]) -> float | None:
            return 2.0 * t if bound() * safety >= t else None

        t, doublings = self._extend(x, y, 1.0, _EXPAND_DOUBLINGS, next_fraction)
        self.expanded_steps += doublings
        return t

    def _extend(
        self, x: PETSc.Vec, y: PETSc.Vec, t: float, limit: int, next_fraction: Callable
    ) -> tuple[float, int]:
        """Extend the step x - t y along y while the potential falls (collective).

        ``next_fraction(t, bound)`` proposes the next fraction (None: stop); ``bound()`` is
        the step bound at x - t y along -y. An extension is taken while (1) the potential
        decreases, (2) its slope along the direction is still negative and (3) the residual
        norm does not more than double in one extension (a pair blocking the direction at a
        tiny gap is then pressed far below its equilibrium gap, which the energy hardly shows
        but the residual does). Every point of the path is admissible (each extension is
        checked from its start).

        Returns:
            (the fraction reached, the number of extensions)
        """
        back = y.copy()
        back.scale(-1.0)
        xt = x.copy()
        xt.axpy(-t, y)
        xn = x.duplicate()
        taken = 0
        try:
            energy = self._energy_at(xt)
            slope, fnorm = self._slope_at(xt, y)
            for _ in range(limit):
                if not (np.isfinite(energy) and slope < 0.0):
                    break
                t_next = next_fraction(
                    t, lambda: min((b.max_step(xt, back) for b in self.step_bounds), default=np.inf)
                )
                if t_next is None:
                    break
                x.copy(xn)
                xn.axpy(-t_next, y)
                e_next = self._energy_at(xn)
                if not e_next < energy:
                    break
                s_next, f_next = self._slope_at(xn, y)
                if f_next > 2.0 * fnorm:
                    break
                t, energy, slope, fnorm = t_next, e_next, s_next, f_next
                xn.copy(xt)
                taken += 1
        finally:
            for v in (back, xt, xn):
                v.destroy()
        return t, taken

    def _slope_at(self, x: PETSc.Vec, y: PETSc.Vec) -> tuple[float, float]:
        """(d/ds E(x - s y) at s = 0, residual norm) at ``x``; uses the work vector."""
        self._assign(x)
        self.assemble_residual(self._work)
        return -self._work.dot(y), self._work.norm()

    def _converged(
        self, snes: PETSc.SNES, it: int, norms: tuple[float, float, float]
    ) -> PETSc.SNES.ConvergedReason:
        fnorm = norms[2]
        if it == 0 and self._restarted_after == 0 and not self._keep_f_char:
            self._f_char = max(self.reference_force, fnorm)
        if it > 0 and self._direction_exact and self._hybrid():
            # The exact-Hessian phase (below exact_hessian_below): a line search that had to
            # cut the exact Newton step below half means its quadratic model does not hold
            # (indefinite Hessian); the next step is a projected one, then exact again.
            taken = norms[1] / self._planned_step if self._planned_step > 0 else 1.0
            self._project_next = taken < 0.5
        self._direction_exact = False
        it += self._restarted_after
        self._fnorm = fnorm
        R = PETSc.SNES.ConvergedReason
        if not np.isfinite(fnorm):
            return R.DIVERGED_FNORM_NAN
        if fnorm <= self._tolerance():
            return R.CONVERGED_FNORM_ABS
        if it >= self.options.max_iterations:
            return R.DIVERGED_MAX_IT
        if self._indefinite_streak >= SADDLE_STREAK:
            # near a saddle of the potential: the projected steps that replace the exact ones
            # leave it at a linear rate; the step goes again with exact steps from the start
            self._left_saddle = True
            return R.DIVERGED_LINE_SEARCH
        if self._stalled_soft(it):
            self._stalled = True
            return R.DIVERGED_LINE_SEARCH
        if it > self._restarted_after and self.patterns.missing(self.A):
            # the next Jacobian needs entries the matrix lacks: restart with a larger matrix
            self._restart = True
            return R.DIVERGED_JACOBIAN_DOMAIN
        return R.ITERATING

    def _stalled_soft(self, iterations: int) -> bool:
        """Whether the solve stops here to go on through (another) continuation stage.

        Outside a continuation: when a step bound has held a pair at its gap floor (asked
        once per attempt) or the last ``continuation_after`` steps were cut (asked every
        ``continuation_after`` cut steps in a row), and a continuation is offered. In
        a continuation: a stage that a split would bring closer to its start
        (``ContinuationPath.can_split``) gets ``continuation_after`` iterations. Collective:
        the counts and the terms' answers are the same on every rank.
        """
        n = self.options.continuation_after
        if n <= 0:
            return False
        if self._continuation:
            return self._stage_splittable and iterations >= n
        if self._held_at_floor and not self._floor_asked:
            self._floor_asked = True  # asked once per attempt
            cause = "floor"
        elif self._cut_streak >= n and self._cut_streak % n == 0:
            cause = "cuts"
        else:
            return False
        if not any([t.continuation_factors() for t in self._continuable_terms()]):
            return False
        self._stall_cause = cause
        self.floor_continuations += cause == "floor"
        return True

    def _hybrid(self) -> bool:
        """Projected steps above ``exact_hessian_below * f_char``, exact below (first attempt)."""
        return bool(np.isfinite(self.options.exact_hessian_below)) and not self._exact_from_start

    def _tolerance(self) -> float:
        """The residual norm below which the step is converged: max(atol, rtol * f_char).

        In a continuation stage before the last, rtol is at least ``_STAGE_RTOL``.
        """
        relative = max(self.options.rtol, self._stage_rtol) * self._f_char  # nan at first
        return self.options.atol if self.options.atol > relative else relative

    def _failure_details(self, iterations: int) -> str:
        """The step bounds' and numeric terms' account of a failed solve."""
        lines = []
        if self.bounded_steps:
            marched = (
                f", {self.marched_substeps} extensions of cut steps along their direction"
                if self.marched_substeps
                else ""
            )
            by = self._cuts_by_inversion
            lines.append(
                f"{self.bounded_steps} of {iterations} Newton steps were cut by a step bound "
                f"({by} to an inversion-free, {self.bounded_steps - by} to a collision-free "
                f"fraction; the last one to {self._last_cut:.2e} of the Newton step{marched})"
            )
        if self._exact_from_start:
            lines.append(
                f"projected Newton steps above {self.options.exact_hessian_below:g} f_char "
                f"failed after {self._first_attempt} iterations, and so did the step again "
                "with the exact contact Hessian from the start"
            )
        if self._continuation:
            lines.append(
                "then the step again through a stiffness continuation (factors "
                + ", ".join(f"{f:.2g}" for f in self._continuation)
                + ", then 1), which did not converge either"
            )
        lines += [r for r in (t.failure_report() for t in self.numeric_terms) if r]
        lines.append(self._what_to_try(iterations))
        return "\n".join(lines)

    def _what_to_try(self, iterations: int) -> str:
        """Advice for a failed solve, from how its Newton steps went."""
        o = self.options
        more = f"SolverOptions(max_iterations={2 * o.max_iterations}) if the residual still fell"
        if self.bounded_steps * 2 >= max(iterations, 1):
            if self._cuts_by_inversion * 2 >= self.bounded_steps:
                tips = [
                    "the steps would invert elements: a smaller time or load step",
                    "a finer mesh where the elements are squeezed",
                    more,
                ]
            else:
                tips = [
                    "if contact pairs are held far inside dhat (see above), a stiffer barrier "
                    "(the suggested stiffness, or a larger dhat)",
                    "a smaller time step (less motion to stop per step)",
                    more,
                ]
            if o.march_after != 1 or o.march_below < 1.0:
                tips.append("SolverOptions(march_after=1, march_below=1.0): extend every cut step")
            return "most Newton steps were cut by a step bound; what to try: " + "; ".join(tips)
        return (
            f"what to try: {more}; a smaller time or load step; a looser rtol (now {o.rtol:g}) "
            "if the residual stalled at round-off"
        )

    # -- numeric terms: projected Hessians and growing sparsity -------------------------------
    @property
    def _revising_terms(self) -> list:
        """The numeric terms that may revise their model for a Newton step."""
        return [t for t in self.numeric_terms if t.revises_newton_steps]

    def _projectable(self) -> bool:
        return any(t.projectable_hessian for t in self.numeric_terms)

    def assemble_projected_jacobian(self, A: PETSc.Mat) -> None:
        """Newton matrix with the PSD-projected Hessians of the numeric terms that offer one."""
        A.zeroEntries()
        fem_petsc.assemble_matrix(A, self.jacobian_form, self.model.bcs, diag=1.0)
        bc_dofs = self.model.dirichlet_dofs()
        for term in self.numeric_terms:
            term.add_jacobian(self.u, A, bc_dofs, project=term.projectable_hessian)
        A.assemble()

    def ensure_matrix_pattern(self, A: PETSc.Mat) -> PETSc.Mat:
        """A, or a new matrix with A's pattern plus the entries numeric terms add at ``u``.

        Call before assembling a Jacobian with numeric terms (contact) into a matrix of your own.
        """
        return self.patterns.ensure(A)

    def _use_matrix(self, A: PETSc.Mat) -> None:
        if A is not self.A:
            self.patterns.forget(self.A)
            self.A = A
            self.snes.setJacobian(weak_callback(self._jacobian), A, A)
            self._jacobian_key = None

    # -- public ------------------------------------------------------------------------------
    def lifted_step(self) -> PETSc.Vec:
        """The linearised step that moves ``u`` onto the step's Dirichlet values.

        Solves K(u) du = -G(u) with du = g - u on Dirichlet dofs (lifting of the prescribed
        increment, including its coupling through numeric terms such as the contact barrier),
        so the interior follows the boundary instead of inverting or colliding next to it.
        ``u`` is unchanged and ``x`` holds it; the caller destroys the returned Vec.
        """
        x, y, b = self.x, self._work.duplicate(), self.b
        self.u.x.scatter_forward()
        x.array_w[:] = self.u.x.petsc_vec.array_r
        with b.localForm() as loc:
            loc.set(0.0)
        fem_petsc.assemble_vector(b, self.residual_form)
        fem_petsc.apply_lifting(b, [self.jacobian_form], [self.model.bcs], x0=[x], alpha=-1.0)
        dolfinx.la.petsc._ghost_update(b, PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        bc_dofs = self.model.dirichlet_dofs()
        increment = np.zeros_like(self.u.x.array)
        for bc in self.model.bcs:
            bc.set(increment, x0=self.u.x.array)  # g - u on the Dirichlet dofs
        for term in self.numeric_terms:
            term.add_residual(self.u, b)
            term.add_dirichlet_lifting(self.u, b, increment, bc_dofs)
        fem_petsc.set_bc(b, self.model.bcs, x, -1.0)
        if self.patterns.active:  # contact entries at u may be missing from the matrix
            self._use_matrix(self.patterns.ensure(self.A))
        self.assemble_jacobian(self.A)
        self._jacobian_key = None
        ksp = self.snes.getKSP()
        ksp.setOperators(self.A)
        ksp.solve(b, y)
        y.scale(-1.0)
        return y

    def step_bound(self, direction: PETSc.Vec) -> float:
        """Largest admissible fraction of ``direction`` from ``x`` (inf without step bounds)."""
        return min((g.max_step(self.x, direction) for g in self.step_bounds), default=np.inf)

    def path_bound(self, origin: np.ndarray, target: np.ndarray, bounds: list) -> float:
        """Largest admissible fraction of the straight path from ``origin`` to ``target``.

        Args:
            origin: Local dof array of the path's start (owned entries are used).
            target: Local dof array of its end; ``origin`` itself checks that state alone
                (a bound <= 0: the state is not admissible).
            bounds: The step bounds to apply (some of :attr:`step_bounds`).

        Returns:
            The smallest fraction the bounds admit (inf without bounds). Uses the solver's
            ``x`` and a work vector, not ``u``.
        """
        x, dx = self.x, self._work
        n = len(x.array_r)
        x.array_w[:] = origin[:n]
        if target is origin:
            dx.set(0.0)
        else:
            dx.array_w[:] = target[:n] - origin[:n]
        return min((b.max_step(x, dx) for b in bounds), default=np.inf)

    def advance(self, direction: PETSc.Vec, fraction: float = 1.0) -> None:
        """Set ``u`` to ``x + fraction * direction``."""
        self.x.axpy(fraction, direction)
        self._assign(self.x)

    def lift_dirichlet(self, step: int) -> None:
        """Move ``u`` (not yet at the step's Dirichlet values) by the :meth:`lifted_step`.

        Raises:
            NewtonConvergenceError: The lifted step inverts elements or collides.
        """
        y = self.lifted_step()
        try:
            if self.step_bound(y) <= 1.0:
                raise NewtonConvergenceError(
                    step,
                    0,
                    float("nan"),
                    float("nan"),
                    "the Dirichlet increment of this step inverts elements (or, with contact, "
                    "collides) even after lifting; use smaller (load) steps",
                )
            self.advance(y)
        finally:
            y.destroy()

    def inverted(self) -> bool:
        """Whether the current ``u`` inverts elements (det F <= 0 at a quadrature point)."""
        guards = [b for b in self.step_bounds if isinstance(b, InversionGuard)]
        if not guards:
            return False
        self.u.x.scatter_forward()
        state = self.u.x.petsc_vec.array_r
        return self.path_bound(state, state, guards[:1]) <= 0.0

    def reset(self) -> None:
        """Start a new run: forget cached Jacobians, contact matrix entries, round-off steps.

        The factor store in use (:meth:`keeping_factors_in`) forgets the previous run's
        factorisations too.
        """
        self._jacobian_key = None
        self.round_off_steps = []
        if self.patterns.active:
            self._use_matrix(self.patterns.restart(self.A))
        if self._factor_store is not None:
            self._factor_store.begin_run(self.snes)

    # -- the factorisations kept for the adjoint -----------------------------------------------
    @property
    def factor_store(self) -> FactorStore | None:
        """The store converged steps keep their factorisations in, or None; read-only.

        Set it for a block of solves with :meth:`keeping_factors_in`.
        """
        return self._factor_store

    @factor_store.setter
    def factor_store(self, store: FactorStore | None) -> None:
        warnings.warn(
            "assigning NewtonSolver.factor_store is deprecated (removed in 0.12): solve inside "
            "'with solver.keeping_factors_in(store):', which puts the previous store back",
            DeprecationWarning,
            stacklevel=2,
        )
        self._factor_store = store

    @contextlib.contextmanager
    def keeping_factors_in(self, store: FactorStore | None) -> Iterator[FactorStore | None]:
        """Converged steps keep their factorisations in ``store`` (None: nowhere) in the block.

        The previous store is back afterwards, also when the block raises.
        """
        previous, self._factor_store = self._factor_store, store
        try:
            yield store
        finally:
            self._factor_store = previous

    def last_factors(self) -> PETSc.PC:
        """The preconditioner holding the factors of the last Newton Jacobian (not kept ones)."""
        return self.snes.getKSP().getPC()

    def detach_last_factors(self) -> PETSc.KSP | None:
        """Take the KSP holding the last Newton factors out of the solver (LU only).

        Later solves factorise into a new KSP, so the returned one keeps the factors of the
        Jacobian the solver factorised last (e.g. the forward's last step while a checkpointed
        sweep recomputes steps). None for a quadratic potential or without an LU
        factorisation. The caller destroys the returned KSP.
        """
        pc = self.last_factors()
        if self.quadratic or pc.getType() != "lu":
            return None
        pc.setReusePreconditioner(True)
        return detach_ksp(self.snes)

    def solve_with_last_factors(self, b: PETSc.Vec, x: PETSc.Vec) -> None:
        """Solve with the last Newton Jacobian's factors (e.g. a quadratic potential's)."""
        self.snes.getKSP().solve(b, x)

    def reported_round_off_steps(self) -> list[tuple[int, float, float, float]]:
        """The run's steps accepted at round-off with a residual above ``ROUND_OFF_REPORTED``.

        Returns:
            (step, residual, tolerance, f_char) of each, as in :attr:`round_off_steps`.
        """
        return [s for s in self.round_off_steps if s[1] > ROUND_OFF_REPORTED * s[3]]

    def set_reference_force(self) -> float:
        """Use the residual norm at the current ``u`` as the simulation's characteristic force."""
        self.reference_force = self.residual_norm()
        return self.reference_force

    def _attempt(self) -> tuple[int, int, bool]:
        """One SNES solve from ``x`` (restarted when the matrix pattern grows).

        Returns:
            (iterations, SNES converged reason, converged)
        """
        self._drop_line_search()
        self._roundoff_converged = False
        self._exact_factors = True
        self._project_next = False
        self._direction_exact = False
        self._planned_step = 0.0
        self._cut_streak = 0
        self._held_at_floor = self._floor_asked = False
        self._stall_cause = None
        self._stalled = False
        self._indefinite_streak = 0
        self._left_saddle = False
        self._assign(self.x)
        self._restarted_after = 0
        self._restart = False
        if self.patterns.active:
            self._use_matrix(self.patterns.ensure(self.A))
        self.snes.solve(None, self.x)
        while self._restart:
            self._restart = False
            self._restarted_after += self.snes.getIterationNumber()
            self._assign(self.x)
            self._use_matrix(self.patterns.ensure(self.A))
            self.snes.solve(None, self.x)
        reason = self.snes.getConvergedReason()
        its = self._restarted_after + self.snes.getIterationNumber()
        self._assign(self.x)
        # Success means the residual test passed, or the Newton increment reached round-off;
        # whatever else PETSc may report (e.g. a user snes_stol) is not convergence.
        converged = self._roundoff_converged or (reason > 0 and self._fnorm <= self._tolerance())
        return its, reason, converged

    def _continuable_terms(self) -> list:
        """The numeric terms that offer a stiffness continuation."""
        return [t for t in self.numeric_terms if t.has_stiffness_continuation]

    def _continued_attempt(self, step: int, x0: PETSc.Vec) -> tuple[int, int, bool]:
        """The step again from ``x0`` through stiffer versions of the numeric terms (collective).

        A too soft contact barrier rests pairs so far inside dhat that the collision check cuts
        every Newton step (the tangential motion of a step is orders of magnitude larger than
        the gaps). The terms that offer a continuation name stiffness factors (from the last
        iterate's contact forces); each stage starts where the previous one ended (converged
        or not: a stage is a way to the next, every iterate admissible), the last one is the
        terms themselves and must converge, so the state reached is a minimiser of the step's
        own potential (the adjoint differentiates that, not the path to it). A stage after a
        converged one that fails (or crawls: ``continuation_after`` iterations) is split:
        the step goes back to the converged stage's state and first through a stage halfway
        between the two (``ContinuationPath.split``).

        Returns:
            (iterations, SNES converged reason, converged); (0, DIVERGED_MAX_IT, False) when no
            term offers a continuation.
        """
        terms = self._continuable_terms()
        path = ContinuationPath([t.continuation_factors() for t in terms])
        if not path.stages:
            return 0, PETSc.SNES.ConvergedReason.DIVERGED_MAX_IT, False
        self._continuation = path.largest_factors()
        why = {
            "floor": "a pair was pressed to the collision check's gap floor",
            "cuts": f"{self._cut_streak} Newton steps in a row were cut",
        }.get(self._stall_cause, "Newton failed")
        logger.info(
            "step %d: %s after %d iterations; again through a stiffness continuation, factors %s",
            step,
            why,
            self.snes.getIterationNumber() + self._restarted_after,
            ", ".join(f"{f:.2g}" for f in self._continuation),
        )
        self._exact_from_start, self._keep_f_char = False, True
        x0.copy(self.x)
        kept, kept_at = x0.duplicate(), None  # the last converged stage's state and position
        total, index = 0, 0
        try:
            while index < len(path.positions):
                its, reason, converged = self._continuation_stage(terms, path, index, kept_at)
                total += its
                if converged:
                    self.x.copy(kept)
                    kept_at = path.positions[index]
                elif path.positions[index] == path.stages and any(
                    [t.below_round_off() for t in terms]
                ):
                    break  # the barrier's own stiffness cannot hold the pairs: no way on
                elif kept_at is not None and path.split(index, kept_at):
                    # the stage was too far from the last converged one: go half the way first
                    self._continuation = path.largest_factors()
                    self.split_stages += 1
                    logger.info(
                        "step %d: continuation stage %d failed after %d iterations; factors now %s",
                        step,
                        index,
                        its,
                        ", ".join(f"{f:.2g}" for f in self._continuation),
                    )
                    kept.copy(self.x)
                    continue
                else:
                    kept_at = None  # go on from where the stage ended
                index += 1
        finally:
            kept.destroy()
            self._eager_march = self._stage_splittable = False
            self._stage_rtol = 0.0
            for term in terms:
                term.set_stiffness_factor(1.0)
            self._forget_energy()
        if converged:
            self.continued_steps += 1
        return total, reason, converged

    def _continuation_stage(
        self, terms: list, path: ContinuationPath, index: int, converged_at: float | None
    ) -> tuple[int, int, bool]:
        """One stage of a continuation from the current iterate (collective).

        A stage that a split would bring closer to its start (``ContinuationPath.can_split``)
        stops as stalled after ``continuation_after`` iterations.
        """
        position = path.positions[index]
        self._stage_splittable = path.can_split(index, converged_at)
        for term, factor in zip(terms, path.factors(position), strict=True):
            term.set_stiffness_factor(factor)
        self._forget_energy()  # the potential has changed
        self._eager_march = position < path.stages
        self._stage_rtol = _STAGE_RTOL if position < path.stages else 0.0
        its, reason, converged = self._attempt()
        logger.debug(
            "continuation stage %d (position %g): %d Newton iterations", index, position, its
        )
        return its, reason, converged

    def solve(self, step: int, retries: bool = True) -> NewtonResult:
        """Minimise from the current ``u`` (which must satisfy the Dirichlet conditions).

        Args:
            step: The step (for messages and the factor store).
            retries: After a failed first attempt, solve again with the exact Hessian from the
                start and then with the stiffness continuation (False: fail at once; for a
                guess that has a fallback of its own).

        Raises:
            NewtonConvergenceError: The solve failed; names the step, iterations and residual.
        """
        self._drop_line_search()
        self._fnorm = self._f_char = float("nan")  # PETSc may stop before the first test
        self._forget_energy()  # loads, history or parameters may have changed
        self._roundoff_converged = False
        self._exact_factors = True
        self.fallbacks = 0
        self.bounded_steps = 0
        self._cuts_by_inversion = 0  # of bounded_steps, those the inversion guard bounded
        self.marched_substeps = 0
        self.expanded_steps = 0
        self._cut_streak = 0
        self._last_cut = 1.0
        self._magnitude = abs(
            collective_comm(self.comm).allreduce(
                fem.assemble_scalar(self.magnitude_form), op=MPI.SUM
            )
        )
        self.u.x.scatter_forward()
        self.x.array_w[:] = self.u.x.petsc_vec.array_r
        self._exact_from_start = self._keep_f_char = False
        self._first_attempt = 0
        self._continuation = ()
        x0 = self.x.copy()
        try:
            its, reason, converged = self._attempt()
            retry = retries and not converged and not self._stalled
            if retry and self._hybrid() and self._projectable():
                # The projected phase crawled (or the exact one failed): the step again from
                # its initial guess with the exact Hessian from the first iteration (projected
                # only where its step is not a descent direction, as exact_hessian_below=inf).
                first = self._first_attempt = its
                logger.info(
                    "step %d: Newton with projected steps above %g f_char %s after %d "
                    "iterations; again with the exact contact Hessian from the start",
                    step,
                    self.options.exact_hessian_below,
                    "stopped near a saddle" if self._left_saddle else "failed",
                    first,
                )
                self._exact_from_start = self._keep_f_char = True
                x0.copy(self.x)
                self.retried_steps += 1
                self.saddle_stops += self._left_saddle
                its, reason, converged = self._attempt()
                its += first
            if not converged and retries:
                more, reason, converged = self._continued_attempt(step, x0)
                its += more
        finally:
            x0.destroy()
        tolerance = self._tolerance()
        if converged and self._fnorm > tolerance:  # the Newton increment reached round-off
            self.round_off_steps.append((step, self._fnorm, tolerance, self._f_char))
        # the step's last factors precondition its adjoint solve (the exact Jacobian's, or the
        # projected one's: closer to the step's exact Jacobian than another step's exact one)
        keep = converged and its > 0 and not self.quadratic
        if keep and self._factor_store is not None:
            self._factor_store.keep(step, self.snes)
        if not converged:
            why = reason_name(PETSc.SNES.ConvergedReason, reason)
            if reason > 0:
                why = f"{why} with the residual above tolerance (a step bound blocked progress?)"
            raise NewtonConvergenceError(
                step, its, self._fnorm, tolerance, why, self._failure_details(its)
            )
        return NewtonResult(its, self._fnorm, self._energy_at(self.x), self._f_char)
