"""How a policy holds up against a real robot's sensor and wheels: success and SPL per perturbation level.

Each level fixes one perturbation of ``EnvConfig.randomize`` at a value (a ``[x, x]`` range) and
leaves the others off; every level runs the same fixed-seed episodes as the plain evaluation, so the
rows differ only in the perturbation. The levels share one compiled program (the ranges are traced).
The ``none`` row is the unperturbed env: a policy trained with randomisation is measured at each
level here, not under its training ranges.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from quicknav_core.config import EnvConfig, EvalConfig, RandomizeConfig
from quicknav_core.env.perturb import randomize_numbers
from quicknav_core.eval.agents import Agent
from quicknav_core.eval.episodes import run_episodes
from quicknav_core.eval.statistics import spl, wilson_interval
from quicknav_core.runtime import Runtime

__all__ = ["LEVELS", "Level", "robustness_levels", "run_robustness"]


@dataclass(frozen=True)
class Level:
    """One row: a perturbation fixed at one value."""

    perturbation: str  # none, lidar_noise, beam_dropout, lidar_bias, latency, wheel_asymmetry
    level: float  # in the perturbation's unit
    unit: str
    randomize: dict[str, Any]  # the RandomizeConfig fields that fix it

    @property
    def label(self) -> str:
        if self.perturbation == "none":
            return "none"
        if self.unit == "%":
            return f"{self.perturbation} {self.level * 100:g} %"
        return f"{self.perturbation} {self.level:g} {self.unit}"


def _fixed(field: str, value: float) -> dict[str, Any]:
    return {field: [value, value]}


# The levels of ``quicknav eval --robustness``: the table (noise 2/5/10 %, dropout 5 %,
# latency 1 and 2 steps, wheel asymmetry 10 %) and a step past each.
LEVELS: tuple[Level, ...] = (
    Level("none", 0.0, "", {}),
    *(Level("lidar_noise", x, "%", _fixed("lidar_noise_frac", x)) for x in (0.02, 0.05, 0.10, 0.20)),
    *(Level("beam_dropout", x, "%", _fixed("beam_dropout", x)) for x in (0.05, 0.10, 0.25)),
    *(Level("lidar_bias", x, "m", _fixed("lidar_bias_m", x)) for x in (-0.1, 0.1)),
    *(Level("latency", k, "steps", _fixed("latency_steps", k)) for k in (1, 2, 3)),
    # the left wheel turns this much slower than commanded: the robot pulls to the left
    *(Level("wheel_asymmetry", x, "%", _fixed("wheel_scale_left", round(1.0 - x, 6)))
      for x in (0.05, 0.10, 0.20)),
)  # fmt: skip


def robustness_levels(env_config: EnvConfig) -> list[tuple[Level, EnvConfig]]:
    """Each level and the env it runs in: ``env_config`` with only that perturbation on.

    A level the env's geometry cannot take (a wheel too fast for the cell size) is left out."""
    out = []
    for level in LEVELS:
        try:
            env = env_config.model_copy(update={"randomize": RandomizeConfig(**level.randomize)})
            out.append((level, EnvConfig.model_validate(env.model_dump())))
        except ValueError:
            continue
    return out


def run_robustness(
    env_config: EnvConfig, agent: Agent, cfg: EvalConfig,
    progress: Callable[[int, int], bool | None] | None = None, params=None,
    runtime: Runtime | None = None,
) -> list[dict[str, Any]]:  # fmt: skip
    """Evaluate ``agent`` at every level on ``cfg``'s episodes: one row per level.

    ``progress(done, total)`` counts the episodes of all levels together; ``params`` are the
    plain evaluation's (its room bank is reused, not built again)."""
    levels = robustness_levels(env_config)
    plain = cfg.model_copy(update={"gif_episodes": 0, "pictures": False})
    # every level is the same program and room bank with other ranges: build once, swap the ranges
    if params is None:
        env, base_params = levels[0][1].build(cfg.split, runtime)
    else:
        from quicknav_core.env.quicknav import QuickNavEnv
        from quicknav_core.env.room_sources import room_source

        env, base_params = QuickNavEnv(levels[0][1], room_source(levels[0][1], runtime)), params
    rows = []
    for i, (level, level_env) in enumerate(levels):
        params = base_params.replace(randomize=randomize_numbers(level_env))
        offset = i * cfg.episodes
        report = None if progress is None else (lambda d, t, o=offset: progress(o + d, t * len(levels)))
        ep = run_episodes(env, params, agent, plain, report, runtime)
        n, k = len(ep.success), int(ep.success.sum())
        lo, hi = wilson_interval(k, n)
        rows.append({
            "perturbation": level.perturbation,
            "level": level.level,
            "unit": level.unit,
            "label": level.label,
            "randomize": level.randomize,
            "episodes": n,
            "success_rate": k / n,
            "success_ci95": [lo, hi],
            "spl": spl(ep.success, ep.path_length, ep.reference_length),
            "mean_steps": float(np.mean(ep.steps)),
            "collisions_per_episode": float(np.mean(ep.collisions)),
        })  # fmt: skip
    return rows
