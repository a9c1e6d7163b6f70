"""The HTTP API (FastAPI). Routers are thin: validate, check limits, talk to the job store."""

from __future__ import annotations

import asyncio
import json
import logging
import math
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Depends, FastAPI, Header, HTTPException, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, PlainTextResponse, StreamingResponse
from pydantic import ValidationError

from quicknav_core.config import TrainConfig, apply_overrides
from quicknav_core.train.presets import PRESETS, get_preset
from service.jobs.models import (
    IdempotencyConflict,
    Job,
    JobKind,
    JobNotFound,
    JobStateError,
    JobStatus,
)
from service.schemas import EvalJobCreate, JobPublic, JobsPublic, SweepJobCreate, TrainJobCreate
from service.settings import Settings, get_settings, make_store

log = logging.getLogger("quicknav.api")


# --------------------------------------------------------------------------- dependencies
async def _store(request: Request):
    return request.app.state.store


async def _settings(request: Request) -> Settings:
    return request.app.state.settings


StoreDep = Annotated[Any, Depends(_store)]
SettingsDep = Annotated[Settings, Depends(_settings)]


async def require_token(
    request: Request, authorization: Annotated[str | None, Header()] = None
) -> None:
    token = request.app.state.settings.api_token
    if token is None:
        return
    if authorization != f"Bearer {token}":
        raise HTTPException(401, "missing or wrong bearer token (Authorization: Bearer <QUICKNAV_API_TOKEN>)",
                            headers={"WWW-Authenticate": "Bearer"})  # fmt: skip


def _limit_error(loc: list[str], msg: str) -> HTTPException:
    return HTTPException(422, [{"loc": ["body", *loc], "msg": msg, "type": "limit"}])


def _validation_error(e: ValidationError, prefix: list[str]) -> HTTPException:
    return HTTPException(422, [{"loc": ["body", *prefix, *map(str, err["loc"])],
                                "msg": err["msg"], "type": err["type"]} for err in e.errors()])  # fmt: skip


def check_train_limits(cfg: TrainConfig, s: Settings, where: list[str]) -> None:
    if cfg.num_envs > s.max_envs:
        raise _limit_error(
            [*where, "num_envs"],
            f"num_envs={cfg.num_envs} exceeds this server's limit max_envs={s.max_envs}",
        )
    if cfg.total_steps > s.max_total_steps:
        raise _limit_error([*where, "total_steps"],
                           f"total_steps={cfg.total_steps} exceeds this server's limit max_total_steps={s.max_total_steps}")  # fmt: skip
    if cfg.env.grid_size > s.max_grid_size:
        raise _limit_error([*where, "env", "grid_size"],
                           f"grid_size={cfg.env.grid_size} exceeds this server's limit max_grid_size={s.max_grid_size}")  # fmt: skip


def public(job: Job) -> JobPublic:
    base = f"/jobs/{job.id}"
    return JobPublic(
        id=job.id, kind=job.kind, status=job.status, progress=job.progress, metrics=job.metrics,
        attempts=job.attempts, error=job.error, result=job.result, cancel_requested=job.cancel_requested,
        created_at=job.created_at, started_at=job.started_at, finished_at=job.finished_at,
        request=job.request,
        links={"self": base, "events": f"{base}/events", "metrics": f"{base}/metrics",
               "artifacts": f"{base}/artifacts", "cancel": f"{base}/cancel"},
    )  # fmt: skip


def _submit(store, kind: JobKind, request: dict, key: str | None, response: Response) -> JobPublic:
    try:
        job, _ = store.submit(kind, request, idempotency_key=key)
    except IdempotencyConflict:
        raise HTTPException(
            409, f"Idempotency-Key {key!r} was already used with a different request body"
        ) from None
    response.status_code = 202
    response.headers["Location"] = f"/jobs/{job.id}"
    return public(job)


def _get(store, job_id: str) -> Job:
    try:
        return store.get(job_id)
    except JobNotFound:
        raise HTTPException(404, f"no job {job_id!r}") from None


# --------------------------------------------------------------------------- routes
# Submission and lookup handlers are async and call the store directly: each store call is one
# short Redis round trip or SQLite transaction, cheaper than a hop through the thread pool. Slow
# work (artifact files, deletes) stays in sync handlers, which FastAPI runs in threads.
jobs = APIRouter(prefix="/jobs", tags=["jobs"], dependencies=[Depends(require_token)])
IdemKey = Annotated[str | None, Header(alias="Idempotency-Key", max_length=200)]


