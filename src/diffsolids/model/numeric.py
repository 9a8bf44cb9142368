"""The protocol of numeric (non-UFL) terms of the incremental potential.

A UFL term answers every question of the solver and the adjoint through ``ufl.derivative``. A
numeric term (IPC contact, or any force computed outside UFL) answers the same questions with
numpy/PETSc: its energy, residual and Jacobian for the Newton solve, the largest admissible step
fraction, its per-step hooks, and the vector-Jacobian products the backward sweep needs with
respect to the previous states, the rest shape and each of its named parameters (paper eqs.
11-15: every term contributes its partial derivatives to the adjoint equations and to the
gradient). :meth:`Model.add_numeric_term <diffsolids.model.Model.add_numeric_term>` takes
instances of :class:`NumericTerm` only; the solver and the sweep call nothing else.

Capabilities that change how the solver works are declared as class attributes rather than
discovered: ``projectable_hessian`` (a PSD-projected Newton matrix exists),
``has_hessian_action`` (the exact Hessian can be applied matrix-free), ``grows_pattern`` (the
Jacobian may need entries outside the finite-element sparsity, see :meth:`matrix_pattern`),
``has_stiffness_continuation`` (a stiffer version of the term exists from which a stalled solve
may walk down to the term itself, see :meth:`continuation_factors`), ``revises_newton_steps``
(the term may replace its model for one Newton step after seeing it, see
:meth:`revise_newton_model`).
"""

import inspect
import warnings
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from dolfinx import fem
from petsc4py import PETSc

if TYPE_CHECKING:
    from diffsolids.states import StateHistory, StepContext

__all__ = ["NumericTerm"]


def _legacy_begin_step(cls: type, hook: Callable) -> Callable:
    """``begin_step(i, traj, coeffs, sim=None)`` of an older subclass, called with a context."""
    warnings.warn(
        f"{cls.__name__}.begin_step(i, traj, coeffs, sim) is deprecated: override "
        "begin_step(self, context) with a diffsolids.states.StepContext (index, step, history, "
        "integrator, phase); the old form is called as hook(context.index, context.history, "
        "context.step) until 0.5",
        DeprecationWarning,
        stacklevel=3,
    )

    def begin_step(self: "NumericTerm", context: "StepContext") -> None:
        hook(self, context.index, context.history, context.step)

    begin_step.__doc__ = hook.__doc__
    return begin_step


