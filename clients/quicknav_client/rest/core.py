"""The sans-IO core of the REST client: every decision, no waiting.

Each client operation (a request with retries, following a job's events, a download) is written
once here, as a generator that *yields effects* -- ``Send`` a request, ``Sleep``, read the next line
of a streamed body, ... -- and receives their results. The sync client (``sync.py``) performs the
effects with ``httpx.Client`` and ``time.sleep``; the async client (``aio.py``) with
``httpx.AsyncClient`` and ``asyncio.sleep``. A transport error while performing an effect is thrown
back into the operation, which decides to retry or to give up. The two clients differ only in how
they wait.
"""

from __future__ import annotations

import copy
import json
import math
import random
import time
import uuid
import warnings
from collections.abc import Callable, Generator, Mapping
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import quote

import httpx

from quicknav_client.errors import ConnectionFailed, WaitTimeout, error_class, format_detail

DEFAULT_URL = "http://127.0.0.1:8000"
TERMINAL_STATUSES = frozenset({"succeeded", "failed", "cancelled"})
# a train job's exported policy: the ONNX model and its manifest (``quicknav export``)
POLICY_FILES = ("policy.onnx", "policy.json")
# Statuses a proxy or a restarting server answers with while the service itself is fine.
RETRY_STATUSES = frozenset({502, 503, 504})
SSE_READ_TIMEOUT_S = 45.0  # three of the server's 15 s keep-alive intervals
TRANSIENT = (httpx.TimeoutException, httpx.NetworkError, httpx.RemoteProtocolError)


# --------------------------------------------------------------------------- effects
@dataclass
class Send:
    """Send a request; the result is the ``httpx.Response`` (body unread when ``stream``)."""

    method: str
    path: str
    kwargs: dict[str, Any] = field(default_factory=dict)  # json, params, headers, timeout
    stream: bool = False


@dataclass
class Sleep:
    seconds: float


@dataclass
class Lines:
    """Start reading a streamed response line by line; the result is a handle for ``NextLine``."""

    response: httpx.Response


@dataclass
class NextLine:
    """The next line of a ``Lines`` handle, or ``END`` when the body is over."""

    lines: Any


@dataclass
class ReadBody:
    """Read a streamed response's whole body (to raise its error with the server's message)."""

    response: httpx.Response


@dataclass
class Close:
    response: httpx.Response


@dataclass
class SaveBody:
    """Write a streamed response's body to a file, chunk by chunk."""

    response: httpx.Response
    path: Path


@dataclass
class Emit:
    """A value for the caller of an iterating operation (an event of a job)."""

    value: Any


END = object()  # NextLine's result at the end of the body

Operation = Generator[Any, Any, Any]


# --------------------------------------------------------------------------- responses
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


def connection_failed(method: str, url: str, attempts: int, cause: Exception | None):
    why = f"{type(cause).__name__}: {cause}" if cause else "no response"
    return ConnectionFailed(
        f"could not reach the QuickNav service at {url} ({method}, {attempts} attempts): {why}",
        method=method,
        url=url,
    )


def backoff_s(attempt: int, base_s: float) -> float:
    # jitter so that many clients cut off by one outage do not come back in lockstep
    return min(base_s * 2**attempt, 10.0) * random.uniform(0.5, 1.0)


def make_timeout(timeout: float | httpx.Timeout | None) -> httpx.Timeout:
    if isinstance(timeout, httpx.Timeout):
        return timeout
    return httpx.Timeout(timeout, connect=None if timeout is None else min(timeout, 10.0))


def default_headers(token: str | None) -> dict[str, str]:
    from quicknav_client import __version__

    headers = {"User-Agent": f"quicknav-client/{__version__}"}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    return headers


def stream_timeout(timeout: httpx.Timeout, deadline: float | None) -> httpx.Timeout:
    """The read timeout of an event stream: past the server's keep-alives, within a deadline.

    The server sends a keep-alive at least every 15 s, so a quiet stream is not a dead one until
    well past that, whatever the client's (shorter) read timeout for plain requests; a wait deadline
    shortens it again so that wait(timeout=...) returns on time.
    """
    read = None if timeout.read is None else max(timeout.read, SSE_READ_TIMEOUT_S)
    if deadline is not None:
        remaining = max(deadline - time.monotonic(), 0.05)
        read = remaining if read is None else min(read, remaining)
    return httpx.Timeout(timeout.connect, read=read, write=timeout.write, pool=timeout.pool)


