"""The kinds of job a worker runs: one function per kind, registered by kind.

The worker (``quicknav_service.worker``) is the mechanics: claim, lease and heartbeat, retries
through store outages, hand-back on shutdown, the job's end. What a job *does* lives here, as
``RUNNERS[kind](worker, job, lost) -> (outcome, result)`` where ``outcome`` is ``done``,
``cancelled``, ``lost`` (another worker owns the job now) or ``shutdown`` (hand it back); a runner
that raises fails the job with the reason. A new kind of job is a function with ``@runs(kind)``.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import Field

from quicknav_core.config import SweepConfig
from quicknav_core.config.base import StrictModel
from quicknav_service.jobs.models import Job, JobKind

if TYPE_CHECKING:  # pragma: no cover
    from quicknav_service.worker import Worker

log = logging.getLogger("quicknav.worker")

Outcome = tuple[str, dict[str, Any]]
Runner = Callable[["Worker", Job, threading.Event], Outcome]
RUNNERS: dict[JobKind, Runner] = {}
COORDINATE_POLL_S = 1.0  # how often a sweep looks at its trial batches


def runs(kind: JobKind) -> Callable[[Runner], Runner]:
    """Register ``fn`` as what a worker runs for jobs of ``kind``."""

    def register(fn: Runner) -> Runner:
        RUNNERS[kind] = fn
        return fn

    return register


class TrialSpec(StrictModel):
    """A trial batch's config: which sweep it belongs to, its place, how many trials it runs."""

    parent: str = Field(description="the sweep job's id")
    batch: int = Field(ge=0, description="the batch's index in its sweep")
    trials: int = Field(ge=1, description="trials this batch runs")
    sweep: SweepConfig


def export_policy(run_dir: Path, provenance: dict[str, Any], trainer=None) -> list[str]:
    """Write a finished train job's ``policy.onnx`` and ``policy.json`` beside its checkpoint; a
    failure is a warning naming the files, never a failed job (the checkpoint is the result)."""
    try:
        from quicknav_core.export import export_run

        export_run(run_dir, run_dir, provenance=provenance, trainer=trainer)
    except Exception as e:  # any failure of the export is reported, none is fatal
        log.warning("job %s: policy export failed", provenance.get("job_id"), exc_info=True)
        return [f"policy.onnx, policy.json: not exported ({type(e).__name__}: {e})"[:500]]
    return []


def record_held_out(worker: Worker, source: str, run_dir: Path, metrics: dict, eval_job_id: str,
                    env: dict) -> None:  # fmt: skip
    """Write an evaluation's held-out figures into the source's policy manifest (and publish it)."""
    from quicknav_core.export import MANIFEST_FILE
    from quicknav_core.export import record_held_out as record

    if record(run_dir, metrics, {"eval_job_id": eval_job_id}, env) and worker.artifacts.remote:
        worker.artifacts.save_file(source, run_dir / MANIFEST_FILE, MANIFEST_FILE)


