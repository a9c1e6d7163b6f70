"""The kinds of job a worker runs: one function per kind, registered by kind.

The worker (``quicknav_service.worker``) is the mechanics: claim, lease and heartbeat, retries
through store outages, hand-back on shutdown, the job's end. What a job *does* lives here, as
``RUNNERS[kind](ctx) -> (outcome, result)``, ``ctx`` a ``JobContext`` (the job, the stores, the
runtime, progress and stop signals), where ``outcome`` is ``done``, ``cancelled``, ``lost`` (another
worker owns the job now) or ``shutdown`` (hand it back); a runner that raises fails the job with the
reason. A new kind of job is a function with ``@runs(kind)``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path
from types import MappingProxyType
from typing import Any

from pydantic import Field

from quicknav_core.config import SweepConfig
from quicknav_core.config.base import StrictModel
from quicknav_core.layout import SWEEP
from quicknav_service.job_context import JobContext
from quicknav_service.jobs.models import JobKind

log = logging.getLogger("quicknav.worker")

Outcome = tuple[str, dict[str, Any]]
Runner = Callable[[JobContext], Outcome]
_REGISTERED: dict[JobKind, Runner] = {}
RUNNERS = MappingProxyType(_REGISTERED)  # read-only: kinds register with @runs at import
COORDINATE_POLL_S = 1.0  # how often a sweep looks at its trial batches


def runs(kind: JobKind) -> Callable[[Runner], Runner]:
    """Register ``fn`` as what a worker runs for jobs of ``kind``."""

    def register(fn: Runner) -> Runner:
        _REGISTERED[kind] = fn
        return fn

    return register


class TrialSpec(StrictModel):
    """A trial batch's config: which sweep it belongs to, its place, how many trials it runs."""

    parent: str = Field(description="the sweep job's id")
    batch: int = Field(ge=0, description="the batch's index in its sweep")
    trials: int = Field(ge=1, description="trials this batch runs")
    sweep: SweepConfig


def export_policy(run_dir: Path, provenance: dict[str, Any]) -> list[str]:
    """Write a finished train job's ``policy.onnx`` and ``policy.json`` beside its checkpoint; a
    failure is a warning naming the files, never a failed job (the checkpoint is the result)."""
    try:
        from quicknav_core.export import export_run

        export_run(run_dir, run_dir, provenance=provenance)
    except Exception as e:  # any failure of the export is reported, none is fatal
        log.warning("job %s: policy export failed", provenance.get("job_id"), exc_info=True)
        return [f"policy.onnx, policy.json: not exported ({type(e).__name__}: {e})"[:500]]
    return []


def record_held_out(ctx: JobContext, source: str, run_dir: Path, metrics: dict, env: dict) -> None:
    """Write an evaluation's held-out figures into the source's policy manifest (and publish it)."""
    from quicknav_core.export import MANIFEST_FILE
    from quicknav_core.export import record_held_out as record

    if record(run_dir, metrics, {"eval_job_id": ctx.job.id}, env) and ctx.artifacts.remote:
        ctx.artifacts.save_file(source, run_dir / MANIFEST_FILE, MANIFEST_FILE)


