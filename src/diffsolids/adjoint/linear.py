"""Linear solves of the adjoint: exact transposed Jacobians, reusing forward factorisations.

The step Jacobian is symmetric (Hessian of a potential; Dirichlet rows and columns are identity),
so K^T lambda = b is K lambda = b. The matrix is always the exact Hessian at u^i. Factorisations
are reused where that stays exact:
* quadratic potentials (linear elasticity): K is the forward matrix itself; the forward LU solves
  the adjoint directly (one factorisation per distinct beta dt);
* otherwise the closest available LU (the forward's last Newton factorisation of the same step
  when the forward kept it, else the latest one) preconditions flexible GMRES on the exact K
  applied matrix-free (a couple of iterations, converged to round-off; FGMRES keeps the
  preconditioned directions, so no extra LU solve forms the solution); when it does not converge
  quickly, K is assembled and factorised and preconditions the following steps;
* when the forward's steps are Krylov solves (a ``pc_type`` such as ``gamg``, no factors), K is
  assembled and solved by GMRES with the same preconditioner to ``rtol`` in the true residual.
"""

from contextlib import nullcontext
from dataclasses import dataclass
from typing import TYPE_CHECKING

from petsc4py import PETSc

from diffsolids.errors import ConvergenceError
from diffsolids.solvers.action import JacobianAction
from diffsolids.solvers.factor_store import lu_solver
from diffsolids.solvers.linear_options import FACTORISATIONS, krylov_solver, reason_name

if TYPE_CHECKING:
    from diffsolids.solvers.newton import NewtonSolver

__all__ = ["AdjointLinearSolver", "AdjointSolverOptions"]


@dataclass
class AdjointSolverOptions:
    """Options of the adjoint linear solves.

    Attributes:
        rtol: Relative residual tolerance of the Krylov solves.
        max_krylov: GMRES iterations before the matrix is refactorised.
        max_iterative: GMRES iterations of a solve preconditioned like a Krylov forward
            (``pc_type`` not a factorisation) before it fails.
        refactor_above: Refactorise for the next steps when a solve needed more iterations.
        shape_partials: How the shape partials of the residual and the objective are formed:
            "auto" (the explicit energy-momentum forms of the built-in terms where they apply,
            UFL's coordinate derivative elsewhere) or "ufl" (UFL's coordinate derivative
            everywhere, the reference); see :class:`~diffsolids.adjoint.forms.AdjointForms`.
    """

    rtol: float = 1e-12
    max_krylov: int = 30
    max_iterative: int = 2000
    refactor_above: int = 12
    shape_partials: str = "auto"


class _FrozenPC:
    """petsc4py python PC applying an existing factorisation (never re-set-up)."""

    def __init__(self, pc: PETSc.PC) -> None:
        self.pc = pc

    def apply(self, pc: PETSc.PC, x: PETSc.Vec, y: PETSc.Vec) -> None:
        self.pc.apply(x, y)


