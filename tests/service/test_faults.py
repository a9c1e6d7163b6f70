"""The fault suite: each fault the job system was built for, injected for real, and what must
happen instead of a stall, a crash or a lost job.

- full disk: a tmpfs filled up under the data folder (slow test) and ENOSPC at the store layer;
- Redis outage: a redis-server of the test's own, killed with SIGKILL and started again;
- memory: the submission budget, and a worker process killed by a signal (slow test);
- cancellation of a running eval and of a train job with a huge chunk (slow test);
- bad input that used to fail late or answer 500 (NUL bytes, absurd tensors, huge configs).
Long end-to-end checks are marked slow (`uv run pytest -m slow`); `benchmarks/chaos.py` runs the
same faults at random over many jobs.
"""

from __future__ import annotations

import json
import signal
import time

import grpc
import httpx
import pytest
import redis

from quicknav_core.config import resolve_eval, resolve_train
from quicknav_service.jobs.models import JobStatus, StoreUnavailable
from quicknav_service.jobs.redis_store import RedisJobStore
from quicknav_service.jobs.sqlite_store import SQLiteJobStore
from quicknav_service.supervisor import exit_reason
from tests.processes import LoggedProcess
from tests.service.conftest import LiveServer
from tests.service.faults import RedisServer, SmallDisk

TINY = {"env.grid_size": 8, "env.train_rooms": 32, "env.test_rooms": 16, "env.max_steps": 60,
        "num_envs": 16, "algorithm.num_steps": 32, "algorithm.num_minibatches": 4,
        "total_steps": 1536, "chunk_steps": 512}  # fmt: skip


def wait_for(predicate, timeout: float = 120.0, what: str = "condition", poll: float = 0.1):
    deadline = time.time() + timeout
    while time.time() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll)
    raise AssertionError(f"timed out waiting for {what}")


def job_of(live, job_id: str) -> dict:
    return httpx.get(f"{live.url}/jobs/{job_id}", timeout=30).json()


# --------------------------------------------------------------------------- bad input
def test_submission__what_cannot_run_is_refused_with_the_field_named(tmp_path):
    with LiveServer(tmp_path, max_job_memory_mb=4096) as live:
        # a legal replay buffer of 10^8 transitions: ~160 GB; it OOM-killed the whole service
        r = httpx.post(f"{live.url}/jobs/train", json={
            "preset": "paper-sac", "overrides": {"algorithm.buffer_size": 100_000_000}})  # fmt: skip
        assert r.status_code == 422, r.text
        detail = r.json()["detail"][0]
        assert detail["loc"] == ["body", "overrides", "algorithm.buffer_size"]
        assert "replay buffer" in detail["msg"] and "max_job_memory_mb=4,096" in detail["msg"]
        # grid 48 with the paper's carving burnt minutes of CPU, then failed: now refused at once
        # (carver "auto" carves it with returns to carved cells; "paper" is the walk that cannot)
        t0 = time.perf_counter()
        r = httpx.post(f"{live.url}/jobs/train", json={"preset": "demo", "overrides": {
            "env.grid_size": 48, "env.robot_radius": 0.05, "env.max_wheel_speed": 0.8,
            "env.carver": "paper"}})  # fmt: skip
        assert r.status_code == 422 and time.perf_counter() - t0 < 10
        assert "return_prob <=" in r.text and "grid_size <=" in r.text
        # the same env through a lower return_prob is accepted
        r = httpx.post(f"{live.url}/jobs/train", json={"preset": "demo", "overrides": {
            "env.grid_size": 48, "env.robot_radius": 0.05, "env.max_wheel_speed": 0.8,
            "env.carver": "paper", "env.return_prob": 0.01}})  # fmt: skip
        assert r.status_code == 202, r.text
        # an eval of 10^5 episodes at grid 32 keeps every trajectory: estimated, within budget
        r = httpx.post(f"{live.url}/jobs/eval", json={"policy": "random", "episodes": 100_000})
        assert r.status_code == 422 and "max_eval_episodes" in r.text
        # a NaN is named as such, not as "should be <= 1"
        r = httpx.post(f"{live.url}/jobs/train", json={
            "preset": "demo", "overrides": {"algorithm.learning_rate": "nan"}})  # fmt: skip
        assert r.status_code == 422 and "finite number" in r.text


