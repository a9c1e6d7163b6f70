"""The job suite on an object store, the fleet's shape: Redis for the queue, a real S3 server
(SeaweedFS) for the artifacts, no shared folder. Train, evaluate, sweep and download through the
API; a job handed back by one machine resumes on another from the bucket's checkpoint; the store
going down mid-job is waited out, or fails the job with a reason naming the store.

Jobs run on worker threads here (each with its own data folder, as machines have); the test with
real worker processes and a SIGKILL is ``test_two_machines_resume_from_the_bucket`` (slow).
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time

import httpx
import pytest
import redis

from quicknav_core.train.run import checkpoint_dir
from quicknav_service.artifacts.s3 import S3Artifacts
from quicknav_service.jobs.models import JobKind, JobStatus
from quicknav_service.jobs.redis_store import RedisJobStore
from quicknav_service.settings import Settings
from quicknav_service.worker import Worker
from tests.processes import LoggedProcess
from tests.service.conftest import LiveServer
from tests.service.test_api import TINY, sse_events, submit_tiny, wait_status
from tests.service.test_sweep_jobs import sweep_config

REDIS_URL = "redis://127.0.0.1:6379/8"  # this file's own DB index


@pytest.fixture
def fleet(tmp_path, s3_env):
    """The API over Redis + S3; ``.machine(name)`` is a worker with its own data folder."""
    client = redis.Redis.from_url(REDIS_URL)
    client.ping()  # no Redis here is a failure, not a skip
    client.flushdb()
    url = s3_env.url()
    store = RedisJobStore(REDIS_URL)
    with LiveServer(tmp_path, store=store, data_dir=tmp_path / "api", redis_url=REDIS_URL,
                    artifacts_url=url, artifacts_retry_s=30) as live:  # fmt: skip
        live.bucket = S3Artifacts(url, tmp_path / "reader", retry_s=0)  # reads the bucket directly
        live.s3 = s3_env

        def machine(name: str, **kw) -> Worker:
            settings = Settings(_env_file=None, data_dir=tmp_path / name, redis_url=REDIS_URL,
                                artifacts_url=url, lease_s=5.0, heartbeat_s=0.5,
                                **{"artifacts_retry_s": 30, **kw})  # fmt: skip
            return Worker(store, settings, worker_id=name)

        live.machine = machine
        yield live
    client.flushdb()


class Hooked:
    """An artifact store that calls ``hook(chunk)`` after each checkpoint it publishes."""

    def __init__(self, inner, hook):
        self._inner, self._hook = inner, hook

    def __getattr__(self, name):
        return getattr(self._inner, name)

    def save(self, job_id, checkpoint_only=False):
        self._inner.save(job_id, checkpoint_only)
        pointer = self._inner.pointer(job_id)
        if checkpoint_only and pointer:
            self._hook(pointer["chunk"])


def in_thread(worker: Worker) -> threading.Thread:
    t = threading.Thread(target=worker.run_burst, kwargs={"poll_s": 0.05}, daemon=True)
    t.start()
    return t


def test_train_eval_sweep_and_download_through_the_api_on_s3(fleet, tmp_path):
    job = submit_tiny(fleet.url)
    a = fleet.machine("machine-a")
    t = in_thread(a)
    events = sse_events(fleet.url, job["id"])
    assert events[-1][1] == "succeeded", events[-1]
    done = httpx.get(f"{fleet.url}/jobs/{job['id']}").json()
    rows = httpx.get(f"{fleet.url}/jobs/{job['id']}/metrics").json()["metrics"]
    assert len(rows) == 3 and rows[-1]["env_steps"] == done["result"]["env_steps"]
    listed = {x["name"]: x["bytes"] for x in
              httpx.get(f"{fleet.url}/jobs/{job['id']}/artifacts").json()["artifacts"]}  # fmt: skip
    assert {"config.json", "metrics.jsonl", "learning_curve.png", "checkpoint/state.msgpack",
            "checkpoint/meta.json"} <= set(listed)  # fmt: skip
    assert not any(n.startswith(".") for n in listed)  # the store's bookkeeping stays hidden
    got = httpx.get(f"{fleet.url}/jobs/{job['id']}/artifacts/checkpoint/state.msgpack")
    assert got.status_code == 200 and got.headers["content-type"] == "application/octet-stream"
    assert got.content == fleet.bucket.read_bytes(job["id"], "checkpoint/state.msgpack")
    assert len(got.content) == listed["checkpoint/state.msgpack"] == int(got.headers["content-length"])
    png = httpx.get(f"{fleet.url}/jobs/{job['id']}/artifacts/learning_curve.png")
    assert png.headers["content-type"] == "image/png" and png.content[:4] == b"\x89PNG"
    assert httpx.get(f"{fleet.url}/jobs/{job['id']}/artifacts/nope.txt").status_code == 404
    assert httpx.get(f"{fleet.url}/jobs/{job['id']}/artifacts/.checkpoint.json").status_code == 404
    assert not a.job_dir(job["id"]).exists()  # the scratch copy went; the bucket has it all
    # the API's machine never had the files: it has no artifacts folder at all
    assert not (tmp_path / "api" / "artifacts").exists()

    # an evaluation on another machine reads the policy from the bucket
    ev = httpx.post(f"{fleet.url}/jobs/eval", json={"job_id": job["id"], "episodes": 8})
    assert ev.status_code == 202, ev.text
    b = fleet.machine("machine-b")
    tb = in_thread(b)
    ev_done = wait_status(fleet.url, ev.json()["id"], {"succeeded", "failed"})
    assert ev_done["status"] == "succeeded", ev_done["error"]
    measured = httpx.get(f"{fleet.url}/jobs/{ev.json()['id']}/artifacts/eval.json").json()
    assert measured["metrics"]["episodes"] == 8 == ev_done["result"]["metrics"]["episodes"]

    # a sweep: trials are child jobs, the study is Optuna's journal on Redis, outputs in the bucket
    t.join(60)
    tb.join(60)  # both drained the queue and stopped
    sweep, _ = fleet.store.submit(JobKind.sweep, {"space": "test"}, sweep_config(trials=2))
    fleet.machine("machine-c").run_burst(poll_s=0.05)
    sw = httpx.get(f"{fleet.url}/jobs/{sweep.id}").json()
    assert sw["status"] == "succeeded", sw["error"]
    names = {x.name for x in fleet.bucket.list(sweep.id)}
    assert {"trials.json", "summary.json", "sweep_config.json"} <= names, names
    assert not any(n.endswith(".db") for n in names)  # no SQLite study on the object store

    # deleting a job deletes its objects
    assert httpx.delete(f"{fleet.url}/jobs/{job['id']}").status_code == 204
    assert fleet.bucket.list(job["id"]) == [] and not fleet.bucket.has_checkpoint(job["id"])


def test_a_job_handed_back_resumes_on_another_machine_from_the_bucket(fleet):
    job = submit_tiny(fleet.url, total_steps=4096)  # 8 chunks
    a = fleet.machine("machine-a")
    a.artifacts = Hooked(a.artifacts, lambda chunk: chunk >= 2 and a.shutdown.set())
    a.run_burst(poll_s=0.05)  # stops after the chunk-2 checkpoint is in the bucket: hands back
    handed = fleet.store.get(job["id"])
    assert handed.status == JobStatus.queued and fleet.bucket.pointer(job["id"])["chunk"] >= 2
    assert not a.job_dir(job["id"]).exists()
    published = fleet.bucket.pointer(job["id"])["chunk"]

    b = fleet.machine("machine-b")
    b.run_burst(poll_s=0.05)
    done = fleet.store.get(job["id"])
    assert done.status == JobStatus.succeeded, done.error
    assert done.worker == "machine-b"  # (a hand-back does not count as an attempt)
    events = [e for _, e in fleet.store.events(job["id"])]
    assert any(e["type"] == "resumed" for e in events)
    # the run went on from the bucket's checkpoint: chunk numbers continue, no chunk twice
    rows = [json.loads(x) for x in fleet.bucket.read_bytes(job["id"], "metrics.jsonl").splitlines()]
    assert [r["chunk"] for r in rows] == list(range(1, len(rows) + 1)) and len(rows) > published
    assert rows[-1]["env_steps"] == done.result["env_steps"] == 4096


def test_an_outage_mid_job_is_waited_out_and_downloads_answer_503(fleet):
    job = submit_tiny(fleet.url)
    a = fleet.machine("machine-a", artifacts_retry_s=60)
    seen: dict = {}

    def outage(chunk: int) -> None:
        if chunk != 1 or seen:
            return
        fleet.s3.stop()
        try:
            r = httpx.get(f"{fleet.url}/jobs/{job['id']}/artifacts", timeout=60)
            seen["list"] = (r.status_code, r.json()["detail"], r.headers.get("retry-after"))
            ready = httpx.get(f"{fleet.url}/readyz", timeout=60)
            seen["ready"] = (ready.status_code, ready.json()["checks"])
        finally:
            threading.Timer(3.0, fleet.s3.start).start()  # back while the next upload retries

    a.artifacts = Hooked(a.artifacts, outage)
    a.run_burst(poll_s=0.05)
    done = fleet.store.get(job["id"])
    assert done.status == JobStatus.succeeded, done.error
    status, detail, retry = seen["list"]
    assert status == 503 and fleet.bucket.url in detail and retry
    # the store as the operator named it (s3://...), never its endpoint (the client library's words)
    endpoint = fleet.s3.endpoint
    assert "http://" not in detail and endpoint not in detail and "127.0.0.1" not in detail, detail
    assert seen["ready"][0] == 503 and seen["ready"][1]["artifacts"].startswith("unreachable")
    assert fleet.bucket.url not in json.dumps(seen["ready"])  # readiness never says where
    assert fleet.bucket.pointer(job["id"])["chunk"] == 3  # the last checkpoint made it
    assert httpx.get(f"{fleet.url}/readyz").status_code == 200


def test_a_store_that_stays_down_fails_the_job_with_a_reason_naming_it(fleet):
    job = submit_tiny(fleet.url)
    a = fleet.machine("machine-a", artifacts_retry_s=2)
    a.artifacts = Hooked(a.artifacts, lambda chunk: chunk == 1 and fleet.s3.stop())
    try:
        a.run_burst(poll_s=0.05)
        done = fleet.store.get(job["id"])
        assert done.status == JobStatus.failed  # finished with a reason: not lost
        assert f"artifact store {fleet.bucket.url} unavailable" in done.error
        assert "retried for 2 s" in done.error and "checkpoint" in done.error
    finally:
        fleet.s3.start()
    assert fleet.bucket.pointer(job["id"])["chunk"] == 1  # what was published stays


@pytest.mark.slow  # two worker processes compile and train: ~60 s on 2 cores
def test_two_machines_resume_from_the_bucket(tmp_path, s3_env):
    """Worker A (its own data folder) is SIGKILLed mid-job; worker B, on another data folder,
    reclaims the job when A's lease lapses and finishes it from the checkpoint in the bucket."""
    client = redis.Redis.from_url(REDIS_URL)
    client.ping()
    client.flushdb()
    store = RedisJobStore(REDIS_URL)
    url = s3_env.url()
    bucket = S3Artifacts(url, tmp_path / "reader", retry_s=0)
    from quicknav_core.config import apply_overrides, get_preset

    cfg = apply_overrides(get_preset("demo"), [f"{k}={v}" for k, v in
                                               {**TINY, "total_steps": 40960}.items()])  # fmt: skip
    job, _ = store.submit("train", {"config": cfg.model_dump(mode="json")}, cfg.model_dump(mode="json"))

    def worker(name: str) -> subprocess.Popen:
        env = {**os.environ, **s3_env.env(), "QUICKNAV_REDIS_URL": REDIS_URL,
               "QUICKNAV_DATA_DIR": str(tmp_path / name), "QUICKNAV_ARTIFACTS_URL": url,
               "QUICKNAV_LEASE_S": "3", "QUICKNAV_HEARTBEAT_S": "0.5", "QUICKNAV_MAX_CHUNK_S": "0.5"}  # fmt: skip
        return LoggedProcess([sys.executable, "-m", "quicknav_cli", "worker"], env=env)

    def wait(pred, what, timeout=180):
        deadline = time.time() + timeout
        while time.time() < deadline:
            if pred():
                return
            time.sleep(0.1)
        raise AssertionError(f"timed out waiting for {what}")

    procs = []
    try:
        a = worker("machine-a")
        procs.append(a)
        wait(lambda: (bucket.pointer(job.id) or {}).get("chunk", 0) >= 2, "A's second checkpoint")
        os.kill(a.pid, signal.SIGKILL)
        a.wait(10)
        killed_at = bucket.pointer(job.id)["chunk"]
        assert store.get(job.id).status == JobStatus.running  # A holds a lease it cannot renew
        b = worker("machine-b")
        procs.append(b)
        wait(lambda: store.get(job.id).status.finished, "the job to finish on B")
        done = store.get(job.id)
        assert done.status == JobStatus.succeeded, done.error
        assert done.attempts == 2 and done.worker.startswith(os.uname().nodename)
        assert done.result["env_steps"] == 40960
        rows = [json.loads(x) for x in bucket.read_bytes(job.id, "metrics.jsonl").splitlines()]
        assert [r["chunk"] for r in rows] == list(range(1, len(rows) + 1)) and len(rows) > killed_at
        # B never saw A's folder: what it resumed from came from the bucket
        assert not (tmp_path / "machine-b" / "work" / job.id).exists()
        assert checkpoint_dir(bucket.run_copy(job.id)) is not None
        # the TensorBoard curve in the bucket has every chunk once, A's included
        events = [a for a in bucket.list(job.id) if a.name.startswith("events.out.tfevents")]
        assert len(events) == 1, events
        data = bucket.read_bytes(job.id, events[0].name)
        # a chunk with no finished episode has no mean return (NaN, left out of TensorBoard): small
        # chunks on a slow machine have some; steps/s is there for every chunk
        assert scalar_steps(data, "train/steps_per_s") == [r["env_steps"] for r in rows]
        finite = [r["env_steps"] for r in rows if r.get("mean_return") is not None
                  and math.isfinite(r["mean_return"])]  # fmt: skip
        assert scalar_steps(data, "train/mean_return") == finite
        # A's scratch copy outlived it; a worker started again on A's data folder clears it
        scratch = tmp_path / "machine-a" / "work" / job.id
        assert scratch.exists()
        again = worker("machine-a")
        procs.append(again)
        wait(lambda: not scratch.exists(), "the new worker on A's folder to clear the dead attempt's scratch", 60)
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(30)
                except subprocess.TimeoutExpired:
                    p.kill()
        client.flushdb()


