"""REST client of the QuickNav job service: submit train/sweep/eval jobs, follow them, fetch results.

    from quicknav_client import QuickNavClient

    with QuickNavClient("http://127.0.0.1:8000") as qn:
        job = qn.train(preset="demo", overrides={"env.grid_size": 8}, total_steps=200_000)
        job.wait(progress=True)
        print(job.status, job.result)
        job.download("learning_curve.png", "curve.png")

Transient failures (refused connections, timeouts, 502/503/504) are retried with exponential
backoff; every submission carries an ``Idempotency-Key`` reused across its retries, so a retry whose
first attempt did reach the server returns the same job instead of queueing a duplicate.
"""

from __future__ import annotations

import asyncio
import copy
import json
import math
import random
import time
import uuid
from collections.abc import AsyncIterator, Callable, Iterator, Mapping
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import quote

import httpx

from quicknav_client.errors import ConnectionFailed, WaitTimeout, error_class, format_detail

DEFAULT_URL = "http://127.0.0.1:8000"
TERMINAL_STATUSES = frozenset({"succeeded", "failed", "cancelled"})
# Statuses a proxy or a restarting server answers with while the service itself is fine.
_RETRY_STATUSES = frozenset({502, 503, 504})
_SSE_READ_TIMEOUT_S = 45.0  # three of the server's 15 s keep-alive intervals
_TRANSIENT = (httpx.TimeoutException, httpx.NetworkError, httpx.RemoteProtocolError)

JobRef = Any  # a job id, a Job or an AsyncJob


# --------------------------------------------------------------------------- shared helpers
def raise_for_status(response: httpx.Response) -> None:
    """Raise the typed error for a failed response, carrying the server's message."""
    if response.is_success:
        return
    try:
        body: Any = response.json()
    except ValueError:
        body = response.text
    if isinstance(body, dict) and "detail" in body:
        message = format_detail(body["detail"])
    else:
        message = (body if isinstance(body, str) else json.dumps(body))[:1000].strip()
    request = response.request
    raise error_class(response.status_code)(
        message or response.reason_phrase,
        status_code=response.status_code,
        body=body,
        method=request.method,
        url=request.url.path,
    )


def _connection_failed(method: str, url: httpx.URL, attempts: int, cause: Exception | None):
    why = f"{type(cause).__name__}: {cause}" if cause else "no response"
    return ConnectionFailed(
        f"could not reach the QuickNav service at {url} ({method}, {attempts} attempts): {why}",
        method=method,
        url=str(url),
    )


def _backoff_s(attempt: int, base_s: float) -> float:
    # jitter so that many clients cut off by one outage do not come back in lockstep
    return min(base_s * 2**attempt, 10.0) * random.uniform(0.5, 1.0)


def _timeout(timeout: float | httpx.Timeout | None) -> httpx.Timeout:
    if isinstance(timeout, httpx.Timeout):
        return timeout
    return httpx.Timeout(timeout, connect=None if timeout is None else min(timeout, 10.0))


def _headers(token: str | None) -> dict[str, str]:
    from quicknav_client import __version__

    headers = {"User-Agent": f"quicknav-client/{__version__}"}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    return headers


def _set_dotted(data: dict, key: str, value: Any) -> None:
    *parents, leaf = key.split(".")
    node = data
    for part in parents:
        child = node.get(part)
        if not isinstance(child, dict):
            child = node[part] = {}
        node = child
    node[leaf] = value


def _as_dict(config: Any) -> dict:
    if hasattr(config, "model_dump"):  # a pydantic config from quicknav_core, without importing it
        return config.model_dump(mode="json")
    return copy.deepcopy(dict(config))


def train_body(
    config: Mapping | str | None,
    preset: str | None,
    overrides: Mapping[str, Any] | None,
    fields: Mapping[str, Any],
) -> dict:
    """The POST /jobs/train body: a preset with overrides, or a full config with them applied."""
    if isinstance(config, str):
        if preset is not None:
            raise ValueError("give the preset once: as `config` or as `preset`, not both")
        config, preset = None, config
    if (config is None) == (preset is None):
        raise ValueError("give exactly one of `config` (a TrainConfig dict) or `preset` (a name)")
    changes = {**(overrides or {}), **fields}
    if preset is not None:
        return {"preset": preset, "overrides": changes}
    data = _as_dict(config)
    for key, value in changes.items():
        _set_dotted(data, key, value)
    return {"config": data}


