"""Request and response bodies of the HTTP API (one schema per direction)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from quicknav_core.config import TrainConfig
from quicknav_core.sweep import SweepConfig
from service.jobs.models import JobKind, JobStatus


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid")


class TrainJobCreate(_In):
    """A full TrainConfig, or a preset name with dotted-path overrides."""

    config: TrainConfig | None = None
    preset: str | None = Field(None, examples=["demo"])
    overrides: dict[str, Any] = Field(default_factory=dict, examples=[{"total_steps": 200000}])

    @model_validator(mode="after")
    def _one(self) -> TrainJobCreate:
        if (self.config is None) == (self.preset is None):
            raise ValueError(
                "give exactly one of 'config' (a TrainConfig) or 'preset' (a preset name)"
            )
        if self.config is not None and self.overrides:
            raise ValueError("'overrides' only apply to a 'preset'")
        return self


class SweepJobCreate(_In):
    """A full SweepConfig, or a built-in search space name with trials/parallel/total_steps."""

    config: SweepConfig | None = None
    space: Literal["ppo", "sac", "td3", "mlp", "lstm", "gtrxl"] | None = None
    trials: int = Field(8, ge=1, le=100_000)
    parallel: int = Field(1, ge=1, le=1024)
    total_steps: int = Field(1_000_000, ge=1)

    @model_validator(mode="after")
    def _one(self) -> SweepJobCreate:
        if (self.config is None) == (self.space is None):
            raise ValueError(
                "give exactly one of 'config' (a SweepConfig) or 'space' (a built-in space)"
            )
        return self


class EvalJobCreate(_In):
    """Evaluate a finished train job's checkpoint, or a baseline policy."""

    job_id: str | None = Field(None, description="a succeeded (or stopped) train job")
    policy: Literal["random", "oracle"] | None = None
    env: dict[str, Any] = Field(default_factory=dict, description="EnvConfig fields for a baseline")
    episodes: int = Field(100, ge=1, le=100_000)
    seed: int = Field(0, ge=0, le=2**31 - 1)
    stochastic: bool = False

    @model_validator(mode="after")
    def _one(self) -> EvalJobCreate:
        if (self.job_id is None) == (self.policy is None):
            raise ValueError(
                "give exactly one of 'job_id' (a train job) or 'policy' (random or oracle)"
            )
        return self


class JobPublic(BaseModel):
    id: str
    kind: JobKind
    status: JobStatus
    progress: float
    metrics: dict[str, Any]
    attempts: int
    error: str | None
    result: dict[str, Any] | None
    cancel_requested: bool
    created_at: float
    started_at: float | None
    finished_at: float | None
    request: dict[str, Any]
    links: dict[str, str]


class JobsPublic(BaseModel):
    data: list[JobPublic]
    count: int


class ErrorPublic(BaseModel):
    detail: Any