# --------------------------------------------------------------------------- request bodies
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
    """The POST /jobs/train body: a preset or a config, with dotted-key overrides (the server
    resolves them; top-level ``fields`` such as ``total_steps=...`` are overrides too)."""
    if isinstance(config, str):
        if preset is not None:
            raise ValueError("give the preset once: as `config` or as `preset`, not both")
        config, preset = None, config
    if (config is None) == (preset is None):
        raise ValueError("give exactly one of `config` (a TrainConfig dict) or `preset` (a name)")
    body: dict[str, Any] = {"preset": preset} if preset is not None else {"config": _as_dict(config)}
    changes = {**(overrides or {}), **fields}
    if changes:
        body["overrides"] = changes
    return body


def sweep_body(
    config: Mapping | str | None,
    trials: int | None,
    parallel: int | None,
    total_steps: int | None,
    overrides: Mapping[str, Any] | None,
    space: str | None = None,
    base: str | None = None,
) -> dict:
    """The POST /jobs/sweep body: a built-in ``space`` name (and the ``base`` preset its trials
    start from) or a SweepConfig, with overrides (keys of the SweepConfig or of its base
    TrainConfig). A name passed as ``config`` is a space too."""
    if isinstance(config, str):
        if space is not None:
            raise ValueError("give the space once: as `space` (its name), not also as `config`")
        config, space = None, config
    if (config is None) == (space is None):
        raise ValueError("give exactly one of `space` (a built-in space name: ppo, sac, td3, ...)"
                         " or `config` (a SweepConfig dict)")  # fmt: skip
    body: dict[str, Any] = {"space": space} if space is not None else {"config": _as_dict(config)}
    for key, value in (("base", base), ("trials", trials), ("parallel", parallel), ("total_steps", total_steps)):
        if value is not None:
            body[key] = value
    if overrides:
        body["overrides"] = dict(overrides)
    return body


def eval_body(
    job: Any,
    policy: str | None,
    episodes: int,
    seed: int,
    env: Mapping | None,
    split: str = "test",
    deterministic: bool = True,
    stochastic: bool | None = None,
    robustness: bool = False,
    shield: bool = False,
    map: str | None = None,
) -> dict:
    """The POST /jobs/eval body (the server checks that exactly one of job and policy is given)."""
    if stochastic is not None:
        warnings.warn("`stochastic` is deprecated: pass deterministic=not stochastic",
                      DeprecationWarning, stacklevel=3)  # fmt: skip
        deterministic = not stochastic
    body: dict[str, Any] = {"episodes": episodes, "seed": seed, "split": split,
                            "deterministic": deterministic}  # fmt: skip
    if job is not None:
        body["job_id"] = job if isinstance(job, str) else job.id
    if policy is not None:
        body["policy"] = policy
    if env:
        body["env"] = dict(env)
    if map is not None:
        body["map"] = map
    if robustness:
        body["robustness"] = True
    if shield:
        body["shield"] = True
    return body


def download_out(out: str | Path | None, path: str | Path | None) -> str | Path | None:
    """The destination of a download; ``path`` is the deprecated name of ``out`` (the CLI's --out)."""
    if path is not None:
        if out is not None:
            raise ValueError("give the destination once, as `out` (`path` is its deprecated name)")
        warnings.warn("download(path=...) is deprecated: pass out=... (as `quicknav jobs download"
                      " --out`)", DeprecationWarning, stacklevel=3)  # fmt: skip
        return path
    return out


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


# --------------------------------------------------------------------------- events and jobs
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
        name, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if name == "data":
            self._data.append(value)
        elif name == "event":
            self._event = value
        elif name == "id" and "\0" not in value:
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


class JobFields:
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
        self.worker: str | None = data.get("worker")
        self.cancel_requested: bool = bool(data.get("cancel_requested"))
        self.created_at: float | None = data.get("created_at")
        self.started_at: float | None = data.get("started_at")
        self.finished_at: float | None = data.get("finished_at")
        self.request: dict[str, Any] = data.get("request") or {}
        self.config: dict[str, Any] = data.get("config") or {}
        self.links: dict[str, str] = data.get("links") or {}
        # pictures that failed to render while the numbers were kept (older servers send none)
        self.warnings: list[str] = list(data.get("warnings") or [])
        # a queued job that no live worker can run: why it waits (older servers send none)
        self.waiting: str | None = data.get("waiting")

    @property
    def phase(self) -> str | None:
        """What a running job is doing: compiling, training or evaluating (None if not said)."""
        phase = self.metrics.get("phase")
        return phase if isinstance(phase, str) else None

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
        return isinstance(other, JobFields) and other.id == self.id

    def __hash__(self) -> int:
        return hash(self.id)


