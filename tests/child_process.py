"""Error paths checked in a child process: the error must reach the user as itself.

A segfault or an exception swallowed while DOLFINx/PETSc objects are freed cannot fail an
in-process test; a child Python process shows both.
"""

import subprocess
import sys
import textwrap
from pathlib import Path

__all__ = ["assert_child_raises"]


def assert_child_raises(script: str, error: str, cwd: Path, timeout: float = 300.0) -> str:
    """Run ``script`` in a new Python; it must exit 1 with ``error`` as the last stderr line.

    Args:
        script: Python source (dedented here).
        error: The start of the last stderr line, e.g. ``"diffsolids.errors.ParameterError: "``.
        cwd: Working directory of the child.
        timeout: Seconds before the child is killed (the test then fails).

    Returns:
        The child's stderr.
    """
    child = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)],
        capture_output=True,
        text=True,
        check=False,
        timeout=timeout,
        cwd=cwd,
    )
    err = child.stderr
    assert child.returncode == 1, f"exit {child.returncode}:\n{err}"
    last = err.strip().splitlines()[-1]
    assert last.startswith(error), err
    for bad in ("SystemError", "Exception ignored", "Segmentation"):
        assert bad not in err, err
    return err