def sweep_body(
    config: Mapping | str | None,
    trials: int | None,
    parallel: int | None,
    total_steps: int | None,
    overrides: Mapping[str, Any] | None,
) -> dict:
    """The POST /jobs/sweep body: a built-in space name with its knobs, or a full SweepConfig."""
    if config is None:
        raise ValueError("give a SweepConfig dict or a built-in space name (ppo, sac, td3, ...)")
    if isinstance(config, str):
        if overrides:
            raise ValueError("`overrides` apply to a SweepConfig dict, not to a built-in space")
        knobs = {"trials": trials, "parallel": parallel, "total_steps": total_steps}
        return {"space": config, **{k: v for k, v in knobs.items() if v is not None}}
    data = _as_dict(config)
    for key, value in (overrides or {}).items():
        _set_dotted(data, key, value)
    for key, value in (
        ("trials", trials),
        ("parallel", parallel),
        ("base.total_steps", total_steps),
    ):
        if value is not None:
            _set_dotted(data, key, value)
    return {"config": data}


def eval_body(
    job: JobRef, policy: str | None, episodes: int, seed: int, env: Mapping | None, stochastic: bool
) -> dict:
    """The POST /jobs/eval body (the server checks that exactly one of job and policy is given)."""
    body: dict[str, Any] = {"episodes": episodes, "seed": seed, "stochastic": stochastic}
    if job is not None:
        body["job_id"] = job if isinstance(job, str) else job.id
    if policy is not None:
        body["policy"] = policy
    if env:
        body["env"] = dict(env)
    return body


def list_params(status: str | None, kind: str | None, limit: int, offset: int) -> dict:
    params: dict[str, Any] = {"limit": limit, "offset": offset}
    if status is not None:
        params["status"] = str(status)
    if kind is not None:
        params["kind"] = str(kind)
    return params


def artifact_path(job_id: str, name: str) -> str:
    return f"/jobs/{job_id}/artifacts/{quote(name.lstrip('/'), safe='/')}"


def download_target(name: str, path: str | Path | None) -> Path:
    basename = PurePosixPath(name).name
    target = Path(path) if path is not None else Path(basename)
    if target.is_dir():
        target = target / basename
    target.parent.mkdir(parents=True, exist_ok=True)
    return target


class SSEParser:
    """Server-Sent Events, line by line: returns an event dict when a blank line completes one.

    The dict is the event's JSON data with ``id`` (the server's event id, an int) and ``type``
    (the SSE event name when the data does not carry one).
    """

    def __init__(self) -> None:
        self._event, self._data, self._id = "", [], None

    def feed(self, line: str) -> dict | None:
        if line == "":
            if not self._data:  # the spec: an event without data is not dispatched
                self._event, self._id = "", None
                return None
            text = "\n".join(self._data)
            try:
                data = json.loads(text)
            except ValueError:
                data = text
            event = dict(data) if isinstance(data, dict) else {"data": data}
            event.setdefault("type", self._event or "message")
            event["id"] = int(self._id) if self._id and self._id.isdigit() else self._id
            self._event, self._data, self._id = "", [], None
            return event
        if line.startswith(":"):  # a comment: the server's keep-alive
            return None
        field, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if field == "data":
            self._data.append(value)
        elif field == "event":
            self._event = value
        elif field == "id" and "\0" not in value:
            self._id = value
        return None


class JobList(list):
    """A page of jobs; ``count`` is the total number matching the filter on the server."""

    def __init__(self, jobs: list, count: int):
        super().__init__(jobs)
        self.count = count


def metrics_summary(metrics: Mapping[str, Any], sep: str = ", ") -> str:
    """The few numbers worth a glance: success, return, throughput, a sweep's best value."""

    def number(key: str) -> float | None:
        # chunks in which no episode ended report NaN (JSON null over /metrics): nothing to show
        value = metrics.get(key)
        ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        return value if ok else None

    parts = []
    if (success := number("success_rate")) is not None:
        parts.append(f"success {success:.0%}")
    if (ret := number("mean_return")) is not None:
        parts.append(f"return {ret:.1f}")
    if (speed := number("steps_per_s")) is not None:
        parts.append(f"{speed:,.0f} steps/s")
    if (best := number("best_value")) is not None:
        parts.append(f"best {best:.4g}")
    return sep.join(parts)