@runs(JobKind.train)
def train(ctx: JobContext) -> Outcome:
    """Train (resuming from the job's checkpoint if it has one); export the policy at the end."""
    from quicknav_core.config import TrainConfig
    from quicknav_core.train.run import checkpoint_dir, train_run

    job = ctx.job
    config = TrainConfig.model_validate(ctx.config)
    # the job's folder with its last published checkpoint (written here, or by a worker elsewhere)
    run_dir = ctx.artifacts.restore(job.id)
    resume = checkpoint_dir(run_dir) is not None
    stop_reason: dict[str, str] = {}

    def on_chunk(r) -> bool:
        metrics = {"phase": "training", "chunk": r.chunk, "chunks": r.chunks,
                   "env_steps": r.env_steps, "total_steps": r.total_steps,
                   "steps_per_s": r.steps_per_s, **r.metrics}  # fmt: skip
        ctx.report(r.env_steps / max(r.total_steps, 1), metrics)
        reason = ctx.stop_reason(fresh=True)
        if reason:
            stop_reason["why"] = reason
            return True
        return False

    def interrupt() -> bool:
        reason = ctx.stop_reason()
        if reason:
            stop_reason["why"] = reason
        return reason is not None

    if resume:
        ctx.publish({"type": "resumed", "from_checkpoint": True})
    ctx.phase("compiling")
    trainer = ctx.trainer_for(config)
    summary = train_run(config, run_dir, callback=on_chunk, resume=resume, trainer=trainer,
                        max_chunk_s=ctx.settings.max_chunk_s, interrupt=interrupt,
                        replay_every_s=ctx.settings.replay_checkpoint_every_s,
                        on_checkpoint=lambda _: ctx.artifacts.save(job.id, checkpoint_only=True),
                        runtime=ctx.runtime)  # fmt: skip
    result = {"env_steps": summary["env_steps"], "total_steps": summary["total_steps"],
              "chunks_done": summary["chunks_done"], "final": summary["final"],
              "warnings": summary["warnings"]}  # fmt: skip
    if stop_reason.get("why", "done") == "done" and ctx.settings.export_policies:
        provenance = {"job_id": job.id, "preset": job.request.get("preset")}
        exported = export_policy(run_dir, provenance)
        result["warnings"] = [*result["warnings"], *exported]
    if summary["total_steps"] != config.total_steps:
        result["note"] = (
            f"total_steps={config.total_steps:,} is not a whole number of updates"
            f" (num_envs x num_steps); the run makes {summary['total_steps']:,} env steps"
        )
    if stop_reason.get("why") != "lost":
        ctx.artifacts.save(job.id)  # the curve, the exported policy, TensorBoard's events
    return stop_reason.get("why", "done"), result


@runs(JobKind.eval)
def evaluate(ctx: JobContext) -> Outcome:
    """Evaluate a trained job's policy or a baseline on held-out episodes."""
    from quicknav_core.config import EvalConfig
    from quicknav_core.eval.evaluate import EvalStopped, run_eval

    job = ctx.job
    cfg = EvalConfig.model_validate(ctx.config)
    run_dir = None
    if cfg.policy == "trained":
        run_dir = ctx.artifacts.run_copy(cfg.source)  # a local copy when the store is remote
        if run_dir is None:
            raise FileNotFoundError(f"train job {cfg.source} has no checkpoint in the artifact"
                                    f" store {ctx.artifacts.url}")  # fmt: skip
    stop_reason: dict[str, str] = {}

    def on_batch(done: int, total: int) -> bool:
        ctx.report(done / total, {"phase": "evaluating", "episodes_done": done, "episodes": total})
        reason = ctx.stop_reason(fresh=True)
        if reason:
            stop_reason["why"] = reason
        return reason is not None

    ctx.phase("compiling")
    try:
        result, _ = run_eval(cfg, ctx.job_dir, run_dir=run_dir, progress=on_batch,
                             runtime=ctx.runtime)  # fmt: skip
    except EvalStopped as e:
        return stop_reason.get("why", "cancelled"), {"episodes_done": e.done, "episodes": e.total}
    ctx.artifacts.save(job.id)
    ctx.report(1.0, result["metrics"])
    if run_dir is not None and cfg.split == "test" and cfg.deterministic:
        # the exported policy's manifest names its held-out success (in the env it trained in)
        ctx.best_effort(record_held_out, ctx, cfg.source, run_dir, result["metrics"],
                        cfg.env.model_dump(mode="json"))  # fmt: skip
    return "done", {"agent": result["agent"], "metrics": result["metrics"],
                    "warnings": result["warnings"]}  # fmt: skip


