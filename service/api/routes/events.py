"""A job's progress as Server-Sent Events: resumable with Last-Event-ID, ends with the terminal event."""

from __future__ import annotations

import asyncio
import json
from typing import Annotated

import anyio
from fastapi import APIRouter, Depends, Header, HTTPException, Request
from fastapi.responses import StreamingResponse

from quicknav_core.config.base import json_safe
from service.api.deps import StoreDep, get_job, require_token
from service.jobs.models import JobNotFound, StoreUnavailable

router = APIRouter(prefix="/jobs", tags=["jobs"], dependencies=[Depends(require_token)])

MAX_EVENT_ID = 2**63 - 1  # event ids are SQLite/Redis 64-bit integers
KEEPALIVE_S = 15.0
POLL_S = 0.05
OUTAGE_POLL_S = 1.0
TERMINAL = ("succeeded", "failed", "cancelled")


@router.get("/{job_id}/events")
async def job_events(job_id: str, request: Request, store: StoreDep,
                     last_event_id: Annotated[str | None, Header(alias="Last-Event-ID")] = None):  # fmt: skip
    """Server-Sent Events of the job's progress; resumable with Last-Event-ID; ends with the terminal event."""
    job_id = (await anyio.to_thread.run_sync(get_job, store, job_id)).id
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
            except StoreUnavailable:  # an outage: keep the stream open and try again
                idle += OUTAGE_POLL_S
                if idle >= KEEPALIVE_S:
                    yield ": keep-alive (job store unavailable)\n\n"
                    idle = 0.0
                await asyncio.sleep(OUTAGE_POLL_S)
                continue
            for seq, ev in events:
                after = seq
                data = json.dumps(json_safe(ev), allow_nan=False)
                yield f"id: {seq}\nevent: {ev.get('type', 'message')}\ndata: {data}\n\n"
                if ev.get("type") in TERMINAL:
                    return
            if events:
                idle = 0.0
                continue
            try:
                if job.status.finished and not await anyio.to_thread.run_sync(
                    store.events, job_id, after
                ):
                    return
            except StoreUnavailable:
                pass
            idle += POLL_S
            if idle >= KEEPALIVE_S:
                yield ": keep-alive\n\n"
                idle = 0.0
            await asyncio.sleep(POLL_S)

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})  # fmt: skip
