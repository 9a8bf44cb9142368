"""Deprecated: :class:`CanonicalLayout` moved to :mod:`diffsolids.mesh.ordering` (0.4).

``from diffsolids.mesh.ordering import CanonicalLayout`` still works and warns; import it
from ``diffsolids.mesh`` (or ``diffsolids.controls``) instead. The alias goes in 0.5.
"""

import warnings
from typing import Any

from diffsolids.mesh import ordering as _ordering

__all__: list[str] = []  # only the deprecated name below, reached through __getattr__


def __getattr__(name: str) -> Any:
    if name == "CanonicalLayout":
        warnings.warn(
            "diffsolids.controls.ordering.CanonicalLayout moved to "
            "diffsolids.mesh.CanonicalLayout (diffsolids.controls.ordering goes in 0.5)",
            DeprecationWarning,
            stacklevel=2,
        )
        return _ordering.CanonicalLayout
    raise AttributeError(f"module 'diffsolids.controls.ordering' has no attribute {name!r}")