def test_api__nul_bytes_short_ids_and_ambiguous_prefixes(live):
    a = httpx.post(f"{live.url}/jobs/eval", json={"policy": "random", "episodes": 3}).json()
    r = httpx.get(f"{live.url}/jobs/{a['id']}/artifacts/bad%00name")
    assert r.status_code == 400 and "NUL" in r.text
    short = a["id"][:8]
    assert httpx.get(f"{live.url}/jobs/{short}").json()["id"] == a["id"]
    assert httpx.post(f"{live.url}/jobs/{short}/cancel", json={}).json()["status"] == "cancelled"
    r = httpx.get(f"{live.url}/jobs/{short[:3]}")  # shorter than 4: not an id prefix, says so
    assert r.status_code == 422 and "give at least 4 characters" in r.text, r.text
    # make two jobs share a prefix: the API asks for more characters instead of guessing
    store = live.store
    twin, _ = store.submit("eval", {"policy": "random"}, {})
    with store._tx() as db:  # rename the twin so that both ids start with the same 4 characters
        db.execute("UPDATE jobs SET id = ? WHERE id = ?", (a["id"][:4] + twin.id[4:], twin.id))
    r = httpx.get(f"{live.url}/jobs/{a['id'][:4]}")
    assert r.status_code == 409 and "matches several jobs" in r.text, r.text


def test_grpc__start_refusals_are_exact_and_bounded(tmp_path):
    from quicknav_client.rollout import RolloutClient, RolloutError

    from quicknav_service.rollout.server import BackgroundServer
    from quicknav_service.settings import Settings

    settings = Settings(data_dir=tmp_path / "data", max_lidar_beams=256)
    server = BackgroundServer(settings, port=0).start()
    try:
        target = f"127.0.0.1:{server.port}"
        cases = [
            (
                {"grid_size": 64, "robot_radius": 0.05, "max_wheel_speed": 0.5, "carver": "paper"},
                "return_prob <=",
            ),
            ({"lidar_beams": 512}, "lidar_beams=512"),
            ({"room_size": "x" * 20_000}, "start.config.room_size"),
        ]
        for config, text in cases:
            t0 = time.perf_counter()
            with RolloutClient(target) as rc, pytest.raises(RolloutError) as e:
                rc.start(num_envs=8, config=config)
            assert e.value.code == grpc.StatusCode.INVALID_ARGUMENT, e.value
            assert text in e.value.message and len(e.value.message) <= 2000
            assert time.perf_counter() - t0 < 10, "refused before any room is carved"
        # a tensor that claims 2^64 elements and carries none: INVALID_ARGUMENT, not INTERNAL
        from quicknav_client.proto.quicknav.v1 import rollout_pb2 as pb

        with RolloutClient(target) as rc:
            rc.start(num_envs=2, config={"grid_size": 8, "lidar_beams": 8, "train_rooms": 8,
                                         "test_rooms": 4})  # fmt: skip
            with pytest.raises(RolloutError) as e:
                rc._call(pb.AgentMessage(step=pb.Step(actions=pb.Tensor(
                    dtype="float32", shape=[2**32, 2**32], data=b""))))  # fmt: skip
            assert e.value.code == grpc.StatusCode.INVALID_ARGUMENT, e.value
        # the session's room bank was carved once and kept for the next session of that config
        assert list((settings.data_dir / "room-banks").glob("bank-8-train-*.npz"))
    finally:
        server.stop()


