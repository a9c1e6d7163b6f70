"""Request and response bodies of the HTTP API (one schema per direction).

The request bodies are the library's request models: the API, the CLI and the SDK send the same
requests to the same ``quicknav_core.config.resolve``.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field

from quicknav_core.config import EvalRequest, SweepRequest, TrainRequest
from service.jobs.models import JobKind, JobStatus

TrainJobCreate = TrainRequest
SweepJobCreate = SweepRequest
EvalJobCreate = EvalRequest


class JobPublic(BaseModel):
    """A job as the API shows it: ``request`` as sent, ``config`` as resolved (what runs)."""

    id: str
    kind: JobKind
    status: JobStatus
    progress: float
    metrics: dict[str, Any]
    attempts: int
    worker: str | None = Field(None, description="the worker running the job (or that ran it last)")
    error: str | None
    result: dict[str, Any] | None
    cancel_requested: bool
    created_at: float
    started_at: float | None
    finished_at: float | None
    request: dict[str, Any]
    config: dict[str, Any]
    links: dict[str, str]


class JobsPublic(BaseModel):
    data: list[JobPublic]
    count: int
