"""Output (VTX/XDMF time series), logging and progress bars."""

from diffsolids.io.logging import configure_logging
from diffsolids.io.output import TrajectoryWriter, von_mises_field
from diffsolids.io.progress import progress_bar

__all__ = ["TrajectoryWriter", "configure_logging", "progress_bar", "von_mises_field"]
