"""Defer the imports QuickNav's dependencies make but QuickNav never uses.

gymnax's package import (which rejax and QuickNav's env need, for ``Environment`` and ``spaces``)
imports every environment it ships, and its Pong imports seaborn at module level, for rendering
Pong frames. seaborn pulls in pandas and ``scipy.stats``: together about 0.9 s of every process that
builds an env or a trainer (measured on a 2-core AMD EPYC VM: 0.91 s of gymnax's 1.46 s), for a
module nothing in QuickNav calls.

``defer_unused_imports`` puts a stand-in for each such module into ``sys.modules`` before anything
imports it. ``import seaborn`` then binds the stand-in, and its first attribute access imports the
real module (which replaces the stand-in in ``sys.modules``) and answers from it: a user's own
``seaborn.lineplot(...)`` in the same process works as before, only the cost moves to where it is
used. A module already imported, or not installed, is left alone. (The standard library's
``importlib.util.LazyLoader`` does not help here: on Python 3.11 the import statement itself reads
the module's ``__spec__``, which loads it.)
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import threading
import types

__all__ = ["DEFERRED_MODULES", "DeferredModule", "defer_unused_imports"]

# imported at module level by a dependency, never used by QuickNav
DEFERRED_MODULES = ("seaborn",)


class DeferredModule(types.ModuleType):
    """A stand-in for a top-level module that imports the real one on its first attribute access."""

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


def defer_unused_imports(names: tuple[str, ...] = DEFERRED_MODULES) -> list[str]:
    """Put a ``DeferredModule`` for each top-level module in ``names`` into ``sys.modules``;
    returns those deferred by this call (not those already imported or deferred, nor those not
    installed)."""
    deferred = []
    for name in names:
        if name in sys.modules:
            continue
        spec = importlib.util.find_spec(name)
        if spec is None:
            continue
        sys.modules[name] = DeferredModule(spec)
        deferred.append(name)
    return deferred
