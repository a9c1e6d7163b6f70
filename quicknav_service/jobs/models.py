"""Job records and the store protocol shared by the SQLite and Redis stores."""

from __future__ import annotations

import hashlib
import json
import time
import uuid
from collections.abc import Callable
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
    trial = "trial"  # a batch of a sweep's trials: a child job the sweep submits, never a client


class Job(BaseModel):
    """One job as stored (JSON, never pickle).

    ``request`` is the body as the client sent it (shown back, and hashed for idempotency);
    ``config`` is what ``quicknav_core.config.resolve`` made of it, the only thing a worker reads.
    """

    id: str
    kind: JobKind
    status: JobStatus = JobStatus.queued
    request: dict[str, Any]
    config: dict[str, Any] = Field(default_factory=dict)
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


class AmbiguousId(KeyError):
    """A short id that is the prefix of several jobs' ids."""

    def __init__(self, prefix: str, matches: list[str]):
        super().__init__(prefix)
        self.prefix = prefix
        self.matches = matches


class JobStateError(Exception):
    """The operation does not fit the job's state (e.g. deleting a running job)."""


class StoreUnavailable(Exception):
    """The store cannot be reached, or cannot write, right now: retry later.

    ``reason`` says what is wrong in words a client may see ("unreachable", "disk full"): never a
    host, port or path. ``disk_full`` marks a store that answers but cannot write.
    """

    def __init__(self, reason: str, disk_full: bool = False, retry_after_s: int = 5):
        super().__init__(reason)
        self.reason = reason
        self.disk_full = disk_full
        self.retry_after_s = retry_after_s


# the store protocol's methods (the ones a guard wraps)
STORE_METHODS = ("submit", "get", "list", "claim", "heartbeat", "progress", "finish", "release",
                 "cancel", "delete", "publish", "events", "counts", "resolve_id",
                 "register_endpoint", "endpoints", "unregister_endpoint", "counts_by_kind",
                 "wait_events", "announce_worker", "live_workers", "withdraw_worker")  # fmt: skip


def guard_store_errors(cls, translate):
    """Wrap a store class's protocol methods so that ``translate(exc)`` (returning a
    ``StoreUnavailable`` or None) turns backend outages into ``StoreUnavailable``."""
    import functools

    def wrap(fn):
        @functools.wraps(fn)
        def guarded(*args, **kwargs):
            try:
                return fn(*args, **kwargs)
            except StoreUnavailable:
                raise
            except Exception as e:
                unavailable = translate(e)
                if unavailable is None:
                    raise
                raise unavailable from e

        return guarded

    for name in STORE_METHODS:
        if name in cls.__dict__:
            setattr(cls, name, wrap(cls.__dict__[name]))
    return cls


def request_hash(kind: str, request: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps([kind, request], sort_keys=True).encode()).hexdigest()


def new_job(
    kind: JobKind,
    request: dict[str, Any],
    config: dict[str, Any],
    idempotency_key: str | None,
    max_attempts: int,
) -> Job:
    now = time.time()
    return Job(
        id=uuid.uuid4().hex, kind=kind, request=request, config=config, created_at=now,
        updated_at=now, max_attempts=max_attempts, idempotency_key=idempotency_key,
        request_hash=request_hash(kind, request),
    )  # fmt: skip


class JobStore(Protocol):
    """What the API and the workers need from a job store (both implementations pass one contract)."""

    def submit(
        self,
        kind: JobKind,
        request: dict[str, Any],
        config: dict[str, Any],
        idempotency_key: str | None = None,
    ) -> tuple[Job, bool]:
        """Queue a job with the request as sent and the config resolved from it; returns (job,
        created). A repeated key with the same request returns the same job (created False); with
        a different request raises IdempotencyConflict."""

    def get(self, job_id: str) -> Job: ...

    def list(self, status: JobStatus | None = None, kind: JobKind | None = None, limit: int = 50,
             offset: int = 0) -> tuple[list[Job], int]: ...  # fmt: skip

    def claim(self, worker: str, lease_s: float,
              can_run: Callable[[Job], bool] | None = None) -> Job | None:  # fmt: skip
        """Take the oldest queued job, or reclaim one whose worker's lease expired, among those
        ``can_run`` accepts (default: any); None if there is none."""

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

    def counts_by_kind(self) -> dict[str, dict[str, int]]:
        """Jobs per kind and status: ``{kind: {status: n}}``, every kind and status present."""

    def wait_events(self, after: dict[str, int], timeout_s: float) -> set[str]:
        """Block until one of the jobs ``after`` names has an event past its number there, or
        ``timeout_s`` passed: the ids of the jobs with news (empty on a timeout). One call serves
        every viewer of those jobs."""

    def resolve_id(self, prefix: str) -> str:
        """The full id of the one job whose id starts with ``prefix`` (JobNotFound if none,
        AmbiguousId if several)."""

    def announce_worker(self, info: dict[str, Any], ttl_s: float) -> None:
        """A worker says what it has (``info["worker"]`` names it) for ``ttl_s``."""

    def live_workers(self) -> list[dict[str, Any]]:
        """The workers whose announcement has not expired, by name."""

    def withdraw_worker(self, worker: str) -> None:
        """A worker that stops takes its announcement back."""

    def register_endpoint(self, endpoint: dict[str, Any], ttl_s: float) -> None:
        """Announce a gRPC Rollout endpoint (``endpoint["worker"]`` names it) for ``ttl_s``
        seconds; announcing again renews it."""

    def endpoints(self) -> list[dict[str, Any]]:
        """The Rollout endpoints announced and not yet expired, oldest first."""

    def unregister_endpoint(self, worker: str) -> None:
        """Withdraw an endpoint (a worker that stops)."""

    def create_session(self, key: str, proof: str, ttl_s: float) -> None:
        """Keep a browser session for ``ttl_s`` seconds: ``key`` names it (a digest of the
        cookie's random id, never the id), ``proof`` ties it to the token it was opened with."""

    def session_proof(self, key: str) -> str | None:
        """The proof of an open, unexpired session, or None."""

    def delete_session(self, key: str) -> None:
        """Close a session (sign-out)."""
