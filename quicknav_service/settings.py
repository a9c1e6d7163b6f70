"""Service settings from ``QUICKNAV_*`` environment variables (and an optional ``.env`` file)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Validated at start; a bad value stops the service with a message naming the variable."""

    # an empty variable (QUICKNAV_API_TOKEN=) means unset, as compose and shells often pass them
    model_config = SettingsConfigDict(
        env_prefix="QUICKNAV_", env_file=".env", extra="ignore", env_ignore_empty=True
    )

    data_dir: Path = Field(Path("quicknav-data"), description="SQLite database and artifacts")
    redis_url: str | None = Field(
        None, description="redis://host:port/db; unset = embedded SQLite store"
    )
    artifacts_url: str | None = Field(
        None, description="s3://bucket[/prefix]: jobs' files on an S3-compatible object store"
        " (credentials and endpoint from AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY,"
        " AWS_ENDPOINT_URL); unset = the artifacts folder under data_dir",
    )  # fmt: skip
    artifacts_retry_s: float = Field(
        60.0, ge=0, le=86_400,
        description="a job retries an upload to the artifact store this long through an outage"
        " before it fails with a reason naming the store",
    )  # fmt: skip
    api_token: str | None = Field(
        None, min_length=8, description="Bearer token required on job endpoints"
    )
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    grpc_port: int = Field(50051, ge=0, le=65535, description="gRPC Rollout port (0 = any free)")
    grpc_enabled: bool = Field(
        True, description="start the gRPC Rollout server in `quicknav serve`"
    )
    grpc_tls_cert: Path | None = Field(
        None, description="PEM certificate chain: the gRPC port speaks TLS (with grpc_tls_key)"
    )
    grpc_tls_key: Path | None = Field(None, description="PEM private key of grpc_tls_cert")
    tls_cert: Path | None = Field(
        None, description="PEM certificate chain: the HTTP API speaks HTTPS (with tls_key)"
    )
    tls_key: Path | None = Field(None, description="PEM private key of tls_cert")
    rollout_advertise: str | None = Field(
        None, description="host[:port] remote agents use to reach this process's Rollout server"
        " (default: this machine's host name and the bound port)",
    )
    worker_grpc_port: int | None = Field(
        None, ge=0, le=65535,
        description="`quicknav worker` also serves gRPC Rollout on this port (unset: it does not)",
    )
    rollout_max_sessions: int = Field(
        16, ge=1, le=10_000,
        description="concurrent Rollout streams per gRPC server (Policy streams are counted apart, to the same limit)",
    )  # fmt: skip
    rollout_memory_mb: int | None = Field(
        None, ge=64, le=16_777_216,
        description="memory a gRPC server's open Rollout streams may hold together, by their"
        " admission estimates (a Start past it is refused RESOURCE_EXHAUSTED until a stream"
        " ends); unset: max_job_memory_mb, the server admitted as one job",
    )  # fmt: skip
    grpc_max_message_mb: int = Field(64, ge=1, le=2047, description="largest gRPC message, MiB")
    rollout_policy_max_envs: int = Field(256, ge=1, le=1024, description="envs in policy mode")
    rollout_policy_cache: int = Field(
        8, ge=1, le=1024, description="trained policies a gRPC server keeps loaded for the Policy"
        " stream (the least recently loaded go first; an open stream keeps its own)",
    )  # fmt: skip
    rollout_idle_s: float = Field(
        300.0,
        gt=0.0,
        le=86_400,
        description="a rollout stream with no message for this long is closed",
    )
    max_envs: int = Field(4096, ge=1, le=1_048_576)
    max_total_steps: int = Field(200_000_000, ge=1)
    max_grid_size: int = Field(64, ge=4, le=256)
    max_devices: int = Field(
        1, ge=1, le=1024,
        description="most devices one training job may span (TrainConfig.devices); set it to"
        " the device count of the workers (`devices: all` is taken as this many)",
    )  # fmt: skip
    devices: str | None = Field(
        None, pattern=r"^\d+(,\d+)*$",
        description="the accelerators a worker owns, as CUDA/ROCm ordinals (e.g. '0,1'): its"
        " jobs see only these (unset: every device of the machine)",
    )  # fmt: skip
    max_eval_episodes: int = Field(10_000, ge=1)
    max_sweep_trials: int = Field(1000, ge=1)
    max_concurrent_jobs: int = Field(
        1, ge=1, le=64, description="worker processes `quicknav serve` runs and supervises"
    )
    max_chunk_s: float = Field(
        10.0, gt=0.0, le=3600.0,
        description="a training chunk (progress event, checkpoint) lasts at most this long",
    )
    max_job_memory_mb: int = Field(
        8192, ge=64, le=16_777_216,
        description="a job whose estimated memory exceeds this is refused at submission",
    )
    max_lidar_beams: int = Field(256, ge=1, le=1024, description="largest lidar_beams accepted")
    lease_s: float = Field(60.0, gt=0.5, le=3600)
    heartbeat_s: float = Field(10.0, gt=0.05, le=600)
    max_attempts: int = Field(3, ge=1, le=100)
    max_body_bytes: int = Field(1_000_000, ge=1024)
    max_map_upload_bytes: int = Field(
        64_000_000, ge=1024, description="largest POST /maps body (a map's files together), bytes"
    )
    max_map_pixels: int = Field(
        25_000_000, ge=1, le=64_000_000, description="most pixels an uploaded map may have"
    )
    map_decode_mb: int = Field(
        1024, ge=16, le=1_048_576, description="memory an API process gives to reading uploaded maps"
        " at once (about 24 bytes per pixel); an upload that finds it held waits up to 30 s, then 503",
    )
    export_policies: bool = Field(
        True, description="every succeeded train job exports its policy (policy.onnx +"
        " policy.json, `quicknav export`); false skips that step (a few seconds per job)",
    )
    replay_checkpoint_every_s: float = Field(
        300.0, ge=0, le=86_400,
        description="SAC/TD3 jobs write their replay buffer with a checkpoint at most this often"
        " (the networks every chunk); a job resumed after a crash refills from a buffer up to"
        " this old. 0: with every checkpoint",
    )  # fmt: skip
    metrics_token: str | None = Field(
        None, description="a bearer token that opens /metrics only (for Prometheus); the API token"
        " opens it too; with neither set, /metrics is as open as every route",
    )
    auth_failures_max: int = Field(
        10, ge=1, le=100_000, description="failed authentications per client address within"
        " auth_failure_window_s before its attempts are refused (429)",
    )
    auth_failure_window_s: float = Field(60.0, gt=0, le=86_400)
    sse_max_per_client: int = Field(16, ge=1, le=10_000, description="event streams per client address")
    sse_max_total: int = Field(512, ge=1, le=100_000, description="event streams in all (per API process)")
    header_timeout_s: float = Field(
        10.0, gt=0, le=3600, description="a request's headers must arrive within this many seconds"
    )
    allowed_hosts: str | None = Field(
        None,
        description="comma-separated Host names the API answers ('*' any); unset: localhost,"
        " 127.0.0.1, ::1 and the bound host (with 0.0.0.0: also this machine's names)",
    )
    trusted_proxies: str | None = Field(
        None,
        description="comma-separated addresses of reverse proxies whose X-Forwarded-For and"
        " X-Forwarded-Proto the API believes (the client's address for the auth limiter and the"
        " event-stream caps); unset: none, every request is the address that connected",
    )
    allowed_origins: str | None = Field(
        None,
        description="comma-separated origins (scheme://host:port) besides the API's own that may"
        " send requests that change state (a page of yours on another origin)",
    )
    embedded_worker: bool = Field(True, description="run workers inside `quicknav serve`")

    @model_validator(mode="after")
    def _check(self) -> Settings:
        if self.heartbeat_s >= self.lease_s:
            raise ValueError(
                f"QUICKNAV_HEARTBEAT_S={self.heartbeat_s} must be below QUICKNAV_LEASE_S={self.lease_s}"
                " (a lease must be renewed before it expires)"
            )
        if self.artifacts_url is not None:
            from quicknav_service.artifacts.s3 import parse_url

            parse_url(self.artifacts_url)
        for cert, key, name in ((self.grpc_tls_cert, self.grpc_tls_key, "GRPC_TLS"),
                                (self.tls_cert, self.tls_key, "TLS")):  # fmt: skip
            if (cert is None) != (key is None):
                raise ValueError(
                    f"QUICKNAV_{name}_CERT and QUICKNAV_{name}_KEY go together: set both or neither"
                )
        return self

    @property
    def artifacts_dir(self) -> Path:
        return self.data_dir / "artifacts"

    @property
    def trusted_hosts(self) -> list[str]:
        """The Host names the API answers: QUICKNAV_ALLOWED_HOSTS, or localhost and the bound one."""
        if self.allowed_hosts:
            return [h.strip().lower() for h in self.allowed_hosts.split(",") if h.strip()]
        hosts = ["localhost", "127.0.0.1", "::1"]
        if self.host in ("0.0.0.0", "::", ""):
            import socket

            hosts += [socket.gethostname().lower(), socket.getfqdn().lower()]
        else:
            hosts.append(self.host.lower())
        return list(dict.fromkeys(hosts))

    @property
    def trusted_origins(self) -> list[str]:
        return [o.strip().rstrip("/").lower() for o in (self.allowed_origins or "").split(",")
                if o.strip()]  # fmt: skip


@lru_cache
def get_settings() -> Settings:
    return Settings()


def make_store(settings: Settings):
    """The job store the settings ask for: Redis when a URL is set, SQLite otherwise."""
    if settings.redis_url:
        from quicknav_service.jobs.redis_store import RedisJobStore

        return RedisJobStore(settings.redis_url, max_attempts=settings.max_attempts)
    from quicknav_service.jobs.sqlite_store import SQLiteJobStore

    settings.data_dir.mkdir(parents=True, exist_ok=True)
    return SQLiteJobStore(settings.data_dir / "jobs.db", max_attempts=settings.max_attempts)
