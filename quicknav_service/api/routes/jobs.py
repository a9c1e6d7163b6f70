"""Job submission and lookup: thin over the jobs service (``quicknav_service.jobs.service``), which
resolves a body into a config, checks this server's limits and talks to the store."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Query, Response

from quicknav_service.api.deps import JobId, JobsDep, SettingsDep, StoreDep, require_token
from quicknav_service.api.errors import AUTH, CHANGE, STORE, responses
from quicknav_service.disk import disk_full
from quicknav_service.jobs.capabilities import Capabilities, job_needs, waiting_reason
from quicknav_service.jobs.models import Job, JobKind, JobStatus
from quicknav_service.schemas import (
    CancelRequest,
    EvalJobCreate,
    JobPublic,
    JobsPublic,
    SweepJobCreate,
    TrainJobCreate,
)

router = APIRouter(prefix="/jobs", tags=["jobs"], dependencies=[Depends(require_token)],
                   responses=responses(*AUTH, *STORE, 422))  # fmt: skip
IdemKey = Annotated[str | None, Header(
    alias="Idempotency-Key", max_length=200,
    description="the same key with the same body returns the same job (a retry is safe)",
)]  # fmt: skip

# SQLite binds 64-bit integers only; no store holds anywhere near this many jobs.
MAX_LIST_OFFSET = 2**31 - 1
SUBMITTED = {"description": "queued", "headers": {"Location": {
    "description": "the job's URL", "required": True, "schema": {"type": "string"}}}}  # fmt: skip


@dataclass(frozen=True)
class Waits:
    """What a queued job may wait for, read once per request: the live workers, and whether
    this server's data folder is full."""

    live: list[Capabilities]
    disk_full: bool = False

    @classmethod
    def now(cls, store, settings) -> Waits:
        return cls(live_workers(store), disk_full(settings.data_dir))


def public(job: Job, waits: Waits | None = None) -> JobPublic:
    """A stored job as the API shows it; given what queued jobs ``waits`` for, a queued job that
    cannot start says why (the data volume is full, or no live worker can run it)."""
    base = f"/jobs/{job.id}"
    warnings = (job.result or {}).get("warnings") or []
    waiting = None
    if waits is not None and job.status == JobStatus.queued:
        waiting = waiting_reason(job_needs(job), waits.live, waits.disk_full)
    return JobPublic(
        id=job.id, kind=job.kind, status=job.status, progress=job.progress, metrics=job.metrics,
        attempts=job.attempts, worker=job.worker, error=job.error, result=job.result,
        warnings=[str(w) for w in warnings], cancel_requested=job.cancel_requested, waiting=waiting,
        created_at=job.created_at, started_at=job.started_at, finished_at=job.finished_at,
        request=job.request, config=job.config,
        links={"self": base, "events": f"{base}/events", "metrics": f"{base}/metrics",
               "artifacts": f"{base}/artifacts", "cancel": f"{base}/cancel"},
    )  # fmt: skip


def live_workers(store) -> list[Capabilities]:
    """The workers that announced themselves and have not expired."""
    out = []
    for info in store.live_workers():
        try:
            out.append(Capabilities.from_dict(info))
        except (KeyError, TypeError):
            continue  # an announcement of another version
    return out


def rendered(model: JobPublic | JobsPublic) -> Response:
    """The model as JSON bytes, encoded here in the handler's thread: a page of jobs (their configs
    included) left to FastAPI would be encoded on the event loop, and hold up every other request."""
    return Response(model.model_dump_json(), media_type="application/json")


def _submitted(job: Job, response: Response) -> JobPublic:
    response.headers["Location"] = f"/jobs/{job.id}"
    return public(job)


# Every handler is a plain function: FastAPI runs it in its thread pool, so a store call, a
# checkpoint's hash (an eval's submission) or a slow Redis never holds the event loop that
# answers /healthz and feeds the event streams.
@router.post("/train", status_code=202, response_model=JobPublic,
             responses={202: SUBMITTED, **responses(*CHANGE, 409)})  # fmt: skip
def submit_train_job(body: TrainJobCreate, jobs: JobsDep, response: Response,
                           idempotency_key: IdemKey = None) -> JobPublic:  # fmt: skip
    """Train from a preset or a full TrainConfig, with dotted-key overrides on top."""
    return _submitted(jobs.submit_train(body, idempotency_key), response)


@router.post("/sweep", status_code=202, response_model=JobPublic,
             responses={202: SUBMITTED, **responses(*CHANGE, 409)})  # fmt: skip
def submit_sweep_job(body: SweepJobCreate, jobs: JobsDep, response: Response,
                           idempotency_key: IdemKey = None) -> JobPublic:  # fmt: skip
    """An Optuna sweep: a built-in space or a full SweepConfig, with overrides on top."""
    return _submitted(jobs.submit_sweep(body, idempotency_key), response)


@router.post("/eval", status_code=202, response_model=JobPublic,
             responses={202: SUBMITTED, **responses(*CHANGE, 404, 409)})  # fmt: skip
def submit_eval_job(body: EvalJobCreate, jobs: JobsDep, response: Response,
                          idempotency_key: IdemKey = None) -> JobPublic:  # fmt: skip
    """Evaluate a train job's checkpoint or a baseline on fixed-seed held-out episodes."""
    return _submitted(jobs.submit_eval(body, idempotency_key), response)


@router.get("", response_model=JobsPublic)
def list_jobs(store: StoreDep, settings: SettingsDep, status: JobStatus | None = None,
                    kind: JobKind | None = None,
                    limit: Annotated[int, Query(ge=1, le=500)] = 50,
                    offset: Annotated[int, Query(ge=0, le=MAX_LIST_OFFSET)] = 0) -> JobsPublic:  # fmt: skip
    """Jobs, newest first; ``count`` is the number matching the filter."""
    data, count = store.list(status=status, kind=kind, limit=limit, offset=offset)
    waits = Waits.now(store, settings) if any(j.status == JobStatus.queued for j in data) else None
    return rendered(JobsPublic(data=[public(j, waits) for j in data], count=count))


@router.get("/{job_id}", response_model=JobPublic, responses=responses(404, 409))
def read_job(job_id: JobId, jobs: JobsDep, store: StoreDep, settings: SettingsDep) -> JobPublic:
    """One job, by its id or a unique prefix of it; a queued job that cannot start says why in
    ``waiting`` (the data volume is full, or no live worker can run it)."""
    job = jobs.get(job_id)
    queued = job.status == JobStatus.queued
    return rendered(public(job, Waits.now(store, settings) if queued else None))


@router.post("/{job_id}/cancel", response_model=JobPublic,
             responses=responses(*CHANGE, 404, 409),
             # clients send {}; the web view's requests instead carry X-QuickNav-Web: 1, which the
             # schema cannot say as an alternative to the body, so it documents the body
             openapi_extra={"requestBody": {"required": True}})  # fmt: skip
def cancel_job(job_id: JobId, jobs: JobsDep, body: CancelRequest | None = None) -> JobPublic:
    """A queued job is cancelled at once; a running one stops at its next chunk boundary. Send
    ``{}`` as a JSON body (or the web view's header): a cross-site form cannot."""
    return public(jobs.cancel(job_id))


@router.delete("/{job_id}", status_code=204, response_class=Response,
               responses={204: {"description": "deleted"}, **responses(403, 404, 409)})  # fmt: skip
def delete_job(job_id: JobId, jobs: JobsDep) -> Response:
    """Delete a finished job and its artifacts (a sweep: with its trial batches)."""
    jobs.delete(job_id)
    return Response(status_code=204)
