"""Form compilation with the JIT options used everywhere in diffsolids."""

import ufl
from dolfinx import fem

__all__ = ["JIT_OPTIONS", "compile_form"]

# Concurrent processes (pytest-xdist, MPI ranks) wait for each other's compilation; big
# Jacobians can take longer than FFCx's default 10 s wait.
JIT_OPTIONS = {"timeout": 600}


def compile_form(form: ufl.Form | None) -> fem.Form | None:
    """Compile a UFL form (None passes through)."""
    if form is None:
        return None
    return fem.form(form, jit_options=JIT_OPTIONS)
