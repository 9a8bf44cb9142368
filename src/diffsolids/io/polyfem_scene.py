"""Deprecated: the PolyFEM scene reader moved to :mod:`diffsolids.polyfem.scene` (0.4).

``from diffsolids.io.polyfem_scene import read_polyfem_scene`` (and the other names) still works
and warns; import from ``diffsolids.polyfem`` instead. The alias goes in 0.5.
"""

import importlib
import warnings
from typing import Any

__all__: list[str] = []  # only the deprecated names below, reached through __getattr__


def moved_names() -> list[str]:
    """The public names of :mod:`diffsolids.polyfem.scene`, reachable here with a warning."""
    return _scene().__all__


def _scene() -> Any:
    # the importer sits above the core (diffsolids.polyfem): the alias reaches up by name
    return importlib.import_module("diffsolids.polyfem.scene")


def moved(module: str, name: str) -> Any:
    """The object ``name`` of :mod:`diffsolids.polyfem.scene`, with a DeprecationWarning."""
    warnings.warn(
        f"{module}.{name} moved to diffsolids.polyfem.{name} ({module} re-exports it until 0.5)",
        DeprecationWarning,
        stacklevel=3,
    )
    return getattr(_scene(), name)


def __getattr__(name: str) -> Any:
    if not name.startswith("__") and name in moved_names():
        return moved(__name__, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