@runs(JobKind.train)
def train(worker: Worker, job: Job, lost: threading.Event) -> Outcome:
    """Train (resuming from the job's checkpoint if it has one); export the policy at the end."""
    from quicknav_core.config import TrainConfig
    from quicknav_core.train.run import checkpoint_dir, train_run

    config = TrainConfig.model_validate(worker.config_of(job))
    # the job's folder with its last published checkpoint (written here, or by a worker elsewhere)
    run_dir = worker.artifacts.restore(job.id)
    resume = checkpoint_dir(run_dir) is not None
    why = worker.stopper(job, lost)
    stop_reason: dict[str, str] = {}

    def on_chunk(r) -> bool:
        metrics = {"phase": "training", "chunk": r.chunk, "chunks": r.chunks,
                   "env_steps": r.env_steps, "total_steps": r.total_steps,
                   "steps_per_s": r.steps_per_s, **r.metrics}  # fmt: skip
        worker.report(job, r.env_steps / max(r.total_steps, 1), metrics)
        reason = why(fresh=True)
        if reason:
            stop_reason["why"] = reason
            return True
        return False

    def interrupt() -> bool:
        reason = why()
        if reason:
            stop_reason["why"] = reason
        return reason is not None

    if resume:
        worker.best_effort(worker.store.publish, job.id, {"type": "resumed", "from_checkpoint": True})
    worker.phase(job, "compiling")
    summary = train_run(config, run_dir, callback=on_chunk, resume=resume,
                        trainer=worker.trainer_for(config), max_chunk_s=worker.settings.max_chunk_s,
                        interrupt=interrupt,
                        replay_every_s=worker.settings.replay_checkpoint_every_s,
                        on_checkpoint=lambda _: worker.artifacts.save(job.id, checkpoint_only=True))  # fmt: skip
    result = {"env_steps": summary["env_steps"], "total_steps": summary["total_steps"],
              "chunks_done": summary["chunks_done"], "final": summary["final"],
              "warnings": summary["warnings"]}  # fmt: skip
    if stop_reason.get("why", "done") == "done" and worker.settings.export_policies:
        provenance = {"job_id": job.id, "preset": job.request.get("preset")}
        exported = export_policy(run_dir, provenance, worker.trainer_for(config))
        result["warnings"] = [*result["warnings"], *exported]
    if summary["total_steps"] != config.total_steps:
        result["note"] = (
            f"total_steps={config.total_steps:,} is not a whole number of updates"
            f" (num_envs x num_steps); the run makes {summary['total_steps']:,} env steps"
        )
    if stop_reason.get("why") != "lost":
        worker.artifacts.save(job.id)  # the curve, the exported policy, TensorBoard's events
    return stop_reason.get("why", "done"), result

@runs(JobKind.eval)
def evaluate(worker: Worker, job: Job, lost: threading.Event) -> Outcome:
    """Evaluate a trained job's policy or a baseline on held-out episodes."""
    from quicknav_core.config import EvalConfig
    from quicknav_core.eval.evaluate import EvalStopped, run_eval

    cfg = EvalConfig.model_validate(worker.config_of(job))
    run_dir = None
    if cfg.policy == "trained":
        run_dir = worker.artifacts.run_copy(cfg.source)  # a local copy when the store is remote
        if run_dir is None:
            raise FileNotFoundError(f"train job {cfg.source} has no checkpoint in the artifact"
                                    f" store {worker.artifacts.url}")  # fmt: skip
    why = worker.stopper(job, lost)
    stop_reason: dict[str, str] = {}

    def on_batch(done: int, total: int) -> bool:
        worker.report(job, done / total,
                     {"phase": "evaluating", "episodes_done": done, "episodes": total})  # fmt: skip
        reason = why(fresh=True)
        if reason:
            stop_reason["why"] = reason
        return reason is not None

    worker.phase(job, "compiling")
    try:
        result, _ = run_eval(cfg, worker.job_dir(job.id), run_dir=run_dir, progress=on_batch)
    except EvalStopped as e:
        return stop_reason.get("why", "cancelled"), {"episodes_done": e.done, "episodes": e.total}
    worker.artifacts.save(job.id)
    worker.report(job, 1.0, result["metrics"])
    if run_dir is not None and cfg.split == "test" and cfg.deterministic:
        # the exported policy's manifest names its held-out success (in the env it trained in)
        worker.best_effort(record_held_out, worker, cfg.source, run_dir, result["metrics"], job.id,
                           cfg.env.model_dump(mode="json"))  # fmt: skip
    return "done", {"agent": result["agent"], "metrics": result["metrics"],
                    "warnings": result["warnings"]}  # fmt: skip

