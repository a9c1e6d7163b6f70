"""Job submission and lookup. A body becomes a config in ``quicknav_core.config.resolve`` (the same
function behind the CLI and the SDK); the job stores the body as sent and the resolved config."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Header, HTTPException, Query, Response

from quicknav_core.config import (
    ConfigError,
    EnvConfig,
    TrainConfig,
    resolve_eval,
    resolve_sweep,
    resolve_train,
)
from service.api.deps import SettingsDep, StoreDep, get_job, require_token
from service.api.limits import Origin, check_eval, check_sweep, check_train
from service.jobs.models import (
    IdempotencyConflict,
    Job,
    JobKind,
    JobStateError,
    JobStatus,
    JobStore,
)
from service.schemas import EvalJobCreate, JobPublic, JobsPublic, SweepJobCreate, TrainJobCreate
from service.settings import Settings

router = APIRouter(prefix="/jobs", tags=["jobs"], dependencies=[Depends(require_token)])
IdemKey = Annotated[str | None, Header(alias="Idempotency-Key", max_length=200)]

# SQLite binds 64-bit integers only; no store holds anywhere near this many jobs.
MAX_LIST_OFFSET = 2**31 - 1


def public(job: Job) -> JobPublic:
    base = f"/jobs/{job.id}"
    return JobPublic(
        id=job.id, kind=job.kind, status=job.status, progress=job.progress, metrics=job.metrics,
        attempts=job.attempts, worker=job.worker, error=job.error, result=job.result, cancel_requested=job.cancel_requested,
        created_at=job.created_at, started_at=job.started_at, finished_at=job.finished_at,
        request=job.request, config=job.config,
        links={"self": base, "events": f"{base}/events", "metrics": f"{base}/metrics",
               "artifacts": f"{base}/artifacts", "cancel": f"{base}/cancel"},
    )  # fmt: skip


def _unprocessable(e: ConfigError) -> HTTPException:
    detail = [{"loc": ["body", *i["loc"]], "msg": i["msg"], "type": i["type"]} for i in e.items]
    return HTTPException(422, detail)


def _submit(store: JobStore, kind: JobKind, body: dict[str, Any], config: dict[str, Any],
            key: str | None, response: Response) -> JobPublic:  # fmt: skip
    try:
        job, _ = store.submit(kind, body, config, idempotency_key=key)
    except IdempotencyConflict:
        raise HTTPException(
            409, f"Idempotency-Key {key!r} was already used with a different request body"
        ) from None
    response.status_code = 202
    response.headers["Location"] = f"/jobs/{job.id}"
    return public(job)


def _as_sent(body) -> dict[str, Any]:
    """The request body as the client set it (defaults left out): stored and hashed."""
    return body.model_dump(mode="json", exclude_unset=True)


# Submission and lookup handlers are async and call the store directly: each store call is one
# short Redis round trip or SQLite transaction, cheaper than a hop through the thread pool. Slow
# work (artifact files, deletes) stays in sync handlers, which FastAPI runs in threads.
@router.post("/train", status_code=202, response_model=JobPublic)
async def submit_train(body: TrainJobCreate, store: StoreDep, settings: SettingsDep,
                       response: Response, idempotency_key: IdemKey = None) -> JobPublic:  # fmt: skip
    """Train from a preset or a full TrainConfig, with dotted-key overrides on top."""
    sent = _as_sent(body)
    try:
        cfg = resolve_train(body)
    except ConfigError as e:
        raise _unprocessable(e) from None
    check_train(cfg, settings, Origin(sent))
    return _submit(store, JobKind.train, sent, cfg.model_dump(mode="json"), idempotency_key,
                   response)  # fmt: skip


@router.post("/sweep", status_code=202, response_model=JobPublic)
async def submit_sweep(body: SweepJobCreate, store: StoreDep, settings: SettingsDep,
                       response: Response, idempotency_key: IdemKey = None) -> JobPublic:  # fmt: skip
    """An Optuna sweep: a built-in space or a full SweepConfig, with overrides on top."""
    sent = _as_sent(body)
    try:
        cfg = resolve_sweep(body)
    except ConfigError as e:
        raise _unprocessable(e) from None
    origin = Origin(sent, fallback="space", shorthands=("trials", "parallel", "total_steps"),
                    prefix="base.")  # fmt: skip
    check_sweep(cfg, settings, origin)
    return _submit(store, JobKind.sweep, sent, cfg.model_dump(mode="json"), idempotency_key,
                   response)  # fmt: skip


def trained_env(store: JobStore, settings: Settings, job_id: str) -> EnvConfig:
    """The env a train job trained in, if it can be evaluated (404 / 422 / 409 otherwise)."""
    src = get_job(store, job_id)
    if src.kind != JobKind.train:
        raise HTTPException(422, [{"loc": ["body", "job_id"], "type": "value_error",
                                   "msg": f"job {job_id} is a {src.kind.value} job; eval needs a train job"}])  # fmt: skip
    from quicknav_core.train.run import checkpoint_dir

    if checkpoint_dir(settings.artifacts_dir / src.id) is None:
        raise HTTPException(409, f"train job {src.id} has no checkpoint yet (status {src.status.value})")
    config = src.config or src.request.get("config")  # jobs stored before configs were: the request
    return TrainConfig.model_validate(config).env


@router.post("/eval", status_code=202, response_model=JobPublic)
async def submit_eval(body: EvalJobCreate, store: StoreDep, settings: SettingsDep,
                      response: Response, idempotency_key: IdemKey = None) -> JobPublic:  # fmt: skip
    """Evaluate a train job's checkpoint or a baseline on fixed-seed held-out episodes."""
    sent = _as_sent(body)
    if body.source is not None:  # a short id names the job by its full one in the stored config
        body = body.model_copy(update={"source": get_job(store, body.source).id})
    try:
        cfg = resolve_eval(body, trained_env=lambda job_id: trained_env(store, settings, job_id))
    except ConfigError as e:
        raise _unprocessable(e) from None
    check_eval(cfg, settings)
    return _submit(store, JobKind.eval, sent, cfg.model_dump(mode="json"), idempotency_key,
                   response)  # fmt: skip


