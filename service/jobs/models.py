"""Job records and the store protocol shared by the SQLite and Redis stores."""

from __future__ import annotations

import hashlib
import json
import time
import uuid
from enum import StrEnum
from typing import Any, Protocol

from pydantic import BaseModel, Field


class JobStatus(StrEnum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"

    @property
    def finished(self) -> bool:
        return self in (JobStatus.succeeded, JobStatus.failed, JobStatus.cancelled)


class JobKind(StrEnum):
    train = "train"
    sweep = "sweep"
    eval = "eval"


class Job(BaseModel):
    """One job as stored (JSON, never pickle)."""

    id: str
    kind: JobKind
    status: JobStatus = JobStatus.queued
    request: dict[str, Any]
    created_at: float
    updated_at: float
    started_at: float | None = None
    finished_at: float | None = None
    attempts: int = 0
    max_attempts: int = 3
    worker: str | None = None
    lease_until: float | None = None
    progress: float = 0.0
    metrics: dict[str, Any] = Field(default_factory=dict)
    result: dict[str, Any] | None = None
    error: str | None = None
    cancel_requested: bool = False
    idempotency_key: str | None = None
    request_hash: str = ""


class IdempotencyConflict(Exception):
    """The idempotency key was used before with a different request body."""


class JobNotFound(KeyError):
    pass


class JobStateError(Exception):
    """The operation does not fit the job's state (e.g. deleting a running job)."""


def request_hash(kind: str, request: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps([kind, request], sort_keys=True).encode()).hexdigest()


def new_job(
    kind: JobKind, request: dict[str, Any], idempotency_key: str | None, max_attempts: int
) -> Job:
    now = time.time()
    return Job(
        id=uuid.uuid4().hex, kind=kind, request=request, created_at=now, updated_at=now,
        max_attempts=max_attempts, idempotency_key=idempotency_key,
        request_hash=request_hash(kind, request),
    )  # fmt: skip


class JobStore(Protocol):
    """What the API and the workers need from a job store (both implementations pass one contract)."""

    def submit(
        self, kind: JobKind, request: dict[str, Any], idempotency_key: str | None = None
    ) -> tuple[Job, bool]:
        """Queue a job; returns (job, created). A repeated key with the same body returns the same
        job (created False); with a different body raises IdempotencyConflict."""

    def get(self, job_id: str) -> Job: ...

    def list(self, status: JobStatus | None = None, kind: JobKind | None = None, limit: int = 50,
             offset: int = 0) -> tuple[list[Job], int]: ...  # fmt: skip

    def claim(self, worker: str, lease_s: float) -> Job | None:
        """Take the oldest queued job, or reclaim one whose worker's lease expired."""

    def heartbeat(self, job_id: str, worker: str, lease_s: float) -> bool:
        """Extend the lease; False if the job is no longer this worker's."""

    def progress(
        self, job_id: str, worker: str, progress: float, metrics: dict[str, Any]
    ) -> None: ...

    def finish(self, job_id: str, worker: str, status: JobStatus, result: dict[str, Any] | None = None,
               error: str | None = None) -> Job: ...  # fmt: skip

    def release(self, job_id: str, worker: str) -> None:
        """Hand a running job back to the queue (graceful shutdown)."""

    def cancel(self, job_id: str) -> Job:
        """Queued: cancelled at once. Running: flagged, the worker stops at a chunk boundary."""

    def delete(self, job_id: str) -> None: ...

    def publish(self, job_id: str, event: dict[str, Any]) -> int:
        """Append a progress event; returns its id (increasing per job)."""

    def events(
        self, job_id: str, after: int = 0, limit: int = 1000
    ) -> list[tuple[int, dict[str, Any]]]: ...

    def counts(self) -> dict[str, int]:
        """Jobs per status."""