class AdjointLinearSolver:
    """Solves K(u^i) lambda = b for the steps of a backward sweep.

    Args:
        newton: The forward NewtonSolver (its forms, Dirichlet conditions and last factors).
        options: Krylov and refactorisation options.
    """

    def __init__(self, newton: "NewtonSolver", options: AdjointSolverOptions | None = None) -> None:
        self.newton = newton
        self.options = options or AdjointSolverOptions()
        self.comm = newton.comm
        self._mats = [newton.create_matrix(), newton.create_matrix()]
        # matrix-free when every numeric term can apply its exact Hessian, else assembled
        matrix_free = all(t.has_hessian_action for t in newton.numeric_terms)
        self.action = JacobianAction(newton) if matrix_free else None
        self._factor_ksps: dict = {}
        self._precond = None  # (PETSc.PC, index of the frozen matrix or -1 for the forward one)
        self._precond_step: int | None = None  # the step whose Jacobian it factorised
        self.stats = {"krylov_iterations": 0, "factorisations": 0, "direct_solves": 0}
        self._quadratic_cache: dict = {}
        self._gmres = PETSc.KSP().create(self.comm)
        self._gmres.setType("fgmres")  # no final preconditioner application
        self._gmres.setTolerances(rtol=self.options.rtol, atol=0.0, max_it=self.options.max_krylov)
        self._gmres.setGMRESRestart(self.options.max_krylov)
        self._gmres.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
        self._gmres.getPC().setType("python")
        self._iterative = None
        if newton.pc_type not in FACTORISATIONS:  # the forward solved without factors
            self._iterative = krylov_solver(
                self.comm, newton.prefix, self.options.rtol, self.options.max_iterative
            )

    def begin(self) -> None:
        """Start a sweep right after a forward run: the forward's last factors are current."""
        store = self.newton.factor_store
        self._stored = dict(store.factors) if store is not None else {}
        # Without a store the SNES's KSP still holds the factors of the last Newton iterate.
        self._precond = None if store is not None else (self.newton.last_factors(), -1)
        self._precond_step = None
        self.stats = {"krylov_iterations": 0, "factorisations": 0, "direct_solves": 0}
        self._quadratic_cache = {}

    def refresh(self, factors: dict) -> None:
        """Use ``factors`` (step -> KSP) as the forward's own factors (after recomputed steps)."""
        self._stored = dict(factors)

    def _factorise(self, A: PETSc.Mat) -> PETSc.KSP:
        ksp = lu_solver(self.comm, A)
        self.stats["factorisations"] += 1
        return ksp

    def solve(self, b: PETSc.Vec, x: PETSc.Vec, step: int) -> int:
        """Solve with the exact Jacobian of ``step`` at the model's current u.

        Returns:
            Krylov iterations (0 for a direct solve).
        """
        if self._iterative is not None:
            return self._solve_iterative(b, x, step)
        if self.newton.quadratic:
            return self._solve_quadratic(b, x)
        self._nearest_stored(step)
        frozen = -1 if self._precond is None else self._precond[1]
        work = 1 if frozen == 0 else 0
        A = self._assembled(work) if self.action is None else None
        its = None
        if self._precond is not None:
            operator = A if self.action is None else self.action.mat
            its = self._krylov(operator, self._precond[0], b, x)
        if its is None or its > self.options.refactor_above:
            if A is None:
                A = self._assembled(work)
            ksp = self._factorise(A)
            if work in self._factor_ksps:
                self._factor_ksps[work].destroy()
            self._factor_ksps[work] = ksp
            self._precond = (ksp.getPC(), work)
            self._precond_step = step
            if its is None:
                ksp.solve(b, x)
                self.stats["direct_solves"] += 1
                its = 0
        return its

    def _nearest_stored(self, step: int) -> None:
        """Precondition with the stored factors of the step nearest to ``step`` (later on a tie).

        Kept when they are nearer than the current preconditioner's step: a store thinned to
        every k-th step then preconditions each step with factors at most k / 2 steps away.
        """
        if not self._stored:
            return
        nearest = min(self._stored, key=lambda k: (abs(k - step), -k))
        current = self._precond_step
        if self._precond is None or current is None or abs(nearest - step) < abs(current - step):
            self._precond = (self._stored[nearest].getPC(), -1)
            self._precond_step = nearest

    def _assembled(self, work: int) -> PETSc.Mat:
        """Exact Jacobian in work matrix ``work`` (its pattern grown for contact if needed)."""
        A = self.newton.ensure_matrix_pattern(self._mats[work])
        self._mats[work] = A
        self.newton.assemble_jacobian(A, exact=True)
        return A

    def _solve_quadratic(self, b: PETSc.Vec, x: PETSc.Vec) -> int:
        """Constant Jacobian (per beta dt): direct solves with one factorisation each."""
        newton = self.newton
        key = newton.quadratic_key()
        if newton.holds_factors_of(key):  # the forward factors are of this very matrix
            newton.solve_with_last_factors(b, x)
        else:
            if key not in self._quadratic_cache:
                A = newton.create_matrix()
                newton.assemble_jacobian(A, exact=True)
                self._quadratic_cache[key] = self._factorise(A)
            self._quadratic_cache[key].solve(b, x)
        self.stats["direct_solves"] += 1
        return 0

    def _solve_iterative(self, b: PETSc.Vec, x: PETSc.Vec, step: int) -> int:
        """GMRES on the assembled exact K, preconditioned like the forward (no factors)."""
        ksp = self._iterative
        ksp.setOperators(self._assembled(0))
        ksp.solve(b, x)
        its = ksp.getIterationNumber()
        self.stats["krylov_iterations"] += its
        if ksp.getConvergedReason() <= 0:
            pc = self.newton.pc_type
            why = reason_name(PETSc.KSP.ConvergedReason, ksp.getConvergedReason())
            raise ConvergenceError(
                f"adjoint linear solve of step {step}: GMRES preconditioned by {pc!r} stopped "
                f"after {its} iterations ({why}) at relative residual "
                f"{ksp.getResidualNorm() / max(b.norm(), 1e-300):.3g} (tolerance "
                f"{self.options.rtol:g}); raise AdjointSolverOptions.max_iterative or solve the "
                "steps with a factorisation (petsc_options pc_type 'lu')"
            )
        return its

    def _krylov(self, A: PETSc.Mat, pc: PETSc.PC, b: PETSc.Vec, x: PETSc.Vec) -> int | None:
        ksp = self._gmres
        ksp.setOperators(A)
        ksp.getPC().setPythonContext(_FrozenPC(pc))
        x.set(0.0)
        with self.action.fixed_state() if self.action is not None else nullcontext():
            ksp.solve(b, x)
        its = ksp.getIterationNumber()
        self.stats["krylov_iterations"] += its
        if ksp.getConvergedReason() <= 0:
            return None
        return its

    def check(self, b: PETSc.Vec, x: PETSc.Vec) -> float:
        """Relative residual of a solution (for tests)."""
        A = self._mats[0]
        self.newton.assemble_jacobian(A, exact=True)
        r = b.duplicate()
        A.mult(x, r)
        r.axpy(-1.0, b)
        bn = b.norm()
        if bn == 0:
            return r.norm()
        return r.norm() / bn

    def destroy(self) -> None:
        """Free PETSc objects."""
        for ksp in [*self._factor_ksps.values(), *self._quadratic_cache.values()]:
            ksp.destroy()
        self._gmres.destroy()
        if self._iterative is not None:
            self._iterative.destroy()
