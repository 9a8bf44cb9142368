"""The package's layering: forms imports nothing of diffsolids, every module has a layer.

``make lint`` runs import-linter on the contracts in pyproject.toml (layers, no cycles); these
tests cover what it cannot see: ``forms/`` lives outside ``src/`` and a new module of
``diffsolids`` that no layer names would escape the contract.
"""

import ast
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _imported_modules(path: Path) -> list[str]:
    """Absolute names of every module a file imports (at any depth of its syntax tree)."""
    names = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path.name}: relative import"
            names.append(node.module or "")
            names.extend(f"{node.module}.{alias.name}" for alias in node.names)
    return names


@pytest.mark.parametrize("path", sorted((ROOT / "forms").glob("*.py")), ids=lambda p: p.name)
def test_forms_import_only_ufl_and_themselves(path: Path) -> None:
    """diffsolids.forms is pure UFL: no import of the rest of diffsolids, of dolfinx or PETSc."""
    for name in _imported_modules(path):
        top = name.split(".")[0]
        assert top not in ("dolfinx", "petsc4py", "mpi4py", "ipctk"), f"{path.name}: {name}"
        if top == "diffsolids":
            assert name.startswith("diffsolids.forms"), f"{path.name} imports {name}"


def _layers(contract: str = "layers") -> list[str]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    (layers,) = [c["layers"] for c in config["contracts"] if c["name"] == contract]
    return layers


def _children(package: Path) -> set[str]:
    children = {p.stem for p in package.glob("*.py") if p.stem != "__init__"}
    return children | {p.parent.name for p in package.glob("*/__init__.py")}


def test_every_module_has_a_layer() -> None:
    """Each module and subpackage directly under src/diffsolids is named by the layers contract."""
    children = _children(ROOT / "src" / "diffsolids")
    named = {layer.removeprefix("diffsolids.") for layer in _layers()}
    assert children - named == set()
    assert named - children == set()


def test_every_contact_module_has_a_layer() -> None:
    """Each module and subpackage of diffsolids.contact is named by the contact layers."""
    children = _children(ROOT / "src" / "diffsolids" / "contact")
    named = {m.strip() for layer in _layers("contact layers") for m in layer.split("|")}
    assert children - named == set()
    assert named - children == set()


def test_a_planted_upward_import_breaks_the_contract() -> None:
    """The contract can fail: errors importing the simulation is refused."""
    grimp = pytest.importorskip("grimp")
    from importlinter.contracts.layers import LayersContract  # noqa: F401  (installed with it)

    graph = grimp.build_graph("diffsolids")
    graph.add_import(importer="diffsolids.errors", imported="diffsolids.simulation")
    layers = _layers()
    chains = graph.find_illegal_dependencies_for_layers(layers=tuple(layers), containers=set())
    assert any(
        d.importer == "diffsolids.errors" and d.imported == "diffsolids.simulation" for d in chains
    )


# DOLFINx's own private names the package uses: the C++ object of a form or function, and the
# ghost update of a PETSc vector (dolfinx.la.petsc has no public equivalent in 0.11)
_FOREIGN_PRIVATE = {"_cpp_object", "_ghost_update"}


def _private_reach_ins(source: str) -> list[tuple[int, str]]:
    """(line, name) of private attributes read on other objects that this source never defines.

    A module may use the private members of its own classes on any instance (``other._x`` in
    the class that sets ``self._x``); a private name it does not define belongs to another
    module, and reading it there is reaching into that module's internals.
    """
    tree = ast.parse(source)
    defined = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.ClassDef):
            defined.add(node.name)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            defined.add(node.attr)
        elif isinstance(node, ast.AnnAssign | ast.Assign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            defined.update(t.id for t in targets if isinstance(t, ast.Name))
    hits = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute) or not node.attr.startswith("_"):
            continue
        if node.attr.startswith("__") or node.attr in _FOREIGN_PRIVATE:
            continue
        if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
            continue
        if node.attr not in defined:
            hits.append((node.lineno, f"{ast.unparse(node.value)}.{node.attr}"))
    return hits


def test_no_module_reads_another_modules_private_members() -> None:
    """The forward, the adjoint and the optimiser talk through public members only."""
    found = [
        f"{path.relative_to(ROOT)}:{line}: {name}"
        for path in sorted((ROOT / "src" / "diffsolids").rglob("*.py"))
        for line, name in _private_reach_ins(path.read_text())
    ]
    assert not found, "private members read across modules:\n" + "\n".join(found)


def test_a_planted_private_reach_in_is_found() -> None:
    """The check above flags a read of another class's private member, not one of its own."""
    planted = "def f(solver):\n    return solver._work\n"
    assert _private_reach_ins(planted) == [(2, "solver._work")]
    own = (
        "class A:\n    def __init__(self):\n        self._w = 1\n"
        "    def g(self, o):\n        return o._w\n"
    )
    assert _private_reach_ins(own) == []


def _attribute_uses(source: str, name: str) -> list[int]:
    """Lines where an attribute ``name`` of an object other than self is read or set."""
    return [
        node.lineno
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.Attribute)
        and node.attr == name
        and not (isinstance(node.value, ast.Name) and node.value.id == "self")
    ]


def test_the_newton_solvers_petsc_objects_stay_in_the_solvers_package() -> None:
    """Outside diffsolids.solvers nobody drives the SNES or swaps the factor store of a
    NewtonSolver: they ask it (``last_factors``, ``keeping_factors_in``, ``reset``)."""
    solvers = ROOT / "src" / "diffsolids" / "solvers"
    found = []
    for path in sorted((ROOT / "src" / "diffsolids").rglob("*.py")):
        if solvers in path.parents:
            continue
        source = path.read_text()
        found += [f"{path.relative_to(ROOT)}:{n}: .snes" for n in _attribute_uses(source, "snes")]
        tree = ast.parse(source)
        found += [
            f"{path.relative_to(ROOT)}:{node.lineno}: factor_store assigned"
            for node in ast.walk(tree)
            if isinstance(node, ast.Attribute)
            and isinstance(node.ctx, ast.Store)
            and node.attr == "factor_store"
            and not (isinstance(node.value, ast.Name) and node.value.id == "self")
        ]
    assert not found, "\n".join(found)
    assert _attribute_uses("def f(s):\n    return s.snes.getKSP()\n", "snes") == [2]
