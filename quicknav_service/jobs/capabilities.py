"""What a job needs and what a worker has: a worker claims only the jobs it can run, and a job that
no live worker can run says why it waits.

A worker announces its ``Capabilities`` in the store while it runs (``JobStore.announce_worker``);
a job's ``Needs`` come from its stored config: the devices a training run spans and the memory the
admission check estimated. There is no backend field in a config today (a job runs on whatever
backend its worker has), so backends are announced and shown but not matched.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import asdict, dataclass
from typing import Any

from quicknav_service.jobs.models import Job, JobKind

# how long a worker's announcement lives without renewal (the worker renews it as it polls)
ANNOUNCE_TTL_S = 30.0


@dataclass(frozen=True)
class Needs:
    """What running a job takes: ``devices`` local devices (``all``: every device of the worker,
    whose count must divide ``num_envs``), about ``memory_mb`` of memory."""

    devices: int | str = 1
    num_envs: int | None = None
    memory_mb: int | None = None


@dataclass(frozen=True)
class Capabilities:
    """What a worker has: its JAX backend, local devices (as many as ``QUICKNAV_DEVICES`` leaves
    it), their kind, and the memory one job may take (``QUICKNAV_MAX_JOB_MEMORY_MB``)."""

    worker: str
    backend: str
    devices: int
    device_kind: str
    memory_mb: int
    disk_full: bool = False  # its data folder takes no writes: it claims nothing until it does

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Capabilities:
        # an announcement from before ``disk_full`` was announced lacks it: not full
        return cls(**{k: data[k] for k in cls.__dataclass_fields__ if k in data or k != "disk_full"})


_NEEDS: OrderedDict[str, Needs] = OrderedDict()  # by job id: a job's config never changes
_NEEDS_MAX = 4096
_NEEDS_LOCK = threading.Lock()


def job_needs(job: Job) -> Needs:
    """A job's needs, from its stored config (a config that does not parse needs nothing special:
    the worker that takes it fails it with the reason). Remembered per job: validating a config
    and estimating its memory costs ~0.4 ms, and a page of 50 queued jobs is listed often."""
    with _NEEDS_LOCK:
        if job.id in _NEEDS:
            _NEEDS.move_to_end(job.id)
            return _NEEDS[job.id]
    needs = _needs(job)
    with _NEEDS_LOCK:
        _NEEDS[job.id] = needs
        while len(_NEEDS) > _NEEDS_MAX:
            _NEEDS.popitem(last=False)
    return needs


def _needs(job: Job) -> Needs:
    config = job.config or job.request.get("config") or {}
    try:
        if job.kind == JobKind.train:
            from quicknav_core.config import TrainConfig
            from quicknav_core.train.memory import megabytes, train_memory

            cfg = TrainConfig.model_validate(config)
            return Needs(cfg.devices, cfg.num_envs, megabytes(train_memory(cfg).total))
        if job.kind == JobKind.eval:
            from quicknav_core.config import EvalConfig
            from quicknav_core.train.memory import eval_memory, megabytes

            return Needs(1, None, megabytes(eval_memory(EvalConfig.model_validate(config)).total))
        if job.kind == JobKind.trial:
            from quicknav_core.config import SweepConfig
            from quicknav_core.train.memory import megabytes, sweep_memory

            return Needs(1, None, megabytes(sweep_memory(SweepConfig.model_validate(config["sweep"])).total))
    except (ValueError, KeyError, TypeError):
        return Needs()
    return Needs()  # a sweep only coordinates its trial batches


def unmet(needs: Needs, caps: Capabilities) -> str | None:
    """Why ``caps`` cannot run a job with ``needs`` (None: it can)."""
    if needs.devices == "all":
        if needs.num_envs is not None and needs.num_envs % caps.devices:
            return f"devices='all' needs a device count dividing num_envs={needs.num_envs}"
    elif int(needs.devices) > caps.devices:
        return f"{needs.devices} devices"
    if needs.memory_mb is not None and needs.memory_mb > caps.memory_mb:
        return f"{needs.memory_mb:,} MB of memory"
    return None


def can_run(caps: Capabilities, job: Job) -> bool:
    return unmet(job_needs(job), caps) is None


DISK_FULL = "waiting: the data volume is full; jobs start when space is freed"


def waiting_reason(needs: Needs, live: list[Capabilities], disk_full: bool = False) -> str | None:
    """Why a queued job waits: the data volume is full (``disk_full``: this server's data folder;
    or every live worker says its own is), or no live worker can run it. None when a worker can,
    or when no worker has announced itself: then it waits for any worker, as every queued job does."""
    if disk_full or (live and all(c.disk_full for c in live)):
        return DISK_FULL
    if not live or any(unmet(needs, c) is None for c in live):
        return None
    wanted = unmet(needs, live[0])
    devices = sorted({c.devices for c in live})
    memory = sorted({c.memory_mb for c in live})
    have = (f"{'/'.join(map(str, devices))} device{'s' if devices[-1] != 1 else ''}"
            f" and up to {memory[-1]:,} MB per job")  # fmt: skip
    n = len(live)
    verb = "has" if n == 1 else "have"
    return f"waiting for a worker with {wanted}; the {n} live worker{'s' if n != 1 else ''} {verb} {have}"
