"""The asynchronous REST client: runs the core's operations with ``httpx.AsyncClient`` and
``asyncio.sleep``. Same methods as the sync client, as coroutines."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable, Mapping
from pathlib import Path
from typing import Any

import httpx

from quicknav_client.rest import core
from quicknav_client.rest.core import (
    END,
    Close,
    Emit,
    JobFields,
    JobList,
    Lines,
    NextLine,
    Operation,
    ReadBody,
    SaveBody,
    Send,
    Sleep,
)


class AsyncJob(JobFields):
    """A job on the server (from :class:`AsyncQuickNavClient`); methods are coroutines."""

    _client: AsyncQuickNavClient

    async def refresh(self) -> AsyncJob:
        """Reload the job's state from the server."""
        self._update(await self._client._get_json(f"/jobs/{self.id}"))
        return self

    def events(self, after: int = 0) -> AsyncIterator[dict]:
        """The job's events, live; resumes after drops (``async for``)."""
        return self._client.events(self.id, after=after)

    async def wait(
        self,
        progress: bool = False,
        timeout: float | None = None,
        on_event: Callable[[dict], None] | None = None,
    ) -> AsyncJob:
        """Follow the job's event stream until it finishes, then refresh; raises WaitTimeout."""
        op = core.wait(self._client._policy, self, progress, timeout, on_event)
        return await self._client._run(op)

    async def metrics_history(self) -> list[dict]:
        """One row per training chunk, from the job's metrics.jsonl."""
        return (await self._client._get_json(f"/jobs/{self.id}/metrics"))["metrics"]

    async def cancel(self) -> AsyncJob:
        """Cancel: a queued job at once, a running one at its next chunk boundary."""
        self._update(await self._client._json("POST", f"/jobs/{self.id}/cancel", json={}))
        return self

    async def delete(self) -> None:
        """Delete a finished job and its artifacts."""
        await self._client._json("DELETE", f"/jobs/{self.id}")

    async def artifacts(self) -> list[dict]:
        """The job's files with their sizes."""
        return (await self._client._get_json(f"/jobs/{self.id}/artifacts"))["artifacts"]

    async def download(
        self, name: str, out: str | Path | None = None, *, path: str | Path | None = None
    ) -> Path:
        """Stream an artifact to ``out`` (a file or a folder; default: its name in the cwd)."""
        return await self._client.download(self.id, name, core.download_out(out, path))

    async def download_policy(self, dest: str | Path = ".") -> Path:
        """This train job's ``policy.onnx`` and ``policy.json`` into the folder ``dest``."""
        return await self._client.download_policy(self.id, dest)


class _Done(Exception):
    """The operation returned (its value travels here: an async generator cannot return one)."""

    def __init__(self, value: Any):
        self.value = value


