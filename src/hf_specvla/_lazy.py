"""Lazy package exports (PEP 562): a package names its public names and the submodule holding each, and a name's
submodule is imported on first access, so a job package (training, a comparison, a policy) loads its heavy parts
(accelerate, MuJoCo, matplotlib) only when a command uses them; and a hook that runs once another package's module
has been imported ([`when_imported`]), so the top package can register with transformers' Auto classes without
loading torch itself."""

from __future__ import annotations

import importlib
import importlib.abc
import sys
from collections.abc import Callable


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


def when_imported(module: str, callback: Callable[[], object]) -> None:
    """Calls ``callback()`` once ``module`` is imported: now if it already is, else as soon as the import that loads
    it has finished and no other module of its top package (``transformers`` for ``transformers.models.auto``) is
    still loading, so a callback that imports that package never meets one of its modules half-initialised.

    How: until then, a finder at the front of ``sys.meta_path`` hands out the top package's modules with a loader
    that counts the ones being executed (the module objects and their code are the usual ones)."""
    if module in sys.modules:
        callback()
    else:
        sys.meta_path.insert(0, _WhenImported(module, callback))


class _WhenImported(importlib.abc.MetaPathFinder):
    def __init__(self, module: str, callback: Callable[[], object]):
        self.module, self.callback = module, callback
        self.package = module.partition(".")[0]
        self.loading = 0  # modules of self.package being executed right now
        self.called = False

    def find_spec(self, fullname, path, target=None):
        if fullname.partition(".")[0] != self.package:
            return None
        for finder in sys.meta_path:  # the spec the finders after this one would give
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                if hasattr(spec.loader, "exec_module"):
                    spec.loader = _CountingLoader(spec.loader, self)
                return spec
        return None

    def finished_one(self) -> None:
        if self.loading or self.called or self.module not in sys.modules:
            return
        self.called = True
        if self in sys.meta_path:
            sys.meta_path.remove(self)
        self.callback()


class _CountingLoader:
    """``loader``, with [`_WhenImported`] told when a module starts and finishes executing; anything else
    (``get_source``, ``get_resource_reader``, ...) is ``loader``'s."""

    def __init__(self, loader, watcher: _WhenImported):
        self.loader, self.watcher = loader, watcher

    def create_module(self, spec):
        return self.loader.create_module(spec)

    def exec_module(self, module) -> None:
        self.watcher.loading += 1
        try:
            self.loader.exec_module(module)
        finally:
            self.watcher.loading -= 1
        self.watcher.finished_one()

    def __getattr__(self, name: str):
        if "loader" not in self.__dict__:  # half-built (copy, pickle): no recursion through self.loader
            raise AttributeError(name)
        return getattr(self.loader, name)
