"""Sphinx configuration of the diffsolids documentation (``make docs``).

The API pages are written at build time from the ``__all__`` lists of the package and its
modules (``docs/api/``, not in git), so that every public name is documented and a new one
needs no edit here; so are the plots of the optimisation logs (``docs/api/figures/``). No
network access: no intersphinx.
"""

import importlib
import inspect
import re
import sys
import tomllib
from pathlib import Path

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS.parent / "src"))
sys.path.insert(0, str(DOCS))  # concept_figures

import diffsolids  # noqa: E402  (loads the MPI of the DOLFINx wheel before dolfinx)

project = "diffsolids"
author = "the diffsolids authors"
copyright = "2026, the diffsolids authors"
with open(DOCS.parent / "pyproject.toml", "rb") as f:
    release = tomllib.load(f)["project"]["version"]

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build", "examples/output*", "**/README.md"]
myst_enable_extensions = ["colon_fence", "deflist"]
myst_heading_anchors = 3

# untagged code blocks are program output, not Python
highlight_language = "text"
html_theme = "furo"
html_title = "diffsolids"
html_static_path = ["_static"]
html_css_files = ["custom.css"]

# Google-style docstrings (the project's convention)
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
# "Attributes:" sections as fields: a dataclass documents its fields once, as members
napoleon_use_ivar = True
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
# types of the documented arguments only: a dataclass documents its fields once, as attributes
# (not again as a list of its __init__ arguments without descriptions)
autodoc_typehints_description_target = "documented_params"
autodoc_typehints_format = "short"
autodoc_preserve_defaults = True
autosummary_generate = False
autosummary_ignore_module_all = False

# A broken cross-reference fails the build (-W). Names of other packages and of the standard
# library have no inventory here (no intersphinx: no network at build time): not checked.
nitpicky = True
nitpick_ignore_regex = [
    ("py:.*", r"(numpy|np|dolfinx|petsc4py|PETSc|ufl|mpi4py|MPI|scipy|basix|ipctk)(\..*)?"),
    ("py:.*", r"(checkpoint_schedules|h5py|matplotlib|tqdm)(\..*)?"),
    ("py:.*", r"(collections\.abc|typing|types|os|pathlib|abc|contextlib|enum)\..*"),
    ("py:class", r"diffsolids\.model\.model\.NumericTermT"),  # a TypeVar: "the term's own type"
]

