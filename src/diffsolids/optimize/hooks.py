"""What the optimiser asks of the objects a user hands it: declared protocols, no probing.

- a remesher is a :class:`RemeshHook`; one that also implements :class:`RemeshCheckpoints`
  lets a checkpointed run resume after a remesh;
- an ``inner_product`` is a callable ``g -> M^{-1} g``; one that is also
  :class:`RebuildableInnerProduct` is rebuilt for the functional made by a remesh;
- a stop condition is a callable ``(record, optimizer) -> bool | str``.
"""

from collections.abc import Callable
from os import PathLike
from types import FunctionType, MethodType
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from diffsolids.reduced_functional import ReducedFunctional

__all__ = ["RebuildableInnerProduct", "RemeshCheckpoints", "RemeshHook", "condition_name"]


@runtime_checkable
class RemeshHook(Protocol):
    """A remesher: asked after every accepted iterate, it may rebuild the scene on a new mesh."""

    def needs_remesh(self, rf: "ReducedFunctional", q: np.ndarray) -> bool:
        """Whether the scene at q should be remeshed (rank 0's answer is used)."""
        ...

    def remesh(
        self, rf: "ReducedFunctional", q: np.ndarray
    ) -> tuple["ReducedFunctional", np.ndarray]:
        """The functional on the new mesh and the parameters there (collective)."""
        ...


@runtime_checkable
class RemeshCheckpoints(Protocol):
    """A remesher whose meshes are checkpointed with the optimisation (collective calls)."""

    def save_checkpoint(self, directory: PathLike, rf: "ReducedFunctional") -> None:
        """Save what :meth:`load_checkpoint` needs to rebuild ``rf``'s mesh."""
        ...

    def load_checkpoint(self, directory: PathLike, rf: "ReducedFunctional") -> "ReducedFunctional":
        """The functional on the saved mesh (``rf``: the freshly built original one)."""
        ...


@runtime_checkable
class RebuildableInnerProduct(Protocol):
    """An inner product ``g -> M^{-1} g`` that depends on the mesh."""

    def __call__(self, g: np.ndarray) -> np.ndarray:
        """M^{-1} g."""
        ...

    def rebuild(self, rf: "ReducedFunctional") -> Callable[[np.ndarray], np.ndarray]:
        """The same inner product for the functional built after a remesh."""
        ...


def condition_name(condition: Callable) -> str:
    """A stop condition's name in the stop reason: its ``__name__`` or its class's."""
    if isinstance(condition, FunctionType | MethodType):
        return condition.__name__
    return type(condition).__name__
