"""The jobs service: the business rules between the HTTP routes and the job store.

Submission (resolve, this server's limits, idempotency), lookup by id or prefix, cancel, and
delete with its cascade. It speaks in jobs and errors of its own (``Invalid``, ``NotFound``,
``Conflict``, ``BadRequest``), never in HTTP: the API maps them to status codes in one place.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from pydantic import BaseModel

from quicknav_core.admission import admit
from quicknav_core.config import (
    ConfigError,
    EnvConfig,
    TrainConfig,
    resolve_eval,
    resolve_sweep,
    resolve_train,
)
from quicknav_core.runtime import Runtime
from quicknav_service.jobs.limits import Origin, server_limits
from quicknav_service.jobs.models import (
    AmbiguousId,
    IdempotencyConflict,
    Job,
    JobKind,
    JobNotFound,
    JobStateError,
    JobStore,
)
from quicknav_service.schemas import MIN_ID_PREFIX, EvalJobCreate, SweepJobCreate, TrainJobCreate
from quicknav_service.settings import Settings

# one page of a store listing while walking all of it (the store caps a page at its own limit)
PAGE = 500



CLIENT_KEY_PREFIX = "client:"  # Idempotency-Keys sent by clients, as the store files them

class ServiceError(Exception):
    """A request the service refuses; ``detail`` says why and what to do."""

    def __init__(self, detail: str):
        super().__init__(detail)
        self.detail = detail


class BadRequest(ServiceError):
    pass


class NotFound(ServiceError):
    pass


class Conflict(ServiceError):
    """The request does not fit the state of things (a job still running, a reused key)."""


class Invalid(ServiceError):
    """Bad fields of the request body: every one of them, ``loc`` relative to the body."""

    def __init__(self, items: list[dict[str, Any]]):
        super().__init__("; ".join(f"{'.'.join(map(str, i['loc']))}: {i['msg']}" for i in items))
        self.items = items


def _as_sent(body: BaseModel) -> dict[str, Any]:
    """The request body as the client set it (defaults left out): stored and hashed."""
    return body.model_dump(mode="json", exclude_unset=True)


class JobsService:
    """What the API does with jobs, over one store and this server's settings."""

    def __init__(self, store: JobStore, settings: Settings, runtime: Runtime | None = None):
        from quicknav_service.runtime import service_runtime

        self.store = store
        self.settings = settings
        self.runtime = runtime if runtime is not None else service_runtime(settings)
        self.artifacts = self.runtime.artifacts
        self.limits = server_limits(settings)

    # ------------------------------------------------------------------ lookup
    def get(self, job_id: str) -> Job:
        """The job, by its id or a unique prefix of it (at least MIN_ID_PREFIX characters)."""
        try:
            return self.store.get(job_id)
        except JobNotFound:
            pass
        if len(job_id) < MIN_ID_PREFIX:
            raise BadRequest(
                f"job id prefix {job_id!r} is too short: give at least {MIN_ID_PREFIX} characters"
                " of the id (the CLI shows 8)"
            )
        try:
            return self.store.get(self.store.resolve_id(job_id))
        except JobNotFound:
            raise NotFound(f"no job {job_id!r}") from None
        except AmbiguousId as e:
            raise Conflict(
                f"job id prefix {job_id!r} matches several jobs ({', '.join(e.matches)}):"
                " give more characters"
            ) from None

    # ------------------------------------------------------------------ submission
    def _submit(self, kind: JobKind, sent: dict[str, Any], config: BaseModel,
                key: str | None) -> Job:  # fmt: skip
        # a client's key lives in its own namespace: it can never name one of the service's own
        # (a sweep's trial batches are filed as "sweep:<id>:batch:<i>")
        stored = None if key is None else CLIENT_KEY_PREFIX + key
        try:
            job, _ = self.store.submit(kind, sent, config.model_dump(mode="json"),
                                       idempotency_key=stored)  # fmt: skip
        except IdempotencyConflict:
            raise Conflict(
                f"Idempotency-Key {key!r} was already used with a different request body"
            ) from None
        return job

    def submit_train(self, body: TrainJobCreate, key: str | None = None) -> Job:
        """Resolve a training request, check this server's limits, queue it."""
        sent = _as_sent(body)
        try:
            cfg = resolve_train(body)
        except ConfigError as e:
            raise Invalid(e.items) from None
        if problems := admit(cfg, self.limits, self.runtime, Origin(sent).loc):
            raise Invalid(problems)
        return self._submit(JobKind.train, sent, cfg, key)

    def submit_sweep(self, body: SweepJobCreate, key: str | None = None) -> Job:
        """Resolve a sweep request, check this server's limits, queue it."""
        sent = _as_sent(body)
        try:
            cfg = resolve_sweep(body)
        except ConfigError as e:
            raise Invalid(e.items) from None
        origin = Origin(sent, fallback="space", shorthands=("trials", "parallel", "total_steps"),
                        prefix="base.")  # fmt: skip
        if problems := admit(cfg, self.limits, self.runtime, origin.loc):
            raise Invalid(problems)
        return self._submit(JobKind.sweep, sent, cfg, key)

    def trained_env(self, job_id: str) -> EnvConfig:
        """The env a train job trained in, if it can be evaluated."""
        src = self.get(job_id)
        if src.kind != JobKind.train:
            raise Invalid([{"loc": ["job_id"], "type": "value_error",
                            "msg": f"job {job_id} is a {src.kind.value} job; eval needs a train job"}])  # fmt: skip
        if not self.artifacts.has_checkpoint(src.id):
            raise Conflict(f"train job {src.id} has no checkpoint yet (status {src.status.value})")
        config = src.config or src.request.get("config")  # jobs stored before configs were
        return TrainConfig.model_validate(config).env

    def map_env(self, env: EnvConfig, name: str, reading: dict[str, Any] | None = None) -> EnvConfig:
        """``env`` on a map an eval names (``map``): an uploaded one, read from this server's
        maps (as ``reading`` says); its grid and step limit at the policy's cell size."""
        from quicknav_core.eval.map_fit import env_on_map

        resolver = self.runtime.map_resolver if self.runtime is not None else None
        return env_on_map(env, name, resolver, stored_only=self.limits.stored_maps_only, reading=reading)

    def submit_eval(self, body: EvalJobCreate, key: str | None = None) -> Job:
        """Resolve an eval request (a short id names the job by its full one), queue it."""
        sent = _as_sent(body)
        job_id = self.get(body.job_id).id if body.job_id is not None else None
        try:
            cfg = resolve_eval(body.as_request(job_id), trained_env=self.trained_env,
                               map_env=self.map_env)  # fmt: skip
        except ConfigError as e:  # the library's name of the trained policy is the body's job_id
            raise Invalid([{**i, "loc": ["job_id"]} if i["loc"] == ["source"] else i
                           for i in e.items]) from None  # fmt: skip
        if problems := admit(cfg, self.limits, self.runtime):
            raise Invalid(problems)
        return self._submit(JobKind.eval, sent, cfg, key)

    # ------------------------------------------------------------------ changes
    def cancel(self, job_id: str) -> Job:
        """A queued job is cancelled at once; a running one stops at its next chunk boundary."""
        return self.store.cancel(self.get(job_id).id)

    def children(self, sweep_id: str) -> Iterator[Job]:
        """Every trial batch a sweep submitted, however many (the store is read page by page)."""
        offset = 0
        while True:
            page, count = self.store.list(kind=JobKind.trial, limit=PAGE, offset=offset)
            yield from (b for b in page if b.config.get("parent") == sweep_id)
            offset += len(page)
            if not page or offset >= count:
                return

    def delete(self, job_id: str) -> None:
        """Delete a finished job, its artifacts, and a sweep's trial batches with theirs. The
        files go first: on a full disk that frees the space the store needs to delete records."""
        job = self.get(job_id)
        if not job.status.finished:
            raise Conflict(f"job {job.id} is {job.status.value}; only finished jobs can be deleted")
        if job.kind == JobKind.sweep:
            mine = list(self.children(job.id))  # all of them before any goes: pages shift on delete
            busy = [b.id for b in mine if not b.status.finished]
            if busy:
                raise Conflict(f"sweep {job.id} still has running trial batches ({', '.join(busy)});"
                               " delete it once they have stopped")  # fmt: skip
            for b in mine:
                self.artifacts.delete(b.id)
                self.store.delete(b.id)
        self.artifacts.delete(job.id)
        try:
            self.store.delete(job.id)
        except JobStateError as e:
            raise Conflict(str(e)) from None