# --------------------------------------------------------------------------- store outages
def test_store__sqlite_full_disk_is_unavailable_not_a_crash(tmp_path):
    store = SQLiteJobStore(tmp_path / "jobs.db")
    job, _ = store.submit("eval", {"policy": "random"}, {"x": 1})
    page_size = store._db.execute("PRAGMA page_count").fetchone()[0]
    store._db.execute(f"PRAGMA max_page_count = {page_size}")  # no room for one more page
    with pytest.raises(StoreUnavailable) as e:
        for i in range(200):
            store.publish(job.id, {"type": "progress", "blob": "x" * 4000, "i": i})
    assert e.value.disk_full and "disk full" in e.value.reason
    assert store.get(job.id).config == {"x": 1}, "reads still work"
    store._db.execute("PRAGMA max_page_count = 1073741823")  # space is back
    store.publish(job.id, {"type": "progress"})


def test_redis_outage__api_answers_503_readiness_names_it_workers_carry_on(tmp_path):
    with RedisServer(tmp_path / "redis") as rs:
        store = RedisJobStore(rs.url, prefix="faults")
        with LiveServer(tmp_path, store=store) as live:
            worker, thread = live.run_worker_in_background("outage-worker")
            before, _ = store.submit("eval", {"policy": "random"}, {"bad": "config"})
            wait_for(lambda: store.get(before.id).status == JobStatus.failed, 30, "a first job")
            rs.kill()
            r = httpx.get(f"{live.url}/jobs/{before.id}", timeout=30)
            assert r.status_code == 503 and int(r.headers["retry-after"]) >= 1
            assert "unreachable" in r.text and str(rs.port) not in r.text
            r = httpx.post(f"{live.url}/jobs/eval", json={"policy": "random"}, timeout=30)
            assert r.status_code == 503
            ready = httpx.get(f"{live.url}/readyz", timeout=30)
            assert ready.status_code == 503 and ready.json()["checks"]["store"] == "redis is unreachable"
            assert str(rs.port) not in ready.text and "127.0.0.1" not in ready.text
            time.sleep(2.0)  # the worker keeps polling a dead Redis
            assert thread.is_alive(), "the worker survives the outage"
            rs.start()  # AOF: everything acknowledged comes back
            assert httpx.get(f"{live.url}/readyz", timeout=30).status_code == 200
            assert job_of(live, before.id)["status"] == "failed", "accepted jobs were not lost"
            after, _ = store.submit("eval", {"policy": "random"}, {"bad": "config"})
            done = wait_for(lambda: store.get(after.id).status.finished and store.get(after.id),
                            30, "the worker to take a job after the outage")  # fmt: skip
            assert done.status == JobStatus.failed and "validation error" in done.error.lower()
            worker.shutdown.set()


def test_redis__worker_process_starts_against_a_dead_redis_and_waits(tmp_path):
    import os
    import sys

    folder = tmp_path / "redis"
    rs = RedisServer(folder)
    env = {**os.environ, "QUICKNAV_REDIS_URL": rs.url, "QUICKNAV_DATA_DIR": str(tmp_path / "data")}
    proc = LoggedProcess([sys.executable, "-m", "quicknav_cli", "worker"], env=env)
    try:
        time.sleep(4.0)
        assert proc.poll() is None, proc.output()
        with rs:
            store = RedisJobStore(rs.url)
            job, _ = store.submit("eval", {"policy": "random"}, {"bad": "config"})
            done = wait_for(lambda: store.get(job.id).status.finished and store.get(job.id), 60,
                            "the worker to reconnect and take the job")  # fmt: skip
            assert done.status == JobStatus.failed and done.worker
    finally:
        proc.terminate()
        proc.wait(30)


# --------------------------------------------------------------------------- memory
def test_exit_reason__names_out_of_memory_and_signals():
    sigkill = -signal.SIGKILL
    assert exit_reason(sigkill, 3, 4).startswith("killed: out of memory")
    assert "SIGKILL" in exit_reason(sigkill, None, None) and "OOM" in exit_reason(sigkill, None, None)
    assert exit_reason(sigkill, 3, 3) == "killed: the worker process got SIGKILL"
    assert exit_reason(-signal.SIGSEGV, 0, 0) == "killed: the worker process got SIGSEGV"
    assert "code 1" in exit_reason(1, 0, 0)


