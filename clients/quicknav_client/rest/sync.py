"""The synchronous REST client: runs the core's operations with ``httpx.Client`` and ``time.sleep``."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping
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


class Job(JobFields):
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
        return self._client._run(core.wait(self._client._policy, self, progress, timeout, on_event))

    def metrics_history(self) -> list[dict]:
        """One row per training chunk, from the job's metrics.jsonl (GET /jobs/{id}/metrics)."""
        return self._client._get_json(f"/jobs/{self.id}/metrics")["metrics"]

    def cancel(self) -> Job:
        """Cancel: a queued job at once, a running one at its next chunk boundary."""
        self._update(self._client._json("POST", f"/jobs/{self.id}/cancel", json={}))
        return self

    def delete(self) -> None:
        """Delete a finished job and its artifacts."""
        self._client._json("DELETE", f"/jobs/{self.id}")

    def artifacts(self) -> list[dict]:
        """The job's files: ``[{"name": "checkpoint/state.msgpack", "bytes": 1234}, ...]``."""
        return self._client._get_json(f"/jobs/{self.id}/artifacts")["artifacts"]

    def download(
        self, name: str, out: str | Path | None = None, *, path: str | Path | None = None
    ) -> Path:
        """Stream an artifact to ``out`` (a file or a folder; default: its name in the cwd)."""
        return self._client.download(self.id, name, core.download_out(out, path))

    def download_policy(self, dest: str | Path = ".") -> Path:
        """This train job's ``policy.onnx`` and ``policy.json`` into the folder ``dest``."""
        return self._client.download_policy(self.id, dest)


