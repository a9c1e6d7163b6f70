"""Many trials, one compiled program: training configs that differ only in traced numbers together.

A config's traced numbers are the fields marked ``TRACED`` in ``quicknav_core.config`` (learning
rate, gamma, clip, the env's speeds, radii and step limit, reward weights, randomisation ranges).
Configs with the same *shape signature* (everything else, and what the room banks hold) share one
template trainer; each trial gets its own traced numbers (its algorithm's, and its env's in its env
params) and the group trains under ``vmap``. Every trial of a group trains with the first config's
seed, so a batched trial equals the same trial trained alone.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from quicknav_core.config import EnvConfig, TrainConfig, traced_fields
from quicknav_core.runtime import Runtime, runtime_or_new


def _blank_traced(data: dict[str, Any], model: type, value: Callable[[str], Any]) -> None:
    for k in traced_fields(model):
        data[k] = value(k)


def _with_traced(cfg: TrainConfig, value: Callable[[type, str], Any]) -> dict[str, Any]:
    """``cfg`` as JSON with every traced number replaced by ``value(model, field)``."""
    from quicknav_core.config import RandomizeConfig, RewardConfig

    data = cfg.model_dump(mode="json")
    _blank_traced(data["algorithm"], type(cfg.algorithm), lambda k: value(type(cfg.algorithm), k))
    _blank_traced(data["env"], EnvConfig, lambda k: value(EnvConfig, k))
    _blank_traced(data["env"]["reward"], RewardConfig, lambda k: value(RewardConfig, k))
    if data["env"]["randomize"] is not None:
        _blank_traced(data["env"]["randomize"], RandomizeConfig, lambda k: value(RandomizeConfig, k))
    return data


def shape_signature(cfg: TrainConfig, runtime: Runtime | None = None) -> str:
    """The config with every traced number blanked, and what the trials must share that numbers
    decide: the env's compile key and its train bank (a map's cells follow room_size; a robot
    wider than a cell starts where it fits). Trials with equal signatures batch together."""
    from quicknav_core.env.room_sources import room_source

    data = _with_traced(cfg, lambda model, k: None)
    env = cfg.env
    shared = {"compile_key": repr(env.compile_key()), "bank": room_source(env, runtime).key("train"),
              "spawn": [env.spawn_radius, env.cell_size] if env.collision_reach else None}  # fmt: skip
    return json.dumps([data, shared], sort_keys=True)


def canonical(cfg: TrainConfig) -> TrainConfig:
    """The config with every traced algorithm number at its default: one template per shape
    signature (the env's numbers are the first trial's: they decide its bank and spawn cells)."""
    defaults = type(cfg.algorithm)().model_dump(mode="json")
    data = cfg.model_dump(mode="json")
    _blank_traced(data["algorithm"], type(cfg.algorithm), lambda k: defaults[k])
    return TrainConfig.model_validate(data)


def template_trainer(cfg: TrainConfig, runtime: Runtime):
    """The trainer of a shape signature, built from the canonical config once per runtime."""
    from quicknav_core.train.trainers import make_trainer

    key = ("trial-template", shape_signature(cfg, runtime))
    return runtime.program(key, lambda: make_trainer(canonical(cfg), runtime))


def train_batch(
    configs: list[TrainConfig], on_chunk: Callable[[int, list[dict]], bool | None] | None = None,
    runtime: Runtime | None = None,
):  # fmt: skip
    """Train configs with one shape signature side by side.

    Returns (template trainer, per-trial final states, per-trial env params, history), history
    being per chunk a list of per-trial episode metrics. ``on_chunk(chunk, per_trial)`` may return
    True to stop early.
    """
    from quicknav_core.env.quicknav import traced_numbers

    runtime = runtime_or_new(runtime)
    if len({shape_signature(c, runtime) for c in configs}) != 1:
        raise ValueError("train_batch needs configs with one shape signature")
    template = template_trainer(configs[0], runtime)
    env_params = [template.env_params.replace(**traced_numbers(c.env)) for c in configs]
    states, history = template.train_batch(configs, env_params, on_chunk)
    return template, states, env_params, history
