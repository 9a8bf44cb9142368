"""Output (VTX/XDMF series), geometry for figures, logging, progress bars, PolyFEM scenes."""

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
from diffsolids.io.polyfem_scene import (
    BoxSideSelection,
    PolyFEMBoundaryValue,
    PolyFEMGeometry,
    PolyFEMMaterial,
    PolyFEMScene,
    PolyFEMSetup,
    read_polyfem_scene,
)
from diffsolids.io.progress import ProgressBar, progress_bar

__all__ = [
    "BoxSideSelection",
    "PolyFEMBoundaryValue",
    "PolyFEMGeometry",
    "PolyFEMMaterial",
    "PolyFEMScene",
    "PolyFEMSetup",
    "ProgressBar",
    "TrajectoryWriter",
    "at_rest_geometry",
    "boundary_edges",
    "configure_logging",
    "deformed_triangles",
    "nodal_displacement",
    "progress_bar",
    "read_polyfem_scene",
    "silhouette_edges",
    "von_mises_field",
    "write_trajectory",
]