@runs(JobKind.sweep)
def sweep(worker: Worker, job: Job, lost: threading.Event) -> Outcome:
    """Coordinate a sweep: create its study, submit its trial batches as child jobs (any
    worker runs them, all telling the one study), follow them, then write the outputs."""
    from quicknav_core.config import SweepConfig
    from quicknav_core.sweep import (
        best_so_far,
        finished_count,
        open_study,
        write_outputs,
        write_trials,
    )

    cfg = SweepConfig.model_validate(worker.config_of(job))
    folder = worker.job_dir(job.id)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "sweep_config.json").write_text(cfg.model_dump_json(indent=2))
    study = open_study(cfg, worker.sweep_storage(job.id), study_name=f"sweep-{job.id}")
    children = []
    for i in range(math.ceil(cfg.trials / cfg.parallel)):
        size = min(cfg.parallel, cfg.trials - i * cfg.parallel)
        spec = TrialSpec(parent=job.id, batch=i, trials=size, sweep=cfg)
        config = spec.model_dump(mode="json")
        # the key makes this idempotent: a coordinator that takes over finds the same children
        child, _ = worker.until_done(worker.store.submit, JobKind.trial, {"parent": job.id, "batch": i},
                                    config, idempotency_key=f"sweep:{job.id}:batch:{i}")  # fmt: skip
        children.append(child.id)
    why = worker.stopper(job, lost)
    shown = None
    while True:
        reason = why()
        if reason in ("lost", "shutdown"):
            return reason, {}
        jobs = [worker.best_effort(worker.store.get, c) for c in children]
        if reason == "cancelled":
            for c in jobs:
                if c is not None and not c.status.finished:
                    worker.best_effort(worker.store.cancel, c.id)
        states = [c.status.value for c in jobs if c is not None]
        best_value, best_params = best_so_far(study)
        metrics = {"finished": finished_count(study), "total": cfg.trials,
                   "batches": len(children), "batches_running": states.count("running"),
                   "batches_failed": states.count("failed"), "best_value": best_value,
                   "best_params": best_params}  # fmt: skip
        if metrics != shown:
            shown = metrics
            worker.report(job, min(1.0, metrics["finished"] / cfg.trials), metrics)
            write_trials(study, cfg, folder)
            publish_soon(worker, job.id)
        if all(c is not None and c.status.finished for c in jobs):
            break
        worker.shutdown.wait(COORDINATE_POLL_S)
    summary = write_outputs(study, cfg, folder)
    worker.artifacts.save(job.id)
    summary.update({"batches": len(children), "children": children,
                    "batches_failed": states.count("failed"),
                    "batches_cancelled": states.count("cancelled")})  # fmt: skip
    if reason == "cancelled":
        return "cancelled", summary
    if summary["best_value"] is None and states.count("failed"):
        first = next(c for c in jobs if c.status.value == "failed")
        raise RuntimeError(f"no trial completed; trial batch {first.id} failed: {first.error}")
    return "done", summary

def publish_soon(worker: Worker, job_id: str) -> None:
    """A sweep's trials so far, published as they change (an outage skips it: the end retries)."""
    try:
        if worker.artifacts.remote:
            worker.artifacts.save(job_id)
    except Exception as e:  # ArtifactUnavailable: what the sweep finds is in its study
        log.warning("sweep %s: its trials so far were not published (%s)", job_id, e)


@runs(JobKind.trial)
def trial(worker: Worker, job: Job, lost: threading.Event) -> Outcome:
    """A batch of a sweep's trials: ask them from the shared study, train, evaluate, tell.
    Run again after its worker died, it first reruns the trials that worker left unfinished."""
    from quicknav_core.sweep import finished_count, open_study, retry_lost, run_batch

    spec = TrialSpec.model_validate(worker.config_of(job))
    cfg = spec.sweep
    parent, tag = spec.parent, str(spec.batch)
    # each batch samples from its own stream (its index; a rerun: also its attempt)
    stream = 1 + spec.batch + 100_003 * (job.attempts - 1)
    study = open_study(cfg, worker.sweep_storage(parent), study_name=f"sweep-{parent}",
                       stream=stream)  # fmt: skip
    retried = retry_lost(study, tag)
    why = worker.stopper(job, lost)
    todo = spec.trials - finished_count(study, tag)
    if todo > 0 and why(fresh=True) is None:
        run_batch(study, cfg, todo, tag=tag, stop=lambda: why() is not None)
    reason = why(fresh=True)
    if reason in ("lost", "shutdown"):
        return reason, {}
    mine = [t for t in study.get_trials(deepcopy=False) if t.user_attrs.get("batch") == tag]
    result = {"parent": parent, "batch": spec.batch, "trials": finished_count(study, tag),
              "retried": retried,
              "values": {str(t.number): t.value for t in mine if t.value is not None}}  # fmt: skip
    return reason or "done", result
