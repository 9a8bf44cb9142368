"""One way into the gmsh API: an empty model with default options, reset again on exit."""

import types
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["gmsh_session"]


@contextmanager
def gmsh_session() -> Iterator[types.ModuleType]:
    """Yield the ``gmsh`` module with no model, default options and a silent terminal.

    gmsh keeps its options in process-wide state that survives ``gmsh.clear()``: an option set
    by one mesher (e.g. ``Mesh.Renumber = 0`` of the remesher) would otherwise change every
    later mesh of the process (non-contiguous node tags, which DOLFINx refuses). The session
    restores the defaults on entry and on exit, and finalizes gmsh when it initialized it.
    """
    import gmsh

    started = not gmsh.isInitialized()
    if started:
        gmsh.initialize(interruptible=False)
    _reset(gmsh)
    try:
        yield gmsh
    finally:
        _reset(gmsh)
        if started:
            gmsh.finalize()


def _reset(gmsh: types.ModuleType) -> None:
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.clear()
    gmsh.parser.clear()
    gmsh.option.restoreDefaults()
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.NumThreads", 1)
