"""PETSc callbacks that do not keep their Python owner alive.

A PETSc object stores the Python callables and contexts it is given on the C side, out of
reach of Python's cycle collector. A solver that gives its SNES its own bound methods (solver ->
SNES -> method -> solver) is therefore never freed, and neither are its matrices, its MUMPS
factorisations and their MPI communicators; after a few hundred solvers MPICH runs out of
communicators and MUMPS corrupts memory. The wrappers here hold only weak references.
"""

import weakref
from collections.abc import Callable
from typing import Any

__all__ = ["WeakContext", "weak_callback"]


def weak_callback(method: Callable[..., Any]) -> Callable[..., Any]:
    """A function calling the bound ``method`` through a weak reference to its object."""
    ref = weakref.WeakMethod(method)

    def call(*args: Any, **kwargs: Any) -> Any:
        target = ref()
        if target is None:
            raise ReferenceError("the object owning this PETSc callback no longer exists")
        return target(*args, **kwargs)

    return call


class WeakContext:
    """A petsc4py python context (Mat, PC) forwarding its methods to a weakly held object."""

    def __init__(self, obj: object) -> None:
        self._ref = weakref.ref(obj)

    def __getattr__(self, name: str) -> Any:
        target = self._ref()
        if target is None:  # PETSc destroying the object looks up optional methods
            raise AttributeError(name)
        return getattr(target, name)
