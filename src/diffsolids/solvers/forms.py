"""Form and expression compilation with the JIT options used everywhere in diffsolids.

``DIFFSOLIDS_JIT_CFLAGS`` (e.g. ``"-O0 -g0"``) overrides the C compiler flags of the generated
kernels: the test suite compiles hundreds of small forms on a cold cache and uses it to spend
seconds, not minutes, in the C compiler.
"""

import os

import numpy as np
import ufl
from dolfinx import fem

__all__ = ["JIT_OPTIONS", "compile_expression", "compile_form"]


def _jit_options() -> dict:
    # Concurrent processes (pytest-xdist, MPI ranks) wait for each other's compilation; big
    # Jacobians can take longer than FFCx's default 10 s wait.
    options: dict = {"timeout": 600}
    flags = os.environ.get("DIFFSOLIDS_JIT_CFLAGS")
    if flags:
        options["cffi_extra_compile_args"] = flags.split()
    return options


JIT_OPTIONS = _jit_options()


def compile_form(form: ufl.Form | None) -> fem.Form | None:
    """Compile a UFL form (None passes through)."""
    if form is None:
        return None
    return fem.form(form, jit_options=JIT_OPTIONS)


def compile_expression(expr, points: np.ndarray) -> fem.Expression:
    """Compile a UFL expression evaluated at reference points."""
    return fem.Expression(expr, points, jit_options=JIT_OPTIONS)
