"""The demo policy, trained once per test run and shared by every test that needs "a trained job".

``trained_demo()`` runs README's own in-process command, ``quicknav train --preset demo``, into the
test run's cache folder (``QUICKNAV_TEST_CACHE``, see ``tests/conftest.py``) and exports its policy
with ``quicknav export``; a file lock makes the first caller of the run train it (any xdist worker,
the fast suite or the slow one) and every later caller read the same folder. The folder's name
holds a digest of the preset's resolved config, so a changed preset trains again.

``seed_trained_job(store, artifacts, run)`` puts that run into a service as a succeeded train job
(the store's own submit, claim and finish, the files copied into the job's artifact folder), so
browser and journey tests drive a policy that learned without training it again.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

from quicknav_core.config import resolve_train
from quicknav_core.layout import RunFolder
from tests.compile_settings import as_a_user_runs

DEMO_REQUEST = {"preset": "demo"}


def cache_root() -> Path:
    return Path(os.environ["QUICKNAV_TEST_CACHE"])


@contextmanager
def file_lock(path: Path):
    """An exclusive lock held across processes (xdist workers, the two suites)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _quicknav(*args: str, cwd: Path) -> None:
    # trained as a user's machine trains it: every XLA optimisation on (tests/compile_settings.py)
    done = subprocess.run([sys.executable, "-m", "quicknav_cli", *args], cwd=cwd, env=as_a_user_runs(),
                          capture_output=True, text=True, timeout=900)  # fmt: skip
    assert done.returncode == 0, f"quicknav {' '.join(args)} failed:\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}"


def trained_demo() -> Path:
    """The run folder of the demo preset trained by ``quicknav train --preset demo`` (README's
    command) with its exported policy, made once per test run."""
    config = resolve_train(DEMO_REQUEST)
    digest = hashlib.sha256(config.model_dump_json().encode()).hexdigest()[:12]
    home = cache_root() / "trained" / f"demo-{digest}"
    run = home / "runs" / f"demo-s{config.seed}"  # where README's command writes it
    with file_lock(home.with_suffix(".lock")):
        if not (home / "done").exists():
            shutil.rmtree(home, ignore_errors=True)
            home.mkdir(parents=True)
            _quicknav("train", "--preset", "demo", cwd=home)
            _quicknav("export", str(run), "--out", str(run), cwd=home)
            (home / "done").write_text(config.model_dump_json())
    assert RunFolder(run).checkpoint() is not None and RunFolder(run).policy.exists()
    return run


# README's building journey trains `--preset building` for 33.5M steps (11-35 min on 2 cores); the
# test run trains the same preset for this many, 2 of its chunks (a policy that has learned to
# follow the plan, not the finished one: the journey test asserts what this budget reaches; on a
# 2-core AMD EPYC VM with AVX-512, 20 % of the office's goals, return 64, against the untrained
# policy's 0 % and -132; 4 chunks, the test run's budget until 2026-11, reached 48 % and 108 in
# twice the time)
BUILDING_TEST_STEPS = 2_097_152


def trained_building() -> Path:
    """The building preset's run folder, trained once per test run for BUILDING_TEST_STEPS by
    ``quicknav train --preset building --total-steps N`` (README's command with a smaller budget)."""
    request = {"preset": "building", "overrides": {"total_steps": BUILDING_TEST_STEPS}}
    config = resolve_train(request)
    digest = hashlib.sha256(config.model_dump_json().encode()).hexdigest()[:12]
    home = cache_root() / "trained" / f"building-{digest}"
    run = home / "runs" / f"building-s{config.seed}"
    with file_lock(home.with_suffix(".lock")):
        if not (home / "done").exists():
            shutil.rmtree(home, ignore_errors=True)
            home.mkdir(parents=True)
            _quicknav("train", "--preset", "building", "--total-steps", str(BUILDING_TEST_STEPS), cwd=home)
            (home / "done").write_text(config.model_dump_json())
    assert RunFolder(run).checkpoint() is not None
    return run


def seed_trained_job(store, artifacts_dir: Path, run: Path, request: dict | None = None) -> str:
    """A succeeded train job in ``store`` whose artifacts (in the local ``artifacts_dir``) are
    ``run``'s: the store's own submit, claim and finish, as a worker would leave it."""
    from quicknav_core.config import TrainConfig
    from quicknav_service.jobs.models import JobKind, JobStatus

    folder = RunFolder(run)
    config = TrainConfig.model_validate_json(folder.config.read_text())
    job, _ = store.submit(JobKind.train, request or DEMO_REQUEST, config.model_dump(mode="json"))
    claimed = store.claim("test-seed", 600, can_run=lambda j: j.id == job.id)
    assert claimed is not None and claimed.id == job.id
    shutil.copytree(folder.path, Path(artifacts_dir) / job.id)
    meta = folder.meta()
    store.finish(job.id, "test-seed", JobStatus.succeeded,
                 result={"env_steps": meta.env_steps, "total_steps": config.total_steps,
                         "chunks_done": meta.chunk, "final": {}, "warnings": []})  # fmt: skip
    return job.id
