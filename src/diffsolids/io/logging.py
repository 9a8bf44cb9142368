"""Log configuration: one handler on rank 0 for the "diffsolids" logger."""

import logging
import sys

from mpi4py import MPI

__all__ = ["configure_logging"]


def configure_logging(level: int | str = logging.INFO, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
    """Print diffsolids log lines (per-step Newton summaries, ...) on rank 0 of ``comm``."""
    logger = logging.getLogger("diffsolids")
    logger.setLevel(level)
    for h in list(logger.handlers):
        if getattr(h, "_diffsolids", False):
            logger.removeHandler(h)
    handler: logging.Handler = (
        logging.StreamHandler(sys.stdout) if comm.rank == 0 else logging.NullHandler()
    )
    handler.setFormatter(logging.Formatter("%(asctime)s %(message)s", "%H:%M:%S"))
    handler._diffsolids = True
    logger.addHandler(handler)
