"""The worker: claims jobs under a lease, runs them through quicknav_core, reports progress.

This module is the mechanics (the loop, lease, heartbeat, backoff, burst mode, hand-back); what
each kind of job does is a function registered in ``quicknav_service.job_kinds``.

- A heartbeat thread renews the lease while a job runs; if the lease is lost (another worker took
  the job over) the run stops at its next unit without reporting anything.
- Training runs through the chunked runner: chunks last at most ``max_chunk_s`` seconds, a
  progress event and a checkpoint after each, and cancellation and shutdown are checked after
  every unit (about a second of training), so a cancel takes effect within seconds and a
  reclaimed job resumes from its last checkpoint. Evaluations run in batches of episodes with a
  progress event and a cancel check after each.
- Graceful shutdown (SIGTERM): stop after the current unit, keep the checkpoint, hand the job back.
- Failures are job failures, never worker deaths: a full disk fails the job with a reason that
  says so and what was kept; a store outage (Redis down, SQLite unable to write) is waited out
  with backoff, and the worker carries on when the store is back.
- Trainers are kept warm across jobs with the same config (same compiled programs), and JAX's
  persistent compilation cache is on, so a repeated job skips compilation.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import os
import socket
import threading
import time
import traceback
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from quicknav_core.layout import RUN
from quicknav_service.artifacts import ArtifactUnavailable, make_artifacts
from quicknav_service.disk import disk_full
from quicknav_service.job_context import JobContext, best_effort, sweep_storage, until_done
from quicknav_service.job_kinds import RUNNERS
from quicknav_service.jobs.capabilities import ANNOUNCE_TTL_S, Capabilities, can_run
from quicknav_service.jobs.models import Job, JobKind, JobNotFound, JobStatus, StoreUnavailable
from quicknav_service.runtime import service_runtime
from quicknav_service.settings import Settings

log = logging.getLogger("quicknav.worker")

MAX_BACKOFF_S = 10.0
SCRATCH_CHECK_S = 60.0  # an idle worker looks for scratch no attempt owns at most this often


def failure_reason(error: BaseException, job_dir: Path) -> str:
    """A job's failure in words a person can act on: a full disk and memory are named."""
    text = f"{type(error).__name__}: {error}"
    if isinstance(error, OSError) and error.errno == errno.ENOSPC:
        return f"disk full (ENOSPC) while writing {error.filename or 'a file'}; {kept(job_dir)}"
    if isinstance(error, MemoryError) or "RESOURCE_EXHAUSTED" in str(error):
        return f"out of memory: {text[:500]}"
    return text


def kept(job_dir: Path) -> str:
    """What a failed job leaves behind (the last checkpoint, metrics lines)."""
    from quicknav_core.layout import RunFolder

    run = RunFolder(job_dir)
    parts = []
    meta = run.meta() if job_dir.exists() else None
    if meta is not None:
        parts.append(f"the checkpoint of chunk {meta.chunk} ({meta.env_steps:,} env steps)")
    metrics = run.metrics
    if metrics.exists():
        lines = sum(1 for line in metrics.read_text().splitlines() if line.strip())
        parts.append(f"metrics.jsonl ({lines} chunks)")
    return "kept: " + (", ".join(parts) if parts else "nothing (no checkpoint yet)")



