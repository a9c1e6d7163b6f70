"""JAX's persistent compilation cache, turned on in one place for the processes that want it (the
CLI's commands, the service's workers). Library code never turns it on by itself."""

from __future__ import annotations

import os
from pathlib import Path

# every program is worth a file, the smallest too: a command compiles a hundred or more small ones
# (initialisers, a checkpoint's template, helpers), each in milliseconds, and loads them faster
# than XLA compiles them. Warm, on a 2-core AMD EPYC VM: `quicknav eval RUN --episodes 100` of the
# demo 10.7 -> 7.6 s, `quicknav export RUN` 11.5 -> 5.8 s against caching programs of 0.5 s and
# more; the cache holds 1.7 MB after both instead of 0.4 MB
MIN_COMPILE_TIME_S = 0.0


def enable_compilation_cache(folder: Path | str | None) -> Path | None:
    """Cache compiled programs in ``folder`` (made if missing). ``JAX_COMPILATION_CACHE_DIR`` in
    the environment wins (an operator's shared cache, a test session's). Returns the folder in
    use; None when there is none (``folder`` None, or it cannot be made: no cache, never no run)."""
    import jax

    chosen = os.environ.get("JAX_COMPILATION_CACHE_DIR") or folder
    if not chosen:
        return None
    path = Path(chosen)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(path.resolve()))
    # an operator's (or a test run's) JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS wins, as JAX's own
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_S)
    return path