@pytest.mark.slow  # two worker processes compile and train: ~60 s on 2 cores
def test_worker_process_killed__its_job_fails_with_the_signal_the_api_lives(tmp_path):
    with LiveServer(tmp_path, start_workers=True, max_chunk_s=1.0) as live:
        body = {"preset": "demo", "overrides": {**TINY, "total_steps": 2_000_000}}
        job = httpx.post(f"{live.url}/jobs/train", json=body).json()
        wait_for(lambda: job_of(live, job["id"])["progress"] > 0, 180, "the job to make progress")
        supervisor = live.app.state.workers
        victim = supervisor.slots[0].proc
        victim.send_signal(signal.SIGKILL)  # what the kernel's OOM killer does
        failed = wait_for(lambda: (j := job_of(live, job["id"]))["status"] == "failed" and j,
                          60, "the job to fail")  # fmt: skip
        assert failed["error"].startswith("killed:") and "SIGKILL" in failed["error"]
        assert httpx.get(f"{live.url}/healthz").status_code == 200, "the API process lives"
        wait_for(lambda: supervisor.restarts >= 1, 30, "a new worker process")
        again = httpx.post(f"{live.url}/jobs/train", json={"preset": "demo", "overrides": TINY}).json()
        done = wait_for(lambda: (j := job_of(live, again["id"]))["status"] in (
            "succeeded", "failed") and j, 300, "the new worker to run a job")  # fmt: skip
        assert done["status"] == "succeeded", done["error"]


# --------------------------------------------------------------------------- disk full
def test_disk_full__queued_jobs_say_why_they_wait_and_start_when_space_is_freed(tmp_path):
    """A data volume with room for job records but not for a job's files: the worker claims
    nothing, and the job (API, CLI) says why it waits; freed space starts it."""
    from typer.testing import CliRunner

    from quicknav_cli.main import app
    from quicknav_service.jobs.capabilities import DISK_FULL

    disk = SmallDisk(tmp_path / "small", mb=8)
    with disk, LiveServer(tmp_path, data_dir=disk.path / "data") as live:
        worker, _ = live.run_worker_in_background()
        disk.fill(leave_bytes=40_000)  # less than the 64 KB the disk probe writes
        # the worker has seen it (its announcement says so) before a job is submitted: a worker
        # that checked the disk just before the fill could otherwise claim the job (under load,
        # CI saw it run)
        wait_for(lambda: any(w.get("disk_full") for w in live.store.live_workers()), 20,
                 "the worker to announce its full disk")  # fmt: skip
        r = httpx.post(f"{live.url}/jobs/eval", json={"policy": "random", "episodes": 3,
                                                      "env": {"grid_size": 8, "max_steps": 20}})  # fmt: skip
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        time.sleep(3 * 0.05 + 1.0)  # many polls of the worker
        job = job_of(live, job_id)
        assert job["status"] == "queued" and job["waiting"] == DISK_FULL, job
        listed = httpx.get(f"{live.url}/jobs").json()["data"]
        assert [j["waiting"] for j in listed if j["id"] == job_id] == [DISK_FULL]
        shown = CliRunner().invoke(app, ["jobs", "list"], env={"QUICKNAV_URL": live.url})
        assert "data volume is full" in shown.output, shown.output
        disk.empty()
        done = wait_for(lambda: (j := job_of(live, job_id))["status"] in (
            "failed", "succeeded") and j, 120, "the job to run once space is back")  # fmt: skip
        assert done["status"] == "succeeded", done["error"]
        assert done["waiting"] is None
        worker.shutdown.set()


