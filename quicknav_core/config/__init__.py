"""Configuration: the pydantic models that are the only objects crossing a boundary, and ``resolve``.

    env.py        EnvConfig, RewardConfig, RandomizeConfig   the environment
    train.py      networks, algorithms, TrainConfig  a training run
    eval.py       EvalConfig                         a held-out evaluation
    sweep.py      SweepConfig, built-in spaces       an Optuna study
    presets.py    named TrainConfigs                 the paper's settings and a demo
    overrides.py  apply_overrides                    dotted keys with typed values
    resolve.py    resolve_train/_sweep/_eval         request -> validated config (every door)

This package imports pydantic only (no JAX): the service validates requests without a device.
"""

from quicknav_core.config.base import TRACED, Split, StrictModel, traced_fields
from quicknav_core.config.env import EnvConfig, RandomizeConfig, RewardConfig
from quicknav_core.config.errors import ConfigError, format_validation_error
from quicknav_core.config.eval import EvalConfig
from quicknav_core.config.overrides import OverrideError, apply_overrides, parse_assignments
from quicknav_core.config.presets import PRESETS, get_preset
from quicknav_core.config.resolve import (
    EvalRequest,
    SweepRequest,
    TrainRequest,
    resolve_env,
    resolve_eval,
    resolve_sweep,
    resolve_train,
)
from quicknav_core.config.sweep import BUILTIN_SPACES, METRICS, ParamSpec, SweepConfig
from quicknav_core.config.train import (
    AlgorithmConfig,
    CurriculumConfig,
    GTrXLNetwork,
    LSTMNetwork,
    MLPNetwork,
    NetworkConfig,
    PPOConfig,
    SACConfig,
    TD3Config,
    TrainConfig,
    network_is_recurrent,
)

__all__ = [
    "BUILTIN_SPACES",
    "METRICS",
    "PRESETS",
    "TRACED",
    "AlgorithmConfig",
    "ConfigError",
    "CurriculumConfig",
    "EnvConfig",
    "EvalConfig",
    "EvalRequest",
    "GTrXLNetwork",
    "LSTMNetwork",
    "MLPNetwork",
    "NetworkConfig",
    "OverrideError",
    "PPOConfig",
    "ParamSpec",
    "RandomizeConfig",
    "RewardConfig",
    "SACConfig",
    "Split",
    "StrictModel",
    "SweepConfig",
    "SweepRequest",
    "TD3Config",
    "TrainConfig",
    "TrainRequest",
    "apply_overrides",
    "format_validation_error",
    "get_preset",
    "network_is_recurrent",
    "parse_assignments",
    "resolve_env",
    "resolve_eval",
    "resolve_sweep",
    "resolve_train",
    "traced_fields",
]
