"""Hyperparameter sweeps with Optuna, many trials per compiled program.

Optuna's ask-and-tell interface hands out ``parallel`` trials at a time. Their configs are grouped
by everything that fixes array shapes; trials in a group differ only in traced numbers (learning
rate, gamma, lambda, clip, coefficients, reward weights, ...) and train side by side in one
vmapped, jit-compiled program (one compile for the whole group). Every trial trains with the base
seed, so a batched trial equals the same trial trained alone.

Each finished trial is evaluated on the *train* room bank with its own episode seed (sweeps never
look at the held-out test bank) and told to the study; a trial that raises is told as failed and
its error kept in the trial's user attributes. Storage: an SQLite file (resumable: rerunning the
same command continues the study) or, with a Redis URL, Optuna's journal storage on Redis so several
workers share a study.
"""

from __future__ import annotations

import csv
import json
import math
import os
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from quicknav_core.config import TrainConfig, apply_overrides
from quicknav_core.config.base import json_safe
from quicknav_core.config.sweep import METRICS, ParamSpec, SweepConfig
from quicknav_core.layout import SWEEP
from quicknav_core.runtime import Runtime, runtime_or_new
from quicknav_core.train.batched import shape_signature, train_batch
from quicknav_core.train.pictures import draw_study

__all__ = ["SweepConfig", "evaluate_trial", "finished_count", "make_storage", "objective_value",
           "open_study", "retry_lost", "run_batch", "run_sweep", "study_storage", "write_outputs",
           "write_trials"]  # fmt: skip

def evaluate_trial(trainer, state, env_params, cfg: SweepConfig) -> dict[str, Any]:
    """Navigation metrics of one trained trial on the train bank (never the test bank)."""
    from quicknav_core.config import EvalConfig
    from quicknav_core.eval.evaluate import PolicyAgent, run_episodes, summarize

    ecfg = EvalConfig(episodes=cfg.eval_episodes, seed=cfg.eval_seed, split="train", pictures=False,
                      gif_episodes=0)  # fmt: skip
    ep = run_episodes(trainer.env, env_params, PolicyAgent(trainer.policy(state)), ecfg,
                      runtime=trainer.runtime)
    env_cfg = trainer.config.env
    return summarize(ep, env_cfg.max_steps, env_cfg.max_wheel_speed * env_cfg.dt)


def objective_value(metrics: dict[str, Any], objective: str) -> float:
    value = metrics[METRICS[objective][0]]
    return float(value["mean"] if isinstance(value, dict) else value)


# --------------------------------------------------------------------------- study
def make_storage(cfg: SweepConfig, out_dir: Path):
    """The study's storage for a sweep run in this process (``quicknav sweep``)."""
    return study_storage(cfg.storage, out_dir)


def study_storage(url: str | None, folder: Path, prefix: str = ""):
    """The one rule for where a study lives, for `quicknav sweep` and the service's sweep jobs:
    ``None``: SQLite in ``folder/study.db`` (one machine); ``redis://``: Optuna's journal on Redis
    (keys under ``prefix``; a fleet); any other URL: an Optuna RDB storage (``postgresql://``...)."""
    import optuna

    if url is None:
        return optuna.storages.RDBStorage(
            f"sqlite:///{(Path(folder) / SWEEP.study).resolve()}",
            engine_kwargs={"connect_args": {"timeout": 60}},
        )
    if url.startswith("redis://") or url.startswith("rediss://"):
        from optuna.storages import JournalStorage
        from optuna.storages.journal import JournalRedisBackend

        return JournalStorage(JournalRedisBackend(url, prefix=prefix))
    return url


def _sample(trial, space: dict[str, ParamSpec]) -> dict[str, Any]:
    params = {}
    for name, spec in space.items():
        if spec.type == "float":
            params[name] = trial.suggest_float(name, spec.low, spec.high)
        elif spec.type == "log_float":
            params[name] = trial.suggest_float(name, spec.low, spec.high, log=True)
        elif spec.type == "int":
            params[name] = trial.suggest_int(name, int(spec.low), int(spec.high))
        else:
            params[name] = trial.suggest_categorical(name, spec.choices)
    return params


FINISHED_STATES = ("COMPLETE", "PRUNED", "FAIL")