# The modules whose ``__all__`` the reference documents, with the title of their page.
API_MODULES = {
    "diffsolids": "The one import: ``import diffsolids as ds``",
    "diffsolids.mesh": "Meshes and domains",
    "diffsolids.model": "Model: materials, terms, boundary conditions",
    "diffsolids.integrators": "Time integrators",
    "diffsolids.simulation": "Simulation and trajectories",
    "diffsolids.states": "Trajectories and the set-up of a step",
    "diffsolids.solvers": "Newton solver",
    "diffsolids.solvers.factor_store": "Factorisations kept for the adjoint",
    "diffsolids.solvers.linear_options": "Linear solvers of the Newton steps (LU or multigrid)",
    "diffsolids.contact": "Contact (IPC barrier and friction)",
    "diffsolids.polyfem.contact": "PolyFEM contact parameters",
    "diffsolids.contact.geometry.flat": "Flat regions of obstacles (convergent formulation)",
    "diffsolids.objectives": "Objectives",
    "diffsolids.controls": "Controls",
    "diffsolids.controls.maps": "Parameter maps",
    "diffsolids.reduced_functional": "Reduced functional",
    "diffsolids.adjoint": "Discrete adjoint",
    "diffsolids.verification": "Gradient checks",
    "diffsolids.optimize": "Optimisation, mesh motion, remeshing",
    "diffsolids.io": "Output, figures, logging",
    "diffsolids.io.expressions": "PolyFEM value expressions",
    "diffsolids.polyfem": "PolyFEM optimisation files (``python -m diffsolids.polyfem``)",
    "diffsolids.errors": "Errors",
    "diffsolids.parallel": "MPI helpers",
    "diffsolids.portability": "Portability (the ipctk CPU check)",
    "diffsolids.forms": "UFL forms (``diffsolids.forms``)",
    "diffsolids.forms.objectives": "UFL objective integrands",
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
        lines = [
            title,
            "=" * len(title),
            "",
            f".. py:module:: {module}",
            "",
            ".. currentmodule:: None",
            "",
            f"``{module}``",
            "",
        ]
        if first:
            lines += [first, ""]
        lines += [".. autosummary::", ""]
        if module == "diffsolids":
            lines += [f"   ~{_canonical(module, n)}" for n in names]
            lines += ["", "Each name links to its description on the page of its module."]
        else:
            lines += [f"   ~{module}.{n}" for n in names]
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
    for stale in api.glob("diffsolids*.rst"):  # pages of modules that moved or left the list
        if stale.stem not in API_MODULES:
            stale.unlink()


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


def _candidates(target: str, module: str | None, cls: str | None) -> list[str]:
    """Where a reference may be documented.

    A top-level name in its subpackage, a name of a module by the API module that lists it, a
    short name in the API module of the docstring's module (or of any module), an attribute of
    the class.
    """
    if target.startswith("diffsolids."):
        name, _, rest = target.removeprefix("diffsolids.").partition(".")
        if name in diffsolids.__all__:
            return [_canonical("diffsolids", name) + (f".{rest}" if rest else "")]
        prefix, _, last = target.rpartition(".")
        return [
            f"{api}.{last}"
            for api in API_MODULES
            if api.startswith(prefix) and last in importlib.import_module(api).__all__
        ]
    head = target.split(".")[0]
    found = []
    for api in sorted(API_MODULES, key=lambda m: not (module or "").startswith(m)):
        if api == "diffsolids":
            continue
        names = importlib.import_module(api).__all__
        if cls and cls in names and (module or "").startswith(api):
            found.append(f"{api}.{cls}.{target}")
        if head in names:
            found.append(f"{api}.{target}")
    return found


def resolve_short_names(app, env, node, contnode):
    """Resolve references the way the docstrings write them (see :func:`_candidates`)."""
    if node.get("refdomain") != "py":
        return None
    target = node.get("reftarget", "").lstrip(".~")
    py = env.get_domain("py")
    for candidate in _candidates(target, node.get("py:module"), node.get("py:class")):
        if candidate == target:
            continue
        ref = py.resolve_xref(
            env, node["refdoc"], app.builder, node["reftype"], candidate, node, contnode
        )
        if ref is not None:
            return ref
    if target.rpartition(".")[2].startswith("_") or _undocumented_member(node, target):
        return contnode  # private, or an attribute without a docstring: shown as code
    return None


def _undocumented_member(node, target: str) -> bool:
    """Does a member reference name an existing attribute of the docstring's class?"""
    module, cls = node.get("py:module"), node.get("py:class")
    if node.get("reftype") not in ("attr", "meth") or not (module and cls) or "." in target:
        return False
    owner = importlib.import_module(module)
    for part in cls.split("."):
        owner = getattr(owner, part, None)
    if owner is None:
        return False
    if hasattr(owner, target):
        return True
    init = getattr(owner, "__init__", None)
    try:
        return f"self.{target}" in inspect.getsource(init)
    except (OSError, TypeError):
        return False


def _documented() -> set[int]:
    """Ids of the objects the API pages document."""
    return {
        id(getattr(mod, n))
        for mod in map(importlib.import_module, API_MODULES)
        for n in mod.__all__
        if hasattr(mod, n)
    }


def public_bases(app, name, obj, options, bases) -> None:
    """Show a class's documented bases: an internal base (``_DensityTerm``) by its bases."""
    documented = _documented()
    i = 0
    while i < len(bases):
        base = bases[i]
        internal = base.__module__.startswith("diffsolids") and id(base) not in documented
        if internal:
            bases[i : i + 1] = [b for b in bases[i].__bases__ if b is not object]
        else:
            i += 1


_MARKER = re.compile(r"^\s*# \[[\w-]+\]\s*$")  # a literalinclude bound: # [optimise]


def strip_markers(app, doctree) -> None:
    """Drop the ``# [name]`` bounds inside an included piece of an example, and its end's blanks.

    ``:start-after:`` and ``:end-before:`` leave the bounds of the pieces in between in the
    text, ``:pyobject:`` the blank lines after a class.
    """
    from docutils import nodes

    for node in doctree.findall(nodes.literal_block):
        if not str(node.get("source", "")).startswith(str(DOCS / "examples")):
            continue
        text = node.astext()
        kept = "\n".join(s for s in text.split("\n") if not _MARKER.match(s)).rstrip() + "\n"
        if kept != text:
            node.rawsource = kept
            node[:] = [nodes.Text(kept)]


def write_figures(app) -> None:
    """Draw ``docs/concept_figures.py``'s figures and plot the optimisation logs.

    The logs ``docs/figures/*_log.csv`` become ``docs/api/figures/*.svg``.

    The data are in git (a few lines of text), the figures are not: they are drawn at each
    build by the library's own ``plot_log`` (matplotlib, a dependency of diffsolids).
    """
    from concept_figures import draw_all

    from diffsolids.optimize.monitor import plot_log, read_log

    out = DOCS / "api" / "figures"
    out.mkdir(parents=True, exist_ok=True)
    draw_all(out)  # the tutorial's scene, the barrier, the data flow
    for log in sorted((DOCS / "figures").glob("*_log.csv")):
        svg = out / f"{log.stem}.svg"
        if not svg.exists() or svg.stat().st_mtime < log.stat().st_mtime:
            plot_log(read_log(log), svg)


def setup(app) -> None:
    """Write the API pages and figures before Sphinx reads the sources; read docstrings."""
    app.connect("builder-inited", write_api_pages, priority=100)
    app.connect("builder-inited", write_figures, priority=100)
    app.connect("autodoc-process-docstring", plain_docstrings)
    app.connect("doctree-read", strip_markers)
    app.connect("missing-reference", resolve_short_names)
    app.connect("autodoc-process-bases", public_bases)
