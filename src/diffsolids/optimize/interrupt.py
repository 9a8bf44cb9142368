"""Ctrl-C during an optimisation: stop at the next safe point instead of inside a solve.

A KeyboardInterrupt raised inside a PETSc callback surfaces as a PETSc error after a stack
dump and leaves the model between two states. While an :class:`InterruptRequest` is active,
the first SIGINT only records the request (the optimiser stops after the current trial, at
the last accepted point, with its checkpoint written); a second SIGINT raises
KeyboardInterrupt as usual.
"""

import logging
import signal
import threading
from types import FrameType, TracebackType

from mpi4py import MPI

from diffsolids.parallel import collective_comm

__all__ = ["InterruptRequest"]

logger = logging.getLogger("diffsolids")


class InterruptRequest:
    """A context that turns the first Ctrl-C into a request the optimiser polls.

    Outside the main thread (where Python cannot install signal handlers) it does nothing.

    Args:
        comm: The run's communicator: :meth:`pending` is true on every rank when any rank
            received the signal.
    """

    def __init__(self, comm: MPI.Comm) -> None:
        self.comm = comm
        self.requested = False
        self._previous: object = None
        self._installed = False

    def __enter__(self) -> "InterruptRequest":
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        value: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if self._installed:
            signal.signal(signal.SIGINT, self._previous)
            self._installed = False

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.requested = True
        signal.signal(signal.SIGINT, self._previous)  # a second Ctrl-C interrupts at once
        logger.warning(
            "opt: interrupt requested; stopping after the current trial at the last accepted "
            "point (Ctrl-C again to abort at once)"
        )

    def pending(self) -> bool:
        """Whether any rank received the signal (collective)."""
        return bool(collective_comm(self.comm).allreduce(self.requested, op=MPI.LOR))