class _ProgressBar:
    """A tqdm bar fed by job events (disabled: does nothing)."""

    def __init__(self, job: _JobFields, enabled: bool):
        self.bar = None
        self.name = f"{job.kind} {job.id[:8]}"
        if enabled:
            from tqdm.auto import tqdm

            self.bar = tqdm(
                total=100.0,
                desc=f"{self.name} {job.status}",
                bar_format="{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}{postfix}]",
            )
            self.bar.update(100.0 * job.progress)

    def update(self, event: dict) -> None:
        if self.bar is None:
            return
        if isinstance(event.get("status"), str):
            self.bar.set_description_str(f"{self.name} {event['status']}")
        if isinstance(event.get("progress"), int | float):
            self.bar.update(max(0.0, 100.0 * event["progress"] - self.bar.n))
        shown = metrics_summary(event.get("metrics") or {})
        if shown:
            self.bar.set_postfix_str(shown)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# --------------------------------------------------------------------------- jobs
class _JobFields:
    """The server's view of a job; ``raw`` keeps the whole JSON object."""

    def __init__(self, client: Any, data: dict):
        self._client = client
        self._update(data)

    def _update(self, data: dict) -> None:
        self.raw: dict[str, Any] = data
        self.id: str = data["id"]
        self.kind: str = data.get("kind", "")
        self.status: str = data.get("status", "")
        self.progress: float = float(data.get("progress") or 0.0)
        self.metrics: dict[str, Any] = data.get("metrics") or {}
        self.error: str | None = data.get("error")
        self.result: dict[str, Any] | None = data.get("result")
        self.attempts: int = int(data.get("attempts") or 0)
        self.cancel_requested: bool = bool(data.get("cancel_requested"))
        self.created_at: float | None = data.get("created_at")
        self.started_at: float | None = data.get("started_at")
        self.finished_at: float | None = data.get("finished_at")
        self.request: dict[str, Any] = data.get("request") or {}
        self.links: dict[str, str] = data.get("links") or {}

    @property
    def done(self) -> bool:
        """The job finished: succeeded, failed or cancelled."""
        return self.status in TERMINAL_STATUSES

    @property
    def succeeded(self) -> bool:
        """The job finished successfully."""
        return self.status == "succeeded"

    def __repr__(self) -> str:
        extra = f", error={self.error!r}" if self.error else ""
        return (
            f"{type(self).__name__}(id={self.id!r}, kind={self.kind!r}, status={self.status!r}, "
            f"progress={self.progress:.2f}{extra})"
        )

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _JobFields) and other.id == self.id

    def __hash__(self) -> int:
        return hash(self.id)


class Job(_JobFields):
    """A job on the server (from :class:`QuickNavClient`); methods talk to the server."""

    _client: QuickNavClient

    def refresh(self) -> Job:
        """Reload the job's state from the server."""
        self._update(self._client._get_json(f"/jobs/{self.id}"))
        return self

    def events(self, after: int = 0) -> Iterator[dict]:
        """The job's events (started, progress, ..., a terminal one), live; resumes after drops."""
        return self._client.events(self.id, after=after)

    def wait(
        self,
        progress: bool = False,
        timeout: float | None = None,
        on_event: Callable[[dict], None] | None = None,
    ) -> Job:
        """Follow the job's event stream until it finishes, then refresh; raises WaitTimeout."""
        if self.done:
            return self
        deadline = None if timeout is None else time.monotonic() + timeout
        bar = _ProgressBar(self, progress)
        try:
            for event in self._client._events(self.id, 0, deadline):
                bar.update(event)
                if on_event is not None:
                    on_event(event)
        finally:
            bar.close()
        return self.refresh()

    def metrics_history(self) -> list[dict]:
        """One row per training chunk, from the job's metrics.jsonl (GET /jobs/{id}/metrics)."""
        return self._client._get_json(f"/jobs/{self.id}/metrics")["metrics"]

    def cancel(self) -> Job:
        """Cancel: a queued job at once, a running one at its next chunk boundary."""
        self._update(self._client._request("POST", f"/jobs/{self.id}/cancel").json())
        return self

    def delete(self) -> None:
        """Delete a finished job and its artifacts."""
        self._client._request("DELETE", f"/jobs/{self.id}")

    def artifacts(self) -> list[dict]:
        """The job's files: ``[{"name": "checkpoint/state.msgpack", "bytes": 1234}, ...]``."""
        return self._client._get_json(f"/jobs/{self.id}/artifacts")["artifacts"]

    def download(self, name: str, path: str | Path | None = None) -> Path:
        """Stream an artifact to ``path`` (a file or a folder; default: its name in the cwd)."""
        return self._client.download(self.id, name, path)


