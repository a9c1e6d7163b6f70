"""What a job runner is handed: its job and the means to do it, never the worker itself (as arq hands
each job function a ``ctx``).

``JobContext`` holds the store, the artifact store, the process's ``Runtime`` (room banks, the map
resolver, compiled programs), the settings, and the job's progress and stop signals. The worker
(``quicknav_service.worker``) builds one per claimed job; runners (``quicknav_service.job_kinds``)
read only it, so the two modules do not import each other.

Store calls come in two kinds: ``best_effort`` for what an outage may skip (a progress event) and
``until_done`` for what must land (a job's end), retried with backoff until the store is back.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from quicknav_core.runtime import Runtime
from quicknav_service.artifacts import ArtifactStore
from quicknav_service.jobs.models import Job, JobKind, JobStore, StoreUnavailable
from quicknav_service.settings import Settings

log = logging.getLogger("quicknav.worker")

MAX_BACKOFF_S = 10.0
CANCEL_POLL_S = 1.0  # a running job's cancel flag is read at most this often


def best_effort(fn: Callable, *args) -> Any:
    """A store call whose loss costs nothing lasting (a progress event): skipped in an outage."""
    try:
        return fn(*args)
    except StoreUnavailable as e:
        log.warning("job store unavailable (%s): %s skipped", e.reason, fn.__name__)
        return None


def until_done(shutdown: threading.Event, fn: Callable, *args, **kwargs) -> Any:
    """A store call that must land (a job's end): retried with backoff through outages. On a
    shutdown it is abandoned: the lease lapses and another worker finishes the job."""
    backoff = 0.25
    while True:
        try:
            return fn(*args, **kwargs)
        except StoreUnavailable as e:
            if shutdown.is_set():
                log.warning("shutting down during a store outage; %s abandoned", fn.__name__)
                return None
            log.warning("job store unavailable (%s): %s again in %.1f s", e.reason, fn.__name__,
                        backoff)  # fmt: skip
            shutdown.wait(backoff)
            backoff = min(backoff * 2, MAX_BACKOFF_S)


def config_of(job: Job) -> dict[str, Any]:
    """The job's resolved config (jobs stored before configs were keep it in the request)."""
    if job.config:
        return job.config
    if job.kind in (JobKind.train, JobKind.sweep) and "config" in job.request:
        return job.request["config"]
    raise ValueError(
        "the job has no resolved config (it was submitted to an older version of the service);"
        " submit it again"
    )


def sweep_storage(settings: Settings, artifacts: ArtifactStore, sweep_id: str):
    """The Optuna storage of a sweep job's study, shared by every worker, by the library's one
    rule (``quicknav_core.sweep.study_storage``): journal storage on this store's Redis (keys
    under quicknav:sweep:<id>:), or SQLite in the sweep's folder with the embedded store."""
    from quicknav_core.sweep import study_storage

    return study_storage(settings.redis_url, artifacts.work_dir(sweep_id),
                         prefix=f"quicknav:sweep:{sweep_id}:")  # fmt: skip


@dataclass
class JobContext:
    """One claimed job and what its runner may use."""

    job: Job
    worker_id: str
    store: JobStore
    artifacts: ArtifactStore
    runtime: Runtime
    settings: Settings
    lost: threading.Event  # another worker owns the job now (the lease was lost)
    shutdown: threading.Event  # the worker is stopping: hand the job back
    _cancel_seen: dict[str, Any] = field(default_factory=lambda: {"at": 0.0, "cancel": False})

    @property
    def config(self) -> dict[str, Any]:
        return config_of(self.job)

    @property
    def job_dir(self) -> Path:
        """The local folder the job writes into (on an object store: uploaded from there)."""
        return self.artifacts.work_dir(self.job.id)

    def best_effort(self, fn: Callable, *args) -> Any:
        return best_effort(fn, *args)

    def until_done(self, fn: Callable, *args, **kwargs) -> Any:
        return until_done(self.shutdown, fn, *args, **kwargs)

    def stop_reason(self, fresh: bool = False) -> str | None:
        """Why the job should stop now (``lost``, ``shutdown``, ``cancelled``), or None. Cheap to
        ask often: the store is read at most every CANCEL_POLL_S seconds, or whenever ``fresh``
        (at chunk ends, which also write progress and checkpoints)."""
        if self.lost.is_set():
            return "lost"
        if self.shutdown.is_set():
            return "shutdown"
        seen, now = self._cancel_seen, time.monotonic()
        if fresh or now - seen["at"] >= CANCEL_POLL_S:
            seen["at"] = now
            try:
                seen["cancel"] = self.store.get(self.job.id).cancel_requested
            except StoreUnavailable:
                pass
        return "cancelled" if seen["cancel"] else None

    def report(self, progress: float, metrics: dict[str, Any]) -> None:
        """Progress and metrics on the job, and a progress event for its viewers."""
        self.best_effort(self.store.progress, self.job.id, self.worker_id, progress, metrics)
        self.best_effort(self.store.publish, self.job.id,
                         {"type": "progress", "progress": progress, "metrics": metrics})  # fmt: skip

    def phase(self, phase: str) -> None:
        """Say what a running job does before its first numbers: ``compiling`` (the jit of its
        first chunk or batch, tens of seconds cold), with the time it began."""
        self.report(self.job.progress, {"phase": phase, "phase_since": round(time.time(), 3)})

    def publish(self, event: dict[str, Any]) -> None:
        self.best_effort(self.store.publish, self.job.id, event)

    def trainer_for(self, config):
        """A warm trainer for this exact config (its compiled chunks are reused across jobs)."""
        from quicknav_core.train.trainers import make_trainer

        return self.runtime.trainers.get(config.model_dump_json(),
                                         lambda: make_trainer(config, self.runtime))  # fmt: skip

    def sweep_storage(self, sweep_id: str):
        return sweep_storage(self.settings, self.artifacts, sweep_id)
