"""What the optimiser needs of a reduced functional: one declared protocol.

:class:`~diffsolids.optimize.LBFGS` and :func:`~diffsolids.optimize.minimize` call only the
members below (never probe for others); :class:`~diffsolids.ReducedFunctional` provides them.
A user's own functional that provides them can be optimised the same way.
"""

from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt
from mpi4py import MPI

if TYPE_CHECKING:
    from diffsolids.controls import ControlSet
    from diffsolids.model import Model
    from diffsolids.states import StateHistory

__all__ = ["OptimizableFunctional"]


@runtime_checkable
class OptimizableFunctional(Protocol):
    """A reduced functional J(q) with its gradient, as the optimiser uses it.

    Attributes:
        comm: The communicator of the model (collective decisions are taken on it).
        controls: The controls q drives (their assignment, bounds and per-block limits).
        model: The model (iterate output).
    """

    comm: MPI.Comm
    controls: "ControlSet"
    model: "Model"

    @property
    def size(self) -> int:
        """Number of parameters."""
        ...

    @property
    def trajectory(self) -> "StateHistory | None":
        """The states of the last forward run (None before the first)."""
        ...

    def initial_parameters(self) -> np.ndarray:
        """The controls' current parameters (the default q0)."""
        ...

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of q (+-inf where unbounded)."""
        ...

    def forward(self, q: npt.ArrayLike) -> float:
        """Assign q, run the forward problem and return J(q)."""
        ...

    def derivative(self) -> np.ndarray:
        """dJ/dq at the last forward run."""
        ...

    def term_values(self) -> dict[str, float]:
        """The additive terms of J at the last forward run (logged per iterate)."""
        ...

    def snapshot(self) -> tuple | None:
        """An opaque record of the last forward run, for :meth:`restore`."""
        ...

    def restore(self, snapshot: tuple | None) -> None:
        """Return to a snapshot (after a rejected trial point)."""
        ...

    def warm_start(self, trajectory: "StateHistory | None") -> None:
        """Start the next forward runs' Newton solves from ``trajectory`` (None: no warm start)."""
        ...

    def dof_layout(self) -> np.ndarray:
        """A fingerprint of this rank's dof layout (checkpoints fit the same layout only)."""
        ...
