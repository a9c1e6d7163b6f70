"""The jobs service's own rules, below the HTTP routes: the delete cascade of a sweep."""

from __future__ import annotations

from quicknav_service.jobs.models import JobKind, JobStatus
from quicknav_service.jobs.service import PAGE, JobsService
from quicknav_service.jobs.sqlite_store import SQLiteJobStore
from quicknav_service.settings import Settings


def test_delete__a_sweep_takes_every_trial_batch_however_many_and_only_its_own(tmp_path):
    """More batches than one store page (the cascade once looked at only the newest 500 trial
    jobs, so a big sweep left orphans behind), interleaved with another sweep's batches."""
    settings = Settings(_env_file=None, data_dir=tmp_path)
    store = SQLiteJobStore(tmp_path / "jobs.db")
    service = JobsService(store, settings)
    sweep, _ = store.submit(JobKind.sweep, {"space": "ppo"}, {})
    other, _ = store.submit(JobKind.sweep, {"space": "lstm"}, {})
    mine, theirs = [], []
    for i in range(PAGE + 200):
        parent = sweep if i % 5 else other
        batch, _ = store.submit(JobKind.trial, {}, {"parent": parent.id, "batch": i})
        (mine if parent is sweep else theirs).append(batch.id)
        settings.artifacts_dir.joinpath(batch.id).mkdir(parents=True)
    for job_id in [sweep.id, *mine]:
        store.cancel(job_id)
    assert len(mine) > PAGE

    service.delete(sweep.id)
    left = {j.id for j in store.list(kind=JobKind.trial, limit=PAGE)[0]}
    left |= {j.id for j in store.list(kind=JobKind.trial, limit=PAGE, offset=PAGE)[0]}
    assert left == set(theirs)
    assert not any(settings.artifacts_dir.joinpath(b).exists() for b in mine)
    assert all(settings.artifacts_dir.joinpath(b).exists() for b in theirs)
    assert store.get(other.id).status == JobStatus.queued