@jobs.post("/train", status_code=202, response_model=JobPublic)
async def submit_train(body: TrainJobCreate, store: StoreDep, settings: SettingsDep, response: Response,
                 idempotency_key: IdemKey = None) -> JobPublic:  # fmt: skip
    if body.preset is not None:
        if body.preset not in PRESETS:
            raise HTTPException(422, [{"loc": ["body", "preset"], "type": "value_error",
                                       "msg": f"unknown preset {body.preset!r}; known: {', '.join(PRESETS)}"}])  # fmt: skip
        try:
            overrides = [f"{k}={json.dumps(v)}" for k, v in body.overrides.items()]
            cfg = apply_overrides(get_preset(body.preset), overrides)
        except ValidationError as e:
            raise _validation_error(e, ["overrides"]) from None
        except ValueError as e:
            raise HTTPException(
                422, [{"loc": ["body", "overrides"], "msg": str(e), "type": "value_error"}]
            ) from None
    else:
        cfg = body.config
    check_train_limits(cfg, settings, ["config"])
    return _submit(
        store, JobKind.train, {"config": cfg.model_dump(mode="json")}, idempotency_key, response
    )


@jobs.post("/sweep", status_code=202, response_model=JobPublic)
async def submit_sweep(body: SweepJobCreate, store: StoreDep, settings: SettingsDep, response: Response,
                 idempotency_key: IdemKey = None) -> JobPublic:  # fmt: skip
    from quicknav_core.sweep import builtin_sweep

    if body.config is not None:
        cfg = body.config
    else:
        cfg = builtin_sweep(
            body.space, trials=body.trials, parallel=body.parallel, study_name=body.space
        )
        cfg = cfg.model_copy(
            update={"base": cfg.base.model_copy(update={"total_steps": body.total_steps})}
        )
    if cfg.storage is not None:
        raise _limit_error(
            ["config", "storage"],
            "sweep jobs keep their study in the job's folder; leave storage unset",
        )
    if cfg.trials > settings.max_sweep_trials:
        raise _limit_error(
            ["config", "trials"] if body.config is not None else ["trials"],
            f"trials={cfg.trials} exceeds this server's limit max_sweep_trials={settings.max_sweep_trials}",
        )
    check_train_limits(cfg.base, settings, ["config", "base"])
    return _submit(
        store, JobKind.sweep, {"config": cfg.model_dump(mode="json")}, idempotency_key, response
    )


@jobs.post("/eval", status_code=202, response_model=JobPublic)
async def submit_eval(body: EvalJobCreate, store: StoreDep, settings: SettingsDep, response: Response,
                idempotency_key: IdemKey = None) -> JobPublic:  # fmt: skip
    from quicknav_core.config import EnvConfig

    if body.episodes > settings.max_eval_episodes:
        raise _limit_error(
            ["episodes"],
            f"episodes={body.episodes} exceeds this server's limit max_eval_episodes={settings.max_eval_episodes}",
        )
    if body.job_id is not None:
        if body.env:
            raise HTTPException(422, [{"loc": ["body", "env"], "type": "value_error",
                                       "msg": "env applies to baseline policies only: a trained job is"
                                              " evaluated in its own env config (leave env out)"}])  # fmt: skip
        src = _get(store, body.job_id)
        if src.kind != JobKind.train:
            raise HTTPException(422, [{"loc": ["body", "job_id"], "type": "value_error",
                                       "msg": f"job {body.job_id} is a {src.kind.value} job; eval needs a train job"}])  # fmt: skip
        ckpt = settings.artifacts_dir / src.id / "checkpoint" / "state.msgpack"
        if not ckpt.exists():
            raise HTTPException(
                409, f"train job {src.id} has no checkpoint yet (status {src.status.value})"
            )
    else:
        try:
            env = EnvConfig.model_validate(body.env)
        except ValidationError as e:
            raise _validation_error(e, ["env"]) from None
        if env.grid_size > settings.max_grid_size:
            raise _limit_error(
                ["env", "grid_size"],
                f"grid_size={env.grid_size} exceeds max_grid_size={settings.max_grid_size}",
            )
    return _submit(store, JobKind.eval, body.model_dump(mode="json"), idempotency_key, response)


# SQLite binds 64-bit integers only; no store holds anywhere near this many jobs.
MAX_LIST_OFFSET = 2**31 - 1
MAX_EVENT_ID = 2**63 - 1  # event ids are SQLite/Redis 64-bit integers