class AsyncJob(_JobFields):
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
        if self.done:
            return self
        deadline = None if timeout is None else time.monotonic() + timeout
        bar = _ProgressBar(self, progress)
        try:
            async for event in self._client._events(self.id, 0, deadline):
                bar.update(event)
                if on_event is not None:
                    on_event(event)
        finally:
            bar.close()
        return await self.refresh()

    async def metrics_history(self) -> list[dict]:
        """One row per training chunk, from the job's metrics.jsonl."""
        return (await self._client._get_json(f"/jobs/{self.id}/metrics"))["metrics"]

    async def cancel(self) -> AsyncJob:
        """Cancel: a queued job at once, a running one at its next chunk boundary."""
        self._update((await self._client._request("POST", f"/jobs/{self.id}/cancel")).json())
        return self

    async def delete(self) -> None:
        """Delete a finished job and its artifacts."""
        await self._client._request("DELETE", f"/jobs/{self.id}")

    async def artifacts(self) -> list[dict]:
        """The job's files with their sizes."""
        return (await self._client._get_json(f"/jobs/{self.id}/artifacts"))["artifacts"]

    async def download(self, name: str, path: str | Path | None = None) -> Path:
        """Stream an artifact to ``path`` (a file or a folder; default: its name in the cwd)."""
        return await self._client.download(self.id, name, path)


# --------------------------------------------------------------------------- clients
class _ClientBase:
    def __init__(self, base_url: str, retries: int, backoff_s: float):
        if retries < 0:
            raise ValueError(f"retries={retries}: must be >= 0")
        self.base_url = base_url.rstrip("/")
        self.retries = retries
        self.backoff_s = backoff_s

    def _stream_timeout(self, deadline: float | None) -> httpx.Timeout:
        # The server sends a keep-alive at least every 15 s, so a quiet stream is not a dead one
        # until well past that, whatever the client's (shorter) read timeout for plain requests;
        # a wait deadline shortens it again so that wait(timeout=...) returns on time.
        timeout = self._http.timeout
        read = None if timeout.read is None else max(timeout.read, _SSE_READ_TIMEOUT_S)
        if deadline is not None:
            remaining = max(deadline - time.monotonic(), 0.05)
            read = remaining if read is None else min(read, remaining)
        return httpx.Timeout(timeout.connect, read=read, write=timeout.write, pool=timeout.pool)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.base_url!r})"


