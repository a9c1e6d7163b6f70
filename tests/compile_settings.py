"""How the test run's processes compile: quickly, since most tests compile far more than they run.

A test builds a program, runs it a few steps and checks the result; on 2 CPU cores XLA's compile,
not the run, is most of its time. So the test processes, and what they start (CLI commands, workers,
servers), compile with XLA's CPU optimisations mostly off (``JAX_DISABLE_MOST_OPTIMIZATIONS``: LLVM
at -O0) and without XLA's newer CPU fusion emitters: the GTrXL equality test's compile falls from
19 to 11 s, its programs run the same numbers to float rounding. They also compile each program's
machine code in one piece (``--xla_cpu_parallel_codegen_split_count=1``): XLA splits it for its
threads by default, which on a run whose processes already keep both cores busy only adds work
(the networks and randomisation tests: 42.0 and 41.6 CPU-s split, 37.7 and 39.3 in one piece,
2-core Intel Xeon VM; a user's -O3 compile of the demo training gained nothing, so it stays as
is). Programs compiled so run slower (the demo training takes 42 s instead of 28), so what mostly
runs keeps a user's settings:

- the trainings that reach a target (``tests/trained.py``), memory admission's measured processes
  (a worker's peak is what it measures) and README's journeys (run as a user runs them) start
  their processes with ``as_a_user_runs()``;
- a test that runs much more than it compiles, in this process, takes the ``optimized`` fixture
  (``tests/conftest.py``), a module fixture uses ``optimized()`` below: its programs compile with
  every optimisation, as a user's would (measure a change with ``tests/cpu_profile.py``: for the
  robustness levels the compiles cost more than the run saved).

JAX's persistent cache keys on both settings, so one cache folder holds both kinds of program.
"""

from __future__ import annotations

import contextlib
import os

# the user's own XLA_FLAGS, kept for the processes that run as a user does
USER_XLA_FLAGS = "QUICKNAV_TEST_USER_XLA_FLAGS"
QUICK_XLA_FLAGS = "--xla_cpu_use_fusion_emitters=false --xla_cpu_parallel_codegen_split_count=1"
QUICK_JAX = "JAX_DISABLE_MOST_OPTIMIZATIONS"


def install() -> None:
    """Compile quickly in this process and every process it starts (their environment inherits
    it); the first pytest process records the user's XLA_FLAGS. Call before JAX's CPU backend
    starts."""
    import jax

    user = os.environ.setdefault(USER_XLA_FLAGS, os.environ.get("XLA_FLAGS", ""))
    os.environ["XLA_FLAGS"] = f"{user} {QUICK_XLA_FLAGS}".strip()
    os.environ[QUICK_JAX] = "1"
    jax.config.update("jax_disable_most_optimizations", True)  # read when jax was imported


@contextlib.contextmanager
def optimized():
    """Compile with every optimisation, as a user's process does, inside the block: for work that
    runs far more than it compiles (an oracle driving a hundred episodes). The in-memory caches of
    compiled programs are emptied first, so that a program compiled at -O0 for an earlier test is
    compiled again (or loaded from the persistent cache, which keys on the settings), not reused;
    the test run's quick settings come back when the block ends."""
    import jax

    jax.clear_caches()
    jax.config.update("jax_disable_most_optimizations", False)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", True)


def as_a_user_runs() -> dict[str, str]:
    """This process's environment with the compile settings a user has: their own XLA_FLAGS,
    every optimisation on."""
    out = {k: v for k, v in os.environ.items() if k not in (QUICK_JAX, "XLA_FLAGS")}
    if os.environ.get(USER_XLA_FLAGS):
        out["XLA_FLAGS"] = os.environ[USER_XLA_FLAGS]
    return out


def with_cpu_devices(count: int) -> dict[str, str]:
    """This process's environment for a process whose JAX has ``count`` CPU devices, the quick
    compile settings kept."""
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={count}"
    return {**os.environ, "XLA_FLAGS": flags.strip()}
