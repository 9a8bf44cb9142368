"""Exception hierarchy: every failure we detect raises one of these with a message that names it."""

from collections.abc import Sequence

import numpy as np

__all__ = [
    "ConvergenceError",
    "DiffsolidsError",
    "IntersectionError",
    "InvertedElementError",
    "MeshError",
    "NewtonConvergenceError",
    "ParameterError",
    "PortabilityError",
    "TagError",
]


class DiffsolidsError(Exception):
    """Base class of all errors raised by diffsolids."""


class ParameterError(DiffsolidsError, ValueError):
    """A non-physical or malformed parameter (dt <= 0, E <= 0, nu out of range, NaN, ...)."""


class TagError(DiffsolidsError, LookupError):
    """A cell or facet tag that does not exist in the mesh, or a required tag that is missing."""

    def __str__(self) -> str:  # LookupError subclasses otherwise print repr(args)
        return str(self.args[0]) if self.args else ""


class MeshError(DiffsolidsError, ValueError):
    """A mesh that cannot be simulated."""


class InvertedElementError(MeshError):
    """Cells with non-positive orientation (inverted elements).

    Attributes:
        cells: Local indices of the offending cells.
    """

    def __init__(self, message: str, cells: np.ndarray | Sequence[int] = ()) -> None:
        super().__init__(message)
        self.cells = cells


class IntersectionError(MeshError):
    """Bodies (or a body with itself) that intersect or are closer than the barrier allows."""


class ConvergenceError(DiffsolidsError, RuntimeError):
    """An iterative solve that did not converge."""


class NewtonConvergenceError(ConvergenceError):
    """A Newton solve of one time step that failed.

    Attributes:
        step: Time-step index (1-based; 1 for a static solve).
        iterations: Newton iterations performed.
        residual: Residual norm at the last iterate.
        reason: PETSc's converged reason (negative) or a short text.
        details: What the solver and the numeric terms (e.g. the contact state) add.
    """

    def __init__(
        self,
        step: int,
        iterations: int,
        residual: float,
        tolerance: float,
        reason: int | str,
        details: str = "",
    ) -> None:
        self.step, self.iterations, self.residual, self.reason = step, iterations, residual, reason
        self.details = details
        super().__init__(
            f"Newton solve of step {step} failed after {iterations} iterations: residual "
            f"{residual:.3e} (tolerance {tolerance:.3e}), reason: {reason}"
            + (f"\n{details}" if details else "")
        )


class PortabilityError(DiffsolidsError, ImportError):
    """A compiled dependency that cannot run on this CPU (e.g. built for AVX-512)."""
