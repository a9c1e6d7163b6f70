"""One waiter per API process for the event streams it serves.

An idle viewer of ``GET /jobs/{id}/events`` must cost nothing: viewers do not poll the store. The
hub's one task blocks on the store for every watched job at once (``JobStore.wait_events``: XREAD
BLOCK on Redis; one indexed query per ``WAIT_POLL_S`` in the embedded store), reads each job's new
events once, keeps the recent ones, and wakes that job's viewers, however many there are. Every
``STATUS_EVERY_S`` it also reads each watched job's record once, so viewers learn that a job was
deleted, or finished without a terminal event, without asking the store themselves.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import anyio

from quicknav_service.jobs.models import JobNotFound, JobStore, StoreUnavailable

log = logging.getLogger("quicknav.events")

WAIT_S = 0.5  # longest block on the store: a newly watched job joins the wait within this
STATUS_EVERY_S = 2.0
OUTAGE_RETRY_S = 1.0
KEPT_EVENTS = 256  # per job: a viewer further behind reads the store itself


@dataclass
class Watched:
    """A watched job: its viewers, the newest event the hub has read, recent events, its state."""

    viewers: int = 0
    seen: int = 0
    recent: list[tuple[int, dict[str, Any]]] = field(default_factory=list)
    finished: bool = False
    deleted: bool = False
    changed: asyncio.Event = field(default_factory=asyncio.Event)

    def wake(self) -> None:
        self.changed.set()
        self.changed = asyncio.Event()


class EventHub:
    def __init__(self, store: JobStore):
        self.store = store
        self.jobs: dict[str, Watched] = {}
        self._task: asyncio.Task | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._status_at = 0.0
        self.store_calls = 0  # what the hub asked of the store (the benchmark and tests read it)

    # ------------------------------------------------------------------ viewers
    def watch(self, job_id: str, after: int) -> Watched:
        """Start watching ``job_id`` from event ``after`` (the viewer has read up to it)."""
        loop = asyncio.get_running_loop()
        if loop is not self._loop:  # one loop per API process; a test client may bring another
            self._loop, self.jobs, self._task = loop, {}, None
        w = self.jobs.setdefault(job_id, Watched(seen=after))
        w.viewers += 1
        w.seen = max(w.seen, after)
        if self._task is None or self._task.done():
            self._task = loop.create_task(self._run(), name="event-hub")
        return w

    def unwatch(self, job_id: str) -> None:
        w = self.jobs.get(job_id)
        if w is None:
            return
        w.viewers -= 1
        if w.viewers <= 0:
            del self.jobs[job_id]

    async def wait(self, w: Watched, after: int, timeout_s: float) -> None:
        """Until the hub has events past ``after`` for this job, its state changed, or a timeout."""
        if w.seen > after or w.deleted:
            return
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(w.changed.wait(), timeout_s)

    async def events(self, job_id: str, w: Watched, after: int) -> list[tuple[int, dict]]:
        """The events past ``after``: from the hub's recent ones, or from the store when the
        viewer is further behind than they reach."""
        if w.recent and w.recent[0][0] <= after + 1:
            return [(s, e) for s, e in w.recent if s > after]
        if w.seen <= after:
            return []
        self.store_calls += 1
        return await anyio.to_thread.run_sync(self.store.events, job_id, after)

    # ------------------------------------------------------------------ the one waiter
    async def _run(self) -> None:
        while self.jobs:
            try:
                await self._round()
            except StoreUnavailable:
                await asyncio.sleep(OUTAGE_RETRY_S)
            except Exception:  # never let the hub die: viewers would hang on their keep-alives
                log.exception("event hub round failed")
                await asyncio.sleep(OUTAGE_RETRY_S)

    async def _round(self) -> None:
        after = {job_id: w.seen for job_id, w in self.jobs.items()}
        self.store_calls += 1
        news = await anyio.to_thread.run_sync(self.store.wait_events, after, WAIT_S)
        for job_id in news:
            w = self.jobs.get(job_id)
            if w is None:
                continue
            self.store_calls += 1
            fresh = await anyio.to_thread.run_sync(self.store.events, job_id, w.seen)
            if fresh:
                w.recent = (w.recent + fresh)[-KEPT_EVENTS:]
                w.seen = fresh[-1][0]
                w.wake()
        if time.monotonic() - self._status_at >= STATUS_EVERY_S:
            self._status_at = time.monotonic()
            for job_id, w in list(self.jobs.items()):
                self.store_calls += 1
                try:
                    job = await anyio.to_thread.run_sync(self.store.get, job_id)
                except JobNotFound:
                    w.deleted = True
                    w.wake()
                    continue
                if job.status.finished and not w.finished:
                    w.finished = True
                    w.wake()

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task
