"""QuickNav: room navigation for reinforcement learning in pure JAX."""

from importlib.metadata import PackageNotFoundError, version

from quicknav_core.deferred_imports import defer_unused_imports

# before any dependency imports them (see deferred_imports)
defer_unused_imports()

try:
    # one source for the version: pyproject.toml's `version`, as installed
    __version__ = version("quicknav")
except PackageNotFoundError:  # a source tree on sys.path without the package installed
    __version__ = "0+unknown"

__all__ = ["__version__"]