@pytest.mark.slow  # trains twice on a filled tmpfs: ~60 s on 2 cores
def test_disk_full__job_fails_with_reason_worker_lives_delete_frees_space(tmp_path):
    disk = SmallDisk(tmp_path / "small", mb=8)
    with disk, LiveServer(tmp_path, data_dir=disk.path / "data") as live:
        worker, thread = live.run_worker_in_background()
        disk.fill(leave_bytes=120_000)  # room for the job's record, not for its checkpoint
        job = httpx.post(f"{live.url}/jobs/train", json={"preset": "demo", "overrides": TINY})
        assert job.status_code == 202, job.text
        job_id = job.json()["id"]
        failed = wait_for(lambda: (j := job_of(live, job_id))["status"] in (
            "failed", "succeeded") and j, 300, "the job to end")  # fmt: skip
        assert failed["status"] == "failed"
        assert "disk full (ENOSPC)" in failed["error"] and "kept:" in failed["error"]
        assert not (live.settings.artifacts_dir / job_id / "checkpoint.new").exists()
        # now nothing at all is free. The worker thread's own disk probe (a 64 KiB file it removes
        # at once) may hold space while the filler writes, and give it back after: CI once saw
        # /readyz's probe fit in exactly that space. Fill again until the disk stays full.
        def full_and_said() -> httpx.Response | None:
            disk.fill()
            ready = httpx.get(f"{live.url}/readyz")
            return ready if ready.status_code == 503 else None

        ready = wait_for(full_and_said, 20, "/readyz to say the disk is full")
        assert ready.json()["checks"]["disk"] == "full", ready.json()
        r = httpx.post(f"{live.url}/jobs/eval", json={"policy": "random", "episodes": 3})
        assert r.status_code in (202, 507), r.text  # a clean answer either way, never a 500
        if r.status_code == 507:
            assert "disk full" in r.text and r.headers["retry-after"]
        codes = [httpx.delete(f"{live.url}/jobs/{job_id}").status_code for _ in range(2)]
        assert 204 in codes and 500 not in codes, codes  # the files go first: space is freed
        disk.empty()
        assert httpx.get(f"{live.url}/readyz").status_code == 200
        assert thread.is_alive(), "the worker lived through it"
        again = httpx.post(f"{live.url}/jobs/train", json={"preset": "demo", "overrides": TINY})
        done = wait_for(lambda: (j := job_of(live, again.json()["id"]))["status"] in (
            "failed", "succeeded") and j, 300, "the next job")  # fmt: skip
        assert done["status"] == "succeeded", done["error"]
        worker.shutdown.set()


# --------------------------------------------------------------------------- cancellation
@pytest.mark.slow  # compiles an evaluation and a training: ~40 s on 2 cores
def test_cancel__running_eval_and_a_huge_chunk_stop_within_seconds(tmp_path):
    with LiveServer(tmp_path, max_chunk_s=1.0) as live:
        worker, _ = live.run_worker_in_background()
        ev = httpx.post(f"{live.url}/jobs/eval", json={
            "policy": "random", "episodes": 2560, "env": {"grid_size": 8, "max_steps": 60}}).json()  # fmt: skip
        wait_for(lambda: job_of(live, ev["id"])["progress"] > 0, 180, "the first batch")
        t0 = time.time()
        httpx.post(f"{live.url}/jobs/{ev['id']}/cancel", json={})
        done = wait_for(lambda: (j := job_of(live, ev["id"]))["status"] in (
            "cancelled", "succeeded") and j, 60, "the eval to stop")  # fmt: skip
        assert done["status"] == "cancelled" and time.time() - t0 < 10
        assert 0 < done["progress"] < 1 and done["result"]["episodes_done"] < 2560

        body = {"preset": "demo", "overrides": {**TINY, "total_steps": 50_000_000,
                                                "chunk_steps": 10_000_000}}  # fmt: skip
        tr = httpx.post(f"{live.url}/jobs/train", json=body).json()
        wait_for(lambda: job_of(live, tr["id"])["progress"] > 0, 180, "the first chunk")
        t0 = time.time()
        httpx.post(f"{live.url}/jobs/{tr['id']}/cancel", json={})
        done = wait_for(lambda: (j := job_of(live, tr["id"]))["status"] in (
            "cancelled", "succeeded") and j, 60, "the train job to stop")  # fmt: skip
        assert done["status"] == "cancelled" and time.time() - t0 < 10
        assert 0 < done["progress"] < 0.5 and done["result"]["env_steps"] < 50_000_000
        events = [json.loads(x.removeprefix("data: ")) for x in httpx.get(
            f"{live.url}/jobs/{tr['id']}/events", timeout=30).text.splitlines() if x.startswith("data: ")]  # fmt: skip
        assert sum(e["type"] == "progress" for e in events) >= 1
        worker.shutdown.set()