@jobs.get("", response_model=JobsPublic)
async def list_jobs(store: StoreDep, status: JobStatus | None = None, kind: JobKind | None = None,
              limit: Annotated[int, Query(ge=1, le=500)] = 50,
              offset: Annotated[int, Query(ge=0, le=MAX_LIST_OFFSET)] = 0) -> JobsPublic:  # fmt: skip
    data, count = store.list(status=status, kind=kind, limit=limit, offset=offset)
    return JobsPublic(data=[public(j) for j in data], count=count)


@jobs.get("/{job_id}", response_model=JobPublic)
async def get_job(job_id: str, store: StoreDep) -> JobPublic:
    return public(_get(store, job_id))


@jobs.post("/{job_id}/cancel", response_model=JobPublic)
async def cancel_job(job_id: str, store: StoreDep) -> JobPublic:
    _get(store, job_id)
    return public(store.cancel(job_id))


@jobs.delete("/{job_id}", status_code=204)
def delete_job(job_id: str, store: StoreDep, settings: SettingsDep) -> Response:
    _get(store, job_id)
    try:
        store.delete(job_id)
    except JobStateError as e:
        raise HTTPException(409, str(e)) from None
    import shutil

    shutil.rmtree(settings.artifacts_dir / job_id, ignore_errors=True)
    return Response(status_code=204)


@jobs.get("/{job_id}/metrics")
def job_metrics(job_id: str, store: StoreDep, settings: SettingsDep) -> dict:
    job = _get(store, job_id)
    path = settings.artifacts_dir / job.id / "metrics.jsonl"
    rows = (
        [json.loads(x) for x in path.read_text().splitlines() if x.strip()] if path.exists() else []
    )
    return {"job_id": job.id, "metrics": rows}


def _artifact_files(root: Path) -> list[dict]:
    if not root.exists():
        return []
    out = []
    for p in sorted(root.rglob("*")):
        if p.is_file() and not p.name.endswith(".tmp"):
            out.append({"name": p.relative_to(root).as_posix(), "bytes": p.stat().st_size})
    return out


@jobs.get("/{job_id}/artifacts")
def list_artifacts(job_id: str, store: StoreDep, settings: SettingsDep) -> dict:
    job = _get(store, job_id)
    return {"job_id": job.id, "artifacts": _artifact_files(settings.artifacts_dir / job.id)}


@jobs.get("/{job_id}/artifacts/{name:path}")
def get_artifact(job_id: str, name: str, store: StoreDep, settings: SettingsDep):
    job = _get(store, job_id)
    root = (settings.artifacts_dir / job.id).resolve()
    target = (root / name).resolve()
    if not target.is_relative_to(root):
        raise HTTPException(400, f"artifact name {name!r} leaves the job's folder")
    if not target.is_file():
        raise HTTPException(404, f"job {job_id} has no artifact {name!r}")
    return FileResponse(target)


class BodyLimit:
    """Refuse request bodies over ``max_bytes`` with 413: by Content-Length up front, and by
    counting for chunked bodies. Pure ASGI (a BaseHTTPMiddleware costs a task per request)."""

    def __init__(self, app, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    def _too_large(self, size: int | str) -> str:
        return f"request body of {size} bytes exceeds the limit of {self.max_bytes} bytes"

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        for name, value in scope["headers"]:
            if name == b"content-length" and value.isdigit() and int(value) > self.max_bytes:
                response = JSONResponse(
                    {"detail": self._too_large(value.decode())}, status_code=413
                )
                return await response(scope, receive, send)
        received = 0

        async def counted():
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise HTTPException(413, self._too_large(f"more than {received}"))
            return message

        return await self.app(scope, counted, send)


def _json_safe(value):
    """JSON without NaN/Infinity (browsers' JSON.parse rejects them): non-finite floats -> null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


@jobs.get("/{job_id}/events")
async def job_events(job_id: str, request: Request, store: StoreDep,
                     last_event_id: Annotated[str | None, Header(alias="Last-Event-ID")] = None):  # fmt: skip
    """Server-Sent Events of the job's progress; resumable with Last-Event-ID; ends with the terminal event."""
    await anyio.to_thread.run_sync(_get, store, job_id)
    try:
        after = int(last_event_id) if last_event_id else 0
        if not 0 <= after <= MAX_EVENT_ID:
            raise ValueError
    except ValueError:
        raise HTTPException(
            400, f"Last-Event-ID must be an event id (an integer from 0 to {MAX_EVENT_ID})"
        ) from None

    async def stream():
        nonlocal after
        idle = 0.0
        while True:
            if await request.is_disconnected():
                return
            try:
                events = await anyio.to_thread.run_sync(store.events, job_id, after)
                job = None if events else await anyio.to_thread.run_sync(store.get, job_id)
            except JobNotFound:  # deleted while someone was watching: say so and end cleanly
                yield f"event: deleted\ndata: {json.dumps({'type': 'deleted', 'job_id': job_id})}\n\n"
                return
            for seq, ev in events:
                after = seq
                data = json.dumps(_json_safe(ev), allow_nan=False)
                yield f"id: {seq}\nevent: {ev.get('type', 'message')}\ndata: {data}\n\n"
                if ev.get("type") in ("succeeded", "failed", "cancelled"):
                    return
            if events:
                idle = 0.0
                continue
            if job.status.finished and not await anyio.to_thread.run_sync(
                store.events, job_id, after
            ):
                return
            idle += 0.05
            if idle >= 15:
                yield ": keep-alive\n\n"
                idle = 0.0
            await asyncio.sleep(0.05)

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})  # fmt: skip


