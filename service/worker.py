"""The worker: claims jobs under a lease, runs them through quicknav_core, reports progress.

- A heartbeat thread renews the lease while a job runs; if the lease is lost (another worker took
  the job over) the run stops at its next chunk boundary without reporting anything.
- Training runs through the chunked runner: a progress event after every chunk, cancellation and
  shutdown checked between chunks, a checkpoint at every chunk boundary, so a reclaimed job resumes
  from its last checkpoint.
- Graceful shutdown (SIGTERM): stop at a chunk boundary, keep the checkpoint, hand the job back.
- Trainers are kept warm across jobs with the same config (same compiled programs), and JAX's
  persistent compilation cache is on, so a repeated job skips compilation.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
import traceback
import uuid
from pathlib import Path
from typing import Any

from service.jobs.models import Job, JobKind, JobStatus
from service.settings import Settings

log = logging.getLogger("quicknav.worker")


class _Stop(Exception):
    """Internal: the run stopped early (cancel, shutdown, or lease lost)."""


class Worker:
    def __init__(self, store, settings: Settings, worker_id: str | None = None):
        self.store = store
        self.settings = settings
        self.id = worker_id or f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
        self.shutdown = threading.Event()
        self.busy = False
        self._trainers: dict[str, Any] = {}
        settings.artifacts_dir.mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------ loop
    def run_forever(self, poll_s: float = 0.25) -> None:
        _enable_jax_cache(self.settings)
        while not self.shutdown.is_set():
            if not self.run_once():
                self.shutdown.wait(poll_s)

    def run_burst(self, poll_s: float = 0.25) -> int:
        """Drain the store, then return the number of jobs run.

        Runs queued jobs and jobs orphaned by a dead worker (reclaimed once their lease lapses), and
        returns only when no job is queued or running: a running job whose worker died may come
        back to the queue, so it is waited for rather than forgotten.
        """
        _enable_jax_cache(self.settings)
        ran = 0
        while not self.shutdown.is_set():
            if self.run_once():
                ran += 1
                continue
            counts = self.store.counts()
            if counts.get("queued", 0) == 0 and counts.get("running", 0) == 0:
                break
            self.shutdown.wait(poll_s)
        return ran

    def run_once(self) -> bool:
        """Claim and run one job; False if the queue was empty (burst mode for tests)."""
        if self.shutdown.is_set():
            return False
        job = self.store.claim(self.id, self.settings.lease_s)
        if job is None:
            return False
        self.busy = True
        lost = threading.Event()
        beat_stop = threading.Event()

        def beat():
            while not beat_stop.wait(self.settings.heartbeat_s):
                if not self.store.heartbeat(job.id, self.id, self.settings.lease_s):
                    lost.set()
                    return

        hb = threading.Thread(target=beat, name=f"heartbeat-{job.id[:8]}", daemon=True)
        hb.start()
        try:
            self._execute(job, lost)
        finally:
            beat_stop.set()
            hb.join()
            self.busy = False
        return True

    # ------------------------------------------------------------------ jobs
    def job_dir(self, job_id: str) -> Path:
        return self.settings.artifacts_dir / job_id

    def _should_stop(self, job: Job, lost: threading.Event) -> str | None:
        if lost.is_set():
            return "lost"
        if self.shutdown.is_set():
            return "shutdown"
        if self.store.get(job.id).cancel_requested:
            return "cancelled"
        return None

    def _execute(self, job: Job, lost: threading.Event) -> None:
        self.store.publish(job.id, {"type": "started", "status": "running", "worker": self.id,
                                    "attempt": job.attempts})  # fmt: skip
        try:
            runner = {
                JobKind.train: self._train,
                JobKind.eval: self._eval,
                JobKind.sweep: self._sweep,
            }
            outcome, result = runner[job.kind](job, lost)
        except Exception as e:
            log.exception("job %s failed", job.id)
            msg = f"{type(e).__name__}: {e}"
            (self.job_dir(job.id)).mkdir(parents=True, exist_ok=True)
            (self.job_dir(job.id) / "error.txt").write_text(traceback.format_exc())
            if not lost.is_set():
                self.store.finish(job.id, self.id, JobStatus.failed, error=msg)
            return
        if outcome == "lost":
            return  # someone else owns the job now
        if outcome == "shutdown":
            self.store.release(job.id, self.id)
        elif outcome == "cancelled":
            self.store.finish(job.id, self.id, JobStatus.cancelled, result=result)
        else:
            self.store.finish(job.id, self.id, JobStatus.succeeded, result=result)

    def trainer_for(self, config):
        """A warm trainer for this exact config (its compiled chunks are reused)."""
        from quicknav_core.train.trainers import make_trainer

        key = config.model_dump_json()
        if key not in self._trainers:
            if len(self._trainers) >= 8:
                self._trainers.pop(next(iter(self._trainers)))
            self._trainers[key] = make_trainer(config)
        return self._trainers[key]

    def _train(self, job: Job, lost: threading.Event):
        from quicknav_core.config import TrainConfig
        from quicknav_core.train.run import CHECKPOINT_DIR, META_FILE, train_run

        config = TrainConfig.model_validate(job.request["config"])
        run_dir = self.job_dir(job.id)
        resume = (run_dir / CHECKPOINT_DIR / META_FILE).exists()
        stop_reason: dict[str, str] = {}

        def on_chunk(r) -> bool:
            metrics = {"chunk": r.chunk, "chunks": r.chunks, "env_steps": r.env_steps,
                       "steps_per_s": r.steps_per_s, **r.metrics}  # fmt: skip
            self.store.progress(job.id, self.id, r.env_steps / max(r.total_steps, 1), metrics)
            self.store.publish(job.id, {"type": "progress", "progress": r.env_steps / max(r.total_steps, 1),
                                        "metrics": metrics})  # fmt: skip
            reason = self._should_stop(job, lost)
            if reason:
                stop_reason["why"] = reason
                return True
            return False

        if resume:
            self.store.publish(job.id, {"type": "resumed", "from_checkpoint": True})
        summary = train_run(config, run_dir, callback=on_chunk, resume=resume,
                            trainer=self.trainer_for(config))  # fmt: skip
        result = {"env_steps": summary["env_steps"], "chunks_done": summary["chunks_done"],
                  "chunks": summary["chunks"], "final": summary["final"]}  # fmt: skip
        return stop_reason.get("why", "done"), result

    def _eval(self, job: Job, lost: threading.Event):
        from quicknav_core.config import EnvConfig
        from quicknav_core.evaluate import EvalConfig, agent_for, agent_from_run, evaluate

        req = job.request
        cfg = EvalConfig(
            episodes=req["episodes"], seed=req["seed"], deterministic=not req.get("stochastic")
        )
        if req.get("job_id"):
            agent, env_cfg, _ = agent_from_run(self.job_dir(req["job_id"]))
        else:
            env_cfg = EnvConfig.model_validate(req.get("env") or {})
            agent = agent_for(req["policy"], env_cfg)
        result, _ = evaluate(env_cfg, agent, cfg, self.job_dir(job.id))
        self.store.publish(
            job.id, {"type": "progress", "progress": 1.0, "metrics": result["metrics"]}
        )
        return "done", {"agent": result["agent"], "metrics": result["metrics"]}

    def _sweep(self, job: Job, lost: threading.Event):
        from quicknav_core.sweep import SweepConfig, run_sweep

        cfg = SweepConfig.model_validate(job.request["config"])
        stop_reason: dict[str, str] = {}

        def on_progress(p) -> bool:
            metrics = {"finished": p["finished"], "total": p["total"], "best_value": p["best_value"],
                       "best_params": p["best_params"]}  # fmt: skip
            self.store.progress(job.id, self.id, p["finished"] / p["total"], metrics)
            self.store.publish(job.id, {"type": "progress", "progress": p["finished"] / p["total"],
                                        "metrics": metrics})  # fmt: skip
            reason = self._should_stop(job, lost)
            if reason:
                stop_reason["why"] = reason
                return True
            return False

        summary = run_sweep(cfg, self.job_dir(job.id), progress=on_progress)
        summary.pop("timings", None)
        return stop_reason.get("why", "done"), summary


def _enable_jax_cache(settings: Settings) -> None:
    import jax

    path = settings.data_dir / "jax-cache"
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path.resolve()))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def start_worker_threads(
    store, settings: Settings, count: int
) -> list[tuple[Worker, threading.Thread]]:
    """In-process workers for `quicknav serve` (the embedded default)."""
    out = []
    for i in range(count):
        w = Worker(store, settings, worker_id=f"embedded-{os.getpid()}-{i}")
        t = threading.Thread(target=w.run_forever, name=f"worker-{i}", daemon=True)
        t.start()
        out.append((w, t))
    return out


def wait_idle(workers, timeout: float = 30.0) -> None:
    """Stop in-process workers at their next chunk boundary."""
    for w, _ in workers:
        w.shutdown.set()
    deadline = time.time() + timeout
    for _, t in workers:
        t.join(max(0.0, deadline - time.time()))
