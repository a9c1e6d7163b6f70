"""Shared fixtures: small environments built once per session (JAX compile time dominates on CPU).

One cache folder serves the whole test run (``QUICKNAV_TEST_CACHE``): JAX's persistent compilation
cache and the demo policy trained once (``tests/trained.py``). ``.ci/run`` makes one, empty, for the
CI run, so both suites and every xdist worker share it; without it, the first pytest process makes
one (its xdist workers inherit it) and removes it when it ends. A program compiled once (by a test,
a CLI command, a worker subprocess) is loaded, not compiled again, when another test builds it.
The test processes compile with XLA's CPU optimisations mostly off (``tests/compile_settings.py``);
a test that runs far more than it compiles takes the ``optimized`` fixture.
"""

from __future__ import annotations

import atexit
import gc
import json
import os
import shutil
import tempfile

import jax
import pytest

from quicknav_core.config import EnvConfig
from tests import compile_settings

# compile quickly (see tests/compile_settings.py): this process and every process it starts
compile_settings.install()

if "QUICKNAV_TEST_CACHE" not in os.environ:  # this process owns the run's folder: it removes it
    os.environ["QUICKNAV_TEST_CACHE"] = tempfile.mkdtemp(prefix="quicknav-tests-")
    atexit.register(shutil.rmtree, os.environ["QUICKNAV_TEST_CACHE"], ignore_errors=True)
_CACHE = os.path.join(os.environ["QUICKNAV_TEST_CACHE"], "jax")
os.makedirs(_CACHE, exist_ok=True)
# this process and every subprocess a test starts (workers, `quicknav serve`); the CLI's own cache
# setting reads QUICKNAV_JAX_CACHE, so CLI commands run by tests use the same folder
os.environ["JAX_COMPILATION_CACHE_DIR"] = _CACHE
os.environ["QUICKNAV_JAX_CACHE"] = _CACHE
jax.config.update("jax_compilation_cache_dir", _CACHE)
# every program, the smallest too: the test run starts hundreds of processes (CLI commands,
# workers, servers) that compile the same initialisers and helpers, and a cached one loads in
# milliseconds. `quicknav export` of the demo run, warm, on a 2-core AMD EPYC VM: 8.6 s with the
# programs under 0.1 s compiled again (179 of them, 5.6 s of XLA), 5.8 s with all of them cached
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
# FastAPI's TestClient sends Host: testserver; the API answers only the names it trusts
os.environ.setdefault("QUICKNAV_ALLOWED_HOSTS", "testserver,localhost,127.0.0.1,::1")
# a train job's policy export costs a worker process ~15 s the first time (jax2onnx); the tests of
# the export set it back on (the journeys run `quicknav serve` as a user does: on by default)
os.environ.setdefault("QUICKNAV_EXPORT_POLICIES", "false")