def test_eval__progress_per_batch_and_the_stored_config_is_what_runs():
    """The runner reports progress after each batch and stops between batches when asked."""
    from quicknav_core.config.eval import EVAL_BATCH
    from quicknav_core.eval.evaluate import EvalStopped, run_eval

    cfg = resolve_eval({"policy": "random", "episodes": 2 * EVAL_BATCH + 5, "env": {
        "grid_size": 8, "lidar_beams": 8, "max_steps": 20, "train_rooms": 16, "test_rooms": 8}})  # fmt: skip
    seen = []
    with pytest.raises(EvalStopped) as e:
        run_eval(cfg.model_copy(update={"pictures": False}),
                 progress=lambda done, total: seen.append((done, total)) or done >= EVAL_BATCH)  # fmt: skip
    assert seen == [(EVAL_BATCH, 2 * EVAL_BATCH + 5)] and e.value.done == EVAL_BATCH


def test_train__total_steps_stop_at_whole_updates_and_say_so():
    cfg = resolve_train({"preset": "demo", "overrides": {**TINY, "total_steps": 1000}})
    from quicknav_core.train.trainers import make_trainer

    trainer = make_trainer(cfg)
    assert trainer.total_env_steps == 1024  # 2 updates of 16 envs x 32 steps, not a whole chunk
    assert trainer.updates_per_unit == 1


def test_store_guard__redis_errors_become_unavailable():
    store = RedisJobStore("redis://127.0.0.1:1/0")  # nothing listens on port 1
    with pytest.raises(StoreUnavailable) as e:
        store.counts()
    assert e.value.reason == "redis is unreachable" and not e.value.disk_full
    assert isinstance(e.value.__cause__, redis.ConnectionError)  # kept for the logs


def test_eval__batched_runner_without_picture_episodes():
    """gif_episodes=0 (what sweeps evaluate with): every batch runs, nothing to draw, no crash
    (the batched runner once concatenated an empty list of picture batches)."""
    from quicknav_core.eval.evaluate import run_episodes

    cfg = resolve_eval({"policy": "random", "episodes": 6, "env": {
        "grid_size": 8, "lidar_beams": 8, "max_steps": 20, "train_rooms": 16, "test_rooms": 8}})  # fmt: skip
    cfg = cfg.model_copy(update={"gif_episodes": 0})
    from quicknav_core.eval.scripted import RandomAgent

    env, params = cfg.env.build("test")
    ep = run_episodes(env, params, RandomAgent(), cfg)
    assert ep.success.shape == (6,) and ep.gif["theta"].shape[0] == 0