class QuickNavClient(_ClientBase):
    """Synchronous client of the QuickNav REST API (use as a context manager, or call close())."""

    def __init__(
        self,
        base_url: str = DEFAULT_URL,
        token: str | None = None,
        timeout: float | httpx.Timeout | None = 30.0,
        retries: int = 3,
        backoff_s: float = 0.5,
        transport: httpx.BaseTransport | None = None,
    ):
        super().__init__(base_url, retries, backoff_s)
        self._http = httpx.Client(
            base_url=self.base_url, headers=_headers(token), timeout=_timeout(timeout),
            transport=transport,
        )  # fmt: skip

    # -- plumbing
    def _request(self, method: str, path: str, **kw) -> httpx.Response:
        cause: Exception | None = None
        for attempt in range(self.retries + 1):
            if attempt:
                time.sleep(_backoff_s(attempt - 1, self.backoff_s))
            try:
                response = self._http.request(method, path, **kw)
            except _TRANSIENT as e:
                cause = e
                continue
            if response.status_code in _RETRY_STATUSES and attempt < self.retries:
                cause = None
                continue
            raise_for_status(response)
            return response
        raise _connection_failed(method, self._http.base_url.join(path), self.retries + 1, cause)

    def _get_json(self, path: str, **kw) -> Any:
        return self._request("GET", path, **kw).json()

    def _send_stream(self, path: str, headers: dict | None = None, timeout=None) -> httpx.Response:
        """GET with a streamed body; connecting is retried, the body is the caller's to read."""
        cause: Exception | None = None
        for attempt in range(self.retries + 1):
            if attempt:
                time.sleep(_backoff_s(attempt - 1, self.backoff_s))
            request = self._http.build_request(
                "GET", path, headers=headers, timeout=timeout or self._http.timeout
            )
            try:
                response = self._http.send(request, stream=True)
            except _TRANSIENT as e:
                cause = e
                continue
            if not response.is_success:
                response.read()
                response.close()
                if response.status_code in _RETRY_STATUSES and attempt < self.retries:
                    continue
                raise_for_status(response)
            return response
        raise _connection_failed("GET", self._http.base_url.join(path), self.retries + 1, cause)

    def _submit(self, path: str, body: dict, idempotency_key: str | None) -> Job:
        # one key per call, reused by every retry of it: a retry returns the job the first made
        headers = {"Idempotency-Key": idempotency_key or uuid.uuid4().hex}
        return Job(self, self._request("POST", path, json=body, headers=headers).json())

    def _events(self, job_id: str, after: int, deadline: float | None) -> Iterator[dict]:
        last_id, failures = after, 0
        while True:
            headers = {"Last-Event-ID": str(last_id)} if last_id else None
            try:
                response = self._send_stream(
                    f"/jobs/{job_id}/events", headers, self._stream_timeout(deadline)
                )
                try:
                    parser = SSEParser()
                    for line in response.iter_lines():
                        failures = 0  # any line, a keep-alive too, shows the connection works
                        if deadline is not None and time.monotonic() > deadline:
                            raise WaitTimeout(f"job {job_id} did not finish in time")
                        event = parser.feed(line)
                        if event is None:
                            continue
                        if isinstance(event["id"], int):
                            last_id = event["id"]
                        yield event
                        if event["type"] in TERMINAL_STATUSES:
                            return
                finally:
                    response.close()
            except _TRANSIENT as e:
                if deadline is not None and time.monotonic() > deadline:
                    raise WaitTimeout(f"job {job_id} did not finish in time") from None
                failures += 1
                if failures > self.retries:
                    raise _connection_failed(
                        "GET", self._http.base_url.join(f"/jobs/{job_id}/events"), failures, e
                    ) from e
                time.sleep(_backoff_s(failures - 1, self.backoff_s))
                continue
            # The stream ended cleanly without a terminal event: either the job finished long
            # ago (its events trimmed) or something between us and the server closed it.
            if self._get_json(f"/jobs/{job_id}")["status"] in TERMINAL_STATUSES:
                return
            if deadline is not None and time.monotonic() > deadline:
                raise WaitTimeout(f"job {job_id} did not finish in time")
            time.sleep(self.backoff_s)

    # -- public API
    def close(self) -> None:
        """Close the connection pool."""
        self._http.close()

    def __enter__(self) -> QuickNavClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def health(self) -> dict:
        """GET /healthz: the API process is up."""
        return self._get_json("/healthz")

    def ready(self) -> dict:
        """GET /readyz: the job store answers (ServerError with its reason if not)."""
        return self._get_json("/readyz")

    def presets(self) -> dict[str, dict]:
        """The server's training presets: ``{name: {"description", "config"}}``."""
        return self._get_json("/presets")

    def train(
        self,
        config: Mapping | str | None = None,
        preset: str | None = None,
        overrides: Mapping[str, Any] | None = None,
        idempotency_key: str | None = None,
        **fields: Any,
    ) -> Job:
        """Submit a train job: a preset (or config) plus dotted ``overrides`` and top-level fields."""
        return self._submit("/jobs/train", train_body(config, preset, overrides, fields),
                            idempotency_key)  # fmt: skip

    def sweep(
        self,
        config: Mapping | str | None = None,
        trials: int | None = None,
        parallel: int | None = None,
        total_steps: int | None = None,
        overrides: Mapping[str, Any] | None = None,
        idempotency_key: str | None = None,
    ) -> Job:
        """Submit a sweep job: a SweepConfig dict, or a built-in space name (ppo, lstm, ...)."""
        body = sweep_body(config, trials, parallel, total_steps, overrides)
        return self._submit("/jobs/sweep", body, idempotency_key)

    def evaluate(
        self,
        job: JobRef = None,
        policy: str | None = None,
        episodes: int = 100,
        seed: int = 0,
        env: Mapping[str, Any] | None = None,
        stochastic: bool = False,
        idempotency_key: str | None = None,
    ) -> Job:
        """Submit an eval job: a train job's checkpoint, or a ``random``/``oracle`` baseline."""
        body = eval_body(job, policy, episodes, seed, env, stochastic)
        return self._submit("/jobs/eval", body, idempotency_key)

    def jobs(
        self, status: str | None = None, kind: str | None = None, limit: int = 50, offset: int = 0
    ) -> JobList:
        """A page of jobs, newest first; ``.count`` is the total matching the filter."""
        page = self._get_json("/jobs", params=list_params(status, kind, limit, offset))
        return JobList([Job(self, d) for d in page["data"]], page["count"])

    def job(self, job_id: str) -> Job:
        """One job by id (NotFound if there is none)."""
        return Job(self, self._get_json(f"/jobs/{job_id}"))

    def events(self, job_id: str, after: int = 0) -> Iterator[dict]:
        """A job's events after event id ``after``, live, until the terminal one."""
        return self._events(job_id, after, None)

    def download(self, job_id: str, name: str, path: str | Path | None = None) -> Path:
        """Stream a job's artifact to a file (written whole or not at all); returns its path."""
        target = download_target(name, path)
        partial = target.with_name(target.name + ".part")
        for attempt in range(self.retries + 1):
            response = self._send_stream(artifact_path(job_id, name))
            try:
                with partial.open("wb") as f:
                    for chunk in response.iter_bytes():
                        f.write(chunk)
            except _TRANSIENT as e:
                partial.unlink(missing_ok=True)
                if attempt == self.retries:
                    raise _connection_failed("GET", response.request.url, attempt + 1, e) from e
                time.sleep(_backoff_s(attempt, self.backoff_s))
                continue
            finally:
                response.close()
            break
        partial.replace(target)
        return target


