"""Operations: liveness, readiness, the presets, Prometheus metrics."""

from __future__ import annotations

import errno
import os
from pathlib import Path

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse, PlainTextResponse, Response

from quicknav_core.config.presets import preset_summaries
from service.api.deps import SettingsDep, StoreDep, require_token
from service.jobs.models import StoreUnavailable

router = APIRouter(tags=["service"])


@router.get("/healthz")
async def healthz() -> dict:
    """The API process is up."""
    return {"status": "ok"}


PROBE_BYTES = 64 * 1024


def disk_check(data_dir: Path) -> str:
    """'ok' if a small file can be written and synced in the data folder, else why not."""
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


@router.get("/readyz")
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
    ready = all(v == "ok" for v in checks.values())
    body = {"status": "ready" if ready else "unavailable", "checks": checks}
    return JSONResponse(body, status_code=200 if ready else 503)


@router.get("/rollout/endpoints", dependencies=[Depends(require_token)])
def rollout_endpoints(store: StoreDep) -> dict:
    """The gRPC Rollout servers that announced themselves: the workers that own an accelerator
    (`quicknav worker --grpc-port`) and the all-in-one `quicknav serve`, oldest first."""
    endpoints = store.endpoints()
    return {"endpoints": endpoints, "count": len(endpoints)}


@router.get("/presets", dependencies=[Depends(require_token)])
def presets() -> dict:
    """The training presets: description, notes and config of each."""
    return preset_summaries()


@router.get("/metrics", response_class=PlainTextResponse)
def prometheus(request: Request, store: StoreDep, settings: SettingsDep) -> Response:
    """Prometheus metrics (prometheus-client): HTTP requests and latencies per route, jobs by
    status and kind, queue depth, heartbeats, job durations, env steps/s, gRPC Rollout streams."""
    from service.api.metrics import CONTENT_TYPE_LATEST, render

    workers = getattr(request.app.state, "workers", [])
    return Response(render(store, settings, len(workers)), media_type=CONTENT_TYPE_LATEST)
