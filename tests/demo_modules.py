"""The demo scripts as modules for the tests (``load_demo("throw").main([...])``).

The demos import their shared helpers (``common``, ``shape_tools``, ...) from ``demos/``, which
is put on ``sys.path`` first. Importable from ``tests/`` and ``tests/mpi/`` (pytest puts
``tests/`` on the path, where ``conftest.py`` is).
"""

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

DEMOS = Path(__file__).resolve().parents[1] / "demos"
DOCS_EXAMPLES = Path(__file__).resolve().parents[1] / "docs" / "examples"

__all__ = ["DEMOS", "DOCS_EXAMPLES", "load_demo", "load_docs_example"]


def load_demo(name: str) -> ModuleType:
    """A fresh module of ``demos/<name>.py``."""
    if str(DEMOS) not in sys.path:
        sys.path.insert(0, str(DEMOS))
    spec = importlib.util.spec_from_file_location(name, DEMOS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def load_docs_example(name: str) -> ModuleType:
    """A fresh module of ``docs/examples/<name>.py`` (its ``main`` is not run).

    The how-to's classes (a new law, numeric term, map) are written once, there; the tests
    check them in depth.
    """
    spec = importlib.util.spec_from_file_location(f"docs_{name}", DOCS_EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
