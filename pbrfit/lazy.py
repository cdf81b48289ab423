"""Submodules imported on first access (PEP 562 module ``__getattr__``), so that importing a
package runs none of its modules: ``import pbrfit.physics`` loads no JAX, and
``pbrfit.physics.brdf`` still finds its module."""

from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType
from typing import Callable, Iterable

__all__ = ["submodules_on_access"]


def submodules_on_access(package: str, path: Iterable[str]) -> Callable[[str], ModuleType]:
    """The module-level ``__getattr__`` of `package` (whose ``__path__`` is `path`): a name
    that is one of its modules or subpackages is imported on first access (the import binds it
    in the package, so later accesses do not come here); any other name is an AttributeError,
    as without it."""
    names = frozenset(m.name for m in pkgutil.iter_modules(path))

    def __getattr__(name: str) -> ModuleType:
        if name in names:
            return importlib.import_module(f"{package}.{name}")
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__
