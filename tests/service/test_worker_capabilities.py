"""Workers take only what they can run: two real worker processes, one with one XLA CPU device and
one with two, on each store. A two-device job waits, saying why, while only the first is up, and
goes to the second every time; the first keeps running one-device jobs."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
import redis

from quicknav_core.config import apply_overrides, get_preset
from quicknav_service.jobs.models import JobStatus
from quicknav_service.jobs.redis_store import RedisJobStore
from quicknav_service.jobs.sqlite_store import SQLiteJobStore
from tests.compile_settings import with_cpu_devices
from tests.processes import LoggedProcess
from tests.service.conftest import LiveServer

REDIS_URL = "redis://127.0.0.1:6379/9"  # this test's own DB index


def _config(devices: int) -> dict:
    cfg = apply_overrides(get_preset("demo"), [
        "env.grid_size=8", "env.train_rooms=16", "env.test_rooms=8", "num_envs=16",
        "algorithm.num_steps=16", "algorithm.num_minibatches=2", "total_steps=1024",
        "chunk_steps=512", f"devices={devices}",
    ])  # fmt: skip
    return cfg.model_dump(mode="json")


def _worker(data: Path, devices: int, redis_url: str | None) -> subprocess.Popen:
    env = {**with_cpu_devices(devices), "QUICKNAV_DATA_DIR": str(data), "QUICKNAV_LEASE_S": "10",
           "QUICKNAV_HEARTBEAT_S": "1"}  # fmt: skip
    env.pop("QUICKNAV_REDIS_URL", None)
    if redis_url:
        env["QUICKNAV_REDIS_URL"] = redis_url
    return LoggedProcess([sys.executable, "-m", "quicknav_cli", "worker"], env=env)


def _wait(pred, what: str, procs, timeout: float = 180):
    deadline = time.time() + timeout
    while time.time() < deadline:
        if pred():
            return
        for p in procs:
            assert p.poll() is None, f"a worker exited: {p.output()}"
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.slow  # two worker processes start JAX and train three tiny jobs: ~70 s per store
@pytest.mark.parametrize("backend", ["sqlite", "redis"])
def test_workers__a_two_device_job_waits_for_and_goes_to_the_two_device_worker(tmp_path, backend):
    data = tmp_path / "data"
    data.mkdir()
    if backend == "redis":
        redis.Redis.from_url(REDIS_URL).flushdb()
        store = RedisJobStore(REDIS_URL, prefix="quicknav")
    else:
        store = SQLiteJobStore(data / "jobs.db")
    redis_url = REDIS_URL if backend == "redis" else None
    procs: list[subprocess.Popen] = []
    try:
        with LiveServer(tmp_path, store=store, data_dir=data) as api:
            wide = [store.submit("train", {"n": i}, _config(2))[0] for i in range(2)]
            narrow, _ = store.submit("train", {"n": "narrow"}, _config(1))
            procs.append(_worker(data, 1, redis_url))
            _wait(lambda: store.get(narrow.id).status == JobStatus.succeeded, "the one-device job", procs)
            time.sleep(2.0)  # a chance to take what it must not
            for job in wide:
                shown = httpx.get(f"{api.url}/jobs/{job.id}").json()
                assert shown["status"] == "queued", shown
                assert shown["waiting"].startswith(
                    "waiting for a worker with 2 devices; the 1 live worker has 1 device"
                ), shown["waiting"]
            listed = httpx.get(f"{api.url}/jobs", params={"status": "queued"}).json()["data"]
            assert {j["id"] for j in listed} == {j.id for j in wide} and all(j["waiting"] for j in listed)

            procs.append(_worker(data, 2, redis_url))
            _wait(lambda: all(store.get(j.id).status.finished for j in wide), "the two-device jobs", procs)
            workers = {w["worker"]: w for w in store.live_workers()}
            assert sorted(w["devices"] for w in workers.values()) == [1, 2]
            two = next(name for name, w in workers.items() if w["devices"] == 2)
            for job in wide:
                done = store.get(job.id)
                assert done.status == JobStatus.succeeded, done.error
                assert done.worker == two  # every time
                assert httpx.get(f"{api.url}/jobs/{job.id}").json()["waiting"] is None
            assert store.get(narrow.id).worker != two
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
        if backend == "redis":
            redis.Redis.from_url(REDIS_URL).flushdb()
