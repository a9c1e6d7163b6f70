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
compile_settings.share_cache(os.environ["QUICKNAV_TEST_CACHE"])
# FastAPI's TestClient sends Host: testserver; the API answers only the names it trusts
os.environ.setdefault("QUICKNAV_ALLOWED_HOSTS", "testserver,localhost,127.0.0.1,::1")
# a train job's policy export costs a worker process ~15 s the first time (jax2onnx); the tests of
# the export set it back on (the journeys run `quicknav serve` as a user does: on by default)
os.environ.setdefault("QUICKNAV_EXPORT_POLICIES", "false")


def _suites(config) -> tuple[bool, bool]:
    """Which of README's suites this run selects: (the fast one, the slow one)."""
    markexpr = config.getoption("markexpr", "").replace(" ", "")
    return {"slow": (False, True), "notslow": (True, False)}.get(markexpr, (True, True))


def pytest_xdist_auto_num_workers(config):
    """``-n auto`` (pyproject's addopts): one xdist worker more than this machine's cores for a run
    that holds the fast suite, whose tests wait on servers, browsers and subprocesses (on 2 cores
    with two workers the cores stood idle 13 % of its run; a third worker took it from 441-457 s
    to 406 s, 2-core AMD EPYC VM), one per core for the slow suite alone, whose tests are
    processes that keep the cores busy themselves (a third worker there gave nothing: 503 -> 518
    s). ``--maxprocesses`` still caps it; PYTEST_XDIST_AUTO_NUM_WORKERS overrides it, as xdist's
    own rule does."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None  # xdist's own rule reads it
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    fast, _ = _suites(config)
    return cores + 1 if fast else cores


# Seconds each long module keeps one xdist worker busy, (in the fast suite, in the slow suite), as
# measured on a 2-core AMD EPYC VM (2026-11-28, per-test wall time summed per module). Only the
# order in which modules are handed out reads them: a module not listed here, or listed with old
# figures, still runs; a listed path that no longer exists fails tests/test_layout.py.
MODULE_SECONDS: dict[str, tuple[int, int]] = {
    "tests/service/test_web_browser.py": (165, 0),  # the demo trained, a browser, live jobs
    "tests/journeys/test_building_journey.py": (0, 130),  # the building policy trained, the journey
    "tests/core/train/test_memory_admission.py": (1, 130),  # six measured processes
    "tests/journeys/test_readme_journeys.py": (22, 125),  # README walked
    "tests/core/train/test_train.py": (76, 25),
    "tests/service/test_maps.py": (56, 0),
    "tests/core/test_export.py": (54, 0),
    "tests/service/test_schemathesis_run.py": (49, 0),  # two tests: last by their count alone
    "tests/service/test_jobs_on_s3.py": (46, 20),
    "tests/core/env/test_room_sources.py": (45, 0),
    "tests/core/train/test_probes.py": (44, 0),
    "tests/core/networks/test_networks.py": (43, 0),
    "tests/service/test_worker_capabilities.py": (0, 40),
    "tests/service/test_web_maps_browser.py": (0, 40),
    "tests/core/env/test_randomize.py": (40, 0),
    "tests/service/test_faults.py": (38, 30),
    "tests/core/eval/test_evaluate.py": (37, 17),
    "tests/core/env/test_rooms.py": (33, 0),
    "tests/core/test_sweep.py": (33, 13),
    "tests/service/test_api.py": (26, 0),
    "tests/core/env/test_wide_robot.py": (26, 0),
    "tests/core/env/test_lidar.py": (23, 0),
    "tests/core/eval/test_robustness.py": (23, 0),
    "tests/core/env/test_plan.py": (23, 0),
    "tests/service/test_sweep_jobs.py": (22, 0),
    "tests/service/test_worker_crash.py": (0, 21),
    "tests/benchmarks/test_numba_reference.py": (21, 0),
    "tests/core/train/test_data_parallel.py": (21, 0),
    "tests/clients/test_onnx_policy.py": (0, 20),
    "tests/core/eval/test_shield.py": (19, 0),
    "tests/core/train/test_curriculum.py": (18, 0),
    "tests/service/test_serve_cli.py": (18, 0),
}


def pytest_collection_modifyitems(config, items):
    """The order xdist hands out modules (``--dist loadfile``, whole modules to a worker): longest
    first by ``MODULE_SECONDS`` for the suites this run selects, then the rest by their number of
    tests. xdist's own order (by the number of tests alone) handed out a two-test module of 49 s
    near the end, and one worker ran it and another 18 s module while the others stood idle."""
    fast, slow = _suites(config)
    modules: dict[str, list] = {}
    for item in items:
        modules.setdefault(item.nodeid.split("::", 1)[0], []).append(item)

    def order(path: str) -> tuple[int, int]:
        seconds = MODULE_SECONDS.get(path, (0, 0))
        expected = fast * seconds[0] + slow * seconds[1]
        return (0, -expected) if expected else (1, -len(modules[path]))

    items[:] = [item for path in sorted(modules, key=order) for item in modules[path]]


@pytest.fixture
def optimized():
    """This test's programs compile with every optimisation, as a user's do: for a test that runs
    far more than it compiles (an oracle driving a hundred episodes), or that holds two programs to
    the same bits as users run them. The in-memory caches of compiled programs are emptied first:
    a program this worker compiled at -O0 for an earlier test is compiled again (or loaded from the
    persistent cache, keyed by its settings), not reused."""
    jax.clear_caches()
    jax.config.update("jax_disable_most_optimizations", False)
    yield
    jax.config.update("jax_disable_most_optimizations", True)


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
