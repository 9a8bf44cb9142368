"""Sphinx configuration of the diffsolids documentation (``make docs``).

The API pages are written at build time from the ``__all__`` lists of the package and its
modules (``docs/api/``, not in git), so that every public name is documented and a new one
needs no edit here. No network access: no intersphinx.
"""

import importlib
import inspect
import re
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS.parent / "src"))

import diffsolids  # noqa: E402  (loads the MPI of the DOLFINx wheel before dolfinx)

project = "diffsolids"
author = "the diffsolids authors"
copyright = "2026, the diffsolids authors"
release = "0.1.0"

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build", "examples/output*", "**/README.md"]
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

html_theme = "furo"
html_title = "diffsolids"
html_static_path = []

# Google-style docstrings (the project's convention)
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
# "Attributes:" sections as fields: a dataclass documents its fields once, as members
napoleon_use_ivar = True
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_format = "short"
autodoc_preserve_defaults = True
autosummary_generate = False
autosummary_ignore_module_all = False

# The modules whose ``__all__`` the reference documents, with the title of their page.
API_MODULES = {
    "diffsolids": "The one import: ``import diffsolids as ds``",
    "diffsolids.mesh": "Meshes and domains",
    "diffsolids.model": "Model: materials, terms, boundary conditions",
    "diffsolids.integrators": "Time integrators",
    "diffsolids.simulation": "Simulation and trajectories",
    "diffsolids.solvers": "Newton solver",
    "diffsolids.contact": "Contact (IPC barrier and friction)",
    "diffsolids.contact.polyfem": "PolyFEM contact parameters",
    "diffsolids.objectives": "Objectives",
    "diffsolids.controls": "Controls",
    "diffsolids.reduced_functional": "Reduced functional",
    "diffsolids.adjoint": "Discrete adjoint",
    "diffsolids.verification": "Gradient checks",
    "diffsolids.optimize": "Optimisation, mesh motion, remeshing",
    "diffsolids.io": "Output, figures, logging",
    "diffsolids.errors": "Errors",
    "diffsolids.parallel": "MPI helpers",
    "diffsolids.portability": "Portability (the ipctk CPU check)",
    "diffsolids.forms": "UFL forms (``diffsolids.forms``)",
}


def _canonical(module: str, name: str) -> str:
    """Where a re-exported name is documented: the top-level names point at their subpackage."""
    if module != "diffsolids":
        return f"{module}.{name}"
    obj = getattr(diffsolids, name)
    if isinstance(obj, type(diffsolids)):  # a module (``errors``)
        return obj.__name__
    home = getattr(obj, "__module__", "diffsolids")
    for candidate in API_MODULES:
        if candidate == "diffsolids" or not home.startswith(candidate):
            continue
        mod = importlib.import_module(candidate)
        if name in getattr(mod, "__all__", ()):
            return f"{candidate}.{name}"
    return f"diffsolids.{name}"


def _directive(module: str, name: str, obj: object) -> str:
    """The autodoc directive of one public name (one page per module, every name on it)."""
    if inspect.isclass(obj):
        kind = "autoexception" if issubclass(obj, BaseException) else "autoclass"
    elif callable(obj):
        kind = "autofunction"
    elif isinstance(obj, type(diffsolids)):
        return f"See :doc:`{obj.__name__}`.\n"
    else:
        kind = "autodata"
    return f".. {kind}:: {module}.{name}\n"


def write_api_pages(app) -> None:
    """Write ``docs/api/<module>.rst`` (a table of the names, then each name) and the index."""
    api = DOCS / "api"
    api.mkdir(exist_ok=True)
    index = [
        "API reference",
        "=============",
        "",
        "Generated from the docstrings of every name in the ``__all__`` list of the package and",
        "of its modules. ``import diffsolids as ds`` gives the names of the first page; the",
        "others are imported from their module (``from diffsolids.objectives import ...``).",
        "",
        ".. toctree::",
        "   :maxdepth: 1",
        "",
    ]
    for module, title in API_MODULES.items():
        mod = importlib.import_module(module)
        names = sorted(mod.__all__, key=str.lower)
        first = (mod.__doc__ or "").strip().split("\n\n")[0]
        lines = [title, "=" * len(title), "", f"``{module}``", ""]
        if first:
            lines += [first, ""]
        lines += [".. autosummary::", ""]
        if module == "diffsolids":
            lines += [f"   ~{_canonical(module, n)}" for n in names]
            lines += ["", "Each name links to its description on the page of its module."]
        else:
            lines += [f"   {module}.{n}" for n in names]
            lines += [""] + [_directive(module, n, getattr(mod, n)) for n in names]
        text = "\n".join(lines) + "\n"
        path = api / f"{module}.rst"
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
        index.append(f"   {module}")
    text = "\n".join(index) + "\n"
    path = api / "index.rst"
    if not path.exists() or path.read_text() != text:
        path.write_text(text)


_LITERAL = re.compile(r"(``.*?``)")


def plain_docstrings(app, what, name, obj, options, lines) -> None:
    """Read the docstrings as the project writes them.

    The docstrings write norms and absolute values as ``|x|`` (never reStructuredText
    substitutions), so ``|`` is escaped outside literals. A module-level constant without a
    docstring of its own (a dict of options) would show its type's docstring: dropped.
    """
    if what in ("data", "attribute") and lines:
        own = type(obj).__doc__
        if own and "\n".join(lines).strip() == inspect.cleandoc(own).strip():
            lines.clear()
            return
    for i, line in enumerate(lines):
        if "|" in line:
            parts = _LITERAL.split(line)
            lines[i] = "".join(p if p.startswith("``") else p.replace("|", "\\|") for p in parts)


def resolve_top_level(app, env, node, contnode):
    """Resolve ``diffsolids.Name[.attr]`` to where Name is documented (its subpackage)."""
    target = node.get("reftarget", "")
    if node.get("refdomain") != "py" or not target.startswith("diffsolids."):
        return None
    name, _, rest = target.removeprefix("diffsolids.").partition(".")
    if name not in diffsolids.__all__:
        return None
    canonical = _canonical("diffsolids", name) + (f".{rest}" if rest else "")
    if canonical == target:
        return None
    py = env.get_domain("py")
    return py.resolve_xref(
        env, node["refdoc"], app.builder, node["reftype"], canonical, node, contnode
    )


def setup(app) -> None:
    """Write the API pages before Sphinx reads the sources; read docstrings as written."""
    app.connect("builder-inited", write_api_pages, priority=100)
    app.connect("autodoc-process-docstring", plain_docstrings)
    app.connect("missing-reference", resolve_top_level)