def pytest_xdist_auto_num_workers(config):
    """``-n auto`` (pyproject's addopts): one xdist worker more than this machine's cores for a run
    that holds the fast suite, whose tests wait on servers, browsers and subprocesses (on 2 cores
    with two workers the cores stood idle 13 % of its run; a third worker took it from 441-457 s
    to 406 s, 2-core AMD EPYC VM; a fourth lost time: 410 -> 445 s, 2-core Intel Xeon VM), one per
    core for the slow suite alone, whose tests are processes that keep the cores busy themselves
    (a third worker there gave nothing: 503 -> 518 s). ``--maxprocesses`` still caps it;
    PYTEST_XDIST_AUTO_NUM_WORKERS overrides it, as xdist's own rule does."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None  # xdist's own rule reads it
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    slow_only = config.getoption("markexpr", "").replace(" ", "") == "slow"
    return cores if slow_only else cores + 1


@pytest.hookimpl(trylast=True)  # after `-m` has deselected: only this run's tests count
def pytest_collection_modifyitems(items):
    """The order xdist hands out modules (``--dist loadfile``: a module's tests of this run are one
    unit, given to the next worker that is nearly idle): the longest first, by the wall seconds
    ``tests/module_seconds.json`` recorded for each module's tests of each suite (a module with slow
    and fast tests in one run counts both), so that no long module starts last and keeps one
    worker busy while the others have nothing left. A module the file does not know goes first (it
    may be long). Refresh the file after a change that moves a module's time a lot:
    ``uv run pytest -p tests.cpu_profile`` for both suites into one ``QUICKNAV_CPU_PROFILE`` folder,
    then ``uv run python -m tests.cpu_profile FOLDER``."""
    from tests.cpu_profile import MODULE_SECONDS

    recorded = json.loads(MODULE_SECONDS.read_text())
    modules: dict[str, list] = {}
    for item in items:
        modules.setdefault(item.nodeid.split("::", 1)[0], []).append(item)

    def order(name: str) -> tuple[int, float]:
        suites = {"slow" if i.get_closest_marker("slow") else "fast" for i in modules[name]}
        seconds = [recorded[suite].get(name) for suite in suites]
        return (1, -sum(seconds)) if None not in seconds else (0, 0.0)

    items[:] = [item for name in sorted(modules, key=order) for item in modules[name]]


def pytest_collection_finish(session):
    """Python's cyclic garbage collector, set for a process that traces thousands of programs: the
    ~200,000 objects its imports made (JAX, flax, the project, the tests) are frozen out of every
    later collection, and a collection starts after 10,000 new objects rather than 700. JAX's
    tracing makes objects by the million, and each full collection walked the whole heap: on
    tests/core (458 tests, three xdist workers, 2-core AMD EPYC VM) the collector took 24.6 CPU-s,
    9.8 so set, and its full collections fell from 20-23 to 9 per worker."""
    gc.collect()
    gc.freeze()
    gc.set_threshold(10_000, 10, 10)


@pytest.fixture
def optimized():
    """This test's programs compile with every optimisation, as a user's do
    (``compile_settings.optimized``): for a test that runs far more than it compiles (an oracle
    driving a hundred episodes), or that holds two programs to the same bits as users run them. A
    module fixture of that kind uses ``compile_settings.optimized()`` itself."""
    with compile_settings.optimized():
        yield


@pytest.fixture(scope="session")
def trained_demo_run():
    """The demo preset's run folder, trained once per test run and shared (``tests/trained.py``)."""
    from tests.trained import trained_demo

    return trained_demo()


@pytest.fixture(scope="session")
def trained_building_run():
    """The building preset trained once per test run on a smaller budget (``tests/trained.py``)."""
    from tests.trained import trained_building

    return trained_building()


@pytest.fixture(scope="session")
def runtime():
    """The test session's Runtime: room banks and compiled programs shared by the tests that take it."""
    from quicknav_core.runtime import Runtime

    return Runtime()


@pytest.fixture(scope="session")
def small_config() -> EnvConfig:
    """An 8x8 room, 8 beams, small banks: fast to compile, still has corridors and corners."""
    return EnvConfig(grid_size=8, lidar_beams=8, train_rooms=64, test_rooms=32)


@pytest.fixture(scope="session")
def small_env(small_config):
    return small_config.build("train")


@pytest.fixture(scope="session")
def default_config() -> EnvConfig:
    """The paper's setting (grid 16, 16 beams) with a smaller train bank."""
    return EnvConfig(train_rooms=128, test_rooms=64)


@pytest.fixture(scope="session")
def default_env(default_config):
    return default_config.build("train")


@pytest.fixture(scope="session")
def s3_server(tmp_path_factory):
    """A real S3 server (SeaweedFS) on loopback ports for this test process; tests that take it
    down (an outage) start it again before they end."""
    from tests.s3_server import S3Server

    server = S3Server(tmp_path_factory.mktemp("seaweedfs")).start()
    yield server
    server.stop()


@pytest.fixture
def s3_env(s3_server, monkeypatch):
    """This process reaches the test S3 server through the usual AWS_* variables; returns the
    server (``s3_server.url()`` gives a fresh prefix in its bucket)."""
    for name, value in s3_server.env().items():
        monkeypatch.setenv(name, value)
    return s3_server
