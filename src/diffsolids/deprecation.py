"""Deprecated module paths: an old dotted path that still imports the moved module, and warns."""

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings
from collections.abc import Mapping

__all__ = ["ModuleAliases", "alias_modules"]


class ModuleAliases(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Import hook mapping old module paths to the modules that replace them.

    ``import old.path`` (or ``from old.path import name``) gives the new module itself (the same
    object as ``import new.path``) and issues a ``DeprecationWarning`` naming the new path and
    the version that removes the old one.
    """

    def __init__(self, moved: Mapping[str, str], removed_in: str) -> None:
        self.moved = dict(moved)
        self.removed_in = removed_in

    def find_spec(
        self, fullname: str, path: object = None, target: types.ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        """A spec for an old path (None for every other module)."""
        if fullname not in self.moved:
            return None
        return importlib.machinery.ModuleSpec(fullname, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        """The new module, imported, after the warning."""
        new = self.moved[spec.name]
        warnings.warn(
            f"{spec.name} moved to {new} (the old path goes in {self.removed_in})",
            DeprecationWarning,
            stacklevel=2,
        )
        return importlib.import_module(new)

    def exec_module(self, module: types.ModuleType) -> None:
        """Nothing to run: the new module is already executed."""


def alias_modules(moved: Mapping[str, str], removed_in: str) -> ModuleAliases:
    """Install a :class:`ModuleAliases` hook for ``moved`` (old path -> new path)."""
    hook = ModuleAliases(moved, removed_in)
    sys.meta_path.append(hook)
    return hook