class AsyncQuickNavClient:
    """Asynchronous client (httpx.AsyncClient): the methods of QuickNavClient, as coroutines."""

    def __init__(
        self,
        base_url: str = core.DEFAULT_URL,
        token: str | None = None,
        timeout: float | httpx.Timeout | None = 30.0,
        retries: int = 3,
        backoff_s: float = 0.5,
        transport: httpx.AsyncBaseTransport | None = None,
    ):
        if retries < 0:
            raise ValueError(f"retries={retries}: must be >= 0")
        self.base_url = base_url.rstrip("/")
        self.retries = retries
        self.backoff_s = backoff_s
        self._http = httpx.AsyncClient(
            base_url=self.base_url, headers=core.default_headers(token),
            timeout=core.make_timeout(timeout), transport=transport,
        )  # fmt: skip
        self._policy = core.Policy(self.base_url, retries, backoff_s, self._http.timeout)

    # -- running operations
    async def _perform(self, effect: Any, opened: list[httpx.Response]) -> Any:
        if isinstance(effect, Send):
            request = self._http.build_request(effect.method, effect.path, **effect.kwargs)
            response = await self._http.send(request, stream=effect.stream)
            if effect.stream:
                opened.append(response)
            return response
        if isinstance(effect, Sleep):
            await asyncio.sleep(effect.seconds)
        elif isinstance(effect, Lines):
            return effect.response.aiter_lines()
        elif isinstance(effect, NextLine):
            return await anext(effect.lines, END)
        elif isinstance(effect, ReadBody):
            await effect.response.aread()
        elif isinstance(effect, Close):
            await effect.response.aclose()
        elif isinstance(effect, SaveBody):
            with effect.path.open("wb") as f:
                async for chunk in effect.response.aiter_bytes():
                    f.write(chunk)
        else:  # pragma: no cover - a core operation yielded something new
            raise TypeError(f"unknown effect {effect!r}")
        return None

    async def _steps(self, op: Operation) -> AsyncIterator[Any]:
        """Drive ``op``; yields what it emits, then raises ``_Done`` with its result."""
        opened: list[httpx.Response] = []
        result: Any = None
        error: BaseException | None = None
        try:
            while True:
                try:
                    effect = op.throw(error) if error is not None else op.send(result)
                except StopIteration as stop:
                    raise _Done(stop.value) from None
                result, error = None, None
                if isinstance(effect, Emit):
                    yield effect.value
                    continue
                try:
                    result = await self._perform(effect, opened)
                except Exception as e:  # the operation decides: retry, or raise
                    error = e
        finally:
            op.close()
            for response in opened:
                await response.aclose()

    async def _run(self, op: Operation) -> Any:
        try:
            async for _ in self._steps(op):
                pass  # an operation run here emits nothing
        except _Done as done:
            return done.value
        raise AssertionError("unreachable: an operation ends with _Done")  # pragma: no cover

    async def _iterate(self, op: Operation) -> AsyncIterator[Any]:
        try:
            async for value in self._steps(op):
                yield value
        except _Done:
            return

    async def _json(self, method: str, path: str, **kw) -> Any:
        return await self._run(core.request_json(self._policy, method, path, **kw))

    async def _get_json(self, path: str, **kw) -> Any:
        return await self._json("GET", path, **kw)

    async def _submit(self, path: str, body: dict, idempotency_key: str | None) -> AsyncJob:
        data = await self._run(core.submit(self._policy, path, body, idempotency_key))
        return AsyncJob(self, data)

    # -- public API
    async def aclose(self) -> None:
        """Close the connection pool."""
        await self._http.aclose()

    async def __aenter__(self) -> AsyncQuickNavClient:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.aclose()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.base_url!r})"

    async def health(self) -> dict:
        """GET /healthz: the API process is up."""
        return await self._get_json("/healthz")

    async def ready(self) -> dict:
        """GET /readyz: the job store answers."""
        return await self._get_json("/readyz")

    async def rollout_endpoints(self) -> list[dict]:
        """The gRPC Rollout servers the service knows (``address``, ``backend``, ``device``,
        ``sessions``, ``max_sessions``); pass an ``address`` to ``RolloutClient``."""
        return (await self._get_json("/rollout/endpoints"))["endpoints"]

    async def presets(self) -> dict[str, dict]:
        """The server's training presets."""
        return await self._get_json("/presets")

    async def train(
        self,
        config: Mapping | str | None = None,
        preset: str | None = None,
        overrides: Mapping[str, Any] | None = None,
        idempotency_key: str | None = None,
        **fields: Any,
    ) -> AsyncJob:
        """Submit a train job: a preset (or config) plus dotted ``overrides`` and top-level fields."""
        body = core.train_body(config, preset, overrides, fields)
        return await self._submit("/jobs/train", body, idempotency_key)

    async def sweep(
        self,
        config: Mapping | str | None = None,
        trials: int | None = None,
        parallel: int | None = None,
        total_steps: int | None = None,
        overrides: Mapping[str, Any] | None = None,
        idempotency_key: str | None = None,
        space: str | None = None,
        base: str | None = None,
    ) -> AsyncJob:
        """Submit a sweep job: a built-in ``space`` (ppo, lstm, ...), its trials starting from
        the ``base`` preset (default: the space's paper preset), or a SweepConfig ``config``."""
        body = core.sweep_body(config, trials, parallel, total_steps, overrides, space, base)
        return await self._submit("/jobs/sweep", body, idempotency_key)

    async def evaluate(
        self,
        job: Any = None,
        policy: str | None = None,
        episodes: int = 100,
        seed: int = 0,
        env: Mapping[str, Any] | None = None,
        split: str = "test",
        deterministic: bool = True,
        stochastic: bool | None = None,
        idempotency_key: str | None = None,
        robustness: bool = False,
        shield: bool = False,
        map: str | None = None,
    ) -> AsyncJob:
        """Submit an eval job: a train job's checkpoint, or a ``random``/``oracle`` baseline.

        ``stochastic`` is the deprecated opposite of ``deterministic`` (the API's name);
        ``robustness`` also runs the episodes at each fixed perturbation level (eval.json's
        ``robustness`` rows, robustness.png); ``shield`` puts the safety layer between the policy
        and the wheels (agent ``<policy>+shield``); ``map`` drives a map uploaded to the server
        (``map:<id>``) at the policy's cell size, the grid and step limit following it.
        """
        body = core.eval_body(job, policy, episodes, seed, env, split, deterministic, stochastic,
                              robustness, shield, map)  # fmt: skip
        return await self._submit("/jobs/eval", body, idempotency_key)

    async def jobs(
        self, status: str | None = None, kind: str | None = None, limit: int = 50, offset: int = 0
    ) -> JobList:
        """A page of jobs, newest first; ``.count`` is the total matching the filter."""
        page = await self._get_json("/jobs", params=core.list_params(status, kind, limit, offset))
        return JobList([AsyncJob(self, d) for d in page["data"]], page["count"])

    async def job(self, job_id: str) -> AsyncJob:
        """One job by id (NotFound if there is none)."""
        return AsyncJob(self, await self._get_json(f"/jobs/{job_id}"))

    def events(self, job_id: str, after: int = 0) -> AsyncIterator[dict]:
        """A job's events after event id ``after``, live, until the terminal one."""
        return self._iterate(core.events(self._policy, job_id, after, None))

    async def download(
        self, job_id: str, name: str, out: str | Path | None = None, *,
        path: str | Path | None = None,
    ) -> Path:
        """Stream a job's artifact to ``out``, a file or a folder (default: its name in the cwd),
        written whole or not at all; returns its path. ``path`` is the deprecated name of ``out``."""
        return await self._run(core.download(self._policy, job_id, name, core.download_out(out, path)))

    # -- maps
    async def upload_map(
        self, path: str | Path, *, name: str | None = None, resolution: float | None = None,
        negate: bool | None = None, occupied_thresh: float | None = None,
        free_thresh: float | None = None,
    ) -> dict:
        """Upload a building map (see ``QuickNavClient.upload_map``)."""
        parts = core.map_upload(path, name, resolution, negate, occupied_thresh, free_thresh)
        return await self._json("POST", "/maps", **parts)

    async def maps(self) -> list[dict]:
        """Every uploaded map, newest first."""
        return (await self._get_json("/maps"))["data"]

    async def map(self, ref: str) -> dict:
        """One map by id or ``map:<id>``."""
        return await self._get_json(f"/maps/{core.map_id(ref)}")

    async def map_preview(self, ref: str, out: str | Path = "preview.png") -> Path:
        """The map's picture as a PNG file."""
        return await self._run(core.save(self._policy, f"/maps/{core.map_id(ref)}/preview.png", Path(out)))

    async def download_map(self, ref: str, dest: str | Path = ".") -> Path:
        """The stored map_server pair (``map.yaml`` and its image) into ``dest``; the YAML's path."""
        return await self._run(core.download_map(self._policy, ref, dest))

    async def delete_map(self, ref: str) -> None:
        """Delete a map (Conflict while a queued or running job uses it)."""
        await self._json("DELETE", f"/maps/{core.map_id(ref)}")

    async def download_policy(self, job_id: str, dest: str | Path = ".") -> Path:
        """Download a train job's exported policy (``policy.onnx`` and its ``policy.json``
        manifest) into the folder ``dest``; returns the folder. A job trained before policies were
        exported, or whose export failed (its warnings say why), answers 404."""
        folder = Path(dest)
        folder.mkdir(parents=True, exist_ok=True)
        for name in core.POLICY_FILES:
            await self.download(job_id, name, folder / name)
        return folder
