"""Progress bars and log lines of long runs (rank 0 only)."""

import contextlib
import sys
from collections.abc import Iterator
from typing import Protocol, TextIO

from mpi4py import MPI

__all__ = ["ProgressBar", "progress_bar", "write_line"]


class ProgressBar(Protocol):
    """What :func:`progress_bar` yields: a tqdm bar, or one that shows nothing."""

    def update(self, n: int = 1) -> None:
        """Advance the bar by ``n`` steps."""
        ...


class _NullBar:
    def update(self, n: int = 1) -> None:
        pass


@contextlib.contextmanager
def progress_bar(
    total: int, comm: MPI.Comm, enabled: bool | None = None, desc: str = "steps"
) -> Iterator["ProgressBar"]:
    """A tqdm bar on rank 0; ``enabled=None`` shows it only when stderr is a terminal."""
    if enabled is None:
        enabled = sys.stderr.isatty()
    if not enabled or comm.rank != 0:
        yield _NullBar()
        return
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, leave=False, dynamic_ncols=True) as bar:
        yield bar


def write_line(text: str, file: TextIO | None = None) -> None:
    """Print one line (to stdout by default) without breaking a progress bar being shown.

    Call it on the rank that prints (it does not check the rank): the bars of
    :func:`progress_bar` are cleared, the line written and the bars drawn again below it.
    """
    out = sys.stdout if file is None else file
    try:
        from tqdm import tqdm
    except ImportError:  # no bars without tqdm either
        print(text, file=out, flush=True)
        return
    tqdm.write(text, file=out)
    out.flush()
