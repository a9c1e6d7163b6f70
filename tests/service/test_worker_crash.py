"""Nothing accepted is lost: SIGTERM hands a job back, SIGKILL loses the lease, a live worker
reclaims the job and resumes it from its last checkpoint (Redis store, real worker processes)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import redis

from quicknav_core.config import apply_overrides, get_preset
from quicknav_service.jobs.models import JobStatus
from quicknav_service.jobs.redis_store import RedisJobStore
from tests.processes import LoggedProcess

REDIS_URL = "redis://127.0.0.1:6379/15"  # this test's own DB index


def _worker(tmp_path: Path, *args: str) -> subprocess.Popen:
    env = {**os.environ, "QUICKNAV_REDIS_URL": REDIS_URL, "QUICKNAV_DATA_DIR": str(tmp_path / "data"),
           "QUICKNAV_LEASE_S": "3", "QUICKNAV_HEARTBEAT_S": "0.5"}  # fmt: skip
    return LoggedProcess([sys.executable, "-m", "quicknav_cli", "worker", *args], env=env)


def _wait(pred, timeout=120, what="condition"):
    deadline = time.time() + timeout
    while time.time() < deadline:
        if pred():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.slow  # two worker processes compile and train: ~90 s on 2 cores
def test_sigterm_hands_back_sigkill_is_reclaimed_and_resumed(tmp_path):
    client = redis.Redis.from_url(REDIS_URL)
    client.ping()  # no Redis is a failure, not a skip
    client.flushdb()
    store = RedisJobStore(REDIS_URL)
    cfg = apply_overrides(get_preset("demo"), [
        "env.grid_size=8", "env.train_rooms=32", "env.test_rooms=16", "num_envs=16",
        "algorithm.num_steps=32", "algorithm.num_minibatches=4", "total_steps=20480", "chunk_steps=512",
    ])  # fmt: skip
    job, _ = store.submit("train", {"config": cfg.model_dump(mode="json")}, cfg.model_dump(mode="json"))
    ckpt_meta = tmp_path / "data" / "artifacts" / job.id / "checkpoint" / "meta.json"

    def chunks_done():
        return json.loads(ckpt_meta.read_text())["chunk"] if ckpt_meta.exists() else 0

    procs = []
    try:
        # 1. SIGTERM: the worker stops at a chunk boundary and hands the job back
        a = _worker(tmp_path)
        procs.append(a)
        _wait(lambda: chunks_done() >= 2, what="first checkpoints")
        a.send_signal(signal.SIGTERM)
        assert a.wait(60) == 0, a.output()
        job_a = store.get(job.id)
        assert job_a.status == JobStatus.queued and job_a.attempts == 0
        after_term = chunks_done()
        assert 2 <= after_term < 40

        # 2. SIGKILL: the next worker dies mid-job; its lease expires
        b = _worker(tmp_path)
        procs.append(b)
        _wait(lambda: chunks_done() >= after_term + 2, what="progress after resume")
        b.send_signal(signal.SIGKILL)
        b.wait(10)
        assert store.get(job.id).status == JobStatus.running  # still leased to the dead worker

        # 3. a live worker reclaims it after the lease and finishes from the last checkpoint
        c = _worker(tmp_path, "--burst")
        procs.append(c)
        assert c.wait(240) == 0, c.output()
        final = store.get(job.id)
        assert final.status == JobStatus.succeeded, final.error
        assert final.attempts == 2  # the graceful hand-back did not count, the crash did
        kinds = [e["type"] for _, e in store.events(job.id)]
        assert kinds.count("resumed") == 2 and kinds[-1] == "succeeded" and "requeued" in kinds
        rows = [
            json.loads(x)
            for x in (tmp_path / "data" / "artifacts" / job.id / "metrics.jsonl")
            .read_text()
            .splitlines()
        ]
        assert [r["chunk"] for r in rows] == list(range(1, 41)), "every chunk exactly once"
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
        client.flushdb()