# --------------------------------------------------------------------------- pictures
@pytest.mark.slow  # trains a tiny job and evaluates it through a worker: ~40 s on 2 cores
def test_pictures_that_fail__jobs_succeed_with_their_numbers_and_a_warning_for_each(
    tmp_path, monkeypatch
):
    """Every picture raises (as matplotlib did on a bin where every episode succeeded): the train
    and eval jobs still succeed, their numbers are stored and served, and each job names every
    missing picture in its warnings."""
    from quicknav_core.eval import pictures
    from quicknav_core.train import pictures as train_pictures

    def broken(*args, **kwargs):
        raise ValueError("'yerr' must not contain negative values")

    monkeypatch.setattr(train_pictures, "draw_learning_curve", broken)
    for name in ("draw_trajectories", "draw_difficulty", "draw_gif"):
        monkeypatch.setattr(pictures, name, broken)
    with LiveServer(tmp_path, export_policies=True) as live:
        worker, _ = live.run_worker_in_background()
        ended = ("failed", "succeeded", "cancelled")
        r = httpx.post(f"{live.url}/jobs/train", json={"preset": "demo", "overrides": TINY})
        train = wait_for(lambda: (j := job_of(live, r.json()["id"]))["status"] in ended and j,
                         300, "the train job")  # fmt: skip
        assert train["status"] == "succeeded", train["error"]
        assert train["result"]["env_steps"] == 1536
        assert train["warnings"] == [
            "learning_curve.png was not drawn: ValueError: 'yerr' must not contain negative values"]
        files = {a["name"] for a in httpx.get(f"{live.url}/jobs/{train['id']}/artifacts").json()["artifacts"]}
        assert "metrics.jsonl" in files and "learning_curve.png" not in files
        assert any(f.startswith("checkpoint/") for f in files), files
        assert {"policy.onnx", "policy.json"} <= files  # the worker exported the policy

        r = httpx.post(f"{live.url}/jobs/eval", json={"job_id": train["id"], "episodes": 6})
        assert r.status_code == 202, r.text
        ev = wait_for(lambda: (j := job_of(live, r.json()["id"]))["status"] in ended and j,
                      300, "the eval job")  # fmt: skip
        assert ev["status"] == "succeeded", ev["error"]
        assert ev["result"]["metrics"]["episodes"] == 6
        missing = sorted(w.split(" ")[0] for w in ev["warnings"])
        assert {"difficulty.png", "trajectories.png"} <= set(missing), ev["warnings"]
        assert ev["result"]["warnings"] == ev["warnings"]
        raw = httpx.get(f"{live.url}/jobs/{ev['id']}/artifacts/eval.json").text
        assert "NaN" not in raw  # standard JSON: an undefined mean (no successes yet) is null
        stored = json.loads(raw)
        assert stored["metrics"] == ev["result"]["metrics"] and stored["warnings"] == ev["warnings"]
        # the policy's manifest now names this held-out evaluation
        manifest = httpx.get(f"{live.url}/jobs/{train['id']}/artifacts/policy.json").json()
        assert manifest["held_out"]["eval_job_id"] == ev["id"]
        assert manifest["held_out"]["success_rate"] == ev["result"]["metrics"]["success_rate"]
        worker.shutdown.set()


def test_export_that_fails__the_train_job_succeeds_with_a_warning(tmp_path, monkeypatch):
    from quicknav_core import export

    def broken(*args, **kwargs):
        raise RuntimeError("the exported policy differs from the JAX one by 1.0e-01 (> 1e-5)")

    monkeypatch.setattr(export, "export_run", broken)
    with LiveServer(tmp_path, export_policies=True) as live:
        worker, _ = live.run_worker_in_background()
        ended = ("failed", "succeeded", "cancelled")
        r = httpx.post(f"{live.url}/jobs/train", json={"preset": "demo", "overrides": TINY})
        train = wait_for(lambda: (j := job_of(live, r.json()["id"]))["status"] in ended and j,
                         300, "the train job")  # fmt: skip
        assert train["status"] == "succeeded", train["error"]
        assert train["result"]["env_steps"] == 1536
        assert train["warnings"] == ["policy.onnx, policy.json: not exported (RuntimeError: the exported"
                                     " policy differs from the JAX one by 1.0e-01 (> 1e-5))"]  # fmt: skip
        files = {a["name"] for a in httpx.get(f"{live.url}/jobs/{train['id']}/artifacts").json()["artifacts"]}
        assert "policy.onnx" not in files and any(f.startswith("checkpoint/") for f in files)
        gone = httpx.get(f"{live.url}/jobs/{train['id']}/artifacts/policy.onnx")
        assert gone.status_code == 404
        worker.shutdown.set()