def open_study(cfg: SweepConfig, storage, study_name: str | None = None, stream: int = 0):
    """The sweep's Optuna study on ``storage`` (created, or loaded when it exists).

    ``stream`` picks the sampler's random stream: processes that each open the study and ask
    (a sweep's trial batches on several workers) need different streams, or every one would
    draw the same params from the same seed."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    seed = (cfg.sampler_seed + 7919 * stream) % 2**31
    sampler = (optuna.samplers.TPESampler(seed=seed) if cfg.sampler == "tpe"
               else optuna.samplers.RandomSampler(seed=seed))  # fmt: skip
    pruner = optuna.pruners.MedianPruner() if cfg.pruner == "median" else optuna.pruners.NopPruner()
    return optuna.create_study(
        study_name=study_name or cfg.study_name, storage=storage, sampler=sampler, pruner=pruner,
        direction=cfg.resolved_direction, load_if_exists=True,
    )  # fmt: skip


def _retried(study) -> set[int]:
    """Numbers of trials lost with their worker and run again (kept as study user attributes)."""
    return {int(k.split(":", 1)[1]) for k in study.user_attrs if k.startswith("retried:")}


def finished_count(study, tag: str | None = None) -> int:
    """Finished trials that count toward ``trials`` (those of batch ``tag`` only, when given): a
    trial lost with its worker and run again under a new number does not count, its rerun does."""
    retried = _retried(study)
    return sum(
        t.state.name in FINISHED_STATES and t.number not in retried
        and (tag is None or t.user_attrs.get("batch") == tag)
        for t in study.get_trials(deepcopy=False)
    )  # fmt: skip


def retry_lost(study, tag: str) -> int:
    """Trials of batch ``tag`` left RUNNING by a worker that died: each is told failed, noted as
    retried (so it does not count) and its params enqueued, so the next ask runs them again.
    Returns how many."""
    import optuna

    lost = [t for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,))
            if t.user_attrs.get("batch") == tag]  # fmt: skip
    for t in lost:
        study.enqueue_trial(t.params, skip_if_exists=False)
        study.set_user_attr(f"retried:{t.number}", "its worker was lost; its params run again")
        study.tell(t.number, state=optuna.trial.TrialState.FAIL)
    return len(lost)


def run_batch(study, cfg: SweepConfig, count: int, tag: str | None = None,
              stop: Callable[[], bool] | None = None,
              runtime: Runtime | None = None) -> list[dict[str, Any]]:  # fmt: skip
    """Ask ``count`` trials, train them (trials that share array shapes side by side in one
    compiled program, kept in ``runtime``), evaluate each on the train bank and tell the study.
    Trials carry ``batch=tag`` when given. ``stop()`` true at a chunk end stops the training and
    tells the group's trials failed ("stopped"). Returns per-group timings."""
    import optuna

    runtime = runtime_or_new(runtime)

    asked = [study.ask() for _ in range(count)]
    groups: dict[str, list[tuple[Any, TrainConfig]]] = {}
    for trial in asked:
        if tag is not None:
            trial.set_user_attr("batch", tag)
        try:
            tcfg = apply_overrides(cfg.base, _sample(trial, cfg.space))
        except Exception as e:
            trial.set_user_attr("error", f"{type(e).__name__}: {e}")
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            continue
        groups.setdefault(shape_signature(tcfg, runtime), []).append((trial, tcfg))
    timings = []
    for members in groups.values():
        t0 = time.perf_counter()
        trials = [m[0] for m in members]
        try:

            def on_chunk(c, per_trial, trials=trials):
                for tr, m in zip(trials, per_trial, strict=True):
                    tr.report(m.get("success_rate", float("nan")), c)
                if stop is not None and stop():
                    return True
                return all(tr.should_prune() for tr in trials) and cfg.pruner != "none"

            trainer, states, env_params, _ = train_batch([m[1] for m in members], on_chunk, runtime)
            if stop is not None and stop():
                for trial in trials:
                    trial.set_user_attr("error", "stopped (the sweep was cancelled or its worker stopped)")
                    study.tell(trial, state=optuna.trial.TrialState.FAIL)
                timings.append({"trials": len(members), "seconds": time.perf_counter() - t0})
                continue
            for trial, state, params in zip(trials, states, env_params, strict=True):
                metrics = evaluate_trial(trainer, state, params, cfg)
                value = objective_value(metrics, cfg.objective)
                trial.set_user_attr("metrics", json.loads(json.dumps(metrics, default=float)))
                if math.isnan(value):
                    trial.set_user_attr("error", f"objective {cfg.objective} is NaN (no successes)")
                    study.tell(trial, state=optuna.trial.TrialState.FAIL)
                else:
                    study.tell(trial, value)
        except Exception as e:
            msg = f"{type(e).__name__}: {e}"
            for trial in trials:
                trial.set_user_attr("error", msg)
                trial.set_user_attr("traceback", traceback.format_exc()[-4000:])
                study.tell(trial, state=optuna.trial.TrialState.FAIL)
        timings.append({"trials": len(members), "seconds": time.perf_counter() - t0})
    return timings


