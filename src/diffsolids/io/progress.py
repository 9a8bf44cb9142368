"""Progress bars for long runs (rank 0 only)."""

import contextlib
import sys

from mpi4py import MPI

__all__ = ["progress_bar"]


class _NullBar:
    def update(self, n: int = 1) -> None:
        pass


@contextlib.contextmanager
def progress_bar(total: int, comm: MPI.Comm, enabled: bool | None = None, desc: str = "steps"):
    """A tqdm bar on rank 0; ``enabled=None`` shows it only when stderr is a terminal."""
    if enabled is None:
        enabled = sys.stderr.isatty()
    if not enabled or comm.rank != 0:
        yield _NullBar()
        return
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, leave=False, dynamic_ncols=True) as bar:
        yield bar
