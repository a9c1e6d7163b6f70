"""Sweep configuration: a base TrainConfig, a search space, an objective, and how to run the study.

The built-in search spaces (``ppo``, ``sac``, ``td3``, ``mlp``, ``lstm``, ``gtrxl``) are the paper's
appendix, each on its paper preset (``SPACE_BASE_PRESET``). A space's parameters are dotted keys of
the base config, set exactly as overrides are (``config.overrides``).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, model_validator

from quicknav_core.config.base import StrictModel
from quicknav_core.config.overrides import OverrideError, override_data
from quicknav_core.config.train import TrainConfig


class ParamSpec(StrictModel):
    """One dimension of a search space."""

    type: Literal["float", "log_float", "int", "categorical"]
    low: float | None = None
    high: float | None = None
    choices: list[Any] | None = None

    @model_validator(mode="after")
    def _check(self) -> ParamSpec:
        if self.type == "categorical":
            if not self.choices:
                raise ValueError("categorical parameter needs a non-empty 'choices' list")
            return self
        if self.low is None or self.high is None:
            raise ValueError(f"{self.type} parameter needs 'low' and 'high'")
        if self.low > self.high:
            raise ValueError(f"low={self.low} > high={self.high}; allowed: low <= high")
        if self.type == "log_float" and self.low <= 0:
            raise ValueError(f"log_float needs low > 0 (got low={self.low})")
        return self

    def probe(self) -> Any:
        """A value inside the dimension (used to check that the parameter names a field)."""
        if self.type == "categorical":
            return self.choices[0]
        return int(self.low) if self.type == "int" else self.low


def _f(lo, hi):
    return {"type": "float", "low": lo, "high": hi}


def _cat(*choices):
    return {"type": "categorical", "choices": list(choices)}


_REWARDS = {
    "env.reward.step_penalty": _f(0.01, 0.5),
    "env.reward.progress_reward": _f(0.1, 1.0),
    "env.reward.cycle_penalty": _f(0.001, 0.5),
}
# The paper's appendix, parameter by parameter.
BUILTIN_SPACES: dict[str, dict[str, dict[str, Any]]] = {
    "ppo": {
        "algorithm.learning_rate": {"type": "log_float", "low": 1e-5, "high": 1e-3},
        "algorithm.num_minibatches": _cat(16, 32, 64, 128, 256),
        "algorithm.num_steps": _cat(64, 128, 256, 512),
        "algorithm.gae_lambda": _f(0.9, 1.0),
        "algorithm.ent_coef": _f(0.0, 0.1),
        "algorithm.clip_eps": _f(0.1, 0.3),
        "algorithm.gamma": _f(0.9, 0.999),
    },
    "sac": {
        "algorithm.learning_rate": {"type": "log_float", "low": 1e-5, "high": 1e-3},
        "algorithm.batch_size": _cat(64, 128, 256, 512),
        "algorithm.buffer_size": _cat(50_000, 100_000, 200_000, 500_000),
        "algorithm.polyak": _f(0.9, 0.999),
        "algorithm.target_entropy_ratio": _f(0.5, 1.0),
        "algorithm.target_update_freq": _cat(1, 2, 3, 4),
        "algorithm.gamma": _f(0.9, 0.999),
    },
    "td3": {
        "algorithm.learning_rate": {"type": "log_float", "low": 1e-5, "high": 1e-3},
        "algorithm.exploration_noise": _f(0.1, 0.5),
        "algorithm.buffer_size": _cat(50_000, 100_000, 200_000, 500_000),
        "algorithm.batch_size": _cat(64, 128, 256, 512),
        "algorithm.polyak": _f(0.9, 0.999),
        "algorithm.target_noise": _f(0.1, 0.4),
        "algorithm.policy_delay": _cat(1, 2, 3, 4),
    },
    "mlp": {
        "network.hidden_layers": {"type": "int", "low": 1, "high": 3},
        "network.hidden_size": _cat(64, 128, 256),
        **_REWARDS,
    },
    "lstm": {
        "network.num_layers": {"type": "int", "low": 2, "high": 10},
        "network.hidden_size": {"type": "int", "low": 5, "high": 16},
        **_REWARDS,
    },
    "gtrxl": {
        "network.embed_size": _cat(8, 16),
        "network.head_size": {"type": "int", "low": 1, "high": 8},
        "network.num_layers": {"type": "int", "low": 2, "high": 5},
        **_REWARDS,
    },
}
# The training preset each built-in space starts from.
SPACE_BASE_PRESET = {"ppo": "paper-ppo", "sac": "paper-sac", "td3": "paper-td3",
                     "mlp": "paper-mlp", "lstm": "paper-lstm", "gtrxl": "paper-gtrxl"}  # fmt: skip
# Env steps per trial of a built-in space unless the request says otherwise (the presets' own
# budgets, 2M to 20M steps, are for one finished agent, not for each of many trials).
BUILTIN_TOTAL_STEPS = 2_000_000

# objective name -> (key in the eval metrics, natural direction)
METRICS = {
    "success_rate": ("success_rate", "maximize"),
    "spl": ("spl", "maximize"),
    "steps_to_goal": ("steps_to_goal_failures_as_limit", "minimize"),
    "return": ("return", "maximize"),
    "collisions": ("collisions_per_episode", "minimize"),
    "collision_free_success": ("collision_free_success_rate", "maximize"),
}


class SweepConfig(StrictModel):
    """A sweep: base TrainConfig, search space, objective, trials, sampler, pruner, storage."""

    base: TrainConfig
    space: dict[str, ParamSpec] = Field(min_length=1)
    objective: Literal[
        "success_rate", "spl", "steps_to_goal", "return", "collisions", "collision_free_success"
    ] = Field("success_rate", description="the eval metric the study optimises (collision_free_success:"
              " the goal reached without a collision, which success_rate does not ask where a"
              " collision does not end the episode)")  # fmt: skip
    direction: Literal["maximize", "minimize"] | None = None  # default: the metric's natural one
    trials: int = Field(20, ge=1, le=100_000)
    parallel: int = Field(
        1, ge=1, le=1024, description="trials asked at once (batched when shapes agree)"
    )
    sampler: Literal["tpe", "random"] = "tpe"
    sampler_seed: int = Field(0, ge=0, le=2**31 - 1)
    pruner: Literal["none", "median"] = "none"
    storage: str | None = Field(
        None, description="None: SQLite file in the sweep folder; redis://... : journal on Redis"
    )
    study_name: str = Field("quicknav", min_length=1, max_length=200)
    eval_episodes: int = Field(50, ge=1, le=10_000)
    eval_seed: int = Field(1000, ge=0, le=2**31 - 1)

    @property
    def resolved_direction(self) -> str:
        return self.direction or METRICS[self.objective][1]

    @model_validator(mode="after")
    def _check_space(self) -> SweepConfig:
        if self.base.curriculum.enabled:
            raise ValueError(
                "base.curriculum.enabled=true: sweep trials train without the curriculum (trials"
                " that share shapes run side by side in one program); allowed: false"
            )
        for name, message in untaken(self.base, self.space).items():
            raise ValueError(f"space: unknown parameter {name!r}: {message}")
        return self


def untaken(base: TrainConfig, space: dict[str, ParamSpec | dict[str, Any]]) -> dict[str, str]:
    """The parameters of ``space`` that ``base`` has no field for, each with why (a value inside
    each dimension is set on the base, as a trial would)."""
    missing = {}
    for name, spec in space.items():
        try:
            override_data(base, {name: ParamSpec.model_validate(spec).probe()})
        except OverrideError as e:
            missing[name] = e.message
    return missing


def builtin_space(name: str) -> dict[str, dict[str, Any]]:
    """A built-in search space by name; unknown names raise ValueError listing the known ones."""
    if name not in BUILTIN_SPACES:
        raise ValueError(f"unknown search space {name!r}; built-in: {', '.join(BUILTIN_SPACES)}")
    return BUILTIN_SPACES[name]