class Worker:
    def __init__(self, store, settings: Settings, worker_id: str | None = None):
        self.store = store
        self.settings = settings
        self.id = worker_id or f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
        self.shutdown = threading.Event()
        self.busy = False
        self._coordinators: list[threading.Thread] = []  # sweeps this worker follows
        self._capabilities: Capabilities | None = None
        self._announced_at = 0.0
        self._announced_full = False
        self._scratch_checked = 0.0
        self.artifacts = make_artifacts(settings)  # a folder, or an object store and a scratch folder
        # room banks (carved once per config, kept on the data disk), uploaded maps, warm trainers
        self.runtime = service_runtime(settings, self.artifacts)
        self.artifacts.work_dir("_").parent.mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------ loop
    @property
    def capabilities(self) -> Capabilities:
        """What this worker has: backend, local devices (after QUICKNAV_DEVICES), their kind, and
        the memory budget of one job. Read once (it starts JAX's backend)."""
        if self._capabilities is None:
            import jax

            devices = jax.local_devices()
            self._capabilities = Capabilities(
                worker=self.id, backend=jax.default_backend(), devices=len(devices),
                device_kind=devices[0].device_kind if devices else "",
                memory_mb=self.settings.max_job_memory_mb,
            )  # fmt: skip
        return self._capabilities

    def can_run(self, job: Job) -> bool:
        return can_run(self.capabilities, job)

    def announce(self, force: bool = False, disk_full: bool = False) -> None:
        """Say what this worker has (renewed as it polls, and whenever its disk fills or frees:
        the API explains waiting jobs by it)."""
        now = time.monotonic()
        changed = disk_full != self._announced_full
        if force or changed or now - self._announced_at >= ANNOUNCE_TTL_S / 3:
            caps = dataclasses.replace(self.capabilities, disk_full=disk_full)
            self.store.announce_worker(caps.to_dict(), ANNOUNCE_TTL_S)
            self._announced_at, self._announced_full = now, disk_full

    def withdraw(self) -> None:
        self.best_effort(self.store.withdraw_worker, self.id)

    def clear_stale_scratch(self) -> list[str]:
        """Drop the scratch copies on this data folder that no attempt owns any more: jobs that
        ended or went back to the queue, and attempts whose lease ran out (a worker killed mid-job;
        whoever resumes it fetches the checkpoint from the store). A job running under a live lease
        (another worker process on this folder) keeps its copy. Returns the jobs cleared."""
        cleared = []
        now = time.time()
        for job_id in self.artifacts.scratch_jobs():
            try:
                job = self.store.get(job_id)
            except JobNotFound:
                job = None
            except StoreUnavailable:
                return cleared  # the next start, or the next idle moment, tries again
            held = (job is not None and job.status == JobStatus.running
                    and (job.lease_until or 0) > now)  # fmt: skip
            if not held:
                self.artifacts.release(job_id)
                cleared.append(job_id)
        if cleared:
            log.info("worker %s: cleared the scratch of %d job(s) no attempt owns: %s", self.id,
                     len(cleared), ", ".join(cleared))  # fmt: skip
        self._scratch_checked = time.monotonic()
        return cleared

    def run_forever(self, poll_s: float = 0.25) -> None:
        """Claim and run jobs until shut down; nothing a job or the store does ends the loop."""
        _enable_jax_cache(self.settings)
        self.clear_stale_scratch()
        try:
            self._loop(poll_s)
        finally:
            self.withdraw()

    def _loop(self, poll_s: float) -> None:
        backoff = poll_s
        while not self.shutdown.is_set():
            try:
                ran = self.run_once()
                backoff = poll_s
            except StoreUnavailable as e:
                log.warning("job store unavailable (%s): retrying in %.1f s", e.reason, backoff)
                self.shutdown.wait(backoff)
                backoff = min(backoff * 2, MAX_BACKOFF_S)
                continue
            except Exception:
                log.exception("worker %s: unexpected error, carrying on", self.id)
                self.shutdown.wait(backoff)
                backoff = min(backoff * 2, MAX_BACKOFF_S)
                continue
            if not ran:
                if time.monotonic() - self._scratch_checked >= SCRATCH_CHECK_S:
                    self.clear_stale_scratch()  # an attempt that died since, its lease now out
                self.shutdown.wait(poll_s)
        self.join_coordinators()

    def run_burst(self, poll_s: float = 0.25) -> int:
        """Drain the store, then return the number of jobs run.

        Runs queued jobs and jobs orphaned by a dead worker (reclaimed once their lease lapses), and
        returns only when no job is queued or running: a running job whose worker died may come
        back to the queue, so it is waited for rather than forgotten.
        """
        _enable_jax_cache(self.settings)
        self.clear_stale_scratch()
        ran = 0
        while not self.shutdown.is_set():
            try:
                if self.run_once():
                    ran += 1
                    continue
                counts = self.store.counts()
                # jobs queued for other workers (more devices, more memory) are not this one's
                mine = any(self.can_run(j) for j in self.store.list(status="queued", limit=500)[0])
            except StoreUnavailable as e:
                log.warning("job store unavailable (%s): waiting", e.reason)
                self.shutdown.wait(1.0)
                continue
            if not mine and counts.get("running", 0) == 0:
                break
            self.shutdown.wait(poll_s)
        self.join_coordinators()
        self.withdraw()
        return ran

    def run_once(self) -> bool:
        """Claim and run one job; False if the queue was empty (burst mode for tests)."""
        if self.shutdown.is_set():
            return False
        # a full data disk: claim nothing (the job would fail writing its first checkpoint); the
        # jobs wait in the queue, and say why, until space is freed
        full = disk_full(self.settings.data_dir)
        self.announce(disk_full=full)
        if full:
            return False
        job = self.store.claim(self.id, self.settings.lease_s, can_run=self.can_run)
        if job is None:
            return False
        if job.kind == JobKind.sweep:
            # a sweep only coordinates (its trials are child jobs any worker claims, this one
            # included): it runs beside the worker's jobs instead of holding the worker
            t = threading.Thread(target=self._run_claimed, args=(job, False),
                                 name=f"sweep-{job.id[:8]}", daemon=True)  # fmt: skip
            self._coordinators = [c for c in self._coordinators if c.is_alive()] + [t]
            t.start()
            return True
        self._run_claimed(job, True)
        return True

    def join_coordinators(self, timeout: float = 30.0) -> None:
        """Wait for the sweeps this worker coordinates to stop (after a shutdown they hand their
        jobs back)."""
        deadline = time.monotonic() + timeout
        for t in self._coordinators:
            t.join(max(0.0, deadline - time.monotonic()))

    def _run_claimed(self, job: Job, busy: bool) -> None:
        """Run a claimed job under a heartbeat that renews its lease."""
        if busy:
            self.busy = True
        lost = threading.Event()
        beat_stop = threading.Event()

        def beat():
            while not beat_stop.wait(self.settings.heartbeat_s):
                try:
                    if not self.store.heartbeat(job.id, self.id, self.settings.lease_s):
                        lost.set()
                        return
                except StoreUnavailable:
                    continue  # an outage: keep trying; the lease decides if it lasts too long
                except Exception:
                    log.exception("heartbeat of job %s", job.id)

        hb = threading.Thread(target=beat, name=f"heartbeat-{job.id[:8]}", daemon=True)
        hb.start()
        try:
            self._execute(job, lost)
        finally:
            beat_stop.set()
            hb.join()
            if busy:
                self.busy = False

    # ------------------------------------------------------------------ store calls
    def best_effort(self, fn: Callable, *args) -> Any:
        """A store call whose loss costs nothing lasting: skipped in an outage (``job_context``)."""
        return best_effort(fn, *args)

    def until_done(self, fn: Callable, *args, **kwargs) -> Any:
        """A store call that must land, retried through outages (``job_context.until_done``)."""
        return until_done(self.shutdown, fn, *args, **kwargs)

    # ------------------------------------------------------------------ jobs
    def job_dir(self, job_id: str) -> Path:
        """The local folder a job writes into (on an object store: uploaded from there)."""
        return self.artifacts.work_dir(job_id)

    def context(self, job: Job, lost: threading.Event) -> JobContext:
        """What the runner of a claimed job is handed."""
        return JobContext(job=job, worker_id=self.id, store=self.store, artifacts=self.artifacts,
                          runtime=self.runtime, settings=self.settings, lost=lost,
                          shutdown=self.shutdown)  # fmt: skip

    def _execute(self, job: Job, lost: threading.Event) -> None:
        self.best_effort(self.store.publish, job.id, {
            "type": "started", "status": "running", "worker": self.id, "attempt": job.attempts})  # fmt: skip
        try:
            outcome, result = RUNNERS[job.kind](self.context(job, lost))
        except Exception as e:
            log.exception("job %s failed", job.id)
            reason = failure_reason(e, self.job_dir(job.id))
            try:
                self.job_dir(job.id).mkdir(parents=True, exist_ok=True)
                (self.job_dir(job.id) / RUN.error).write_text(traceback.format_exc())
                if not isinstance(e, ArtifactUnavailable) and not lost.is_set():
                    self.artifacts.save(job.id)  # what the failed job made, for its owner to read
            except (OSError, ArtifactUnavailable):
                pass  # a full disk or a store outage: the reason says so, the traceback is in the log
            if not lost.is_set():
                self.until_done(self.store.finish, job.id, self.id, JobStatus.failed, error=reason)
                self.artifacts.release(job.id)
            return
        if outcome == "lost":
            return  # someone else owns the job now (perhaps in this very folder)
        self.artifacts.release(job.id)  # the store has its files (a scratch copy goes)
        if outcome == "shutdown":
            self.until_done(self.store.release, job.id, self.id)
        elif outcome == "cancelled":
            self.until_done(self.store.finish, job.id, self.id, JobStatus.cancelled, result=result)
        else:
            self.until_done(self.store.finish, job.id, self.id, JobStatus.succeeded, result=result)

    def sweep_storage(self, sweep_id: str):
        """The Optuna storage of a sweep job's study (``job_context.sweep_storage``)."""
        return sweep_storage(self.settings, self.artifacts, sweep_id)