misc = APIRouter(tags=["service"])


@misc.get("/healthz")
async def healthz() -> dict:
    return {"status": "ok"}


@misc.get("/readyz")
def readyz(store: StoreDep) -> Response:
    try:
        store.counts()
    except Exception as e:
        return JSONResponse(
            {"status": "unavailable", "detail": f"{type(e).__name__}: {e}"}, status_code=503
        )
    return JSONResponse({"status": "ready"})


@misc.get("/presets", dependencies=[Depends(require_token)])
def presets() -> dict:
    return {
        name: {"description": p["description"], "config": p["config"]}
        for name, p in PRESETS.items()
    }


@misc.get("/metrics", response_class=PlainTextResponse)
def prometheus(request: Request, store: StoreDep) -> str:
    counts = store.counts()
    running, _ = store.list(status=JobStatus.running, limit=500)
    steps = sum(float(j.metrics.get("steps_per_s", 0.0) or 0.0) for j in running)
    workers = getattr(request.app.state, "workers", [])
    lines = ["# HELP quicknav_jobs Jobs by status.", "# TYPE quicknav_jobs gauge"]
    lines += [f'quicknav_jobs{{status="{s}"}} {n}' for s, n in counts.items()]
    lines += ["# HELP quicknav_queue_depth Jobs waiting for a worker.", "# TYPE quicknav_queue_depth gauge",
              f"quicknav_queue_depth {counts.get('queued', 0)}",
              "# HELP quicknav_busy_workers Jobs being run by a worker.", "# TYPE quicknav_busy_workers gauge",
              f"quicknav_busy_workers {counts.get('running', 0)}",
              "# HELP quicknav_embedded_workers In-process workers of this API process.",
              "# TYPE quicknav_embedded_workers gauge", f"quicknav_embedded_workers {len(workers)}",
              "# HELP quicknav_env_steps_per_second Training throughput of running jobs.",
              "# TYPE quicknav_env_steps_per_second gauge", f"quicknav_env_steps_per_second {steps:.1f}"]  # fmt: skip
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- app
def create_app(
    settings: Settings | None = None, store=None, start_workers: bool | None = None
) -> FastAPI:
    """The API; with ``start_workers`` (default: settings.embedded_worker) in-process workers run too."""
    settings = settings or get_settings()
    store = store if store is not None else make_store(settings)
    settings.artifacts_dir.mkdir(parents=True, exist_ok=True)
    run_workers = settings.embedded_worker if start_workers is None else start_workers

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        app.state.workers = []
        if run_workers:
            from service.worker import start_worker_threads

            app.state.workers = start_worker_threads(store, settings, settings.max_concurrent_jobs)
        yield
        if app.state.workers:
            from service.worker import wait_idle

            await anyio.to_thread.run_sync(wait_idle, app.state.workers)

    app = FastAPI(title="QuickNav", version="0.1.0", lifespan=lifespan,
                  description="Submit train, sweep and eval jobs; follow their progress; fetch results.")  # fmt: skip
    app.state.settings = settings
    app.state.store = store
    app.state.workers = []

    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)

    @app.exception_handler(RequestValidationError)
    async def validation_handler(request: Request, exc: RequestValidationError):
        detail = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
        return JSONResponse({"detail": detail}, status_code=422)

    app.include_router(jobs)
    app.include_router(misc)
    return app