class NumericTerm(ABC):
    """A contribution to a step's incremental potential computed outside UFL.

    All methods are collective under MPI. Arrays named ``u``/``lam`` are DOLFINx Functions or
    local arrays of the model's vector space V (owned entries first, then ghosts); vectors and
    matrices are the solver's PETSc objects, to which a term adds its owned rows only.

    Attributes:
        name: Human-readable name (used in reports and errors).
        parameter_names: Names of the term's own parameters the adjoint can differentiate
            (e.g. ``("friction",)``), see :meth:`adjoint_parameter`.
    """

    name: ClassVar[str] = "numeric term"
    projectable_hessian: ClassVar[bool] = False
    has_hessian_action: ClassVar[bool] = False
    grows_pattern: ClassVar[bool] = False
    has_stiffness_continuation: ClassVar[bool] = False
    revises_newton_steps: ClassVar[bool] = False
    parameter_names: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Adapt an overridden ``begin_step`` of the pre-0.4 form (i, traj, coeffs, sim)."""
        super().__init_subclass__(**kwargs)
        hook = cls.__dict__.get("begin_step")
        if hook is not None and len(inspect.signature(hook).parameters) > 2:
            cls.begin_step = _legacy_begin_step(cls, hook)

    # -- the Newton solve ------------------------------------------------------------------
    @abstractmethod
    def energy(self, u: fem.Function) -> float:
        """The term's part of the incremental potential at ``u`` (the same on every rank)."""

    @abstractmethod
    def add_residual(self, u: fem.Function, b: PETSc.Vec) -> None:
        """Add the gradient of :meth:`energy` w.r.t. u to the owned entries of ``b``."""

    @abstractmethod
    def add_jacobian(
        self, u: fem.Function, A: PETSc.Mat, bc_dofs: np.ndarray, project: bool = False
    ) -> None:
        """Add the Hessian w.r.t. u to the owned rows of ``A``, skipping Dirichlet rows/columns.

        Args:
            u: Current displacement.
            A: Matrix to add to (not yet assembled).
            bc_dofs: Local indices of Dirichlet dofs.
            project: Add the PSD-projected Hessian instead of the exact one (only called when
                ``projectable_hessian``).
        """

    def add_adjoint_jacobian(self, u: fem.Function, A: PETSc.Mat, bc_dofs: np.ndarray) -> None:
        """Add the exact Hessian w.r.t. u^i (adjoint matrix); the exact :meth:`add_jacobian`."""
        self.add_jacobian(u, A, bc_dofs, project=False)

    def add_hessian_action(self, u: fem.Function, direction: np.ndarray, y: PETSc.Vec) -> None:
        """y[owned] += H direction with the exact Hessian (when ``has_hessian_action``)."""
        raise NotImplementedError(f"{self.name} has no matrix-free Hessian action")

    def add_dirichlet_lifting(  # noqa: B027 - optional: most terms couple no prescribed dofs
        self, u: fem.Function, b: PETSc.Vec, increment: np.ndarray, bc_dofs: np.ndarray
    ) -> None:
        """b[owned free rows] += H[free, prescribed] increment; nothing for most terms.

        The matrix of :meth:`add_jacobian` drops Dirichlet columns: a term coupling free and
        prescribed dofs adds here the response of the free dofs to the prescribed increment.
        """

    def matrix_pattern(self, u: fem.Function, bc_dofs: np.ndarray) -> tuple[Any, Any] | None:
        """Global (rows, cols) the Jacobian may need at ``u`` (when ``grows_pattern``)."""
        return None

    def max_step(self, x: PETSc.Vec, dx: PETSc.Vec) -> float:
        """Largest admissible fraction of the step ``x -> x + dx`` (inf: no bound)."""
        return np.inf

    def admits(self, u: np.ndarray, step: int) -> bool:
        """Whether the state ``u`` (a local V array) is admissible at step ``step`` (collective).

        Asked of a Newton start that is not reached from u^{i-1} along a checked path (the
        branch reference, ``Simulation.branch_reference``); Newton's own steps are bounded
        by :meth:`max_step`. Default: every state is.
        """
        return True

    def failure_report(self) -> str | None:
        """What a failed Newton solve should tell the user about this term (None: nothing)."""
        return None

    def continuation_factors(self) -> tuple[float, ...]:
        """Stiffness factors (> 1, decreasing) for a continuation from the last evaluated iterate.

        Only asked when ``has_stiffness_continuation`` and a step's solve has failed; empty:
        a continuation would not help (collective).
        """
        return ()

    def held_at_floor(self) -> bool:
        """Whether the last step bound of the term held a pair at its round-off floor.

        A barrier that lets a Newton step press a pair down to the gap floor of its step
        bound (a few ulps of the coordinates) is too soft for its load: the solver then asks
        for a stiffness continuation at once rather than after ``continuation_after`` cut
        steps. Only asked when ``has_stiffness_continuation`` (collective). Default: False.
        """
        return False

    def below_round_off(self) -> bool:
        """Whether the term's own stiffness cannot hold its pairs above round-off (collective).

        Asked when the last stage of a stiffness continuation fails: True ends the solve at
        once (no stage between it and a converged one can help). Only asked when
        ``has_stiffness_continuation``. Default: False.
        """
        return False

    def revise_newton_model(self, u: fem.Function, step: np.ndarray, bc_dofs: np.ndarray) -> bool:
        """Replace the term's model for a Newton step that ``step`` would take badly (collective).

        Only asked when ``revises_newton_steps``. ``step`` is the Newton step from ``u`` (a
        local V array). When this returns True (the same on all ranks) the solver solves the
        step again with :meth:`add_jacobian` (``project=True``) and :meth:`add_model_change`
        giving the revised model, then calls :meth:`end_model_revision`. Default: False.
        """
        return False

    def add_model_change(self, b: PETSc.Vec, bc_dofs: np.ndarray) -> None:  # noqa: B027
        """Add the revised model's gradient minus the term's own to the owned rows of ``b``."""

    def end_model_revision(self) -> None:  # noqa: B027 - optional hook
        """Back to the term's own model (after :meth:`revise_newton_model` returned True)."""

    def set_stiffness_factor(self, factor: float) -> None:
        """Scale the term's stiffness by ``factor`` (1: the term itself) for the next solves."""
        raise NotImplementedError(f"{self.name} has no stiffness continuation")

    # -- per-step hooks --------------------------------------------------------------------
    def begin_step(self, context: "StepContext") -> None:  # noqa: B027 - optional hook
        """Called before step ``context.index`` is solved, or differentiated (``context.phase``)."""

    def end_step(self, i: int, traj: "StateHistory") -> Any:
        """Called after step ``i`` converged; may return a record of the step."""
        return None

    def update_rest_positions(self) -> None:  # noqa: B027 - optional hook
        """Called after the rest shape (mesh geometry) changed."""

    # -- the backward sweep ----------------------------------------------------------------
    def adjoint_history(self, u: fem.Function, lam: np.ndarray) -> dict[int, np.ndarray]:
        """Lam . dG_i/du^{i-j} for the previous states the term reads, keyed by j >= 1."""
        return {}

    def adjoint_shape(self, u: fem.Function, lam: np.ndarray) -> np.ndarray | None:
        """Lam . dG_i/dX over the geometry dofs (None: the term does not depend on the shape)."""
        return None

    def adjoint_parameter(self, name: str, u: fem.Function, lam: np.ndarray) -> np.ndarray:
        """Lam . dG_i/dp for the term's parameter ``name`` (one of ``parameter_names``)."""
        raise KeyError(f"{self.name} has no parameter {name!r} (it has {self.parameter_names})")
