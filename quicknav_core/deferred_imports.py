"""Defer the imports QuickNav's dependencies make but QuickNav never uses.

gymnax's package import (which rejax and QuickNav's env need, for ``Environment`` and ``spaces``)
imports every environment it ships, and its Pong imports seaborn at module level, for rendering
Pong frames. seaborn pulls in pandas and ``scipy.stats``: together about 0.9 s of every process that
builds an env or a trainer (measured on a 2-core AMD EPYC VM: 0.91 s of gymnax's 1.46 s), for a
module nothing in QuickNav calls. Its Catch imports ``matplotlib.pyplot`` the same way (0.3-0.4 s
of the 1.2 s that importing QuickNav's env took after seaborn was deferred); QuickNav draws with
pyplot only in its render modules, which import it when they draw.

``defer_unused_imports`` puts a stand-in for each such module into ``sys.modules`` before anything
imports it. ``import seaborn`` then binds the stand-in, and its first attribute access imports the
real module (which replaces the stand-in in ``sys.modules``) and answers from it: a user's own
``seaborn.lineplot(...)`` in the same process works as before, only the cost moves to where it is
used. A submodule (``matplotlib.pyplot``) is found without importing its package, and is bound
as the package's attribute when the package is imported, as the import system would bind it. A
module already imported, or not installed, is left alone. (The standard library's
``importlib.util.LazyLoader`` does not help here: on Python 3.11 the import statement itself reads
the module's ``__spec__``, which loads it.)
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import threading
import types

__all__ = ["DEFERRED_MODULES", "DeferredModule", "defer_unused_imports"]

# imported at module level by a dependency, never used by QuickNav
DEFERRED_MODULES = ("seaborn", "matplotlib.pyplot")


class DeferredModule(types.ModuleType):
    """A stand-in for a module that imports the real one on its first attribute access."""

    def __init__(self, spec: importlib.machinery.ModuleSpec):
        super().__init__(spec.name)
        self.__spec__ = spec  # the import system reads it (not initialising: it is "imported")
        self.__file__ = spec.origin
        self._deferred_lock = threading.Lock()
        self._deferred_real: types.ModuleType | None = None

    def _deferred_load(self) -> types.ModuleType:
        with self._deferred_lock:
            if self._deferred_real is None:
                name = self.__name__
                if sys.modules.get(name) is self:
                    del sys.modules[name]
                self._deferred_real = importlib.import_module(name)
        return self._deferred_real

    def __getattr__(self, attr: str):  # only for names the stand-in does not have itself
        return getattr(self._deferred_load(), attr)

    def __dir__(self) -> list[str]:
        return dir(self._deferred_load())

    def __repr__(self) -> str:
        return f"<deferred module {self.__name__!r}: imported on first use>"


def _find_spec(name: str) -> importlib.machinery.ModuleSpec | None:
    """``name``'s spec, without importing its package (``find_spec`` of a submodule would)."""
    parent, _, _ = name.rpartition(".")
    if not parent or parent in sys.modules:
        return importlib.util.find_spec(name)
    package = _find_spec(parent)
    if package is None or package.submodule_search_locations is None:
        return None
    return importlib.machinery.PathFinder.find_spec(name, list(package.submodule_search_locations))


class _BindWhenImported(importlib.abc.MetaPathFinder):
    """Binds a deferred submodule as its package's attribute once the package is imported (the
    import system binds a submodule only when it loads it, and ``import a.b; a.b.f()`` reads it).
    Finds nothing itself: it wraps the loader the other finders give for the package."""

    def __init__(self, package: str, child: str, stand_in: DeferredModule):
        self.package, self.child, self.stand_in = package, child, stand_in

    def find_spec(self, name, path=None, target=None):
        if name != self.package:
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            return spec
        loader, hook = spec.loader, self

        class _Loader(importlib.abc.Loader):
            def create_module(self, spec):
                return loader.create_module(spec)

            def exec_module(self, module):
                loader.exec_module(module)
                if sys.modules.get(f"{hook.package}.{hook.child}") is hook.stand_in:
                    setattr(module, hook.child, hook.stand_in)

        spec.loader = _Loader()
        return spec


def defer_unused_imports(names: tuple[str, ...] = DEFERRED_MODULES) -> list[str]:
    """Put a ``DeferredModule`` for each module in ``names`` into ``sys.modules``; returns those
    deferred by this call (not those already imported or deferred, nor those not installed)."""
    deferred = []
    for name in names:
        if name in sys.modules:
            continue
        spec = _find_spec(name)
        if spec is None:
            continue
        stand_in = sys.modules[name] = DeferredModule(spec)
        package, _, child = name.rpartition(".")
        if package in sys.modules:
            setattr(sys.modules[package], child, stand_in)
        elif package:
            sys.meta_path.insert(0, _BindWhenImported(package, child, stand_in))
        deferred.append(name)
    return deferred