class ProgressBar:
    """A tqdm bar fed by job events (disabled: does nothing)."""

    def __init__(self, job: JobFields, enabled: bool):
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


# --------------------------------------------------------------------------- operations
@dataclass
class Policy:
    """How a client retries: ``retries`` more attempts after the first, exponential backoff."""

    base_url: str
    retries: int
    backoff_s: float
    timeout: httpx.Timeout

    def url(self, path: str) -> str:
        return f"{self.base_url}{path}"


def request(p: Policy, method: str, path: str, **kwargs) -> Operation:
    """A request with retries on transport errors and 502/503/504; returns the checked response."""
    cause: Exception | None = None
    for attempt in range(p.retries + 1):
        if attempt:
            yield Sleep(backoff_s(attempt - 1, p.backoff_s))
        try:
            response = yield Send(method, path, kwargs)
        except TRANSIENT as e:
            cause = e
            continue
        if response.status_code in RETRY_STATUSES and attempt < p.retries:
            cause = None
            continue
        raise_for_status(response)
        return response
    raise connection_failed(method, p.url(path), p.retries + 1, cause)


def request_json(p: Policy, method: str, path: str, **kwargs) -> Operation:
    response = yield from request(p, method, path, **kwargs)
    return response.json() if response.content else None


def submit(p: Policy, path: str, body: dict, idempotency_key: str | None) -> Operation:
    """POST a job; one Idempotency-Key per call, reused by every retry of it, so a retry whose
    first attempt did reach the server returns the job that attempt made."""
    headers = {"Idempotency-Key": idempotency_key or uuid.uuid4().hex}
    return (yield from request_json(p, "POST", path, json=body, headers=headers))


def open_stream(p: Policy, path: str, headers: dict | None = None, timeout=None) -> Operation:
    """GET with a streamed body; connecting is retried, the body is the caller's to read."""
    cause: Exception | None = None
    for attempt in range(p.retries + 1):
        if attempt:
            yield Sleep(backoff_s(attempt - 1, p.backoff_s))
        try:
            response = yield Send("GET", path, {"headers": headers, "timeout": timeout or p.timeout},
                                  stream=True)  # fmt: skip
        except TRANSIENT as e:
            cause = e
            continue
        if not response.is_success:
            yield ReadBody(response)
            yield Close(response)
            if response.status_code in RETRY_STATUSES and attempt < p.retries:
                continue
            raise_for_status(response)
        return response
    raise connection_failed("GET", p.url(path), p.retries + 1, cause)


def events(p: Policy, job_id: str, after: int, deadline: float | None,
           deliver: Callable[[dict], None] | None = None) -> Operation:  # fmt: skip
    """A job's events after ``after``, until the terminal one; resumes after dropped connections.

    Each event is emitted (``Emit``), or given to ``deliver`` when one is passed. (Responses an
    operation leaves open when it ends early are closed by the client that runs it.)
    """
    path = f"/jobs/{job_id}/events"
    last_id, failures = after, 0
    while True:
        headers = {"Last-Event-ID": str(last_id)} if last_id else None
        response = None
        try:
            response = yield from open_stream(p, path, headers, stream_timeout(p.timeout, deadline))
            parser = SSEParser()
            lines = yield Lines(response)
            terminal = False
            while not terminal and (line := (yield NextLine(lines))) is not END:
                failures = 0  # any line, a keep-alive too, shows the connection works
                if deadline is not None and time.monotonic() > deadline:
                    raise WaitTimeout(f"job {job_id} did not finish in time")
                event = parser.feed(line)
                if event is None:
                    continue
                if isinstance(event["id"], int):
                    last_id = event["id"]
                terminal = event["type"] in TERMINAL_STATUSES
                if deliver is not None:
                    deliver(event)
                else:
                    yield Emit(event)
            yield Close(response)
            if terminal:
                return
        except TRANSIENT as e:
            if response is not None:
                yield Close(response)
            if deadline is not None and time.monotonic() > deadline:
                raise WaitTimeout(f"job {job_id} did not finish in time") from None
            failures += 1
            if failures > p.retries:
                raise connection_failed("GET", p.url(path), failures, e) from e
            yield Sleep(backoff_s(failures - 1, p.backoff_s))
            continue
        # The stream ended cleanly without a terminal event: either the job finished long ago
        # (its events trimmed) or something between us and the server closed it.
        job = yield from request_json(p, "GET", f"/jobs/{job_id}")
        if job["status"] in TERMINAL_STATUSES:
            return
        if deadline is not None and time.monotonic() > deadline:
            raise WaitTimeout(f"job {job_id} did not finish in time")
        yield Sleep(p.backoff_s)


