"""Many trials, one compiled program: training configs that differ only in traced numbers together.

A config's traced numbers are the fields marked ``TRACED`` in ``quicknav_core.config`` (learning
rate, gamma, clip, reward weights, ...). Configs with the same *shape signature* (everything else)
share one template trainer; each trial gets its own traced numbers (its algorithm's, and its reward
weights in its env params) and the group trains under ``vmap``. Every trial of a group trains with
the first config's seed, so a batched trial equals the same trial trained alone.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from quicknav_core.config import RewardConfig, TrainConfig, traced_fields

# template trainers by shape signature: their compiled batch programs are reused by later groups
_TEMPLATES: dict[str, Any] = {}
_MAX_TEMPLATES = 8


def _traced(cfg: TrainConfig) -> tuple[frozenset[str], frozenset[str]]:
    return traced_fields(type(cfg.algorithm)), traced_fields(RewardConfig)


def shape_signature(cfg: TrainConfig) -> str:
    """The config with every traced number blanked: trials with equal signatures batch together."""
    algo_traced, reward_traced = _traced(cfg)
    data = cfg.model_dump(mode="json")
    for k in algo_traced:
        data["algorithm"].pop(k, None)
    for k in reward_traced:
        data["env"]["reward"].pop(k, None)
    return json.dumps(data, sort_keys=True)


def canonical(cfg: TrainConfig) -> TrainConfig:
    """The config with every traced number at its default: one template per shape signature."""
    algo_traced, reward_traced = _traced(cfg)
    data = cfg.model_dump(mode="json")
    algo_defaults = type(cfg.algorithm)().model_dump(mode="json")
    reward_defaults = RewardConfig().model_dump(mode="json")
    for k in algo_traced:
        data["algorithm"][k] = algo_defaults[k]
    for k in reward_traced:
        data["env"]["reward"][k] = reward_defaults[k]
    return TrainConfig.model_validate(data)


def template_trainer(cfg: TrainConfig):
    """The (cached) trainer of a shape signature, built from the canonical config."""
    from quicknav_core.train.trainers import make_trainer

    sig = shape_signature(cfg)
    if sig not in _TEMPLATES:
        if len(_TEMPLATES) >= _MAX_TEMPLATES:
            _TEMPLATES.pop(next(iter(_TEMPLATES)))
        _TEMPLATES[sig] = make_trainer(canonical(cfg))
    return _TEMPLATES[sig]


def train_batch(
    configs: list[TrainConfig], on_chunk: Callable[[int, list[dict]], bool | None] | None = None
):
    """Train configs with one shape signature side by side.

    Returns (template trainer, per-trial final states, per-trial env params, history), history
    being per chunk a list of per-trial episode metrics. ``on_chunk(chunk, per_trial)`` may return
    True to stop early.
    """
    from quicknav_core.env.reward import reward_numbers

    if len({shape_signature(c) for c in configs}) != 1:
        raise ValueError("train_batch needs configs with one shape signature")
    template = template_trainer(configs[0])
    env_params = [template.env_params.replace(**reward_numbers(c.env.reward)) for c in configs]
    states, history = template.train_batch(configs, env_params, on_chunk)
    return template, states, env_params, history
