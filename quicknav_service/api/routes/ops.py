"""Operations: liveness, readiness, the presets, Prometheus metrics."""

from __future__ import annotations

import errno
import os
import threading
import time
from pathlib import Path

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse, PlainTextResponse, Response

from quicknav_core.config.presets import preset_summaries
from quicknav_service.api.deps import SettingsDep, StoreDep, require_metrics_token, require_token
from quicknav_service.api.errors import AUTH, STORE, responses
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


PROBE_BYTES = 64 * 1024
# an open route must not be a way to make the server write: a good disk is probed at most this often
DISK_PROBE_EVERY_S = 5.0
# below this many free bytes (statvfs, which writes nothing) a cached "ok" is not trusted
DISK_LOW_BYTES = 4 * PROBE_BYTES
_disk_probes: dict[Path, float] = {}
_disk_lock = threading.Lock()


def disk_check(data_dir: Path) -> str:
    """'ok' if a small file could be written and synced in the data folder, else why not.

    Only a good answer is reused, for DISK_PROBE_EVERY_S seconds and only while the file system
    still reports free space; a failing probe writes nothing that lasts, so a full or unwritable
    disk is probed again on the next call and its recovery is seen at once."""
    with _disk_lock:
        last_ok = _disk_probes.get(data_dir)
        if last_ok is not None and time.monotonic() - last_ok < DISK_PROBE_EVERY_S \
                and _free_bytes(data_dir) >= DISK_LOW_BYTES:  # fmt: skip
            return "ok"
        result = _probe_disk(data_dir)
        if result == "ok":
            _disk_probes[data_dir] = time.monotonic()
        else:
            _disk_probes.pop(data_dir, None)
        return result


def _free_bytes(data_dir: Path) -> int:
    try:
        st = os.statvfs(data_dir)
    except OSError:
        return 0
    return st.f_bavail * st.f_frsize


def _probe_disk(data_dir: Path) -> str:
    probe = data_dir / f".ready-probe-{os.getpid()}"
    try:
        with open(probe, "wb") as f:
            f.write(b"\0" * PROBE_BYTES)
            f.flush()
            os.fsync(f.fileno())
        return "ok"
    except OSError as e:
        return "full" if e.errno == errno.ENOSPC else "not writable"
    finally:
        probe.unlink(missing_ok=True)


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
