"""A sweep's study opens in ``optuna-dashboard`` as the docs say (it is a dev dependency: ``uv run
optuna-dashboard STORAGE``): the SQLite ``study.db`` of a sweep folder and a study in Optuna's
journal on Redis (``--storage redis://...``). The studies are made by QuickNav's own storage and
study code with hand-told trials (no training); the dashboard runs as the real program and is asked
over HTTP for the studies it sees."""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

import httpx
import pytest
import redis

from quicknav_core.config import resolve_sweep
from quicknav_core.sweep import make_storage, open_study
from tests.processes import LoggedProcess
from tests.service.conftest import free_port

REDIS_URL = "redis://127.0.0.1:6379/11"  # this file's own DB index


def dashboard_program() -> str:
    found = Path(sys.executable).parent / "optuna-dashboard"
    assert found.exists() or shutil.which("optuna-dashboard"), (
        "optuna-dashboard is not installed: `uv sync` installs it (dev group)")  # fmt: skip
    return str(found) if found.exists() else shutil.which("optuna-dashboard")


def studies_seen(storage_url: str) -> list[dict]:
    port = free_port()
    proc = LoggedProcess([dashboard_program(), storage_url, "--port", str(port), "--quiet"])
    try:
        deadline = time.time() + 60
        while True:
            try:
                r = httpx.get(f"http://127.0.0.1:{port}/api/studies", timeout=2)
                if r.status_code == 200:
                    return r.json()["study_summaries"]
            except httpx.HTTPError:
                pass
            assert proc.poll() is None and time.time() < deadline, proc.output()
            time.sleep(0.3)
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def tell_two_trials(cfg, storage) -> None:
    study = open_study(cfg, storage)
    for value in (0.5, 0.75):
        trial = study.ask()
        trial.suggest_float("algorithm.learning_rate", 1e-4, 1e-2, log=True)
        study.tell(trial, value)


def test_dashboard__opens_a_sweep_folders_sqlite_study(tmp_path):
    cfg = resolve_sweep({"space": "ppo"})
    tell_two_trials(cfg, make_storage(cfg, tmp_path))
    seen = studies_seen(f"sqlite:///{tmp_path / 'study.db'}")
    assert [(s["study_name"], s.get("n_trials", 2)) for s in seen] == [(cfg.study_name, 2)], seen


def test_dashboard__opens_a_study_in_the_redis_journal(tmp_path):
    client = redis.Redis.from_url(REDIS_URL)
    try:
        client.ping()
    except redis.ConnectionError:
        pytest.fail(f"no Redis on {REDIS_URL}: start `redis-server` (CI has one)")
    client.flushdb()
    try:
        cfg = resolve_sweep({"space": "lstm", "overrides": {"storage": REDIS_URL}})
        tell_two_trials(cfg, make_storage(cfg, tmp_path))
        assert [s["study_name"] for s in studies_seen(REDIS_URL)] == [cfg.study_name]
    finally:
        client.flushdb()
