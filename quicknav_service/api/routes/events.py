"""A job's progress as Server-Sent Events: resumable with Last-Event-ID, ends with the terminal event.

A viewer reads the job's past events from the store once, then waits on the process's event hub
(``api.event_hub``), which blocks on the store for every watched job at once: an idle viewer costs
neither store calls nor a thread, and keep-alives go out every KEEPALIVE_S on time."""

from __future__ import annotations

import asyncio
import json
import re
import time
from typing import Annotated

import anyio
from fastapi import APIRouter, Depends, Header, HTTPException, Request
from fastapi.responses import StreamingResponse

from quicknav_core.config.base import json_safe
from quicknav_service.api.deps import JobId, JobsDep, StoreDep, client_address, require_token
from quicknav_service.api.errors import AUTH, STORE, responses
from quicknav_service.api.event_hub import EventHub
from quicknav_service.jobs.models import JobNotFound, StoreUnavailable

router = APIRouter(prefix="/jobs", tags=["jobs"], dependencies=[Depends(require_token)])


class EventStreamResponse(StreamingResponse):
    media_type = "text/event-stream"
    on_close = None  # called once the response has ended, however it ended

    async def __call__(self, scope, receive, send):
        try:
            await super().__call__(scope, receive, send)
        finally:
            if self.on_close is not None:
                self.on_close()


EVENTS_DOC = {
    "description": "Server-Sent Events: `id: <n>`, `event: <type>` (started, progress, ...; the"
    " last is succeeded, failed or cancelled, or deleted), `data: <JSON>`; keep-alive comments",
    # each event, as an SSE client parses it (the stream's items; keep-alive comments are none)
    "content": {"text/event-stream": {"schema": {
        "type": "object", "required": ["event", "data"],
        "properties": {
            "id": {"type": "string", "pattern": "^[0-9]+$",
                   "description": "the event's id, for Last-Event-ID (the deleted event has none)"},
            "event": {"type": "string", "description": "started, progress, ...; the last is"
                      " succeeded, failed, cancelled or deleted"},
            "data": {"type": "string", "contentMediaType": "application/json",
                     "description": "the event as a JSON object: its type and the job's fields"},
        },
    }}},
}

class StreamSlots:
    """Open event streams, per client address and in all (per API process): a stream beyond
    either cap is refused with 503 and Retry-After, so idle viewers cannot take the server."""

    RETRY_AFTER_S = 5

    def __init__(self, per_client: int, total: int):
        self.per_client = per_client
        self.total = total
        self.open: dict[str, int] = {}

    def take(self, client: str) -> None:
        if sum(self.open.values()) >= self.total:
            raise HTTPException(503, f"{self.total} event streams are open, this server's limit"
                                     " (QUICKNAV_SSE_MAX_TOTAL): retry later or poll GET /jobs/{id}",
                                headers={"Retry-After": str(self.RETRY_AFTER_S)})  # fmt: skip
        if self.open.get(client, 0) >= self.per_client:
            raise HTTPException(503, f"this address has {self.per_client} event streams open, the"
                                     " limit (QUICKNAV_SSE_MAX_PER_CLIENT): close one",
                                headers={"Retry-After": str(self.RETRY_AFTER_S)})  # fmt: skip
        self.open[client] = self.open.get(client, 0) + 1

    def give_back(self, client: str) -> None:
        left = self.open.get(client, 1) - 1
        if left > 0:
            self.open[client] = left
        else:
            self.open.pop(client, None)


# what Last-Event-ID takes (the document's pattern and the route's check): up to 18 ASCII digits,
# below the 64-bit ids SQLite and Redis give events; a sign, spaces or other digits are refused
EVENT_ID = r"^[0-9]{1,18}$"
KEEPALIVE_S = 15.0
OUTAGE_POLL_S = 1.0
FINISHED_GRACE_S = 1.0  # a finished job's terminal event may be a moment behind its record
TERMINAL = ("succeeded", "failed", "cancelled")


