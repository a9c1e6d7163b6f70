"""Build a network module from its config."""

from __future__ import annotations

import flax.linen as nn

from quicknav_core.config.train import TRAINER_LOG_STD, GTrXLNetwork, LSTMNetwork, MLPNetwork
from quicknav_core.networks.gtrxl import GTrXLPolicy
from quicknav_core.networks.lstm import LSTMPolicy
from quicknav_core.networks.mlp import MLPPolicy


def make_network(
    config: MLPNetwork | LSTMNetwork | GTrXLNetwork, action_dim: int = 2, obs_dim: int = 0
) -> nn.Module:
    """The Flax module for a network config (all share the recurrent interface); a log-std
    field left to the trainer (None) is what QuickNav's recurrent PPO does. ``obs_dim``: the
    observation's width, which an MLP reading past frames carries."""
    learned, init = TRAINER_LOG_STD["recurrent-ppo"]
    std = {
        "learned_log_std": learned if config.learned_log_std is None else config.learned_log_std,
        "init_log_std": init if config.init_log_std is None else config.init_log_std,
    }
    if isinstance(config, MLPNetwork):
        return MLPPolicy(
            action_dim=action_dim, hidden_sizes=tuple(config.hidden_sizes),
            memory_size=config.memory_size, dropout_rate=config.dropout,
            frames=config.frames, frame_stride=config.frame_stride, obs_dim=obs_dim,
            **std,
        )  # fmt: skip
    if isinstance(config, LSTMNetwork):
        return LSTMPolicy(
            action_dim=action_dim, num_layers=config.num_layers, hidden_size=config.hidden_size,
            **std,
        )  # fmt: skip
    if isinstance(config, GTrXLNetwork):
        return GTrXLPolicy(
            action_dim=action_dim, embed_size=config.embed_size, num_heads=config.num_heads,
            head_size=config.head_size, num_layers=config.num_layers,
            memory_length=config.memory_length, gate_bias=config.gate_bias,
            **std,
        )  # fmt: skip
    raise TypeError(f"unknown network config {type(config).__name__}")