class AsyncQuickNavClient(_ClientBase):
    """Asynchronous client (httpx.AsyncClient): the methods of QuickNavClient, as coroutines."""

    def __init__(
        self,
        base_url: str = DEFAULT_URL,
        token: str | None = None,
        timeout: float | httpx.Timeout | None = 30.0,
        retries: int = 3,
        backoff_s: float = 0.5,
        transport: httpx.AsyncBaseTransport | None = None,
    ):
        super().__init__(base_url, retries, backoff_s)
        self._http = httpx.AsyncClient(
            base_url=self.base_url, headers=_headers(token), timeout=_timeout(timeout),
            transport=transport,
        )  # fmt: skip

    # -- plumbing
    async def _request(self, method: str, path: str, **kw) -> httpx.Response:
        cause: Exception | None = None
        for attempt in range(self.retries + 1):
            if attempt:
                await asyncio.sleep(_backoff_s(attempt - 1, self.backoff_s))
            try:
                response = await self._http.request(method, path, **kw)
            except _TRANSIENT as e:
                cause = e
                continue
            if response.status_code in _RETRY_STATUSES and attempt < self.retries:
                cause = None
                continue
            raise_for_status(response)
            return response
        raise _connection_failed(method, self._http.base_url.join(path), self.retries + 1, cause)

    async def _get_json(self, path: str, **kw) -> Any:
        return (await self._request("GET", path, **kw)).json()

    async def _send_stream(self, path: str, headers: dict | None = None, timeout=None):
        cause: Exception | None = None
        for attempt in range(self.retries + 1):
            if attempt:
                await asyncio.sleep(_backoff_s(attempt - 1, self.backoff_s))
            request = self._http.build_request(
                "GET", path, headers=headers, timeout=timeout or self._http.timeout
            )
            try:
                response = await self._http.send(request, stream=True)
            except _TRANSIENT as e:
                cause = e
                continue
            if not response.is_success:
                await response.aread()
                await response.aclose()
                if response.status_code in _RETRY_STATUSES and attempt < self.retries:
                    continue
                raise_for_status(response)
            return response
        raise _connection_failed("GET", self._http.base_url.join(path), self.retries + 1, cause)

    async def _submit(self, path: str, body: dict, idempotency_key: str | None) -> AsyncJob:
        headers = {"Idempotency-Key": idempotency_key or uuid.uuid4().hex}
        return AsyncJob(
            self, (await self._request("POST", path, json=body, headers=headers)).json()
        )

    async def _events(self, job_id: str, after: int, deadline: float | None) -> AsyncIterator[dict]:
        last_id, failures = after, 0
        while True:
            headers = {"Last-Event-ID": str(last_id)} if last_id else None
            try:
                response = await self._send_stream(
                    f"/jobs/{job_id}/events", headers, self._stream_timeout(deadline)
                )
                try:
                    parser = SSEParser()
                    async for line in response.aiter_lines():
                        failures = 0  # any line, a keep-alive too, shows the connection works
                        if deadline is not None and time.monotonic() > deadline:
                            raise WaitTimeout(f"job {job_id} did not finish in time")
                        event = parser.feed(line)
                        if event is None:
                            continue
                        if isinstance(event["id"], int):
                            last_id = event["id"]
                        yield event
                        if event["type"] in TERMINAL_STATUSES:
                            return
                finally:
                    await response.aclose()
            except _TRANSIENT as e:
                if deadline is not None and time.monotonic() > deadline:
                    raise WaitTimeout(f"job {job_id} did not finish in time") from None
                failures += 1
                if failures > self.retries:
                    raise _connection_failed(
                        "GET", self._http.base_url.join(f"/jobs/{job_id}/events"), failures, e
                    ) from e
                await asyncio.sleep(_backoff_s(failures - 1, self.backoff_s))
                continue
            if (await self._get_json(f"/jobs/{job_id}"))["status"] in TERMINAL_STATUSES:
                return
            if deadline is not None and time.monotonic() > deadline:
                raise WaitTimeout(f"job {job_id} did not finish in time")
            await asyncio.sleep(self.backoff_s)

    # -- public API
    async def aclose(self) -> None:
        """Close the connection pool."""
        await self._http.aclose()

    async def __aenter__(self) -> AsyncQuickNavClient:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.aclose()

    async def health(self) -> dict:
        """GET /healthz: the API process is up."""
        return await self._get_json("/healthz")

    async def ready(self) -> dict:
        """GET /readyz: the job store answers."""
        return await self._get_json("/readyz")

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
        body = train_body(config, preset, overrides, fields)
        return await self._submit("/jobs/train", body, idempotency_key)

    async def sweep(
        self,
        config: Mapping | str | None = None,
        trials: int | None = None,
        parallel: int | None = None,
        total_steps: int | None = None,
        overrides: Mapping[str, Any] | None = None,
        idempotency_key: str | None = None,
    ) -> AsyncJob:
        """Submit a sweep job: a SweepConfig dict, or a built-in space name."""
        body = sweep_body(config, trials, parallel, total_steps, overrides)
        return await self._submit("/jobs/sweep", body, idempotency_key)

    async def evaluate(
        self,
        job: JobRef = None,
        policy: str | None = None,
        episodes: int = 100,
        seed: int = 0,
        env: Mapping[str, Any] | None = None,
        stochastic: bool = False,
        idempotency_key: str | None = None,
    ) -> AsyncJob:
        """Submit an eval job: a train job's checkpoint, or a ``random``/``oracle`` baseline."""
        body = eval_body(job, policy, episodes, seed, env, stochastic)
        return await self._submit("/jobs/eval", body, idempotency_key)

    async def jobs(
        self, status: str | None = None, kind: str | None = None, limit: int = 50, offset: int = 0
    ) -> JobList:
        """A page of jobs, newest first; ``.count`` is the total matching the filter."""
        page = await self._get_json("/jobs", params=list_params(status, kind, limit, offset))
        return JobList([AsyncJob(self, d) for d in page["data"]], page["count"])

    async def job(self, job_id: str) -> AsyncJob:
        """One job by id (NotFound if there is none)."""
        return AsyncJob(self, await self._get_json(f"/jobs/{job_id}"))

    def events(self, job_id: str, after: int = 0) -> AsyncIterator[dict]:
        """A job's events after event id ``after``, live, until the terminal one."""
        return self._events(job_id, after, None)

    async def download(self, job_id: str, name: str, path: str | Path | None = None) -> Path:
        """Stream a job's artifact to a file (written whole or not at all); returns its path."""
        target = download_target(name, path)
        partial = target.with_name(target.name + ".part")
        for attempt in range(self.retries + 1):
            response = await self._send_stream(artifact_path(job_id, name))
            try:
                with partial.open("wb") as f:
                    async for chunk in response.aiter_bytes():
                        f.write(chunk)
            except _TRANSIENT as e:
                partial.unlink(missing_ok=True)
                if attempt == self.retries:
                    raise _connection_failed("GET", response.request.url, attempt + 1, e) from e
                await asyncio.sleep(_backoff_s(attempt, self.backoff_s))
                continue
            finally:
                await response.aclose()
            break
        partial.replace(target)
        return target
