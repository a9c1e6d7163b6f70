"""Sweep jobs spread over workers: the sweep coordinates, its trial batches are child jobs any worker
claims, and all of them tell one Optuna study (SQLite in the sweep's folder, or journal storage on
the store's Redis). Cancelling the sweep cancels its batches; a batch whose worker died reruns the
trials it left unfinished, and no trial counts twice."""

from __future__ import annotations

import json
import threading

import optuna
import pytest
import redis

from quicknav_core.config import SweepConfig
from quicknav_core.sweep import finished_count, open_study
from quicknav_service.jobs.models import JobKind, JobStatus
from quicknav_service.jobs.redis_store import RedisJobStore
from quicknav_service.jobs.sqlite_store import SQLiteJobStore
from quicknav_service.settings import Settings
from quicknav_service.worker import Worker
from tests.core.test_sweep import BASE, SPACE

REDIS_URL = "redis://127.0.0.1:6379/12"  # this file's own DB index


def sweep_config(trials: int, parallel: int = 1) -> dict:
    return SweepConfig.model_validate({
        "base": BASE, "space": SPACE, "trials": trials, "parallel": parallel, "eval_episodes": 4,
        "objective": "return"}).model_dump(mode="json")  # fmt: skip


def children_of(store, sweep_id: str):
    data, _ = store.list(kind=JobKind.trial, limit=500)
    return sorted((j for j in data if j.config["parent"] == sweep_id), key=lambda j: j.config["batch"])


def settings_for(tmp_path, **kw) -> Settings:
    return Settings(_env_file=None, data_dir=tmp_path / "data", lease_s=5.0, heartbeat_s=0.5, **kw)


def test_sweep_job__trial_batches_are_child_jobs_telling_one_study(tmp_path):
    settings = settings_for(tmp_path)
    store = SQLiteJobStore(settings.data_dir / "jobs.db")
    sweep, _ = store.submit(JobKind.sweep, {"space": "test"}, sweep_config(trials=3))
    worker = Worker(store, settings, "w1")
    worker.run_burst(poll_s=0.05)

    done = store.get(sweep.id)
    assert done.status == JobStatus.succeeded, done.error
    kids = children_of(store, sweep.id)
    assert [k.config["batch"] for k in kids] == [0, 1, 2] and all(k.config["trials"] == 1 for k in kids)
    assert all(k.status == JobStatus.succeeded and k.worker == "w1" for k in kids)
    assert done.result["batches"] == 3 and done.result["children"] == [k.id for k in kids]
    # the study in the sweep's folder holds exactly the three trials, one per batch
    study = optuna.load_study(study_name=f"sweep-{sweep.id}",
                              storage=f"sqlite:///{settings.artifacts_dir / sweep.id / 'study.db'}")  # fmt: skip
    assert len(study.trials) == 3 and all(t.state.name == "COMPLETE" for t in study.trials)
    assert sorted(t.user_attrs["batch"] for t in study.trials) == ["0", "1", "2"]
    # each batch draws from its own random stream: three different trials, not one three times
    assert len({json.dumps(t.params, sort_keys=True) for t in study.trials}) == 3
    assert done.result["best_value"] == study.best_value
    listed = json.loads((settings.artifacts_dir / sweep.id / "trials.json").read_text())
    assert len(listed["trials"]) == 3 and all(t["counted"] for t in listed["trials"])
    assert done.metrics["finished"] == 3 and done.progress == 1.0
    for name in ("trials.csv", "best_params.json", "optimization_history.png"):
        assert (settings.artifacts_dir / sweep.id / name).exists(), name
    # deleting the sweep deletes its batches too
    from fastapi.testclient import TestClient

    from quicknav_service.api.main import create_app

    client = TestClient(create_app(settings, store, start_workers=False))
    assert client.delete(f"/jobs/{sweep.id}").status_code == 204
    assert children_of(store, sweep.id) == [] and not (settings.artifacts_dir / sweep.id).exists()


