"""Operations: liveness, readiness, the presets, Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse, PlainTextResponse, Response

from quicknav_core.config.presets import preset_summaries
from quicknav_service.api.deps import SettingsDep, StoreDep, require_metrics_token, require_token
from quicknav_service.api.errors import AUTH, STORE, responses
from quicknav_service.disk import disk_check
from quicknav_service.jobs.models import StoreUnavailable
from quicknav_service.schemas import (
    Health,
    PresetPublic,
    Readiness,
    RolloutEndpoint,
    RolloutEndpoints,
)

router = APIRouter(tags=["service"])


@router.get("/healthz", response_model=Health)
async def healthz() -> Health:
    """The API process is up."""
    return Health(status="ok")


def artifacts_check(settings) -> str:
    """``ok``, or what failed (the kind of error, not where the store lives or its answer)."""
    from quicknav_service.artifacts import ArtifactUnavailable, make_artifacts

    try:
        make_artifacts(settings).check()
    except ArtifactUnavailable as e:
        cause = e.__cause__
        return f"unreachable ({type(cause).__name__ if cause else 'error'})"
    return "ok"


@router.get("/readyz", response_model=Readiness,
            responses={503: {"model": Readiness, "description": "not ready: the failing checks"}})  # fmt: skip
def readyz(store: StoreDep, settings: SettingsDep) -> Response:
    """Ready when the job store answers and the data folder takes writes; what is down is named,
    never where it lives."""
    checks = {"store": "ok", "disk": disk_check(settings.data_dir)}
    try:
        store.counts()
    except StoreUnavailable as e:
        checks["store"] = e.reason
    except Exception as e:  # a bug: still say "not ready", with the kind of error only
        checks["store"] = f"error ({type(e).__name__})"
    if settings.artifacts_url:
        checks["artifacts"] = artifacts_check(settings)
    ready = all(v == "ok" for v in checks.values())
    body = {"status": "ready" if ready else "unavailable", "checks": checks}
    return JSONResponse(body, status_code=200 if ready else 503)


@router.get("/rollout/endpoints", dependencies=[Depends(require_token)],
            response_model=RolloutEndpoints, responses=responses(*AUTH, *STORE))  # fmt: skip
def rollout_endpoints(store: StoreDep) -> RolloutEndpoints:
    """The gRPC Rollout servers that announced themselves: the workers that own an accelerator
    (`quicknav worker --grpc-port`) and the all-in-one `quicknav serve`, oldest first."""
    endpoints = [RolloutEndpoint.model_validate(e) for e in store.endpoints()]
    return RolloutEndpoints(endpoints=endpoints, count=len(endpoints))


@router.get("/presets", dependencies=[Depends(require_token)],
            response_model=dict[str, PresetPublic], responses=responses(*AUTH))  # fmt: skip
def list_presets() -> dict[str, PresetPublic]:
    """The training presets by name: description, notes and config of each."""
    return {name: PresetPublic.model_validate(p) for name, p in preset_summaries().items()}


METRICS_DOC = {"description": "Prometheus text exposition format",
               "content": {"text/plain": {"schema": {"type": "string"}}}}  # fmt: skip


@router.head("/metrics", include_in_schema=False, dependencies=[Depends(require_metrics_token)])
def prometheus_head() -> Response:
    """Probes that check the page with HEAD (its body is built only for GET)."""
    from quicknav_service.api.metrics import CONTENT_TYPE_LATEST

    return Response(media_type=CONTENT_TYPE_LATEST)


@router.get("/metrics", response_class=PlainTextResponse, dependencies=[Depends(require_metrics_token)],
            responses={200: METRICS_DOC, **responses(*AUTH, *STORE)})  # fmt: skip
def metrics(request: Request, store: StoreDep, settings: SettingsDep) -> Response:
    """Prometheus metrics (prometheus-client): HTTP requests and latencies per route, jobs by
    status and kind, queue depth, heartbeats, job durations, env steps/s, gRPC Rollout streams.
    With QUICKNAV_API_TOKEN or QUICKNAV_METRICS_TOKEN set, a scrape sends one of them as a bearer
    token (Prometheus: ``authorization: {credentials: ...}``)."""
    from quicknav_service.api.metrics import CONTENT_TYPE_LATEST, render

    workers = getattr(request.app.state, "workers", [])
    return Response(render(store, settings, len(workers)), media_type=CONTENT_TYPE_LATEST)