def scalar_steps(data: bytes, tag: str) -> list[int]:
    """The steps of ``tag``'s scalars in a TensorBoard events file (TFRecords of Event protos)."""
    import struct

    from tensorboardX.proto.event_pb2 import Event

    steps, at = [], 0
    while at < len(data):
        (length,) = struct.unpack("<Q", data[at:at + 8])
        event = Event.FromString(data[at + 12:at + 12 + length])  # length, its crc, data, crc
        at += 12 + length + 4
        steps += [event.step for v in event.summary.value if v.tag == tag]
    return steps


def test_a_policy_in_the_bucket_is_served_over_grpc(tmp_path, s3_env):
    """PolicyService.Load reads a train job's checkpoint from the bucket (the server's machine never
    had the run folder); with the store down, Load answers UNAVAILABLE naming the store."""
    import grpc
    import numpy as np
    from quicknav_client import RemotePolicy, RolloutError

    from quicknav_core.config import TrainConfig
    from quicknav_core.export import random_observations
    from quicknav_core.train import train_run
    from quicknav_core.train.run import load_run
    from quicknav_service.rollout.server import BackgroundServer

    url = s3_env.url()
    trainer_side = S3Artifacts(url, tmp_path / "trainer", retry_s=0)
    cfg = TrainConfig.model_validate({
        "env": {"grid_size": 8, "train_rooms": 16, "test_rooms": 8, "lidar_beams": 8, "max_steps": 40},
        "algorithm": {"name": "ppo", "num_steps": 16, "num_minibatches": 2, "num_epochs": 1},
        "num_envs": 8, "total_steps": 256, "chunk_steps": 128,
    })  # fmt: skip
    train_run(cfg, trainer_side.work_dir("job-mlp"))
    _, trainer, state, _ = load_run(trainer_side.work_dir("job-mlp"))
    policy = trainer.policy(state)
    trainer_side.save("job-mlp")
    trainer_side.release("job-mlp")
    settings = Settings(_env_file=None, data_dir=tmp_path / "server", host="127.0.0.1", grpc_port=0,
                        artifacts_url=url, artifacts_retry_s=0)  # fmt: skip
    srv = BackgroundServer(settings, port=0).start()
    try:
        obs = random_observations(cfg.env, 3, seed=1)
        with RemotePolicy(f"127.0.0.1:{srv.port}") as rp:
            rp.load("job-mlp", rows=3)
            got = rp.act(obs, np.ones(3, bool))
        _, want = policy.act(policy.initial_carry(3), obs, np.ones(3, bool), None, True)
        np.testing.assert_allclose(got, np.asarray(want), atol=1e-5)
        s3_env.stop()
        try:
            with RemotePolicy(f"127.0.0.1:{srv.port}") as rp, pytest.raises(RolloutError) as e:
                rp.load("job-mlp", rows=1)
            assert e.value.code == grpc.StatusCode.UNAVAILABLE and url in e.value.message
        finally:
            s3_env.start()
    finally:
        srv.stop()