@runs(JobKind.sweep)
def sweep(ctx: JobContext) -> Outcome:
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

    job = ctx.job
    cfg = SweepConfig.model_validate(ctx.config)
    folder = ctx.job_dir
    folder.mkdir(parents=True, exist_ok=True)
    (folder / SWEEP.config).write_text(cfg.model_dump_json(indent=2))
    study = open_study(cfg, ctx.sweep_storage(job.id), study_name=f"sweep-{job.id}")
    children = []
    for i in range(math.ceil(cfg.trials / cfg.parallel)):
        size = min(cfg.parallel, cfg.trials - i * cfg.parallel)
        spec = TrialSpec(parent=job.id, batch=i, trials=size, sweep=cfg)
        config = spec.model_dump(mode="json")
        # the key makes this idempotent: a coordinator that takes over finds the same children
        child, _ = ctx.until_done(ctx.store.submit, JobKind.trial, {"parent": job.id, "batch": i},
                                  config, idempotency_key=f"sweep:{job.id}:batch:{i}")  # fmt: skip
        children.append(child.id)
    shown = None
    while True:
        reason = ctx.stop_reason()
        if reason in ("lost", "shutdown"):
            return reason, {}
        jobs = [ctx.best_effort(ctx.store.get, c) for c in children]
        if reason == "cancelled":
            for c in jobs:
                if c is not None and not c.status.finished:
                    ctx.best_effort(ctx.store.cancel, c.id)
        states = [c.status.value for c in jobs if c is not None]
        best_value, best_params = best_so_far(study)
        metrics = {"finished": finished_count(study), "total": cfg.trials,
                   "batches": len(children), "batches_running": states.count("running"),
                   "batches_failed": states.count("failed"), "best_value": best_value,
                   "best_params": best_params}  # fmt: skip
        if metrics != shown:
            shown = metrics
            ctx.report(min(1.0, metrics["finished"] / cfg.trials), metrics)
            write_trials(study, cfg, folder)
            publish_soon(ctx)
        if all(c is not None and c.status.finished for c in jobs):
            break
        ctx.shutdown.wait(COORDINATE_POLL_S)
    summary = write_outputs(study, cfg, folder)
    ctx.artifacts.save(job.id)
    summary.update({"batches": len(children), "children": children,
                    "batches_failed": states.count("failed"),
                    "batches_cancelled": states.count("cancelled")})  # fmt: skip
    if reason == "cancelled":
        return "cancelled", summary
    if summary["best_value"] is None and states.count("failed"):
        first = next(c for c in jobs if c.status.value == "failed")
        raise RuntimeError(f"no trial completed; trial batch {first.id} failed: {first.error}")
    return "done", summary


def publish_soon(ctx: JobContext) -> None:
    """A sweep's trials so far, published as they change (an outage skips it: the end retries)."""
    try:
        if ctx.artifacts.remote:
            ctx.artifacts.save(ctx.job.id)
    except Exception as e:  # ArtifactUnavailable: what the sweep finds is in its study
        log.warning("sweep %s: its trials so far were not published (%s)", ctx.job.id, e)


@runs(JobKind.trial)
def trial(ctx: JobContext) -> Outcome:
    """A batch of a sweep's trials: ask them from the shared study, train, evaluate, tell.
    Run again after its worker died, it first reruns the trials that worker left unfinished."""
    from quicknav_core.sweep import finished_count, open_study, retry_lost, run_batch

    spec = TrialSpec.model_validate(ctx.config)
    cfg = spec.sweep
    parent, tag = spec.parent, str(spec.batch)
    # each batch samples from its own stream (its index; a rerun: also its attempt)
    stream = 1 + spec.batch + 100_003 * (ctx.job.attempts - 1)
    study = open_study(cfg, ctx.sweep_storage(parent), study_name=f"sweep-{parent}",
                       stream=stream)  # fmt: skip
    retried = retry_lost(study, tag)
    todo = spec.trials - finished_count(study, tag)
    if todo > 0 and ctx.stop_reason(fresh=True) is None:
        run_batch(study, cfg, todo, tag=tag, stop=lambda: ctx.stop_reason() is not None,
                  runtime=ctx.runtime)  # fmt: skip
    reason = ctx.stop_reason(fresh=True)
    if reason in ("lost", "shutdown"):
        return reason, {}
    mine = [t for t in study.get_trials(deepcopy=False) if t.user_attrs.get("batch") == tag]
    result = {"parent": parent, "batch": spec.batch, "trials": finished_count(study, tag),
              "retried": retried,
              "values": {str(t.number): t.value for t in mine if t.value is not None}}  # fmt: skip
    return reason or "done", result
