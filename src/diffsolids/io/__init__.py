"""Output (VTX/XDMF series), geometry for figures, logging, progress bars.

The PolyFEM scene reader moved to :mod:`diffsolids.polyfem`; its names are still reachable here
with a DeprecationWarning until 0.5.
"""

import importlib
from typing import Any

from diffsolids.io.geometry import (
    boundary_edges,
    deformed_triangles,
    nodal_displacement,
    silhouette_edges,
)
from diffsolids.io.logging import configure_logging
from diffsolids.io.output import (
    TrajectoryWriter,
    at_rest_geometry,
    von_mises_field,
    write_trajectory,
)
from diffsolids.io.progress import ProgressBar, progress_bar

__all__ = [
    "ProgressBar",
    "TrajectoryWriter",
    "at_rest_geometry",
    "boundary_edges",
    "configure_logging",
    "deformed_triangles",
    "nodal_displacement",
    "progress_bar",
    "silhouette_edges",
    "von_mises_field",
    "write_trajectory",
]


def __getattr__(name: str) -> Any:
    polyfem_scene = importlib.import_module("diffsolids.io.polyfem_scene")
    if not name.startswith("__") and name in polyfem_scene.moved_names():
        return polyfem_scene.moved(__name__, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
