"""Wall and CPU time of the contact term's operations (``ContactTerm.timing_summary``)."""

import contextlib
import functools
import time
from collections.abc import Callable, Iterator
from typing import Any

__all__ = ["timed", "timed_kernel", "timing_summary"]


@contextlib.contextmanager
def timed(entries: dict[str, list], name: str) -> Iterator[None]:
    """Add the wall and process CPU time of the block to ``entries[name]`` ([wall, calls, cpu])."""
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        yield
    finally:
        entry = entries.setdefault(name, [0.0, 0, 0.0])
        entry[0] += time.perf_counter() - t0
        entry[1] += 1
        entry[2] += time.process_time() - c0


def timed_kernel(name: str) -> Callable[[Callable], Callable]:
    """Record the wall and CPU time of a method under ``name`` in ``self.timings``."""

    def decorate(method: Callable) -> Callable:
        @functools.wraps(method)
        def wrapped(self: Any, *args: Any, **kwargs: Any) -> Any:
            with timed(self.timings, name):
                return method(self, *args, **kwargs)

        return wrapped

    return decorate


def timing_summary(entries: dict[str, list]) -> dict[str, dict[str, float]]:
    """Wall seconds, calls, mean wall ms and process CPU seconds per operation."""
    return {
        k: {"seconds": t, "calls": n, "mean_ms": 1e3 * t / max(n, 1), "cpu_seconds": c}
        for k, (t, n, c) in entries.items()
    }