class QuickNavClient:
    """Synchronous client of the QuickNav REST API (use as a context manager, or call close()).

    Transient failures (refused connections, timeouts, 502/503/504) are retried with exponential
    backoff; every submission carries an ``Idempotency-Key`` reused across its retries.
    """

    def __init__(
        self,
        base_url: str = core.DEFAULT_URL,
        token: str | None = None,
        timeout: float | httpx.Timeout | None = 30.0,
        retries: int = 3,
        backoff_s: float = 0.5,
        transport: httpx.BaseTransport | None = None,
    ):
        if retries < 0:
            raise ValueError(f"retries={retries}: must be >= 0")
        self.base_url = base_url.rstrip("/")
        self.retries = retries
        self.backoff_s = backoff_s
        self._http = httpx.Client(
            base_url=self.base_url, headers=core.default_headers(token),
            timeout=core.make_timeout(timeout), transport=transport,
        )  # fmt: skip
        self._policy = core.Policy(self.base_url, retries, backoff_s, self._http.timeout)

    # -- running operations
    def _perform(self, effect: Any, opened: list[httpx.Response]) -> Any:
        if isinstance(effect, Send):
            request = self._http.build_request(effect.method, effect.path, **effect.kwargs)
            response = self._http.send(request, stream=effect.stream)
            if effect.stream:
                opened.append(response)
            return response
        if isinstance(effect, Sleep):
            time.sleep(effect.seconds)
        elif isinstance(effect, Lines):
            return effect.response.iter_lines()
        elif isinstance(effect, NextLine):
            return next(effect.lines, END)
        elif isinstance(effect, ReadBody):
            effect.response.read()
        elif isinstance(effect, Close):
            effect.response.close()
        elif isinstance(effect, SaveBody):
            with effect.path.open("wb") as f:
                for chunk in effect.response.iter_bytes():
                    f.write(chunk)
        else:  # pragma: no cover - a core operation yielded something new
            raise TypeError(f"unknown effect {effect!r}")
        return None

    def _steps(self, op: Operation) -> Iterator[Any]:
        """Drive ``op``; yields what it emits, returns its result (as StopIteration's value)."""
        opened: list[httpx.Response] = []
        result: Any = None
        error: BaseException | None = None
        try:
            while True:
                try:
                    effect = op.throw(error) if error is not None else op.send(result)
                except StopIteration as stop:
                    return stop.value
                result, error = None, None
                if isinstance(effect, Emit):
                    yield effect.value
                    continue
                try:
                    result = self._perform(effect, opened)
                except Exception as e:  # the operation decides: retry, or raise
                    error = e
        finally:
            op.close()
            for response in opened:
                response.close()

    def _run(self, op: Operation) -> Any:
        steps = self._steps(op)
        try:
            while True:
                next(steps)  # an operation run here emits nothing
        except StopIteration as stop:
            return stop.value

    def _json(self, method: str, path: str, **kw) -> Any:
        return self._run(core.request_json(self._policy, method, path, **kw))

    def _get_json(self, path: str, **kw) -> Any:
        return self._json("GET", path, **kw)

    def _submit(self, path: str, body: dict, idempotency_key: str | None) -> Job:
        return Job(self, self._run(core.submit(self._policy, path, body, idempotency_key)))

    # -- public API
    def close(self) -> None:
        """Close the connection pool."""
        self._http.close()

    def __enter__(self) -> QuickNavClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.base_url!r})"

    def health(self) -> dict:
        """GET /healthz: the API process is up."""
        return self._get_json("/healthz")

    def ready(self) -> dict:
        """GET /readyz: the job store answers (ServerError with its reason if not)."""
        return self._get_json("/readyz")

    def rollout_endpoints(self) -> list[dict]:
        """The gRPC Rollout servers the service knows (``address``, ``backend``, ``device``,
        ``sessions``, ``max_sessions``); pass an ``address`` to ``RolloutClient``."""
        return (self._get_json("/rollout/endpoints"))["endpoints"]

    def presets(self) -> dict[str, dict]:
        """The server's training presets: ``{name: {"description", "config", ...}}``."""
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
        body = core.train_body(config, preset, overrides, fields)
        return self._submit("/jobs/train", body, idempotency_key)

    def sweep(
        self,
        config: Mapping | str | None = None,
        trials: int | None = None,
        parallel: int | None = None,
        total_steps: int | None = None,
        overrides: Mapping[str, Any] | None = None,
        idempotency_key: str | None = None,
        space: str | None = None,
        base: str | None = None,
    ) -> Job:
        """Submit a sweep job: a built-in ``space`` (ppo, lstm, ...), its trials starting from
        the ``base`` preset (default: the space's paper preset), or a SweepConfig ``config``."""
        body = core.sweep_body(config, trials, parallel, total_steps, overrides, space, base)
        return self._submit("/jobs/sweep", body, idempotency_key)

    def evaluate(
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
    ) -> Job:
        """Submit an eval job: a train job's checkpoint, or a ``random``/``oracle`` baseline.

        ``env`` sets fields of the env the episodes run in (the trained policy's own, or the
        default env for a baseline); ``stochastic`` is the deprecated opposite of deterministic;
        ``robustness`` also runs the episodes at each fixed perturbation level (eval.json's
        ``robustness`` rows, robustness.png); ``shield`` puts the safety layer between the policy
        and the wheels (agent ``<policy>+shield``); ``map`` drives a map uploaded to the server
        (``map:<id>``, ``maps()``) at the policy's cell size, the grid and step limit following it.
        """
        body = core.eval_body(job, policy, episodes, seed, env, split, deterministic, stochastic,
                              robustness, shield, map)  # fmt: skip
        return self._submit("/jobs/eval", body, idempotency_key)

    def jobs(
        self, status: str | None = None, kind: str | None = None, limit: int = 50, offset: int = 0
    ) -> JobList:
        """A page of jobs, newest first; ``.count`` is the total matching the filter."""
        page = self._get_json("/jobs", params=core.list_params(status, kind, limit, offset))
        return JobList([Job(self, d) for d in page["data"]], page["count"])

    def job(self, job_id: str) -> Job:
        """One job by id (NotFound if there is none)."""
        return Job(self, self._get_json(f"/jobs/{job_id}"))

    def events(self, job_id: str, after: int = 0) -> Iterator[dict]:
        """A job's events after event id ``after``, live, until the terminal one."""
        return self._steps(core.events(self._policy, job_id, after, None))

    def download(
        self, job_id: str, name: str, out: str | Path | None = None, *,
        path: str | Path | None = None,
    ) -> Path:
        """Stream a job's artifact to ``out``, a file or a folder (default: its name in the cwd),
        written whole or not at all; returns its path. ``path`` is the deprecated name of ``out``."""
        return self._run(core.download(self._policy, job_id, name, core.download_out(out, path)))

    # -- maps
    def upload_map(
        self, path: str | Path, *, name: str | None = None, resolution: float | None = None,
        negate: bool | None = None, occupied_thresh: float | None = None,
        free_thresh: float | None = None,
    ) -> dict:
        """Upload a building map: a map_server ``.yaml`` (its image goes with it) or a ``.png``/
        ``.pgm`` with ``resolution`` (metres per pixel). Returns the map; name it in an env config
        as its ``ref`` (``env.maps.train: ["map:<id>"]``). The same files give the same map."""
        parts = core.map_upload(path, name, resolution, negate, occupied_thresh, free_thresh)
        return self._json("POST", "/maps", **parts)

    def maps(self) -> list[dict]:
        """Every uploaded map, newest first."""
        return self._get_json("/maps")["data"]

    def map(self, ref: str) -> dict:
        """One map by id or ``map:<id>``: size, resolution, free space, the env that holds it."""
        return self._get_json(f"/maps/{core.map_id(ref)}")

    def map_preview(self, ref: str, out: str | Path = "preview.png") -> Path:
        """The map's picture as a PNG file."""
        return self._run(core.save(self._policy, f"/maps/{core.map_id(ref)}/preview.png", Path(out)))

    def download_map(self, ref: str, dest: str | Path = ".") -> Path:
        """The stored map_server pair (``map.yaml`` and its image) into ``dest``; the YAML's path."""
        return self._run(core.download_map(self._policy, ref, dest))

    def delete_map(self, ref: str) -> None:
        """Delete a map (Conflict while a queued or running job uses it)."""
        self._json("DELETE", f"/maps/{core.map_id(ref)}")

    def download_policy(self, job_id: str, dest: str | Path = ".") -> Path:
        """Download a train job's exported policy (``policy.onnx`` and its ``policy.json``
        manifest) into the folder ``dest``; returns the folder. A job trained before policies were
        exported, or whose export failed (its warnings say why), answers 404."""
        folder = Path(dest)
        folder.mkdir(parents=True, exist_ok=True)
        for name in core.POLICY_FILES:
            self.download(job_id, name, folder / name)
        return folder
