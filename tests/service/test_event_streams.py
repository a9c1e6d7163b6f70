"""Event streams at scale: idle viewers cost the store nothing, news reaches all of them at once,
keep-alives go out on time, and a job deleted under its viewers ends their streams."""

from __future__ import annotations

import asyncio
import itertools
import time

import httpx
import pytest

from quicknav_service.api.event_hub import STATUS_EVERY_S, WAIT_S
from quicknav_service.api.routes import events as events_route
from tests.service.conftest import LiveServer


async def _follow(url: str, job_id: str, got: list, ready: asyncio.Event, n: int, opened: list,
                  after: int = 0):  # fmt: skip
    headers = {"Last-Event-ID": str(after)} if after else {}
    async with httpx.AsyncClient(timeout=30) as client, client.stream(
        "GET", f"{url}/jobs/{job_id}/events", headers=headers
    ) as r:  # fmt: skip
        assert r.status_code == 200
        opened.append(1)
        if len(opened) == n:
            ready.set()
        async for line in r.aiter_lines():
            if line.startswith("event:") or line.startswith(":"):
                got.append((time.monotonic(), line))
            if line in ("event: succeeded", "event: deleted"):
                return


@pytest.mark.parametrize("viewers", [40])
def test_event_streams__idle_viewers_ask_the_store_nothing_and_news_reaches_all(tmp_path, monkeypatch, viewers):
    monkeypatch.setattr(events_route, "KEEPALIVE_S", 1.5)
    with LiveServer(tmp_path, sse_max_per_client=viewers + 1, sse_max_total=viewers + 1) as live:
        job, _ = live.store.submit("eval", {"policy": "random"}, {})
        gone, _ = live.store.submit("eval", {"policy": "random"}, {})
        hub = live.app.state.event_hub

        async def scenario():
            ready, opened = asyncio.Event(), []
            logs = [[] for _ in range(viewers)]
            tasks = [asyncio.create_task(_follow(live.url, job.id, logs[i], ready, viewers, opened))
                     for i in range(viewers)]  # fmt: skip
            await asyncio.wait_for(ready.wait(), 30)
            await asyncio.sleep(0.5)
            calls, t0 = hub.store_calls, time.monotonic()
            await asyncio.sleep(3.0)  # all idle
            idle_calls, idle_s = hub.store_calls - calls, time.monotonic() - t0
            sent = time.monotonic()
            claimed = await asyncio.to_thread(live.store.claim, "w", 30)
            await asyncio.to_thread(live.store.publish, claimed.id, {"type": "progress", "progress": 0.5})
            await asyncio.to_thread(live.store.finish, claimed.id, "w", "succeeded", {})
            await asyncio.wait_for(asyncio.gather(*tasks), 20)
            return logs, idle_calls, idle_s, sent

        logs, idle_calls, idle_s, sent = asyncio.run(scenario())
        # one wait per WAIT_S and one status read per STATUS_EVERY_S for the one watched job,
        # however many viewers: nothing per viewer
        assert idle_calls <= idle_s / WAIT_S + idle_s / STATUS_EVERY_S + 3, idle_calls
        for log in logs:
            kinds = [line for _, line in log]
            assert kinds[-2:] == ["event: progress", "event: succeeded"], kinds
            keepalives = [t for t, line in log if line.startswith(": keep-alive")]
            assert len(keepalives) >= 2  # 1.5 s apart over the idle 3.5 s, not drifting
            assert all(1.3 <= b - a <= 2.2 for a, b in itertools.pairwise(keepalives))
            got_at = next(t for t, line in log if line == "event: progress")
            assert got_at - sent < 2 * WAIT_S + 0.5

        # a job deleted while watched (a viewer resuming after its last event): it hears so and
        # its stream ends
        live.store.cancel(gone.id)
        last = live.store.events(gone.id)[-1][0]

        async def deleted():
            log, ready = [], asyncio.Event()
            task = asyncio.create_task(_follow(live.url, gone.id, log, ready, 1, [], after=last))
            await asyncio.wait_for(ready.wait(), 10)
            await asyncio.to_thread(live.store.delete, gone.id)
            await asyncio.wait_for(task, STATUS_EVERY_S + 5)
            return log

        log = asyncio.run(deleted())
        assert [line for _, line in log if line.startswith("event:")][-1] == "event: deleted"