def _enable_jax_cache(settings: Settings) -> None:
    """The worker's devices (QUICKNAV_DEVICES); JAX's persistent compilation cache in the data
    folder, unless JAX_COMPILATION_CACHE_DIR already names one (an operator's shared cache, or a
    test session's)."""
    import jax

    from quicknav_core.compile_cache import enable_compilation_cache

    if settings.devices is not None:
        # before the first computation starts a backend: this worker sees only its devices
        jax.config.update("jax_cuda_visible_devices", settings.devices)
        jax.config.update("jax_rocm_visible_devices", settings.devices)
    enable_compilation_cache(settings.data_dir / "jax-cache")


def start_worker_threads(
    store, settings: Settings, count: int
) -> list[tuple[Worker, threading.Thread]]:
    """In-process workers (tests, and `quicknav serve --worker-threads`)."""
    out = []
    for i in range(count):
        w = Worker(store, settings, worker_id=f"embedded-{os.getpid()}-{i}")
        t = threading.Thread(target=w.run_forever, name=f"worker-{i}", daemon=True)
        t.start()
        out.append((w, t))
    return out


def stop_workers(workers, timeout: float = 30.0) -> None:
    """Stop in-process workers at their next unit and wait for them (up to ``timeout``)."""
    for w, _ in workers:
        w.shutdown.set()
    deadline = time.time() + timeout
    for _, t in workers:
        t.join(max(0.0, deadline - time.time()))
