"""Deprecated: scene assembly moved to :mod:`diffsolids.mesh.scene` (0.1, December 2026).

``from diffsolids.contact.scenes import combine_meshes`` still works and warns; import from
``diffsolids.mesh`` (or ``diffsolids``) instead. The alias goes in 0.5.
"""

import warnings
from typing import Any

from diffsolids.mesh import scene as _scene

__all__: list[str] = []  # only the deprecated names below, reached through __getattr__

_MOVED = ("combine_meshes", "simplex_ball", "simplex_box")


def __getattr__(name: str) -> Any:
    if name in _MOVED:
        warnings.warn(
            f"diffsolids.contact.scenes.{name} moved to diffsolids.mesh.{name} "
            "(diffsolids.contact.scenes goes in 0.5)",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(_scene, name)
    raise AttributeError(f"module 'diffsolids.contact.scenes' has no attribute {name!r}")
