"""Request and response bodies of the HTTP API (one schema per direction).

The train and sweep bodies are the library's request models: the API, the CLI and the SDK send the
same requests to the same ``quicknav_core.config.resolve``. The eval body extends the library's
``EvalFields`` (the fields both doors share) with ``job_id``, the service's name of the trained
policy (the library's ``source`` is a run folder for the CLI): what it documents is exactly what it
accepts.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from quicknav_core.config import SweepRequest, TrainRequest
from quicknav_core.config.base import exactly_one_of
from quicknav_core.config.resolve import EvalFields, not_both_ways
from quicknav_service.jobs.models import JobKind, JobStatus

# Ids are shown (CLI, web) by their first 8 characters; shorter prefixes match too many jobs.
MIN_ID_PREFIX = 4
ID_DESCRIPTION = f"a job's id or a unique prefix of it (at least {MIN_ID_PREFIX} characters)"

TrainJobCreate = TrainRequest
SweepJobCreate = SweepRequest


class EvalJobCreate(EvalFields):
    """Evaluate a train job's checkpoint (``job_id``) or a baseline (``policy``) on fixed-seed
    held-out episodes. The fields besides ``job_id`` are the library's (``EvalFields``), one model
    for both doors."""

    model_config = exactly_one_of("job_id", "policy", also=not_both_ways)

    job_id: str | None = Field(
        None, min_length=MIN_ID_PREFIX, max_length=200,
        description=f"the train job whose policy is evaluated: {ID_DESCRIPTION}",
    )  # fmt: skip

    @classmethod
    def unknown_field_hint(cls, key: str) -> str | None:
        """The library's names of the trained policy, which the service calls ``job_id``."""
        if key in ("source", "run"):
            return 'the service names the trained policy by train job id: {"job_id": "<id>"}'
        return None

    @model_validator(mode="after")
    def _one(self) -> EvalJobCreate:
        if (self.job_id is None) == (self.policy is None):
            raise ValueError("give exactly one of 'job_id' (a train job) or 'policy' (random, oracle or dwa)")
        return self

    def as_request(self, job_id: str | None) -> dict[str, Any]:
        """The library's request (an ``EvalRequest``), the trained policy named by its full id."""
        sent = self.model_dump(exclude_unset=True, exclude={"job_id"})
        if job_id is not None:
            sent["source"] = job_id
        return sent


class CancelRequest(BaseModel):
    """The body of a cancel: an empty JSON object (it makes the request one a cross-site form
    cannot send)."""

    model_config = ConfigDict(extra="forbid")


class JobPublic(BaseModel):
    """A job as the API shows it: ``request`` as sent, ``config`` as resolved (what runs)."""

    id: str
    kind: JobKind
    status: JobStatus
    progress: float
    metrics: dict[str, Any]
    attempts: int
    worker: str | None = Field(None, description="the worker running the job (or that ran it last)")
    error: str | None
    result: dict[str, Any] | None
    warnings: list[str] = Field(
        default_factory=list,
        description="what went wrong without failing the job (e.g. a picture that did not render,"
        " named by its artifact); empty when all went well",
    )
    cancel_requested: bool
    waiting: str | None = Field(
        None,
        description="for a queued job that cannot start: why it waits (\"waiting: the data volume"
        " is full; jobs start when space is freed\", or \"waiting for a worker with 2 devices; the"
        " 1 live worker has 1 device ...\"); null otherwise",
    )
    created_at: float
    started_at: float | None
    finished_at: float | None
    request: dict[str, Any]
    config: dict[str, Any]
    links: dict[str, str]


class JobsPublic(BaseModel):
    """A page of jobs, newest first; ``count`` is the number matching the filter."""

    data: list[JobPublic]
    count: int


class JobMetricsPublic(BaseModel):
    """A job's metrics history: one row per training chunk."""

    job_id: str
    metrics: list[dict[str, Any]]


class ArtifactPublic(BaseModel):
    name: str = Field(description="path inside the job's folder, e.g. checkpoint/state.msgpack")
    bytes: int


class ArtifactsPublic(BaseModel):
    job_id: str
    artifacts: list[ArtifactPublic]


class MapPublic(BaseModel):
    """An uploaded map. ``ref`` is how an env config names it: ``env.maps.train: ["map:<id>"]``."""

    id: str = Field(description="digest of the stored map files: the same map uploaded twice is one")
    ref: str = Field(description="the name to put in env.maps.train / env.maps.test")
    name: str
    created: float = Field(description="upload time, seconds since the epoch")
    files: list[str] = Field(description="the file names as uploaded")
    width_px: int
    height_px: int
    resolution: float = Field(description="metres per pixel")
    width_m: float
    height_m: float
    free_fraction: float = Field(description="share of pixels that are free")
    unknown_fraction: float = Field(description="share of pixels neither occupied nor free")
    bytes: int = Field(description="size of the stored map files")
    preview_m_per_px: float = Field(description="metres per pixel of preview.png")
    suggested_env: dict[str, Any] = Field(
        description="env fields that hold this map at 0.5 m cells: rooms, maps.train, grid_size"
        " (with grid_rows or grid_cols for a map that is not square: the grid follows its shape),"
        " room_size and max_steps (twice the map's longest shortest path at full speed; a"
        " starting point, a job may set its own)"
    )
    notes: list[str] = Field(
        default_factory=list, description="what to know before using suggested_env: free space"
        " the grid loses at 0.5 m cells, a grid above this server's limit (and the setting that"
        " raises it), a map too large for any grid",
    )
    preview_url: str
    used_by: list[str] = Field(
        default_factory=list, description="queued or running jobs whose config names this map"
    )


class MapsPublic(BaseModel):
    """Every uploaded map, newest first."""

    data: list[MapPublic]
    count: int


class Health(BaseModel):
    status: Literal["ok"]


class Readiness(BaseModel):
    status: Literal["ready", "unavailable"]
    checks: dict[str, str] = Field(description="'ok' or what is wrong, per check (store, disk)")


class RolloutEndpoint(BaseModel):
    """A gRPC Rollout server that announced itself."""

    model_config = ConfigDict(extra="allow")

    worker: str
    address: str = Field(description="host:port of the gRPC server")
    sessions: int = Field(0, description="open Rollout streams")
    max_sessions: int | None = None
    env_steps_served: int = 0
    memory_held_mb: int = Field(0, description="what the open Rollout streams hold together, by"
                                " their admission estimates, MB")  # fmt: skip
    memory_budget_mb: int | None = Field(None, description="what they may hold together"
                                         " (QUICKNAV_ROLLOUT_MEMORY_MB), MB")  # fmt: skip


class RolloutEndpoints(BaseModel):
    endpoints: list[RolloutEndpoint]
    count: int


class PresetPublic(BaseModel):
    description: str
    notes: str | None = None
    config: dict[str, Any] = Field(description="the preset as written: what differs from the defaults")
    resolved: dict[str, Any] = Field(description="the whole TrainConfig the preset gives")


class HTTPError(BaseModel):
    """An error: ``detail`` says what is wrong and what to do."""

    detail: str


class FieldError(BaseModel):
    loc: list[str | int] = Field(description="where: 'body', 'query', 'path' or 'header', then the field")
    msg: str
    type: str


class ValidationErrorBody(BaseModel):
    """A request that cannot be accepted: every bad field at once."""

    detail: list[FieldError]
