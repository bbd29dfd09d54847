"""Lazy package exports (PEP 562): a package names its public names and the submodule holding each, and a name's
submodule is imported on first access, so a job package (training, a comparison, a policy) loads its heavy parts
(accelerate, MuJoCo, matplotlib) only when a command uses them."""

from __future__ import annotations

import importlib


def lazy_exports(package: str, exports: dict[str, tuple[str, ...]], module_globals: dict | None = None):
    """``(__getattr__, __dir__)`` for ``package``'s ``__init__``: ``exports`` maps a submodule (``".methods"``,
    relative to ``package``) to the names it provides; ``module_globals`` (the package's ``globals()``) are listed by
    ``dir`` too."""
    where = {name: module for module, names in exports.items() for name in names}

    def __getattr__(name: str):
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(where[name], package), name)

    def __dir__() -> list[str]:
        return sorted(set(where) | set(module_globals or ()))

    return __getattr__, __dir__