def wait(p: Policy, job: JobFields, progress: bool, timeout: float | None,
         on_event: Callable[[dict], None] | None) -> Operation:  # fmt: skip
    """Follow a job's events until it finishes (a progress bar, a callback), then refresh it."""
    if job.done:
        return job
    deadline = None if timeout is None else time.monotonic() + timeout
    bar = ProgressBar(job, progress)

    def deliver(event: dict) -> None:
        bar.update(event)
        if on_event is not None:
            on_event(event)

    try:
        yield from events(p, job.id, 0, deadline, deliver)
    finally:
        bar.close()  # no effect is yielded here: safe when the operation is closed
    job._update((yield from request_json(p, "GET", f"/jobs/{job.id}")))
    return job


def download(p: Policy, job_id: str, name: str, path: str | Path | None) -> Operation:
    """Stream a job's artifact to a file, written whole or not at all; returns its path."""
    return (yield from save(p, artifact_path(job_id, name), download_target(name, path)))


def save(p: Policy, url_path: str, target: Path) -> Operation:
    """Stream a GET's body to ``target``, written whole or not at all; returns the path."""
    partial = target.with_name(target.name + ".part")
    for attempt in range(p.retries + 1):
        response = yield from open_stream(p, url_path)
        try:
            yield SaveBody(response, partial)
        except TRANSIENT as e:
            yield Close(response)
            partial.unlink(missing_ok=True)
            if attempt == p.retries:
                raise connection_failed("GET", str(response.request.url), attempt + 1, e) from e
            yield Sleep(backoff_s(attempt, p.backoff_s))
            continue
        yield Close(response)
        break
    partial.replace(target)
    return target


# --------------------------------------------------------------------------- maps
MAP_IMAGE_SUFFIXES = (".pgm", ".png")
MAP_FILES = ("map.yaml", "map.pgm", "map.png")  # what a stored map may hold, by name


def _yaml_image(yaml_path: Path) -> Path:
    """The image a map_server YAML names (read without a YAML library: one ``image:`` line)."""
    for line in yaml_path.read_text().splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() == "image":
            name = value.split("#", 1)[0].strip().strip("'\"")
            return yaml_path.parent / name
    raise ValueError(f"{yaml_path}: no 'image:' line; a map_server YAML names its image")


def map_upload(path: str | Path, name: str | None, resolution: float | None, negate: bool | None,
               occupied_thresh: float | None, free_thresh: float | None) -> dict[str, Any]:  # fmt: skip
    """The multipart request of ``POST /maps`` for a map file: a map_server .yaml goes with the
    image it names; a .png/.pgm alone (then ``resolution`` is needed: the server says so)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such map file")
    paths = [path, _yaml_image(path)] if path.suffix.lower() in (".yaml", ".yml") else [path]
    for extra in paths[1:]:
        if not extra.is_file():
            raise FileNotFoundError(f"{path} names image {extra.name!r}, which is not there"
                                    f" ({extra.absolute()}: no such file)")  # fmt: skip
    form = {"name": name, "resolution": resolution, "occupied_thresh": occupied_thresh,
            "free_thresh": free_thresh, "negate": None if negate is None else str(bool(negate)).lower()}  # fmt: skip
    return {"files": [("files", (f.name, f.read_bytes())) for f in paths],
            "data": {k: str(v) for k, v in form.items() if v is not None}}


def map_id(ref: str) -> str:
    """A map's id from its id or its ``map:<id>`` reference."""
    return ref.removeprefix("map:")


def download_map(p: Policy, ref: str, dest: str | Path) -> Operation:
    """A stored map's ``map.yaml`` and its image into the folder ``dest``; returns the YAML's path."""
    folder = Path(dest)
    folder.mkdir(parents=True, exist_ok=True)
    meta = yield from request_json(p, "GET", f"/maps/{map_id(ref)}")
    yaml_path = yield from save(p, f"/maps/{meta['id']}/files/map.yaml", folder / "map.yaml")
    image = _yaml_image(yaml_path).name
    yield from save(p, f"/maps/{meta['id']}/files/{image}", folder / image)
    return yaml_path