def test_sweep_job__cancelling_the_sweep_cancels_its_batches(tmp_path):
    settings = settings_for(tmp_path)
    store = SQLiteJobStore(settings.data_dir / "jobs.db")
    sweep, _ = store.submit(JobKind.sweep, {"space": "test"}, sweep_config(trials=4))
    worker = Worker(store, settings, "w1")
    assert worker.run_once()  # claims the sweep: its coordinator submits the batches
    for _ in range(200):
        if len(children_of(store, sweep.id)) == 4:
            break
        threading.Event().wait(0.05)
    store.cancel(sweep.id)
    worker.join_coordinators(timeout=20)
    assert store.get(sweep.id).status == JobStatus.cancelled
    assert [k.status for k in children_of(store, sweep.id)] == [JobStatus.cancelled] * 4
    assert worker.run_burst(poll_s=0.05) == 0  # nothing left to run


@pytest.fixture
def redis_store():
    client = redis.Redis.from_url(REDIS_URL)
    client.ping()  # no Redis here is a failure, not a skip
    client.flushdb()
    yield RedisJobStore(REDIS_URL)
    client.flushdb()


def test_sweep_job__two_workers_share_the_study_on_redis(tmp_path, redis_store):
    settings = settings_for(tmp_path, redis_url=REDIS_URL)
    sweep, _ = redis_store.submit(JobKind.sweep, {"space": "test"}, sweep_config(trials=4))
    workers = [Worker(redis_store, settings, f"w{i}") for i in (1, 2)]
    threads = [threading.Thread(target=w.run_burst, kwargs={"poll_s": 0.05}) for w in workers]
    for t in threads:
        t.start()
    for t in threads:
        t.join(600)
    done = redis_store.get(sweep.id)
    assert done.status == JobStatus.succeeded, done.error
    kids = children_of(redis_store, sweep.id)
    assert len(kids) == 4 and all(k.status == JobStatus.succeeded for k in kids)
    # one study in Redis's journal, under the sweep's own key prefix, with each trial once
    study = open_study(SweepConfig.model_validate(sweep.config), workers[0].sweep_storage(sweep.id),
                       study_name=f"sweep-{sweep.id}")  # fmt: skip
    assert len(study.trials) == 4 and finished_count(study) == 4
    assert len({json.dumps(t.params, sort_keys=True) for t in study.trials}) == 4
    assert redis.Redis.from_url(REDIS_URL).keys(f"quicknav:sweep:{sweep.id}:*")
    assert not (settings.artifacts_dir / sweep.id / "study.db").exists()


def test_sweep_job__a_batch_rerun_after_its_worker_died_reruns_its_lost_trial(tmp_path):
    settings = settings_for(tmp_path)
    store = SQLiteJobStore(settings.data_dir / "jobs.db")
    worker = Worker(store, settings, "w2")
    config = sweep_config(trials=1)
    sweep, _ = store.submit(JobKind.sweep, {"space": "test"}, config)
    (settings.artifacts_dir / sweep.id).mkdir(parents=True)
    cfg = SweepConfig.model_validate(config)
    # a worker asked batch 0's trial and died mid-training: the trial is left RUNNING
    study = open_study(cfg, worker.sweep_storage(sweep.id), study_name=f"sweep-{sweep.id}")
    lost = study.ask()
    lost.suggest_float("algorithm.learning_rate", 1e-4, 1e-2, log=True)
    lost.suggest_float("env.reward.step_penalty", 0.01, 0.5)
    lost.set_user_attr("batch", "0")
    batch, _ = store.submit(JobKind.trial, {"parent": sweep.id, "batch": 0},
                            {"parent": sweep.id, "batch": 0, "trials": 1, "sweep": config})  # fmt: skip
    store.cancel(sweep.id)  # only the batch runs here; the sweep itself is not the subject
    worker.run_burst(poll_s=0.05)

    assert store.get(batch.id).status == JobStatus.succeeded
    assert store.get(batch.id).result["retried"] == 1
    study = open_study(cfg, worker.sweep_storage(sweep.id), study_name=f"sweep-{sweep.id}")
    old, new = study.trials
    assert old.state.name == "FAIL" and new.state.name == "COMPLETE"
    assert new.params == lost.params  # the same trial, run again
    assert finished_count(study) == 1 and finished_count(study, "0") == 1  # counted once
