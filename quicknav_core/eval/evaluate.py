"""Held-out evaluation with navigation metrics: success (95% CI), steps to goal, SPL, collisions.

``run_eval(EvalConfig)`` runs what a resolved config names (a trained policy or a baseline);
``evaluate(env_config, agent, cfg)`` runs any ``Agent`` (``scripted`` holds the baselines) and
writes what it found. The parts live beside it: ``episodes`` runs them, ``statistics`` counts
them, ``pictures`` draws them; their names stay importable from here.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from quicknav_core.config import EnvConfig, EvalConfig
from quicknav_core.config.base import json_safe
from quicknav_core.eval.agents import Agent, PolicyAgent, agent_from_run
from quicknav_core.eval.episodes import Episodes, EvalStopped, replay_data, run_episodes
from quicknav_core.eval.pictures import draw_all, draw_difficulty, draw_gif, draw_trajectories
from quicknav_core.eval.robustness import robustness_levels, run_robustness
from quicknav_core.eval.scripted import baseline_agent
from quicknav_core.eval.shield import ShieldedAgent
from quicknav_core.eval.statistics import (
    PATH_BIN_EDGES,
    by_path_length,
    spl,
    summarize,
    wilson_interval,
)
from quicknav_core.layout import EVAL
from quicknav_core.runtime import Runtime, runtime_or_new

__all__ = ["PATH_BIN_EDGES", "Agent", "Episodes", "EvalStopped", "PolicyAgent", "agent_from_run",
           "by_path_length", "draw_all", "draw_difficulty", "draw_gif", "draw_trajectories",
           "evaluate", "make_agent", "replay_data", "run_episodes", "run_eval", "spl",
           "summarize", "wilson_interval"]  # fmt: skip


def evaluate(
    env_config: EnvConfig, agent: Agent, cfg: EvalConfig, out_dir: Path | None = None,
    progress: Callable[[int, int], bool | None] | None = None, runtime: Runtime | None = None,
) -> tuple[dict[str, Any], Episodes]:  # fmt: skip
    """Evaluate ``agent`` (banks and compiled programs from ``runtime``); with ``out_dir`` write eval.json (with success and SPL per difficulty
    bin), replay.json, trajectories.png, difficulty.png and episodes.gif. With ``cfg.robustness``
    the same episodes also run at each perturbation level (``eval.robustness``): eval.json's
    ``robustness`` rows and robustness.png.

    ``progress(done, total)`` after every batch of episodes may return True to stop
    (``EvalStopped``: nothing is written). The numbers are written before the pictures; a picture
    that fails is left out and named in the result's ``warnings`` (always present, in eval.json too).
    """
    runtime = runtime_or_new(runtime)
    env, params = env_config.build(cfg.split, runtime)
    total = cfg.episodes * (1 + len(robustness_levels(env_config)) if cfg.robustness else 1)
    report = None if progress is None else (lambda done, _n: progress(done, total))
    ep = run_episodes(env, params, agent, cfg, report, runtime)
    step_length = env_config.max_wheel_speed * env_config.dt
    result = {
        "agent": agent.name,
        "eval_config": cfg.model_dump(mode="json"),
        "env_config": env_config.model_dump(mode="json"),
        "metrics": summarize(ep, env_config.max_steps, step_length),
        "by_path_length": by_path_length(ep, env_config.room_size, env_config.max_steps),
        "per_episode": {
            "success": ep.success.tolist(),
            "steps": ep.steps.tolist(),
            "return": [round(float(r), 4) for r in ep.returns],
            "collisions": ep.collisions.tolist(),
            "path_length": [round(float(p), 4) for p in ep.path_length],
            "reference_length": [round(float(r), 4) for r in ep.reference_length],
        },
        "warnings": [],
    }
    if cfg.robustness:
        later = None if progress is None else (lambda done, _n: progress(cfg.episodes + done, total))
        result["robustness"] = run_robustness(env_config, agent, cfg, later, params, runtime)
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        write_json(out_dir / EVAL.result, result)
        if ep.gif["theta"].shape[0]:
            write_json(out_dir / EVAL.replay, replay_data(ep, env_config, agent.name, runtime), indent=None)
        if cfg.pictures:
            result["warnings"] = draw_all(ep, env_config, result["by_path_length"], out_dir,
                                          agent.name, gif=bool(cfg.gif_episodes),
                                          robustness=result.get("robustness"), split=cfg.split,
                                          map_name=runtime.map_name)  # fmt: skip
            if result["warnings"]:
                write_json(out_dir / EVAL.result, result)
    return result, ep


def write_json(path: Path, value: Any, indent: int | None = 2) -> None:
    """Standard JSON: an undefined number (the mean steps of no successes) is null, never NaN,
    which JSON parsers other than Python's refuse."""
    path.write_text(json.dumps(json_safe(value), indent=indent, allow_nan=False))


def make_agent(cfg: EvalConfig, run_dir: Path | str | None = None, runtime: Runtime | None = None
               ) -> tuple[Agent, EnvConfig]:  # fmt: skip
    """The agent an EvalConfig names and the env it runs in: a baseline in ``cfg.env`` (default
    env if unset), or the trained policy of ``run_dir`` (default: ``cfg.source`` read as a run
    folder) in ``cfg.env`` or else the run's own env."""
    if cfg.policy != "trained":
        env = cfg.env or EnvConfig()
        agent = baseline_agent(cfg.policy, env)
    else:
        where = run_dir if run_dir is not None else cfg.source
        if where is None:
            raise ValueError("policy='trained' needs a source: the run folder of the trained policy")
        agent, run_env, _ = agent_from_run(Path(where))
        env = cfg.env or run_env
    return (ShieldedAgent(agent, env) if cfg.shield else agent), env


def run_eval(
    cfg: EvalConfig, out_dir: Path | None = None, run_dir: Path | str | None = None,
    progress: Callable[[int, int], bool | None] | None = None, runtime: Runtime | None = None,
) -> tuple[dict[str, Any], Episodes]:  # fmt: skip
    """Evaluate what a (resolved) EvalConfig names; see ``make_agent`` and ``evaluate``."""
    runtime = runtime_or_new(runtime)
    agent, env = make_agent(cfg, run_dir, runtime)
    return evaluate(env, agent, cfg, out_dir, progress, runtime)