def deleted(job_id: str) -> str:
    return f"event: deleted\ndata: {json.dumps({'type': 'deleted', 'job_id': job_id})}\n\n"


@router.get("/{job_id}/events", response_class=EventStreamResponse,
            responses={200: EVENTS_DOC, **responses(*AUTH, *STORE, 400, 404, 409, 422)})  # fmt: skip
# (503 with Retry-After also when this client or the server has too many streams open)
async def job_events(job_id: JobId, request: Request, store: StoreDep, jobs: JobsDep,
                     last_event_id: Annotated[str | None, Header(
                         alias="Last-Event-ID", description="resume after this event id",
                         json_schema_extra={"pattern": EVENT_ID})] = None,
                     ) -> EventStreamResponse:  # fmt: skip
    """Server-Sent Events of the job's progress; resumable with Last-Event-ID; ends with the terminal event."""
    job_id = (await anyio.to_thread.run_sync(jobs.get, job_id)).id
    if last_event_id is not None and not re.fullmatch(EVENT_ID, last_event_id):
        raise HTTPException(400, "Last-Event-ID must be an event id: 1 to 18 ASCII digits")
    after = int(last_event_id) if last_event_id is not None else 0

    slots: StreamSlots = request.app.state.streams
    client = client_address(request)
    slots.take(client)

    hub: EventHub = request.app.state.event_hub

    def sse(seq: int, ev: dict) -> str:
        data = json.dumps(json_safe(ev), allow_nan=False)
        return f"id: {seq}\nevent: {ev.get('type', 'message')}\ndata: {data}\n\n"

    async def stream():
        nonlocal after
        # what happened before this viewer came, read once from the store
        while True:
            try:
                events = await anyio.to_thread.run_sync(store.events, job_id, after)
                break
            except JobNotFound:
                yield deleted(job_id)
                return
            except StoreUnavailable:  # an outage: keep the stream open and try again
                yield ": keep-alive (job store unavailable)\n\n"
                await asyncio.sleep(OUTAGE_POLL_S)
        for seq, ev in events:
            after = seq
            yield sse(seq, ev)
            if ev.get("type") in TERMINAL:
                return
        # then the hub wakes this viewer when there is news: an idle viewer asks nothing
        watched = hub.watch(job_id, after)
        try:
            quiet_since = time.monotonic()
            finished_at = None
            while True:
                left = KEEPALIVE_S - (time.monotonic() - quiet_since)
                # an idle viewer sleeps until news or its keep-alive; the hub wakes it when the
                # job ends, and then it looks again every FINISHED_GRACE_S
                await hub.wait(watched, after, FINISHED_GRACE_S if watched.finished else max(0.0, left))
                try:
                    events = await hub.events(job_id, watched, after)
                except StoreUnavailable:  # an outage while behind the hub: wait, then again
                    await asyncio.sleep(OUTAGE_POLL_S)
                    events = []
                for seq, ev in events:
                    after = seq
                    yield sse(seq, ev)
                    if ev.get("type") in TERMINAL:
                        return
                if events:
                    quiet_since = time.monotonic()
                    continue
                if watched.deleted:  # deleted while someone was watching: say so, end cleanly
                    yield deleted(job_id)
                    return
                if watched.finished:
                    # finished without a terminal event past ``after`` (older jobs, or the event
                    # is on its way): give it a moment, then end
                    finished_at = finished_at or time.monotonic()
                    if time.monotonic() - finished_at >= FINISHED_GRACE_S:
                        return
                if time.monotonic() - quiet_since >= KEEPALIVE_S:
                    yield ": keep-alive\n\n"
                    quiet_since = time.monotonic()
        finally:
            hub.unwatch(job_id)

    response = EventStreamResponse(stream(), headers={"Cache-Control": "no-cache",
                                                      "X-Accel-Buffering": "no"})  # fmt: skip
    response.on_close = lambda: slots.give_back(client)
    return response