@router.get("", response_model=JobsPublic)
async def list_jobs(store: StoreDep, status: JobStatus | None = None, kind: JobKind | None = None,
                    limit: Annotated[int, Query(ge=1, le=500)] = 50,
                    offset: Annotated[int, Query(ge=0, le=MAX_LIST_OFFSET)] = 0) -> JobsPublic:  # fmt: skip
    """Jobs, newest first; ``count`` is the number matching the filter."""
    data, count = store.list(status=status, kind=kind, limit=limit, offset=offset)
    return JobsPublic(data=[public(j) for j in data], count=count)


@router.get("/{job_id}", response_model=JobPublic)
async def read_job(job_id: str, store: StoreDep) -> JobPublic:
    return public(get_job(store, job_id))


@router.post("/{job_id}/cancel", response_model=JobPublic)
async def cancel_job(job_id: str, store: StoreDep) -> JobPublic:
    """A queued job is cancelled at once; a running one stops at its next chunk boundary."""
    return public(store.cancel(get_job(store, job_id).id))


@router.delete("/{job_id}", status_code=204)
def delete_job(job_id: str, store: StoreDep, settings: SettingsDep) -> Response:
    """Delete a finished job and its artifacts. The files go first: on a full disk that frees the
    space the store needs to delete the record."""
    import shutil

    job = get_job(store, job_id)
    if not job.status.finished:
        raise HTTPException(409, f"job {job.id} is {job.status.value}; only finished jobs can be deleted")
    if job.kind == JobKind.sweep:  # its trial batches go with it
        batches, _ = store.list(kind=JobKind.trial, limit=500)
        mine = [b for b in batches if b.config.get("parent") == job.id]
        busy = [b.id for b in mine if not b.status.finished]
        if busy:
            raise HTTPException(409, f"sweep {job.id} still has running trial batches ({', '.join(busy)});"
                                     " delete it once they have stopped")  # fmt: skip
        for b in mine:
            shutil.rmtree(settings.artifacts_dir / b.id, ignore_errors=True)
            store.delete(b.id)
    shutil.rmtree(settings.artifacts_dir / job.id, ignore_errors=True)
    try:
        store.delete(job.id)
    except JobStateError as e:
        raise HTTPException(409, str(e)) from None
    return Response(status_code=204)
