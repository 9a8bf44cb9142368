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
