"""Output (VTX/XDMF time series), deformed geometry for figures, logging and progress bars."""

from diffsolids.io.geometry import (
    boundary_edges,
    deformed_triangles,
    nodal_displacement,
    silhouette_edges,
)
from diffsolids.io.logging import configure_logging
from diffsolids.io.output import TrajectoryWriter, von_mises_field, write_trajectory
from diffsolids.io.progress import progress_bar

__all__ = [
    "TrajectoryWriter",
    "boundary_edges",
    "configure_logging",
    "deformed_triangles",
    "nodal_displacement",
    "progress_bar",
    "silhouette_edges",
    "von_mises_field",
    "write_trajectory",
]