def run_sweep(
    cfg: SweepConfig, out_dir: Path, progress: Callable[[dict], None] | None = None,
    runtime: Runtime | None = None,
) -> dict[str, Any]:  # fmt: skip
    """Run (or continue) a study until it has ``cfg.trials`` finished trials; write the outputs."""
    import optuna

    runtime = runtime_or_new(runtime)

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / SWEEP.config).write_text(cfg.model_dump_json(indent=2))
    study = open_study(cfg, make_storage(cfg, out_dir))
    # trials left running by an interrupted earlier run are failed, not lost
    for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
        study.tell(t.number, state=optuna.trial.TrialState.FAIL)
    timings = []
    while True:
        done = finished_count(study)
        if done >= cfg.trials:
            break
        timings += run_batch(study, cfg, min(cfg.parallel, cfg.trials - done), runtime=runtime)
        write_trials(study, cfg, out_dir)
        if progress:
            best = best_so_far(study)
            stop = progress({"finished": finished_count(study), "total": cfg.trials,
                             "best_value": best[0], "best_params": best[1]})  # fmt: skip
            if stop:  # the caller asked to stop between batches (cancel, shutdown)
                summary = write_outputs(study, cfg, out_dir)
                summary["timings"] = timings
                summary["stopped"] = True
                return summary
    summary = write_outputs(study, cfg, out_dir)
    summary["timings"] = timings
    return summary


def best_so_far(study) -> tuple[float | None, dict | None]:
    try:
        return study.best_value, study.best_params
    except ValueError:
        return None, None


def write_trials(study, cfg: SweepConfig, out_dir: Path) -> dict[str, Any]:
    """``trials.json``: the objective, its direction and every trial so far (number, state, value,
    params, metrics, error, seconds), rewritten after each batch so a running sweep can be watched."""
    rows = []
    retried = _retried(study)
    for t in study.get_trials(deepcopy=False):
        seconds = ((t.datetime_complete - t.datetime_start).total_seconds()
                   if t.datetime_complete and t.datetime_start else None)  # fmt: skip
        value = t.value if t.value is not None and math.isfinite(t.value) else None
        error = study.user_attrs.get(f"retried:{t.number}") if t.number in retried else None
        rows.append({"number": t.number, "state": t.state.name, "value": value, "params": t.params,
                     "metrics": t.user_attrs.get("metrics"),
                     "error": error or t.user_attrs.get("error"), "seconds": seconds,
                     "batch": t.user_attrs.get("batch"), "counted": t.number not in retried})  # fmt: skip
    out = {"objective": cfg.objective, "direction": cfg.resolved_direction, "trials": rows}
    tmp = out_dir / f"{SWEEP.trials}.tmp"
    tmp.write_text(json.dumps(json_safe(out), default=float, allow_nan=False))
    os.replace(tmp, out_dir / SWEEP.trials)
    return out


def write_outputs(study, cfg: SweepConfig, out_dir: Path) -> dict[str, Any]:
    """best_params.json, best_config.json, trials.csv, trials.json and the Optuna plots (PNG)."""

    write_trials(study, cfg, out_dir)
    trials = study.get_trials(deepcopy=False)
    with open(out_dir / SWEEP.trials_csv, "w", newline="") as f:
        names = sorted({k for t in trials for k in t.params})
        w = csv.writer(f)
        w.writerow(["number", "state", "value", *names, "error"])
        for t in trials:
            w.writerow([t.number, t.state.name, t.value, *[t.params.get(n) for n in names],
                        t.user_attrs.get("error", "")])  # fmt: skip
    best_value, best_params = best_so_far(study)
    out = {"study": study.study_name, "trials": len(trials), "best_value": best_value,
           "best_params": best_params, "direction": cfg.resolved_direction, "objective": cfg.objective}  # fmt: skip
    if best_params is not None:
        (out_dir / SWEEP.best_params).write_text(
            json.dumps({"value": best_value, "params": best_params}, indent=2)
        )
        (out_dir / SWEEP.best_config).write_text(
            apply_overrides(cfg.base, best_params).model_dump_json(indent=2)
        )
    plot_errors = draw_study(study, cfg, out_dir)  # a picture never costs a sweep its numbers
    if plot_errors:
        out["plot_errors"] = plot_errors
    (out_dir / SWEEP.summary).write_text(json.dumps(out, indent=2, default=str))
    return out
